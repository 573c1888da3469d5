"""Shared presentation rules: policy order and colours, number formatting, condition labels."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from mixed_traffic.schema import METRICS, POLICIES

#: One fixed colour per known policy (colour-blind-safe tab10 entries), used by every figure.
POLICY_COLORS: dict[str, str] = {
    "auto": "#1f77b4",
    "auto-raw": "#9467bd",
    "acc-lc": "#ff7f0e",
    "acc-lc-tuned": "#d62728",
    "idm": "#7f7f7f",
    "random": "#2ca02c",
}
_EXTRA_COLORS = ("#8c564b", "#e377c2", "#bcbd22", "#17becf")
REFERENCE_COLOR = "#333333"
"""Colour of the 0 % all-human reference."""
CI_METHODS = (
    "95 % confidence intervals: for metrics that cannot be negative (times, delays, speeds, "
    "speed spreads, fuel, shares, counts) a log-scale (delta-method) t-interval of the mean, "
    "mean·exp(±t·se/mean) with se the standard error, printed 'mean [low, high]', which stays "
    ">= 0; Student t (mean ± half-width) for signed quantities (AvgR, wave speed) and for "
    "paired differences."
)
"""The reports' note on which interval is used where."""


def order_policies(policies: Iterable[Any]) -> list[str]:
    """Known policies in :data:`POLICIES` order, then the others alphabetically."""
    names = {str(p) for p in policies if p is not None and p == p}
    known = [p for p in POLICIES if p in names]
    return known + sorted(names - set(known))


def policy_palette(policies: Iterable[Any]) -> dict[str, str]:
    """Colour per policy: fixed for known ones, stable (sorted) extra colours for the rest."""
    out: dict[str, str] = {}
    extra = iter(_EXTRA_COLORS * 4)
    for p in order_policies(policies):
        out[p] = POLICY_COLORS.get(p) or next(extra)
    return out


def is_missing(x: Any) -> bool:
    """True for None and NaN."""
    return x is None or (isinstance(x, float) and math.isnan(x))


def decimals_for(x: float) -> int:
    """Decimals used to print ``x``: 1 from 100 up, 2 from 0.1 up (and for 0), else 3."""
    ax = abs(x)
    if ax >= 100:
        return 1
    if ax >= 0.1 or ax == 0:
        return 2
    return 3


def fmt_num(x: Any, decimals: int | None = None) -> str:
    """A metric value as the report prints it ('n/a' when missing)."""
    if is_missing(x):
        return "n/a"
    x = float(x)
    d = decimals_for(x) if decimals is None else decimals
    return f"{x:.{d}f}"


def fmt_mean_ci(mean: Any, ci: Any) -> str:
    """'53.61 ± 0.42' (the half-width with the mean's decimals); the mean alone without a CI."""
    if is_missing(mean):
        return "n/a"
    d = decimals_for(float(mean))
    if is_missing(ci):
        return fmt_num(mean, d)
    return f"{fmt_num(mean, d)} ± {fmt_num(ci, d)}"


def fmt_interval(mean: Any, lo: Any, hi: Any) -> str:
    """'2.47 [2.01, 3.03]': a mean and its (asymmetric) 95 % interval, all with the mean's
    decimals; the mean alone without an interval."""
    if is_missing(mean):
        return "n/a"
    d = decimals_for(float(mean))
    if is_missing(lo) or is_missing(hi):
        return fmt_num(mean, d)
    return f"{fmt_num(mean, d)} [{fmt_num(lo, d)}, {fmt_num(hi, d)}]"


def fmt_level(key: str, mean: Any, lo: Any, hi: Any) -> str:
    """Metric ``key``'s mean with its 95 % interval ``(lo, hi)`` as summarise gives them:
    '2.47 [2.01, 3.03]' for a non-negative metric (log-scale interval, asymmetric),
    '0.41 ± 0.02' for a signed one (Student t-interval, symmetric)."""
    if METRICS[key].nonnegative:
        return fmt_interval(mean, lo, hi)
    return fmt_mean_ci(mean, (hi - lo) / 2)


def fmt_count(x: Any) -> str:
    """An integer count ('n/a' when missing)."""
    return "n/a" if is_missing(x) else str(int(round(float(x))))


def fmt_penetration(p: Any) -> str:
    """A penetration fraction as a percentage: 0.2 -> '20 %'."""
    return "n/a" if is_missing(p) else f"{float(p) * 100:.0f} %"


def fmt_density(k: Any) -> str:
    """A density as '120 veh/km'."""
    return "n/a" if is_missing(k) else f"{float(k):g} veh/km"


def with_unit(key: str, value: str) -> str:
    """Append the metric's unit to a formatted value ('53.61 s/km'; no unit for '-')."""
    unit = METRICS[key].unit
    if unit in ("", "-") or value == "n/a":
        return value
    return f"{value} {unit}" if unit != "%" else f"{value} %"


def describe_condition(cond: dict[str, Any]) -> str:
    """'straight, 120 veh/km, 20 % AVs, normal weather' from a condition dict (keys optional)."""
    parts = []
    if "scenario" in cond:
        parts.append(str(cond["scenario"]))
    if "density" in cond:
        parts.append(fmt_density(cond["density"]))
    if "penetration" in cond:
        parts.append(f"{fmt_penetration(cond['penetration'])} AVs")
    if "weather" in cond:
        parts.append(f"{cond['weather']} weather")
    if cond.get("detection_range", 1.0) != 1.0:
        parts.append(f"detection range {fmt_penetration(cond['detection_range'])} of nominal")
    return ", ".join(parts)
