"""Tables shaped like the paper's macroscopic and microscopic tables, with safety counts beside.

Table builders return *numeric* DataFrames (``{m}_mean``/``{m}_lo``/``{m}_hi`` columns: the mean
and its 95 % interval from :func:`analysis.results.summarise`, plus safety counts)
with ``attrs`` describing them (``title``, ``metrics``, ``condition``); :func:`format_table`
turns one into display strings and :func:`to_text` into markdown or plain text.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import pandas as pd

from analysis.results import (
    CONDITION_KEYS,
    filter_condition,
    reference_condition,
    summarise,
)
from analysis.style import (
    describe_condition,
    fmt_count,
    fmt_level,
    fmt_num,
    fmt_penetration,
    order_policies,
)
from mixed_traffic.schema import MACRO, METRICS, MICRO, SMOOTHING, TERMINAL_REASONS, label

TERMINAL_KEYS = tuple(f"terminal_{r}" for r in TERMINAL_REASONS)
#: Safety columns placed beside every results table.
SAFETY_COLUMNS = (
    "av_trips", "collisions", "terminal_events", "teleports", "route_completion", "sm_share",
)  # fmt: skip
SAFETY_HEADERS = {
    "av_trips": "AV trips",
    "collisions": "collisions",
    "terminal_events": "terminal events",
    "teleports": "teleports",
    "route_completion": "completion (%)",
    "sm_share": "safety module (%)",
}
#: Columns ``safety_counts`` adds to a table.
_SAFETY_OUT = ("episodes", "av_trips", "collisions", "terminal_events", *TERMINAL_KEYS,
               "teleports", "route_completion", "sm_share")  # fmt: skip
#: Metrics of the per-cell sweep table.
CELL_METRICS = ("dt_tf", *MACRO, "pt_rt")


def safety_counts(df: pd.DataFrame, by: Sequence[str]) -> pd.DataFrame:
    """Safety counts per group over successful episodes.

    Sums of AV trips, collisions, terminal events (every reason, also per reason as
    ``terminal_<reason>``) and teleports; route completion is the AV-trip-weighted mean (%);
    ``sm_share`` the episode mean of the AUTO safety module's intervention share (%).
    """
    by = list(by)
    ok = df[df["status"] == "ok"].copy()
    ok["terminal_events"] = ok[list(TERMINAL_KEYS)].fillna(0).sum(axis=1)
    rows: list[dict[str, Any]] = []
    groups = ok.groupby(by, dropna=False, sort=True) if by else [((), ok)]
    for key, group in groups:
        key = key if isinstance(key, tuple) else (key,)
        row: dict[str, Any] = dict(zip(by, key))
        row["episodes"] = len(group)
        for col in ("av_trips", "collisions", "teleports", "terminal_events", *TERMINAL_KEYS):
            row[col] = float(group[col].fillna(0).sum())
        row["route_completion"] = _weighted_completion(group)
        # share of the AUTO agent's actions its safety module changed (episode mean)
        row["sm_share"] = group["sm_share"].mean() if "sm_share" in group else float("nan")
        rows.append(row)
    cols = [*by, "episodes", "av_trips", "collisions", "terminal_events", *TERMINAL_KEYS]
    return pd.DataFrame(rows, columns=[*cols, "teleports", "route_completion", "sm_share"])


def _weighted_completion(group: pd.DataFrame) -> float:
    """Route completion (%) weighted by AV trips; plain mean when trips are unknown."""
    comp = group["route_completion"]
    trips = group["av_trips"].fillna(0)
    valid = comp.notna()
    if not valid.any():
        return float("nan")
    if trips[valid].sum() > 0:
        return float((comp[valid] * trips[valid]).sum() / trips[valid].sum())
    return float(comp[valid].mean())


def metric_table(
    df: pd.DataFrame,
    metrics: Sequence[str],
    by: Sequence[str] = ("policy",),
    condition: dict[str, Any] | None = None,
    title: str = "",
) -> pd.DataFrame:
    """Mean and 95 % CI of ``metrics`` per group (rows), with the safety counts beside them.

    ``condition`` restricts the rows first (e.g. one density and penetration). Policies are
    ordered as in :data:`mixed_traffic.schema.POLICIES`.
    """
    sub = filter_condition(df, condition) if condition else df
    by = list(by)
    if sub.empty:
        out = pd.DataFrame(columns=[*by, "n_ok", "n_failed"])
    else:
        stats = summarise(sub, by, metrics)
        keep = [*by, "n_ok", "n_failed"]
        for m in metrics:
            keep += [f"{m}_mean", f"{m}_lo", f"{m}_hi"]
        out = stats[keep].merge(safety_counts(sub, by), on=by, how="left")
        if "policy" in by:
            order = {p: i for i, p in enumerate(order_policies(out["policy"]))}
            out = out.sort_values(
                by=["policy", *[b for b in by if b != "policy"]],
                key=lambda s: s.map(order) if s.name == "policy" else s,
                kind="stable",
            ).reset_index(drop=True)
    out.attrs.update(title=title, metrics=tuple(metrics), by=tuple(by), condition=condition or {})
    return out


def macro_table(df: pd.DataFrame, condition: dict[str, Any] | None = None) -> pd.DataFrame:
    """The paper's macroscopic table (AvgDT-A, AvgAT-C, AvgDI-C) per policy + safety counts.

    Without ``condition`` the :func:`~analysis.results.reference_condition` is used.
    """
    condition = reference_condition(df) if condition is None else condition
    title = "Macroscopic evaluation"
    if condition:
        title += f" ({describe_condition(condition)})"
    return metric_table(df, MACRO, condition=condition, title=title)


def micro_table(df: pd.DataFrame, condition: dict[str, Any] | None = None) -> pd.DataFrame:
    """The paper's microscopic table (MinTTC-A … AvgDEC-C) per policy + safety counts."""
    condition = reference_condition(df) if condition is None else condition
    title = "Microscopic evaluation"
    if condition:
        title += f" ({describe_condition(condition)})"
    return metric_table(df, MICRO, condition=condition, title=title)


