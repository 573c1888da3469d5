"""Rebuild a PDF report from a results folder alone (no SUMO, no torch).

python -m mixed_traffic.report RESULTS_DIR [--out reports/NAME.pdf] [--title TITLE]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path


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
        help="output PDF (default: reports/<RESULTS_DIR name>.pdf); figures are saved beside it",
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
    out = args.out or Path("reports") / f"{results_dir.resolve().name}.pdf"
    if out.suffix.lower() != ".pdf":
        parser.error(f"--out {str(out)!r} must end in .pdf")

    from analysis.report import build_report

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


if __name__ == "__main__":
    sys.exit(main())
