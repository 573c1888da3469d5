"""The benchmark report: the table of tasks x controllers (``scores.json`` of
``python -m mixed_traffic.benchmark``), its figures, the PPO training curves, a PDF and the
table of docs/benchmark.md (no SUMO, no torch).

The score (signed) has a Student t-interval over seeds; the speed std as a share of all-human
traffic's (non-negative) the log-scale t-interval of :func:`analysis.results.nonneg_mean_ci`,
which stays >= 0 (:data:`CI_NOTE`). Figures: the score per task and controller with its 95 %
t-interval over seeds, the fleet speed std, and each PPO run's held-out evaluation over
training time.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from reportlab.platypus import Spacer

from analysis.figures import new_figure, save_figure
from analysis.pdf import figure, grid, make_styles, para, write_pdf
from analysis.style import order_policies, policy_palette
from mixed_traffic.provenance import atomic_write

#: The table of a markdown page (docs/benchmark.md) sits between these lines.
TABLE_BEGIN = "<!-- benchmark-table: begin (written by python -m mixed_traffic.benchmark) -->"
TABLE_END = "<!-- benchmark-table: end -->"
COLUMNS = (("mean_speed", "mean speed [m/s]"), ("speed_std", "speed std [m/s]"),
           ("fuel", "fuel [l/100 km]"), ("dt_tf", "DT-TF [s]"))  # fmt: skip
CI_NOTE = ("95 % intervals over seeds: the score, which can be negative, mean ± Student t "
           "half-width; speed std / all human, a ratio >= 0, mean [low, high] of the log-scale "
           "(delta-method) t-interval mean·exp(±t·se/mean), which stays >= 0.")  # fmt: skip
"""The table's note on its intervals."""


def _fmt(value: Any, digits: int = 2) -> str:
    return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"  # fmt: skip


def _ci(mean: float, half: float) -> str:
    return f"{_fmt(mean)} ± {_fmt(half)}"


def _interval(mean: float, lo: float, hi: float) -> str:
    return f"{_fmt(mean)} [{_fmt(lo)}, {_fmt(hi)}]"


