"""PDF report of a results folder (reportlab, so the text stays extractable).

Contents: title; findings; configuration and provenance; the macroscopic, microscopic and
per-cell tables with safety counts beside them; the figures; the safety counts by policy; the
failed episodes with their errors. Built from result files alone (no SUMO, no torch).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import pandas as pd
from reportlab.lib import colors
from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import ParagraphStyle, getSampleStyleSheet
from reportlab.lib.units import cm
from reportlab.pdfbase.pdfmetrics import stringWidth
from reportlab.platypus import (
    Image,
    KeepTogether,
    Paragraph,
    SimpleDocTemplate,
    Spacer,
    Table,
    TableStyle,
)

from analysis import figures as figs
from analysis import findings as fnd
from analysis import tables as tbl
from analysis.results import load_results
from analysis.style import fmt_density, fmt_penetration
from mixed_traffic.schema import METRICS

PAGE_WIDTH = A4[0] - 3.0 * cm
"""Usable width of the page (1.5 cm margins)."""
_ERROR_CHARS = 300


def _styles() -> dict[str, ParagraphStyle]:
    """Paragraph styles of the report."""
    base = getSampleStyleSheet()
    return {
        "title": base["Title"],
        "h1": base["Heading2"],
        "h2": base["Heading4"],
        "body": base["BodyText"],
        "small": ParagraphStyle("small", parent=base["BodyText"], fontSize=8, leading=10),
        "cell": ParagraphStyle("cell", parent=base["BodyText"], fontSize=7, leading=8.5),
        "head": ParagraphStyle(
            "head", parent=base["BodyText"], fontSize=7, leading=8.5, fontName="Helvetica-Bold"
        ),
        "bullet": ParagraphStyle("bullet", parent=base["BodyText"], leftIndent=10, bulletIndent=0),
    }


def _p(text: Any, style: ParagraphStyle) -> Paragraph:
    """A paragraph of plain (escaped) text."""
    return Paragraph(escape(str(text)), style)


def _auto_widths(rows: Sequence[Sequence[Any]], total: float = PAGE_WIDTH) -> list[float]:
    """Column widths from the content: natural widths if they fit, else shrunk towards the
    longest word of each column (headers may wrap at spaces, values rarely)."""
    pad = 7.0

    def width(text: str, bold: bool = False) -> float:
        return stringWidth(text, "Helvetica-Bold" if bold else "Helvetica", 7) + pad

    natural, minimum = [], []
    for j in range(len(rows[0])):
        head = str(rows[0][j])
        cells = [str(r[j]) for r in rows[1:]]
        head_word = max((width(w, True) for w in head.split()), default=pad)
        natural.append(max([head_word, *(width(c) for c in cells)]))
        words = [w for c in cells for w in c.split()]
        minimum.append(max([head_word, *(width(w) for w in words)]))
    if sum(natural) <= total:
        return natural
    slack = [n - m for n, m in zip(natural, minimum)]
    excess = sum(natural) - total
    if sum(slack) <= 0 or excess >= sum(slack):
        scale = total / sum(minimum)
        return [m * scale for m in minimum]
    return [n - s * excess / sum(slack) for n, s in zip(natural, slack)]


def _grid(
    rows: Sequence[Sequence[Any]], styles: dict[str, ParagraphStyle], col_widths=None
) -> Table:
    """A table with a bold header row, wrapping cells and a light grid."""
    col_widths = col_widths or _auto_widths(rows)
    data = [[_p(c, styles["head"]) for c in rows[0]]]
    data += [[_p(c, styles["cell"]) for c in r] for r in rows[1:]]
    table = Table(data, colWidths=col_widths, repeatRows=1, hAlign="LEFT")
    table.setStyle(
        TableStyle(
            [
                ("GRID", (0, 0), (-1, -1), 0.3, colors.grey),
                ("BACKGROUND", (0, 0), (-1, 0), colors.HexColor("#e8eef7")),
                ("VALIGN", (0, 0), (-1, -1), "TOP"),
                ("LEFTPADDING", (0, 0), (-1, -1), 3),
                ("RIGHTPADDING", (0, 0), (-1, -1), 3),
            ]
        )
    )
    return table


def _frame_rows(shown: pd.DataFrame) -> list[list[str]]:
    """Header + body rows of a formatted table."""
    return [list(shown.columns)] + shown.astype(str).to_numpy().tolist()


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


def _figure(path: Path, caption: str, styles: dict[str, ParagraphStyle]) -> KeepTogether:
    """An embedded PNG scaled to the page width, with its caption."""
    from PIL import Image as PILImage

    with PILImage.open(path) as im:
        w, h = im.size
    width = PAGE_WIDTH
    height = width * h / w
    max_h = 11 * cm
    if height > max_h:
        width, height = width * max_h / height, max_h
    return KeepTogether(
        [Image(str(path), width=width, height=height), _p(caption, styles["small"])]
    )


_FIGURE_CAPTIONS = {
    "penetration": "DT-TF (mean time of all vehicles to cross the 1 km measurement segment) against AV "
    "penetration per policy; dashed line: the 0 % all-IDM reference (paper Fig. 'Scalability "
    "Analysis' (d)).",
    "density": "AvgDT-A, AvgAT-C and AvgDI-C against traffic density per policy "
    "(paper Fig. 'Scalability Analysis' (a)-(c)).",
    "micro": "Microscopic metrics per policy (paper table 'Microscopic Evaluation').",
    "weather": "PT-RT (share of AV time with TTC < 4 s) per weather preset "
    "(paper table 'Robustness under Different Weather Conditions').",
}


def _table_block(table: pd.DataFrame, styles: dict[str, ParagraphStyle]) -> list[Any]:
    """Heading, formatted table and a note, or a note that there is nothing to show."""
    out: list[Any] = [_p(table.attrs.get("title", ""), styles["h2"])]
    if table.empty:
        return out + [_p("No successful episodes for this table.", styles["small"])]
    out.append(_grid(_frame_rows(tbl.format_table(table)), styles))
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

    styles = _styles()
    title = title or f"Mixed-traffic results: {results_dir.name}"
    story: list[Any] = [_p(title, styles["title"])]

    story.append(_p("Findings", styles["h1"]))
    items = fnd.findings(df) or ["No successful episodes: no findings."]
    story += [Paragraph(escape(t), styles["bullet"], bulletText="•") for t in items]
    story.append(
        _p(
            "Means over seeds with 95 % t confidence intervals (mean ± half-width); differences are "
            "only called out when the intervals do not overlap.",
            styles["small"],
        )
    )

    story.append(_p("Configuration and provenance", styles["h1"]))
    story.append(_grid(provenance_rows(df, results_dir), styles, [4 * cm, PAGE_WIDTH - 4 * cm]))
    configs = df["config"].dropna().unique()
    if len(configs) == 1:
        cfg = json.loads(configs[0])
        flat = {k: v for k, v in cfg.items() if not isinstance(v, dict)}
        story.append(Spacer(1, 4))
        story.append(_p("Environment config: " + json.dumps(flat, sort_keys=True), styles["small"]))

    story.append(_p("Results tables", styles["h1"]))
    story.append(
        _p(
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
    story.append(Spacer(1, 6))
    story.append(_metric_legend(("dt_tf", *tbl.MACRO, *tbl.MICRO, "pt_rt"), styles))

    if made:
        story.append(_p("Figures", styles["h1"]))
        for key, path in made.items():
            story.append(
                _figure(
                    path, _FIGURE_CAPTIONS[key] + " Error bars: 95 % t-CI across seeds.", styles
                )
            )
            story.append(Spacer(1, 8))

    story.append(_p("Safety counts", styles["h1"]))
    safety = tbl.safety_table(df)
    if safety.empty:
        story.append(_p("No successful episodes.", styles["small"]))
    else:
        story.append(_grid(_frame_rows(tbl.format_table(safety)), styles))
        tele = int(safety["teleports"].sum())
        if tele:
            story.append(_p(f"Warning: {tele} SUMO teleports occurred.", styles["body"]))

    if (df["status"] != "ok").any():
        story.append(_p("Failed episodes", styles["h1"]))
        widths = [1.5 * cm, 1.6 * cm, 1.8 * cm, 1.4 * cm, 1.4 * cm, 1.0 * cm]
        widths.append(PAGE_WIDTH - sum(widths))
        story.append(_grid(failed_rows(df), styles, widths))

    _write_pdf(story, out_pdf, title)
    return out_pdf


def _write_pdf(story: list[Any], out_pdf: Path, title: str) -> None:
    """Render ``story`` to a temporary file beside ``out_pdf`` and rename it into place."""
    tmp = out_pdf.with_name(f".{out_pdf.stem}.{os.getpid()}.tmp")
    try:
        doc = SimpleDocTemplate(
            str(tmp),
            pagesize=A4,
            leftMargin=1.5 * cm,
            rightMargin=1.5 * cm,
            topMargin=1.5 * cm,
            bottomMargin=1.5 * cm,
            title=title,
            author="mixed_traffic analysis",
        )
        doc.build(story, onLaterPages=_page_number, onFirstPage=_page_number)
        os.replace(tmp, out_pdf)
    finally:
        tmp.unlink(missing_ok=True)


def _page_number(canvas: Any, doc: Any) -> None:
    """Footer with the page number."""
    canvas.saveState()
    canvas.setFont("Helvetica", 7)
    canvas.drawRightString(A4[0] - 1.5 * cm, 0.8 * cm, f"page {doc.page}")
    canvas.restoreState()


__all__ = ["build_report", "failed_rows", "provenance_rows"]
