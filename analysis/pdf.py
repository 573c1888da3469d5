"""reportlab building blocks of the PDF report: page width, paragraph styles, tables whose
column widths follow their content, embedded figures, and the atomic write of the PDF.

Lengths are in PDF points (1 cm = 28.35 pt); the page is A4 with 1.5 cm margins.
"""

from __future__ import annotations

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
    Table,
    TableStyle,
)

PAGE_WIDTH = A4[0] - 3.0 * cm
"""Usable width of the page (1.5 cm margins)."""


def make_styles() -> dict[str, ParagraphStyle]:
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


def para(text: Any, style: ParagraphStyle) -> Paragraph:
    """A paragraph of plain (escaped) text."""
    return Paragraph(escape(str(text)), style)


def auto_widths(rows: Sequence[Sequence[Any]], total: float = PAGE_WIDTH) -> list[float]:
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


def grid(
    rows: Sequence[Sequence[Any]],
    styles: dict[str, ParagraphStyle],
    col_widths: Sequence[float] | None = None,
) -> Table:
    """A table with a bold header row, wrapping cells and a light grid.

    ``rows`` is the header row then the body rows (one value per column); ``col_widths`` are in
    points (default: :func:`auto_widths`).
    """
    col_widths = col_widths or auto_widths(rows)
    data = [[para(c, styles["head"]) for c in rows[0]]]
    data += [[para(c, styles["cell"]) for c in r] for r in rows[1:]]
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


def frame_rows(shown: pd.DataFrame) -> list[list[str]]:
    """Header + body rows of a formatted table."""
    return [list(shown.columns)] + shown.astype(str).to_numpy().tolist()


def figure(path: Path, caption: str, styles: dict[str, ParagraphStyle]) -> KeepTogether:
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
        [Image(str(path), width=width, height=height), para(caption, styles["small"])]
    )


def write_pdf(story: list[Any], out_pdf: Path, title: str) -> None:
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


__all__ = [
    "PAGE_WIDTH", "auto_widths", "figure", "frame_rows", "grid", "make_styles", "para", "write_pdf",
]  # fmt: skip
