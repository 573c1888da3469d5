"""seaborn figures of sweep results with 95 % confidence intervals across seeds.

Figures are drawn on ``matplotlib.figure.Figure`` with the Agg canvas (no pyplot, no GUI
backend, nothing global switched). Each ``plot_*`` function saves one PNG atomically and returns
its path, or returns ``None`` when the data lacks the dimension the figure needs. Error bars are
the same intervals as the tables (:func:`analysis.results.summarise`): log-scale t-intervals,
asymmetric and never below 0, for non-negative metrics; Student t for signed ones.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import seaborn as sns
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from analysis.results import (
    filter_condition,
    ok_rows,
    reference_condition,
    summarise,
    sweep_condition,
)
from analysis.style import REFERENCE_COLOR, describe_condition, order_policies, policy_palette
from mixed_traffic.schema import MACRO, METRICS, MICRO, SMOOTHING, label

DPI = 170
"""Resolution of saved PNGs (sharp when embedded in an A4 PDF)."""
_STYLE = "whitegrid"
_CONTEXT = "paper"


def save_figure(fig: Figure, path: str | os.PathLike[str], dpi: int = DPI) -> Path:
    """Save ``fig`` as PNG atomically (temporary file + rename) and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp")
    try:
        FigureCanvasAgg(fig)
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def new_figure(
    width: float, height: float, ncols: int = 1, nrows: int = 1
) -> tuple[Figure, list[Axes]]:
    """A figure with ``nrows`` x ``ncols`` axes (row-major list) in the report's seaborn style."""
    with sns.axes_style(_STYLE), sns.plotting_context(_CONTEXT, font_scale=1.1):
        fig = Figure(figsize=(width, height), layout="constrained")
        axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    return fig, list(axes)


def _ci_note(metrics: Iterable[str]) -> str:
    """Footnote naming the error bars' interval: '95 % CI across seeds (log-scale t)' for
    non-negative metrics, Student t for signed ones (as short as the x label leaves room for)."""
    kinds = {"log-scale t" if METRICS[m].nonnegative else "Student t" for m in metrics}
    return f"95 % CI across seeds ({' / '.join(sorted(kinds))})"


def _yerr(stats: pd.DataFrame, metric: str) -> np.ndarray:
    """Error bars of ``stats``' rows, shape (2, rows): mean - lo and hi - mean [metric unit]
    (asymmetric for a non-negative metric's log-scale interval); 0 without an interval."""
    mean = stats[f"{metric}_mean"].to_numpy(float)
    lo, hi = stats[f"{metric}_lo"].to_numpy(float), stats[f"{metric}_hi"].to_numpy(float)
    return np.nan_to_num(np.stack([mean - lo, hi - mean]))


def _errorbar_lines(
    ax: Axes, stats: pd.DataFrame, x: str, metric: str, x_scale: float = 1.0, jitter: float = 0.0
) -> None:
    """One line with CI error bars per policy (colour from the fixed palette)."""
    palette = policy_palette(stats["policy"])
    policies = order_policies(stats["policy"])
    offsets = (np.arange(len(policies)) - (len(policies) - 1) / 2) * jitter
    for off, policy in zip(offsets, policies):
        s = stats[stats["policy"] == policy].sort_values(x)
        s = s[s[f"{metric}_n"] > 0]
        if s.empty:
            continue
        ax.errorbar(
            s[x] * x_scale + off,
            s[f"{metric}_mean"],
            yerr=_yerr(s, metric),
            color=palette[policy],
            marker="o",
            markersize=5,
            linewidth=1.8,
            capsize=4,
            label=policy,
        )


