"""Short findings worded from the data.

Rules: a change or a difference is only called a rise/fall or better/worse when the two 95 %
t-intervals do not overlap; otherwise it is reported as "within noise". A single seed (no
interval) is said so. Numbers are formatted exactly as in the tables.
"""

from __future__ import annotations

import math

import pandas as pd

from analysis.results import (
    filter_condition,
    ok_rows,
    reference_condition,
    summarise,
    sweep_condition,
)
from analysis.style import (
    describe_condition,
    fmt_density,
    fmt_num,
    fmt_penetration,
    order_policies,
    with_unit,
)
from analysis.tables import TERMINAL_KEYS
from mixed_traffic.schema import MACRO, METRICS


def _separated(m1: float, h1: float, m2: float, h2: float) -> bool | None:
    """True if the intervals [m±h] do not overlap, False if they do, None without intervals."""
    if any(isinstance(v, float) and math.isnan(v) for v in (h1, h2)):
        return None
    return abs(m1 - m2) > h1 + h2


def _noise_note(sep: bool | None) -> str:
    if sep is None:
        return " (too few seeds for a confidence interval)"
    return "" if sep else " (within noise: the 95 % CIs overlap)"


def _value(key: str, mean: float) -> str:
    return with_unit(key, fmt_num(mean))


_AXIS_FORMAT = {"penetration": fmt_penetration, "density": fmt_density, "weather": str}


def trend(df: pd.DataFrame, vary: str, metric: str) -> list[str]:
    """Per policy: how ``metric`` changes from the lowest to the highest value of ``vary``.

    For penetration the 0 % all-IDM cells are left out of the trend and reported as a reference.
    """
    cond = sweep_condition(df, vary)
    if cond is None:
        return []
    sub = ok_rows(filter_condition(df, cond))
    with_avs = sub[sub["penetration"] > 0]
    stats = summarise(with_avs, ["policy", vary], [metric])
    fmt_x = _AXIS_FORMAT.get(vary, str)
    name = METRICS[metric].label
    out: list[str] = []
    for policy in order_policies(stats["policy"]):
        s = stats[(stats["policy"] == policy) & (stats[f"{metric}_n"] > 0)].sort_values(vary)
        if len(s) < 2:
            continue
        lo, hi = s.iloc[0], s.iloc[-1]
        m1, h1, m2, h2 = (
            lo[f"{metric}_mean"],
            lo[f"{metric}_ci"],
            hi[f"{metric}_mean"],
            hi[f"{metric}_ci"],
        )
        sep = _separated(m1, h1, m2, h2)
        verb = ("falls" if m2 < m1 else "rises") if sep else "changes"
        out.append(
            f"{name} with {policy} {verb} from {_value(metric, m1)} at {fmt_x(lo[vary])}"
            f" to {_value(metric, m2)} at {fmt_x(hi[vary])}{_noise_note(sep)}."
        )
    ref = summarise(sub[sub["penetration"] == 0], [], [metric])
    if vary == "penetration" and not ref.empty and ref[f"{metric}_n"].iloc[0] > 0:
        out.append(
            f"All-IDM reference (0 % AVs): {name} = {_value(metric, ref[f'{metric}_mean'].iloc[0])}"
            f" ({describe_condition(cond)})."
        )
    return out


def policy_comparisons(df: pd.DataFrame, metrics: tuple[str, ...] = MACRO) -> list[str]:
    """The first policy against each other one on ``metrics`` at each density of the reference condition."""
    cond = reference_condition(df)
    if cond is None:
        return []
    base = {k: v for k, v in cond.items() if k != "density"}
    sub = ok_rows(filter_condition(df, base))
    stats = summarise(sub, ["policy", "density"], list(metrics))
    policies = order_policies(stats["policy"])
    if len(policies) < 2:
        return []
    first = policies[0]
    out: list[str] = []
    for density in sorted(stats["density"].dropna().unique()):
        at = stats[stats["density"] == density]
        a = at[at["policy"] == first]
        if a.empty:
            continue
        for other in policies[1:]:
            b = at[at["policy"] == other]
            if b.empty:
                continue
            for m in metrics:
                ma, ha, mb, hb = (
                    a[f"{m}_mean"].iloc[0], a[f"{m}_ci"].iloc[0], b[f"{m}_mean"].iloc[0], b[f"{m}_ci"].iloc[0]
                )  # fmt: skip
                if math.isnan(ma) or math.isnan(mb):
                    continue
                sep = _separated(ma, ha, mb, hb)
                verdict = _noise_note(sep)
                better = METRICS[m].better
                if sep and better:
                    a_better = (ma < mb) == (better == "lower")
                    verdict = f" ({first} {'better' if a_better else 'worse'}; {better} is better)"
                out.append(
                    f"{first} vs {other} {METRICS[m].label} at {fmt_density(density)}: "
                    f"{fmt_num(ma)} vs {_value(m, mb)}{verdict}."
                )
    return out


def weather_summary(df: pd.DataFrame, metric: str = "pt_rt") -> list[str]:
    """Per policy: ``metric`` under each weather preset (normal, rain, fog, night order)."""
    cond = sweep_condition(df, "weather")
    if cond is None:
        return []
    stats = summarise(ok_rows(filter_condition(df, cond)), ["policy", "weather"], [metric])
    order = ("normal", "rain", "fog", "night")
    out = []
    for policy in order_policies(stats["policy"]):
        s = stats[(stats["policy"] == policy) & (stats[f"{metric}_n"] > 0)]
        s = s.sort_values(
            "weather", key=lambda c: c.map(lambda w: order.index(w) if w in order else 9)
        )
        if len(s) < 2:
            continue
        parts = ", ".join(
            f"{w} {_value(metric, m)}" for w, m in zip(s["weather"], s[f"{metric}_mean"])
        )
        out.append(f"{METRICS[metric].label} with {policy}: {parts}.")
    return out


def safety_summary(df: pd.DataFrame) -> list[str]:
    """Collisions, terminal events, teleports and route completion, per policy and in total."""
    ok = ok_rows(df)
    if ok.empty:
        return []
    out: list[str] = []
    for policy in order_policies(ok["policy"]):
        g = ok[ok["policy"] == policy]
        collisions = int(g["collisions"].fillna(0).sum())
        terminal = int(g[list(TERMINAL_KEYS)].fillna(0).to_numpy().sum())
        trips = int(g["av_trips"].fillna(0).sum())
        teleports = int(g["teleports"].fillna(0).sum())
        text = (
            f"{policy}: {collisions} collisions / {terminal} terminal events in {trips} AV trips"
            f" ({len(g)} episodes), {teleports} teleports"
        )
        comp = g["route_completion"].dropna()
        if not comp.empty and trips > 0:
            w = g.loc[comp.index, "av_trips"].fillna(0)
            value = (comp * w).sum() / w.sum() if w.sum() > 0 else comp.mean()
            text += f", route completion {fmt_num(value)} %"
        out.append(text + ".")
    return out


def failures(df: pd.DataFrame) -> list[str]:
    """How many episodes failed (they are excluded from every statistic)."""
    n_failed = int((df["status"] != "ok").sum())
    if n_failed == 0:
        return []
    return [
        f"{n_failed} of {len(df)} episodes failed and are excluded from the statistics"
        " (see 'Failed episodes')."
    ]


def findings(df: pd.DataFrame) -> list[str]:
    """All findings, most important first."""
    out: list[str] = []
    out += trend(df, "penetration", "dt_tf")
    out += trend(df, "density", "avg_dt_a")
    out += weather_summary(df)
    out += policy_comparisons(df)
    out += safety_summary(df)
    out += failures(df)
    return out
