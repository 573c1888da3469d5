"""PDF reports of the paper's comparison studies (``python -m mixed_traffic.study``), in the
style of its tables: macroscopic (AvgDT-A, AvgAT-C, AvgDI-C), microscopic (MinTTC-A … AvgDEC-C)
and AvgR / AvgIT, each mean and 95 % CI over seeds (log-scale t-interval for non-negative
metrics, Student t for AvgR), then every method's paired difference to the reference policy
(the same training pipeline and budget as the others), the methods' training lineage and, for
trained methods, their learning curves.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd
from reportlab.platypus import Paragraph, Spacer

from analysis import tables as tbl
from analysis.figures import new_figure, save_figure
from analysis.findings import by_seed
from analysis.pdf import figure, frame_rows, grid, make_styles, para, write_pdf
from analysis.report import failed_rows
from analysis.results import load_results, ok_rows
from analysis.stats import paired_difference
from analysis.style import CI_METHODS, describe_condition, fmt_mean_ci, fmt_num, order_policies
from mixed_traffic.schema import MACRO, METRICS, MICRO

PAIRED_METRICS = (*MACRO, *MICRO, "avg_r")
"""Metrics of the paired-difference table."""
CURVE_WINDOW = 5
"""Curve rows in the running mean of the learning curves."""


def paired_rows(df: pd.DataFrame, reference: str,
                metrics: Sequence[str] = PAIRED_METRICS) -> list[list[str]]:  # fmt: skip
    """Header + one row per policy: ``policy − reference`` per metric as 'Δ ± half-width'
    with its paired t-test verdict (* where the 95 % interval excludes 0)."""
    ok = ok_rows(df)
    ref = ok[ok["policy"] == reference]
    rows = [["policy", *(f"Δ {METRICS[m].label} ({METRICS[m].unit})" for m in metrics)]]
    for policy in order_policies(ok["policy"]):
        if policy == reference:
            continue
        mine = ok[ok["policy"] == policy]
        row = [policy]
        for m in metrics:
            a, b = by_seed(mine, m), by_seed(ref, m)
            if not (len(a) and len(b)):
                row.append("n/a")
                continue
            d = paired_difference(a, b)
            star = "*" if d.significant else ""
            p = "p<0.001" if d.p < 0.001 else f"p={fmt_num(d.p)}"
            row.append(f"{fmt_mean_ci(d.mean, d.half_width)}{star} ({p})")
        rows.append(row)
    return rows


def verdicts(df: pd.DataFrame, reference: str,
             metrics: Sequence[str] = PAIRED_METRICS) -> list[str]:  # fmt: skip
    """Per metric: which policy has the best mean, and whether the reference is beaten by a
    difference whose 95 % paired interval excludes 0."""
    ok = ok_rows(df)
    ref = ok[ok["policy"] == reference]
    out = []
    for m in metrics:
        better = METRICS[m].better
        means = ok.groupby("policy")[m].mean().dropna()
        if means.empty or not better:
            continue
        best = means.idxmin() if better == "lower" else means.idxmax()
        beats = []
        for policy in means.index:
            if policy == reference:
                continue
            d = paired_difference(by_seed(ok[ok["policy"] == policy], m), by_seed(ref, m))
            if d.significant and (d.mean < 0) == (better == "lower"):
                beats.append(policy)
        lead = f"{METRICS[m].label} ({better} is better): best mean {best} ({fmt_num(means[best])})"
        tail = (f"; better than {reference} beyond noise: {', '.join(beats)}" if beats
                else f"; no method beats {reference} beyond noise")  # fmt: skip
        out.append(lead + tail + ".")
    return out + fallback_notes(ok)


LEANS_ON_SAFETY = 50.0
"""Safety-module share [%] above which a policy's numbers are mostly ACC-LC's fallback."""


def fallback_notes(ok: pd.DataFrame) -> list[str]:
    """A warning per policy whose decisions the safety module changed more than
    ``LEANS_ON_SAFETY`` % of the time: its metrics then describe the fallback."""
    share = ok.groupby("policy")["sm_share"].mean().dropna()
    return [f"{p}: the safety module changed {share[p]:.0f} % of its decisions, so its numbers "
            "are mostly those of the ACC-LC fallback, not of the policy."
            for p in order_policies(share.index) if share[p] > LEANS_ON_SAFETY]  # fmt: skip


def lineage_rows(policies: Sequence[str], checkpoints: Path) -> list[list[str]]:
    """Header + one row per trained policy: transitions, updates, wall time and command."""
    rows = [["policy", "transitions", "updates", "wall time (min)", "training command"]]
    for p in policies:
        info = checkpoints / f"{p}.json"
        if not info.is_file():
            continue
        d = json.loads(info.read_text())
        cmd = d.get("study_command") or d.get("command", "")
        wall = d.get("wall_time_s") or d.get("wall_time") or float("nan")
        rows.append([p, str(d.get("env_steps", "")), str(d.get("updates", "")),
                     fmt_num(float(wall) / 60), cmd])  # fmt: skip
    return rows


def plot_learning_curves(policies: Sequence[str], checkpoints: Path, out: Path) -> Path | None:
    """Reward per decision and terminal events per AV trip over transitions of each policy's
    training (``<name>.csv``), running means over ``CURVE_WINDOW`` rows; None without curves."""
    curves = {p: checkpoints / f"{p}.csv" for p in policies}
    curves = {p: pd.read_csv(c) for p, c in curves.items() if c.is_file()}
    if not curves:
        return None
    fig, axes = new_figure(10, 3.8, ncols=2)
    for p, df in curves.items():
        x = df["env_steps"] / 1e3
        for ax, col in zip(axes, ("mean_reward_per_action", "terminal_rate")):
            y = pd.to_numeric(df[col], errors="coerce").rolling(CURVE_WINDOW, min_periods=1).mean()
            ax.plot(x, y, label=p, linewidth=1.6)
    axes[0].set_ylabel("reward per decision (scaled) [-]")
    axes[1].set_ylabel("terminal events per AV trip [-]")
    for ax in axes:
        ax.set_xlabel("transitions received [thousands]")
    axes[0].legend(fontsize=7)
    fig.suptitle(f"Learning curves (running mean over {CURVE_WINDOW} rows of 10k transitions)")
    return save_figure(fig, out)


def build_study_report(results_dir: Path, out_pdf: Path, study: str, reference: str,
                       checkpoints: Path, setup: str,
                       policies: Sequence[str] | None = None) -> Path:  # fmt: skip
    """Write the PDF of ``study`` from the records of ``policies`` (default: all) in
    ``results_dir``; returns its path."""
    df = load_results(results_dir)
    if policies is not None:
        df = df[df["policy"].isin(policies)]
    if df.empty:
        raise ValueError(f"no records in {str(results_dir)!r}: nothing to report")
    styles = make_styles()
    title = f"Mixed-traffic study: {study}"
    cond = {k: df[k].iloc[0] for k in ("scenario", "density", "penetration", "weather")}
    story: list[Any] = [para(title, styles["title"]), para(setup, styles["small"])]
    story.append(para("Findings", styles["h1"]))
    story += [Paragraph(t, styles["bullet"], bulletText="•") for t in verdicts(df, reference)]
    story.append(para("Results tables", styles["h1"]))
    story.append(
        para(f"{describe_condition(cond)}; means over seeds. {CI_METHODS}", styles["small"])
    )
    for table in (tbl.macro_table(df), tbl.micro_table(df),
                  tbl.metric_table(df, ("avg_r", "avg_it"),
                                   title="Reward and inference time")):  # fmt: skip
        story.append(para(table.attrs["title"], styles["h2"]))
        story.append(grid(frame_rows(tbl.format_table(table)), styles))
    # the shipped AUTO too, where it ran (trained longer: not a same-budget comparison)
    for ref in dict.fromkeys([reference, *(["auto"] if (df["policy"] == "auto").any() else [])]):
        story.append(para(f"Paired differences to {ref}", styles["h1"]))
        story.append(para(f"Each method minus {ref}, paired by seed (the seed fixes the demand "
                          "and the human drivers): mean ± 95 % t half-width, paired t-test p; * "
                          "where the interval excludes 0.", styles["small"]))  # fmt: skip
        story.append(grid(paired_rows(df, ref), styles))
    trained = [p for p in order_policies(df["policy"]) if (checkpoints / f"{p}.json").is_file()]
    fig = plot_learning_curves(
        trained, checkpoints, out_pdf.with_name(f"{out_pdf.stem}-curves.png")
    )
    if fig is not None:
        story += [para("Learning curves", styles["h1"]),
                  figure(fig, "Training curves of the study's methods (same budget, seed and "
                         "scenarios).", styles)]  # fmt: skip
    story.append(para("Training lineage", styles["h1"]))
    story.append(grid(lineage_rows(trained, checkpoints), styles))
    if (df["status"] != "ok").any():
        story += [
            Spacer(1, 6),
            para("Failed episodes", styles["h1"]),
            grid(failed_rows(df), styles),
        ]
    write_pdf(story, out_pdf, title)
    return out_pdf


__all__ = ["build_study_report", "paired_rows", "plot_learning_curves", "verdicts"]