def plot_penetration(
    df: pd.DataFrame, out_dir: str | os.PathLike[str], metric: str = "dt_tf", name: str = ""
) -> Path | None:
    """DT-TF (or ``metric``) against AV penetration [%] per policy, with the 0 % reference.

    The all-human 0 % cells (any policy) are drawn as a dashed horizontal line with its CI band and
    a point at 0 %. ``None`` when penetration takes fewer than two values under one condition.
    """
    cond = sweep_condition(df, "penetration")
    if cond is None:
        return None
    sub = ok_rows(filter_condition(df, cond))
    fig, (ax,) = new_figure(6.4, 4.2)
    if not _penetration_panel(ax, sub, metric):
        return None
    ax.set_title(f"{METRICS[metric].label} vs penetration\n{describe_condition(cond)}", fontsize=10)
    ax.legend(title="policy", frameon=True)
    fig.text(0.99, 0.0, _ci_note([metric]), ha="right", va="bottom", fontsize=7)
    return save_figure(fig, Path(out_dir) / f"{name}{metric}_vs_penetration.png")


def plot_smoothing(
    df: pd.DataFrame,
    out_dir: str | os.PathLike[str],
    metrics: Sequence[str] = SMOOTHING[1:],
    name: str = "",
) -> Path | None:
    """One panel per traffic-smoothing metric (speed spread, fuel, speed spread ahead of and
    behind the AVs) against AV penetration [%], one line per policy, the 0 % reference dashed
    where it has a value; the ahead and behind panels share their y axis. ``None`` without two
    penetrations under one condition or without any of ``metrics`` (older records)."""
    cond = sweep_condition(df, "penetration")
    if cond is None:
        return None
    sub = ok_rows(filter_condition(df, cond))
    metrics = [m for m in metrics if sub[m].notna().any()]
    if not metrics:
        return None
    ncols = min(2, len(metrics))
    nrows = -(-len(metrics) // ncols)
    fig, axes = new_figure(4.4 * ncols + 1.6, 3.4 * nrows, ncols=ncols, nrows=nrows)
    for ax in axes[len(metrics) :]:
        ax.set_visible(False)
    drawn = []
    for letter, ax, m in zip("abcdefgh", axes, metrics):
        if _penetration_panel(ax, sub, m, legend_ref=not drawn):
            ax.set_title(f"({letter}) {METRICS[m].label}", fontsize=10)
            drawn.append(ax)
        else:
            ax.set_visible(False)
    if not drawn:
        return None
    _share_y(ax for ax, m in zip(axes, metrics) if m in ("speed_std_ahead", "speed_std_behind"))
    handles, labels = drawn[0].get_legend_handles_labels()
    fig.legend(handles, labels, title="policy", loc="outside right center")
    fig.suptitle(f"Traffic smoothing vs penetration — {describe_condition(cond)}", fontsize=10)
    fig.text(0.99, 0.0, _ci_note(metrics), ha="right", va="bottom", fontsize=7)
    return save_figure(fig, Path(out_dir) / f"{name}smoothing_vs_penetration.png")


def _share_y(axes: Iterable[Axes]) -> None:
    """One y range for ``axes`` (the union of their own)."""
    axes = list(axes)
    if len(axes) > 1:
        lows, highs = zip(*(ax.get_ylim() for ax in axes))
        for ax in axes:
            ax.set_ylim(min(lows), max(highs))


def _penetration_panel(ax: Axes, sub: pd.DataFrame, metric: str, legend_ref: bool = True) -> bool:
    """``metric`` against AV penetration [%] on ``ax``: a line with CI error bars per policy and
    the 0 % all-human cells (any policy) as a dashed line with its CI band and a point at 0 %.
    False (nothing drawn) without a value or with fewer than two penetrations."""
    stats = summarise(sub[sub["penetration"] > 0], ["policy", "penetration"], [metric])
    ref = summarise(sub[sub["penetration"] == 0], [], [metric])
    has_ref = not ref.empty and ref[f"{metric}_n"].iloc[0] > 0
    if stats.empty or stats[f"{metric}_n"].sum() == 0:
        return False
    if stats["penetration"].nunique() + int(has_ref) < 2:
        return False
    _errorbar_lines(ax, stats, "penetration", metric, x_scale=100.0, jitter=1.0)
    if has_ref:
        m, lo, hi = (ref[f"{metric}_{c}"].iloc[0] for c in ("mean", "lo", "hi"))
        ax.axhline(m, color=REFERENCE_COLOR, linestyle="--", linewidth=1.3,
                   label="0 % (all human)" if legend_ref else None)  # fmt: skip
        if lo == lo:
            ax.axhspan(lo, hi, color=REFERENCE_COLOR, alpha=0.10, linewidth=0)
        ax.errorbar([0], [m], yerr=_yerr(ref, metric), color=REFERENCE_COLOR, marker="s", capsize=4)
    ticks = sorted(
        {0.0, *(stats["penetration"] * 100).round(6)}
        if has_ref
        else set(stats["penetration"] * 100)
    )
    ax.set_xticks(ticks)
    ax.set_xlabel("AV penetration rate (%)")
    ax.set_ylabel(label(metric))
    return True


def plot_density(
    df: pd.DataFrame,
    out_dir: str | os.PathLike[str],
    metrics: Sequence[str] = MACRO,
    name: str = "",
) -> Path | None:
    """AvgDT-A, AvgAT-C and AvgDI-C (paper Fig. "Scalability Analysis" (a)-(c)) vs density.

    One panel per metric, one line per policy. ``None`` without two densities under one
    condition.
    """
    return _plot_axis(df, out_dir, "density", metrics, "traffic density (veh/km)", 1.0,
                      "Macroscopic metrics vs density", f"{name}macro_vs_density.png")  # fmt: skip


def plot_detection_range(
    df: pd.DataFrame,
    out_dir: str | os.PathLike[str],
    metrics: Sequence[str] = ("avg_r", "avg_dt_a", "pt_rt"),
    name: str = "",
) -> Path | None:
    """AvgR (paper tables "Impact of Detection Range"), AvgDT-A and PT-RT against the
    detection range [% of the nominal ranges]; ``None`` without two ranges."""
    return _plot_axis(df, out_dir, "detection_range", metrics,
                      "detection range (% of nominal)", 100.0,
                      "Metrics vs detection range", f"{name}metrics_vs_detection_range.png")  # fmt: skip


def _plot_axis(df: pd.DataFrame, out_dir: str | os.PathLike[str], axis: str,
               metrics: Sequence[str], xlabel: str, x_scale: float, title: str,
               file: str) -> Path | None:  # fmt: skip
    """One panel per metric against the numeric sweep ``axis`` (shown times ``x_scale``), one
    line per policy; ``None`` without two values of ``axis`` under one condition."""
    cond = sweep_condition(df, axis)
    if cond is None:
        return None
    sub = ok_rows(filter_condition(df, cond))
    stats = summarise(sub, ["policy", axis], list(metrics))
    metrics = [m for m in metrics if stats[f"{m}_n"].sum() > 0]
    if not metrics:
        return None
    fig, axes = new_figure(3.6 * len(metrics), 3.6, ncols=len(metrics))
    span = float(stats[axis].max() - stats[axis].min()) * x_scale or 1.0
    for letter, ax, m in zip("abcdefgh", axes, metrics):
        _errorbar_lines(ax, stats, axis, m, x_scale=x_scale, jitter=span * 0.012)
        ax.set_xticks(sorted((stats[axis] * x_scale).round(6).unique()))
        ax.set_xlabel(xlabel)
        ax.set_ylabel(label(m))
        ax.set_title(f"({letter}) {METRICS[m].label}", fontsize=10)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, title="policy", loc="outside right center")
    fig.suptitle(f"{title} — {describe_condition(cond)}", fontsize=10)
    return save_figure(fig, Path(out_dir) / file)