def cell_table(df: pd.DataFrame, metrics: Sequence[str] = CELL_METRICS) -> pd.DataFrame:
    """One row per sweep cell (policy, scenario, density, penetration, weather) across seeds."""
    return metric_table(df, metrics, by=CONDITION_KEYS, title="Per-cell results")


def smoothing_table(df: pd.DataFrame, metrics: Sequence[str] = SMOOTHING) -> pd.DataFrame:
    """Traffic smoothing per sweep cell across seeds: DT-TF, the speed spread, fuel and the
    speed spread ahead of / behind the AVs, mean and 95 % CI (no safety columns: they are in the
    per-cell table). Empty when no episode measured any of ``metrics`` beyond those of the
    per-cell table (records from before these measures)."""
    ok = df[df["status"] == "ok"]
    extra = [m for m in metrics if m not in CELL_METRICS]
    if ok.empty or ok[extra].isna().all().all():
        out = pd.DataFrame(columns=[*CONDITION_KEYS, "n_ok", "n_failed"])
    else:
        out = metric_table(df, metrics, by=CONDITION_KEYS)
        out = out.drop(columns=[c for c in out.columns if c in _SAFETY_OUT])
    out.attrs.update(title="Traffic smoothing per cell", metrics=tuple(metrics),
                     by=CONDITION_KEYS, condition={})  # fmt: skip
    return out


def safety_table(df: pd.DataFrame, by: Sequence[str] = ("policy",)) -> pd.DataFrame:
    """Safety counts per policy over every condition, with terminal events by reason."""
    out = safety_counts(df, by)
    failed = df[df["status"] != "ok"].groupby(list(by), dropna=False).size()
    out.insert(len(by) + 1, "failed", [int(failed.get(k, 0)) for k in out[by[0]]])
    if "policy" in by and not out.empty:
        order = {p: i for i, p in enumerate(order_policies(out["policy"]))}
        out = out.sort_values("policy", key=lambda s: s.map(order)).reset_index(drop=True)
    out.attrs.update(title="Safety counts (all conditions)", by=tuple(by))
    return out