def table_rows(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    """Header + one row per task and controller."""
    head = ["task", "controller", "score [95 % CI]", *(c[1] for c in COLUMNS),
            "speed std / all human [95 % CI]", "terminal events"]  # fmt: skip
    body = [[r["task"], r["policy"], _ci(r["score"], r["score_half_width"]),
             *(_fmt(r[c]) for c, _ in COLUMNS),
             _interval(r["std_ratio"], r["std_ratio_lo"], r["std_ratio_hi"]),
             str(r["terminal_events"])] for r in rows]  # fmt: skip
    return [head, *body]


def markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The table as Markdown."""
    table = table_rows(rows)
    lines = ["| " + " | ".join(table[0]) + " |", "|" + "---|" * len(table[0])]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in table[1:]])


def plot_scores(rows: Sequence[dict[str, Any]], out: Path) -> Path:
    """Score and speed std per task (groups) and controller (bars), score with its CI."""
    df = pd.DataFrame(rows)
    tasks = list(dict.fromkeys(df["task"]))
    policies = order_policies(df["policy"])
    palette = policy_palette(policies)
    fig, axes = new_figure(11, 4.2, ncols=2)
    width = 0.8 / len(policies)
    for ax, (col, err, label) in zip(axes, (("score", "score_half_width", "score [-] (0 = all "
                                             "human, 1 = reference)"),
                                            ("speed_std", None, "fleet speed std [m/s]"))):  # fmt: skip
        for i, p in enumerate(policies):
            sub = df[df["policy"] == p].set_index("task").reindex(tasks)
            xs = np.arange(len(tasks)) + (i - (len(policies) - 1) / 2) * width
            yerr = np.nan_to_num(sub[err].to_numpy(float)) if err else None
            ax.bar(xs, sub[col].to_numpy(float), width * 0.95, yerr=yerr, capsize=2,
                   color=palette[p], label=p)  # fmt: skip
        ax.set_xticks(range(len(tasks)), tasks)
        ax.set_xlabel("task")
        ax.set_ylabel(label)
    axes[0].axhline(0, color="black", lw=0.6)
    axes[0].axhline(1, color="black", lw=0.6, ls=":")
    axes[1].legend(fontsize=7)
    return save_figure(fig, out)


def plot_training(curves: dict[str, pd.DataFrame], out: Path) -> Path | None:
    """Each PPO run's validation speed std and mean speed (ratios to all human, the legs that
    were validated; runs from before validation are left out) over training hours; ``None``
    without such runs."""
    curves = {k: df.dropna(subset=["val_std_ratio"]) for k, df in curves.items()
              if "val_std_ratio" in df}  # fmt: skip
    if not curves:
        return None
    fig, axes = new_figure(11, 3.8, ncols=2)
    for name, df in curves.items():
        hours = df["train_seconds"] / 3600
        axes[0].plot(hours, df["val_std_ratio"], marker=".", label=name)
        axes[1].plot(hours, df["val_speed_ratio"], marker=".", label=name)
    axes[0].axhline(0.5, color="black", lw=0.8, ls="--", label="half the all-human std")
    axes[0].set_ylabel("speed std / all-human std [-]")
    axes[1].axhline(1.0, color="black", lw=0.6, ls=":")
    axes[1].set_ylabel("mean speed / all-human [-]")
    for ax in axes:
        ax.set_xlabel("training time [h] (one core)")
    axes[0].legend(fontsize=7)
    return save_figure(fig, out)


def read_curves(folders: Sequence[Path]) -> dict[str, pd.DataFrame]:
    """``curves.csv`` of each PPO run folder that has one, by folder name."""
    return {f.name: pd.read_csv(f / "curves.csv") for f in folders if (f / "curves.csv").is_file()}


def update_table(page: Path, table: str) -> None:
    """Replace the text between the markdown ``page``'s markers by ``table``; ValueError
    naming the page when it has none."""
    text = page.read_text()
    pattern = re.compile(re.escape(TABLE_BEGIN) + ".*?" + re.escape(TABLE_END), re.S)
    if not pattern.search(text):
        raise ValueError(f"{page} has no table markers ({TABLE_BEGIN} ... {TABLE_END})")
    new = pattern.sub(lambda _: f"{TABLE_BEGIN}\n{table}\n{TABLE_END}", text)
    atomic_write(page, lambda f: f.write(new.encode()))


def build(rows: Sequence[dict[str, Any]], runs: Sequence[Path], out_pdf: Path,
          notes: Sequence[str] = ()) -> Path:  # fmt: skip
    """Write the PDF (and its PNGs beside it) atomically; its path."""
    out_pdf.parent.mkdir(parents=True, exist_ok=True)
    styles = make_styles()
    story: list[Any] = [para("mixed_traffic benchmark", styles["title"])]
    story += [para(n, styles["body"]) for n in notes]
    story += [Spacer(1, 4), grid(table_rows(rows), styles), para(CI_NOTE, styles["small"]),
              Spacer(1, 6)]  # fmt: skip
    png = plot_scores(rows, out_pdf.with_name(f"{out_pdf.stem}-scores.png"))
    story.append(figure(png, "Score (bars: mean over seeds, whiskers: 95 % t-interval) and fleet "
                        "speed std of each controller on each task's held-out configs.", styles))  # fmt: skip
    curves = read_curves(runs)
    png = plot_training(curves, out_pdf.with_name(f"{out_pdf.stem}-ppo.png"))
    if png is not None:
        story.append(figure(png, "PPO (Stable-Baselines3) runs, one line per run folder (task "
                            "and training seed; a run started from another's weights goes on from "
                            "its time): greedy evaluation after each leg on the task's held-out "
                            "configs (seed 1000), as ratios to all-human traffic on the same seed.",
                            styles))  # fmt: skip
    write_pdf(story, out_pdf, "mixed_traffic benchmark")
    return out_pdf