def _bars(ax: Axes, stats: pd.DataFrame, metric: str, hue: str | None = None) -> None:
    """Bars of the per-policy mean with CI error bars (optionally grouped by ``hue``)."""
    palette = policy_palette(stats["policy"])
    policies = order_policies(stats["policy"])
    groups = [None] if hue is None else list(dict.fromkeys(stats[hue]))
    width = 0.8 / len(policies)
    for i, policy in enumerate(policies):
        xs, ys, es = [], [], np.zeros((2, 0))
        for j, g in enumerate(groups):
            s = stats[stats["policy"] == policy]
            if hue is not None:
                s = s[s[hue] == g]
            if s.empty or s[f"{metric}_n"].iloc[0] == 0:
                continue
            xs.append(j + (i - (len(policies) - 1) / 2) * width)
            ys.append(s[f"{metric}_mean"].iloc[0])
            es = np.hstack([es, _yerr(s.iloc[:1], metric)])
        ax.bar(xs, ys, width=width * 0.95, yerr=es, capsize=3, color=palette[policy], label=policy)
    ax.set_xticks(range(len(groups)))
    ax.set_xticklabels([] if hue is None else [str(g) for g in groups])


def plot_micro(
    df: pd.DataFrame,
    out_dir: str | os.PathLike[str],
    metrics: Sequence[str] = MICRO,
    condition: dict[str, Any] | None = None,
    name: str = "",
) -> Path | None:
    """Small multiples: one bar panel per microscopic metric, one bar per policy, with CIs.

    Uses ``condition`` or the tables' :func:`~analysis.results.reference_condition`.
    """
    cond = reference_condition(df) if condition is None else condition
    if cond is None:
        return None
    sub = ok_rows(filter_condition(df, cond))
    stats = summarise(sub, ["policy"], list(metrics))
    metrics = [m for m in metrics if not stats.empty and stats[f"{m}_n"].sum() > 0]
    if not metrics:
        return None
    ncols = min(3, len(metrics))
    nrows = -(-len(metrics) // ncols)
    fig, axes = new_figure(3.0 * ncols + 0.8, 3.0 * nrows, ncols=ncols, nrows=nrows)
    for ax in axes[len(metrics) :]:
        ax.set_visible(False)
    for ax, m in zip(axes, metrics):
        _bars(ax, stats, m)
        ax.set_ylabel(label(m))
        better = METRICS[m].better
        ax.set_title(METRICS[m].label + (f" ({better} is better)" if better else ""), fontsize=9)
    handles, labels = axes[0].get_legend_handles_labels()
    if len(axes) > len(metrics):
        axes[-1].set_visible(True)
        axes[-1].axis("off")
        axes[-1].legend(handles, labels, title="policy", loc="center")
    else:
        fig.legend(handles, labels, title="policy", loc="outside right center")
    fig.suptitle(f"Microscopic metrics per policy — {describe_condition(cond)}", fontsize=10)
    return save_figure(fig, Path(out_dir) / f"{name}micro_per_policy.png")


def plot_weather(
    df: pd.DataFrame, out_dir: str | os.PathLike[str], metric: str = "pt_rt", name: str = ""
) -> Path | None:
    """PT-RT (share of AV time with TTC < 4 s) per weather preset and policy (paper's robustness table).

    ``None`` unless the data has at least two weathers under one condition.
    """
    cond = sweep_condition(df, "weather")
    if cond is None:
        return None
    sub = ok_rows(filter_condition(df, cond))
    order = {w: i for i, w in enumerate(("normal", "rain", "fog", "night"))}
    stats = summarise(sub, ["policy", "weather"], [metric])
    stats = stats.sort_values("weather", key=lambda s: s.map(lambda w: order.get(w, 99)))
    if stats[f"{metric}_n"].sum() == 0:
        return None
    fig, (ax,) = new_figure(6.4, 4.0)
    _bars(ax, stats, metric, hue="weather")
    ax.set_xlabel("weather")
    ax.set_ylabel(label(metric))
    ax.set_title(f"{METRICS[metric].label} per weather — {describe_condition(cond)}", fontsize=10)
    ax.legend(title="policy")
    return save_figure(fig, Path(out_dir) / f"{name}{metric}_per_weather.png")


def all_figures(
    df: pd.DataFrame, out_dir: str | os.PathLike[str], name: str = ""
) -> dict[str, Path]:
    """Every figure the data supports: {'penetration', 'smoothing', 'density', 'micro',
    'weather', 'detection_range'} -> PNG path."""
    made = {
        "penetration": plot_penetration(df, out_dir, name=name),
        "smoothing": plot_smoothing(df, out_dir, name=name),
        "density": plot_density(df, out_dir, name=name),
        "micro": plot_micro(df, out_dir, name=name),
        "weather": plot_weather(df, out_dir, name=name),
        "detection_range": plot_detection_range(df, out_dir, name=name),
    }
    return {k: v for k, v in made.items() if v is not None}
