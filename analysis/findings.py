"""Short findings worded from the data.

Rules: a difference between two groups of episodes that differ in one factor only (two policies
in the same cell, or one policy at the lowest and the highest value of a sweep axis) is tested
with :func:`analysis.stats.paired_difference`. When the two groups share at least two seeds (the
seed fixes the demand and the human drivers), the per-seed differences are paired: the difference
is called (better/worse, rises/falls) only when the 95 % t-interval of the mean per-seed
difference excludes 0 (paired t-test). Otherwise Welch's t-test is used and the difference is
called only when p < 0.05. Anything else is reported as "within noise"; with fewer than two
episodes in a group there is no test, and the finding says so. Each finding names the test, the
difference (mean ± 95 % half-width, in the metric's unit) and its p-value. Numbers are formatted
exactly as in the tables.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from analysis.results import (
    filter_condition,
    ok_rows,
    reference_condition,
    summarise,
    sweep_condition,
)
from analysis.stats import MIN_PAIRS, Difference, paired_difference
from analysis.style import (
    describe_condition,
    fmt_density,
    fmt_mean_ci,
    fmt_num,
    fmt_penetration,
    order_policies,
    with_unit,
)
from analysis.tables import TERMINAL_KEYS
from mixed_traffic.schema import MACRO, METRICS


def _value(key: str, mean: float) -> str:
    return with_unit(key, fmt_num(mean))


_WELCH = f"Welch's t-test (fewer than {MIN_PAIRS} shared seeds)"


def _fmt_p(p: float) -> str:
    """'p = 0.020', 'p = 0.54' (table number format), 'p < 0.001'."""
    return "p < 0.001" if p < 0.001 else f"p = {fmt_num(p)}"


def _test_note(d: Difference, metric: str) -> str:
    """Which test, the difference (mean ± 95 % half-width, metric unit) and its p-value."""
    which = f"paired t-test over {d.n} seeds" if d.paired else _WELCH
    diff = with_unit(metric, fmt_mean_ci(d.mean, d.half_width))
    return f"{which}: difference {diff}, {_fmt_p(d.p)}"


def _noise_note(d: Difference, metric: str) -> str:
    """' (too few seeds for a test)', ' (within noise; <test>)' or ' (<test>)'."""
    sig = d.significant
    if sig is None:
        return " (too few seeds for a test)"
    return f" ({'' if sig else 'within noise; '}{_test_note(d, metric)})"


def by_seed(rows: pd.DataFrame, metric: str) -> pd.Series:
    """Finite values of ``metric`` in ``rows`` (episodes of one condition), indexed by seed, or
    by (seed, copy) where batches of copies ran (copy i of a seed pairs with copy i).

    Returns a float Series of shape (n,) in the metric's unit; NaN/inf values are dropped.
    """
    values = pd.to_numeric(rows[metric], errors="coerce").astype(float)
    copies = rows["copy"] if "copy" in rows else pd.Series(0, index=rows.index)
    labels = (pd.Index(rows["seed"], name="seed") if not (copies.fillna(0) > 0).any()
              else pd.Index(list(zip(rows["seed"], copies)), name="seed"))  # fmt: skip
    s = pd.Series(values.to_numpy(), index=labels, name=metric)
    return s[np.isfinite(s.to_numpy())]


_AXIS_FORMAT = {"penetration": fmt_penetration, "density": fmt_density, "weather": str,
                "detection_range": fmt_penetration}  # fmt: skip


def _axis_values(rows: pd.DataFrame, vary: str, metric: str) -> list[tuple[Any, pd.Series]]:
    """(value of ``vary``, ``metric`` by seed) for each value with data, in ascending order."""
    out = []
    for x, group in rows.groupby(vary, sort=True):
        s = by_seed(group, metric)
        if len(s):
            out.append((x, s))
    return out


def trend(df: pd.DataFrame, vary: str, metric: str) -> list[str]:
    """Per policy: how ``metric`` changes from the lowest to the highest value of ``vary``.

    The change is tested with :func:`paired_difference` (highest minus lowest, paired by seed
    when the seeds match). For penetration the 0 % all-human cells are left out of the trend and
    reported as a reference.
    """
    cond = sweep_condition(df, vary)
    if cond is None:
        return []
    sub = ok_rows(filter_condition(df, cond))
    with_avs = sub[sub["penetration"] > 0]
    fmt_x = _AXIS_FORMAT.get(vary, str)
    name = METRICS[metric].label
    out: list[str] = []
    for policy in order_policies(with_avs["policy"]):
        values = _axis_values(with_avs[with_avs["policy"] == policy], vary, metric)
        if len(values) < 2:
            continue
        (x1, s1), (x2, s2) = values[0], values[-1]
        d = paired_difference(s2, s1)
        verb = ("falls" if d.mean < 0 else "rises") if d.significant else "changes"
        out.append(
            f"{name} with {policy} {verb} from {_value(metric, s1.mean())} at {fmt_x(x1)}"
            f" to {_value(metric, s2.mean())} at {fmt_x(x2)}{_noise_note(d, metric)}."
        )
    ref = summarise(sub[sub["penetration"] == 0], [], [metric])
    if vary == "penetration" and not ref.empty and ref[f"{metric}_n"].iloc[0] > 0:
        out.append(
            f"All-human reference (0 % AVs): {name} = {_value(metric, ref[f'{metric}_mean'].iloc[0])}"
            f" ({describe_condition(cond)})."
        )
    return out


def wake(df: pd.DataFrame) -> list[str]:
    """Per policy, at its lowest AV share of the penetration sweep: the speed spread behind the
    AVs against the one ahead of them, paired by episode (a damping AV leaves a calmer wake)."""
    cond = sweep_condition(df, "penetration") or reference_condition(df)
    if cond is None:
        return []
    sub = ok_rows(filter_condition(df, {k: v for k, v in cond.items() if k != "penetration"}))
    sub = sub[sub["penetration"] > 0]
    out: list[str] = []
    for policy in order_policies(sub["policy"]):
        mine = sub[sub["policy"] == policy]
        at = mine[mine["penetration"] == mine["penetration"].min()]
        behind, ahead = by_seed(at, "speed_std_behind"), by_seed(at, "speed_std_ahead")
        if not (len(behind) and len(ahead)):
            continue
        d = paired_difference(behind, ahead)
        verdict = _noise_note(d, "speed_std_behind")
        if d.significant:
            calmer = "calmer" if d.mean < 0 else "rougher"
            verdict = f" ({calmer} behind; {_test_note(d, 'speed_std_behind')})"
        out.append(
            f"Speed std behind vs ahead of the AVs with {policy} at "
            f"{fmt_penetration(at['penetration'].iloc[0])}: {fmt_num(behind.mean())} vs "
            f"{_value('speed_std_ahead', ahead.mean())}{verdict}."
        )
    return out


def compare(first: str, other: str, a: pd.Series, b: pd.Series, metric: str, where: str) -> str:
    """One finding: policy ``first`` (values ``a`` by seed) against ``other`` (``b``) on ``metric``.

    ``where`` names the condition (e.g. '120 veh/km'). The verdict follows
    :attr:`analysis.stats.Difference.significant` of ``paired_difference(a, b)``.
    """
    d = paired_difference(a, b)
    verdict = _noise_note(d, metric)
    better = METRICS[metric].better
    if d.significant:
        if better:
            a_better = (d.mean < 0) == (better == "lower")
            verdict = f"{first} {'better' if a_better else 'worse'}; {better} is better"
        else:
            verdict = f"{first} {'higher' if d.mean > 0 else 'lower'}"
        verdict = f" ({verdict}; {_test_note(d, metric)})"
    return (
        f"{first} vs {other} {METRICS[metric].label} at {where}: "
        f"{fmt_num(a.mean())} vs {_value(metric, b.mean())}{verdict}."
    )


def policy_comparisons(df: pd.DataFrame, metrics: tuple[str, ...] = MACRO) -> list[str]:
    """The first policy against each other one on ``metrics`` at each density of the reference
    condition (same scenario, penetration and weather), paired by seed where possible."""
    cond = reference_condition(df)
    if cond is None:
        return []
    base = {k: v for k, v in cond.items() if k != "density"}
    sub = ok_rows(filter_condition(df, base))
    policies = order_policies(sub["policy"])
    if len(policies) < 2:
        return []
    first = policies[0]
    out: list[str] = []
    for density in sorted(sub["density"].dropna().unique()):
        at = sub[sub["density"] == density]
        for other in policies[1:]:
            for m in metrics:
                a = by_seed(at[at["policy"] == first], m)
                b = by_seed(at[at["policy"] == other], m)
                if len(a) and len(b):
                    out.append(compare(first, other, a, b, m, fmt_density(density)))
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
    out += trend(df, "penetration", "fuel")
    out += wake(df)
    out += trend(df, "density", "avg_dt_a")
    out += trend(df, "detection_range", "avg_r")
    out += weather_summary(df)
    out += policy_comparisons(df)
    out += safety_summary(df)
    out += failures(df)
    return out