_COND_FORMAT = {"density": lambda v: fmt_num(v, 0), "penetration": fmt_penetration,
                "detection_range": fmt_penetration}  # fmt: skip
_COND_HEADER = {"density": "density (veh/km)", "penetration": "AV share", "weather": "weather",
                "detection_range": "detection range"}  # fmt: skip


def format_table(table: pd.DataFrame, drop_constant: bool = True) -> pd.DataFrame:
    """Display strings: group columns, 'n', metric columns 'mean [lo, hi]' (non-negative metrics)
    or 'mean ± half-width' (signed ones, :func:`analysis.style.fmt_level`) with labelled
    headers, safety.

    With ``drop_constant`` the group columns (other than policy) that take one value are dropped
    (they belong in the caption). Tables grouped by more than the policy (per-cell) show the
    collision, terminal-event and teleport counts in one compact column.
    """
    by = list(table.attrs.get("by", ("policy",)))
    metrics = list(table.attrs.get("metrics", ()))
    cols: dict[str, list[str]] = {}
    for b in by:
        if b not in table.columns:
            continue
        if (
            drop_constant
            and b != "policy"
            and len(table) > 0
            and table[b].nunique(dropna=False) <= 1
        ):
            continue
        fmt = _COND_FORMAT.get(b, lambda v: "n/a" if v is None or v != v else str(v))
        cols[_COND_HEADER.get(b, b)] = [fmt(v) for v in table[b]]
    if "n_ok" in table.columns:
        cols["n"] = [
            fmt_count(o) + (f" (+{int(f)} failed)" if f else "")
            for o, f in zip(table["n_ok"], table.get("n_failed", [0] * len(table)))
        ]
    elif "episodes" in table.columns:
        cols["episodes"] = [fmt_count(v) for v in table["episodes"]]
        if "failed" in table.columns:
            cols["failed"] = [fmt_count(v) for v in table["failed"]]
    for m in metrics:
        cols[label(m)] = [
            fmt_level(m, *v) for v in zip(table[f"{m}_mean"], table[f"{m}_lo"], table[f"{m}_hi"])
        ]
    safety = [*SAFETY_COLUMNS]
    if "terminal_collision" in table.columns and not metrics:
        safety = [
            "av_trips",
            "collisions",
            "terminal_events",
            *TERMINAL_KEYS,
            "teleports",
            "route_completion",
            "sm_share",
        ]
    compact = len(by) > 1 and bool(metrics)
    if compact and {"collisions", "terminal_events", "teleports"} <= set(table.columns):
        cols["AV trips"] = [fmt_count(v) for v in table["av_trips"]]
        cols["collisions / terminal / teleports"] = [
            f"{fmt_count(a)} / {fmt_count(b)} / {fmt_count(c)}"
            for a, b, c in zip(table["collisions"], table["terminal_events"], table["teleports"])
        ]
        safety = ["route_completion", "sm_share"]
    for s in safety:
        if s not in table.columns or (s == "sm_share" and table[s].isna().all()):
            continue
        header = SAFETY_HEADERS.get(s) or METRICS[s].label
        fmt = fmt_num if s in ("route_completion", "sm_share") else fmt_count
        cols[header] = [fmt(v) for v in table[s]]
    return pd.DataFrame(cols)


def to_text(table: pd.DataFrame, fmt: str = "markdown") -> str:
    """A table as markdown (``fmt='markdown'``) or aligned plain text (``fmt='text'``)."""
    shown = format_table(table)
    headers = list(shown.columns)
    rows = shown.astype(str).to_numpy().tolist()
    title = table.attrs.get("title", "")
    if fmt == "markdown":
        lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return (f"**{title}**\n\n" if title else "") + "\n".join(lines)
    if fmt == "text":
        widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(headers)]
        line = "  ".join(h.ljust(w) for h, w in zip(headers, widths))
        body = ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in rows]
        return "\n".join(([title] if title else []) + [line, "-" * len(line), *body])
    raise ValueError(f"to_text: fmt must be 'markdown' or 'text', got {fmt!r}")
