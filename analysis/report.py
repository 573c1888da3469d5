"""PDF report of a results folder (reportlab, so the text stays extractable), and its CLI.

Contents: title; findings; configuration and provenance; the macroscopic, microscopic and
per-cell tables with safety counts beside them; the figures; the safety counts by policy; the
failed episodes with their errors. Built from result files alone (no SUMO, no torch).

python -m mixed_traffic.report RESULTS_DIR [--out FILE.pdf] [--title TITLE]
(``python -m analysis.report`` is the same command.)
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import pandas as pd
from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.units import cm
from reportlab.platypus import Paragraph, Spacer

from analysis import figures as figs
from analysis import findings as fnd
from analysis import tables as tbl
from analysis import traffic_figures as tf
from analysis.pdf import PAGE_WIDTH, figure, frame_rows, grid, make_styles, para, write_pdf
from analysis.results import load_results
from analysis.style import CI_METHODS, fmt_density, fmt_penetration
from mixed_traffic.schema import FD_DIR, METRICS, SMOOTHING

_ERROR_CHARS = 300


def _unique(series: pd.Series) -> str:
    """Distinct values of a column, comma separated (counts when more than one)."""
    counts = series.dropna().astype(str).value_counts()
    if counts.empty:
        return "n/a"
    if len(counts) == 1:
        return counts.index[0]
    return ", ".join(f"{v} ({n})" for v, n in sorted(counts.items()))


def provenance_rows(df: pd.DataFrame, results_dir: Path) -> list[list[str]]:
    """(item, value) rows describing where the results came from and what was run."""
    seeds = sorted({int(s) for s in df["seed"].dropna()})
    created = df["created"].dropna().astype(str)
    n_ok = int((df["status"] == "ok").sum())
    wall = df["wall_time"].dropna()
    return [
        ["item", "value"],
        ["results", str(results_dir)],
        ["episodes", f"{len(df)} ({n_ok} ok, {len(df) - n_ok} failed)"],
        ["policies", ", ".join(map(str, dict.fromkeys(df["policy"].dropna())))],
        ["scenarios", _unique(df["scenario"])],
        ["densities", ", ".join(fmt_density(v) for v in sorted(df["density"].dropna().unique()))],
        [
            "AV penetration",
            ", ".join(fmt_penetration(v) for v in sorted(df["penetration"].dropna().unique())),
        ],
        ["weather", _unique(df["weather"])],
        ["seeds", f"{len(seeds)}: {', '.join(map(str, seeds))}" if seeds else "n/a"],
        ["episode length", _unique(df["episode_length"].map(lambda v: f"{v:g} s"))],
        ["step length", _unique(df["step_length"].map(lambda v: f"{v:g} s"))],
        ["warm-up", _unique(df["warmup"].dropna().map(lambda v: f"{v:g} s"))],
        ["git revision", _unique(df["git_revision"])],
        ["code hash", _unique(df["code"])],
        ["SUMO version", _unique(df["sumo_version"])],
        ["records created", f"{created.min()} to {created.max()}" if len(created) else "n/a"],
        ["episode wall time", f"{wall.sum():.0f} s in total, {wall.mean():.1f} s mean" if len(wall) else "n/a"],
        ["report generated", _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")],
    ]  # fmt: skip


def failed_rows(df: pd.DataFrame) -> list[list[str]]:
    """(cell, error) rows of the failed episodes."""
    failed = df[df["status"] != "ok"]
    rows = [["policy", "scenario", "density", "AV share", "weather", "seed", "error"]]
    for _, r in failed.iterrows():
        err = str(r["error"] or "no error message")
        if len(err) > _ERROR_CHARS:
            err = err[:_ERROR_CHARS] + " ..."
        rows.append(
            [
                str(r["policy"]),
                str(r["scenario"]),
                fmt_density(r["density"]),
                fmt_penetration(r["penetration"]),
                str(r["weather"]),
                str(r["seed"]),
                err,
            ]
        )
    return rows


_FIGURE_CAPTIONS = {
    "penetration": "DT-TF (mean time of all vehicles to cross the 1 km measurement segment) against AV "
    "penetration per policy; dashed line: the 0 % all-human reference (paper Fig. 'Scalability "
    "Analysis' (d)).",
    "smoothing": "Traffic smoothing against AV penetration per policy: the speed spread of all "
    "vehicles in the measurement segment, the fleet's fuel per distance (SUMO's emission model), "
    "and the speed spread of the vehicles within 200 m ahead of and behind each AV in its lane "
    "(equal y axes; behind below ahead: the AVs leave a calmer wake). Dashed: the 0 % all-human "
    "reference (it has no AVs, so no values ahead or behind).",
    "density": "AvgDT-A, AvgAT-C and AvgDI-C against traffic density per policy "
    "(paper Fig. 'Scalability Analysis' (a)-(c)).",
    "micro": "Microscopic metrics per policy (paper table 'Microscopic Evaluation').",
    "weather": "PT-RT (share of AV time with TTC < 4 s) per weather preset "
    "(paper table 'Robustness under Different Weather Conditions').",
    "detection_range": "AvgR, AvgDT-A and PT-RT against the LiDAR and camera detection range "
    "as a share of the nominal 90 m / 60 m (paper tables 'Impact of Detection Range').",
}


def _table_block(table: pd.DataFrame, styles: dict[str, ParagraphStyle]) -> list[Any]:
    """Heading, formatted table and a note, or a note that there is nothing to show."""
    out: list[Any] = [para(table.attrs.get("title", ""), styles["h2"])]
    if table.empty:
        return out + [para("No successful episodes for this table.", styles["small"])]
    out.append(grid(frame_rows(tbl.format_table(table)), styles))
    return out


def _metric_legend(keys: Sequence[str], styles: dict[str, ParagraphStyle]) -> Paragraph:
    """One line per metric: label (unit): description; better direction."""
    parts = []
    for k in keys:
        m = METRICS[k]
        better = f"; {m.better} is better" if m.better else ""
        parts.append(
            f"<b>{escape(m.label)}</b> ({escape(m.unit)}): {escape(m.description)}{better}"
        )
    return Paragraph("<br/>".join(parts), styles["small"])


def build_report(
    results_dir: str | os.PathLike[str],
    out_pdf: str | os.PathLike[str],
    title: str | None = None,
    figures_dir: str | os.PathLike[str] | None = None,
) -> Path:
    """Write the PDF report of ``results_dir`` to ``out_pdf`` atomically; returns its path.

    Figures are saved as PNGs in ``figures_dir`` (default: beside the PDF, named
    ``<pdf stem>-<figure>.png``).

    Raises:
        FileNotFoundError: ``results_dir`` is missing or holds no records file.
        ValueError: the records files hold no records.
    """
    results_dir = Path(results_dir)
    out_pdf = Path(out_pdf)
    df = load_results(results_dir)
    if df.empty:
        raise ValueError(f"no records in {str(results_dir)!r}: nothing to report")
    out_pdf.parent.mkdir(parents=True, exist_ok=True)
    fig_dir = Path(figures_dir) if figures_dir is not None else out_pdf.parent
    made = figs.all_figures(df, fig_dir, name=f"{out_pdf.stem}-")

    styles = make_styles()
    title = title or f"Mixed-traffic results: {results_dir.name}"
    story: list[Any] = [para(title, styles["title"])]

    story.append(para("Findings", styles["h1"]))
    items = fnd.findings(df) or ["No successful episodes: no findings."]
    story += [Paragraph(escape(t), styles["bullet"], bulletText="•") for t in items]
    story.append(
        para(
            f"Means over seeds with {CI_METHODS} A difference "
            "between two policies, or between the lowest and the highest value of a sweep axis, is "
            "only called out when the 95 % t-interval of the mean per-seed difference excludes 0 "
            "(paired t-test on the seeds both groups ran; the seed fixes the demand and the human "
            "drivers) or, with fewer than two shared seeds, when Welch's t-test gives p < 0.05; "
            "otherwise it is reported as within noise. Each finding names its test, the difference "
            "(mean ± half-width) and its p-value.",
            styles["small"],
        )
    )

    story.append(para("Configuration and provenance", styles["h1"]))
    story.append(grid(provenance_rows(df, results_dir), styles, [4 * cm, PAGE_WIDTH - 4 * cm]))
    configs = df["config"].dropna().unique()
    if len(configs) == 1:
        cfg = json.loads(configs[0])
        flat = {k: v for k, v in cfg.items() if not isinstance(v, dict)}
        story.append(Spacer(1, 4))
        story.append(
            para("Environment config: " + json.dumps(flat, sort_keys=True), styles["small"])
        )

    story.append(para("Results tables", styles["h1"]))
    story.append(
        para(
            "Rows are policies; each table carries its safety counts (summed over its episodes; "
            "route completion weighted by AV trips).",
            styles["small"],
        )
    )
    for table in (tbl.macro_table(df), tbl.micro_table(df)):
        story += _table_block(table, styles)
    cells = tbl.cell_table(df)
    if len(cells) > 1:
        story += _table_block(cells, styles)
    smoothing = tbl.smoothing_table(df)
    if not smoothing.empty:
        story += _table_block(smoothing, styles)
    story.append(Spacer(1, 6))
    legend = ("dt_tf", *tbl.MACRO, *tbl.MICRO, "pt_rt", *SMOOTHING[1:])
    story.append(_metric_legend(legend, styles))

    if made:
        story.append(para("Figures", styles["h1"]))
        for key, path in made.items():
            story.append(
                figure(path, f"{_FIGURE_CAPTIONS[key]} Error bars: 95 % CI across seeds.", styles)
            )
            story.append(Spacer(1, 8))

    story += _traffic_sections(df, results_dir, fig_dir, out_pdf.stem, styles)

    story.append(para("Safety counts", styles["h1"]))
    safety = tbl.safety_table(df)
    if safety.empty:
        story.append(para("No successful episodes.", styles["small"]))
    else:
        story.append(grid(frame_rows(tbl.format_table(safety)), styles))
        tele = int(safety["teleports"].sum())
        if tele:
            story.append(para(f"Warning: {tele} SUMO teleports occurred.", styles["body"]))

    if (df["status"] != "ok").any():
        story.append(para("Failed episodes", styles["h1"]))
        widths = [1.5 * cm, 1.6 * cm, 1.8 * cm, 1.4 * cm, 1.4 * cm, 1.0 * cm]
        widths.append(PAGE_WIDTH - sum(widths))
        story.append(grid(failed_rows(df), styles, widths))

    write_pdf(story, out_pdf, title)
    return out_pdf


def _traffic_sections(df: pd.DataFrame, results_dir: Path, fig_dir: Path, stem: str,
                      styles: dict[str, ParagraphStyle]) -> list[Any]:  # fmt: skip
    """The "Fundamental diagram" and "Space-time diagram" sections."""
    humans = results_dir / FD_DIR
    extra = load_results(humans) if (humans / "records.jsonl").is_file() else df.iloc[:0]
    out: list[Any] = [para("Fundamental diagram", styles["h1"])]
    fd = tf.plot_fundamental_diagram(df, extra, fig_dir / f"{stem}-fundamental_diagram.png")
    out.append(
        figure(fd, "Flow against density per lane (Edie's definitions over the measurement "
               "segment after warm-up; one point per episode): all-human traffic over densities "
               "(extra one-seed cells and the sweep's 0 % cells) against the sweep's cells with "
               "100 % of each AV policy. Grey: the empirical capacity (1,800-2,300 veh/h/lane at "
               "18-35 veh/km/lane) and jam density (120-160 veh/km/lane).", styles)
        if fd else para("No episode measured a flow.", styles["small"])
    )  # fmt: skip
    out.append(para("Space-time diagram", styles["h1"]))
    st = tf.plot_space_time(tf.trace_files(results_dir), fig_dir / f"{stem}-space_time.png")
    out.append(
        figure(st, "Every vehicle's position along the measurement segment over time, coloured "
               "by its speed (every 0.5 s); stop-and-go waves are the red bands that run "
               "upstream.", styles)
        if st else para("No trajectories were recorded for this sweep.", styles["small"])
    )  # fmt: skip
    return out


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface."""
    parser = argparse.ArgumentParser(
        prog="python -m mixed_traffic.report",
        description=(
            "Build the PDF report (tables, figures with 95 % CIs, safety counts, findings, "
            "provenance) from the episode records in RESULTS_DIR (records.jsonl and/or "
            "records.parquet). Needs no SUMO."
        ),
    )
    parser.add_argument(
        "results_dir", metavar="RESULTS_DIR", type=Path, help="folder with records.jsonl"
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output PDF (default: RESULTS_DIR/<its name>.pdf); figures are saved beside it",
    )
    parser.add_argument(
        "--title", default=None, help="report title (default: from the folder name)"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status (2 for bad arguments or unusable results)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    results_dir: Path = args.results_dir
    if not results_dir.exists():
        parser.error(f"results directory {str(results_dir)!r} does not exist")
    out = args.out or results_dir / f"{results_dir.resolve().name}.pdf"
    if out.suffix.lower() != ".pdf":
        parser.error(f"--out {str(out)!r} must end in .pdf")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            path = build_report(results_dir, out, title=args.title)
        except (FileNotFoundError, ValueError) as exc:
            parser.error(str(exc))
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    print(f"report written to {path}")
    return 0


__all__ = ["build_parser", "build_report", "failed_rows", "main", "provenance_rows"]


if __name__ == "__main__":
    sys.exit(main())
