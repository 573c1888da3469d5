"""Kept for the documented command ``python -m mixed_traffic.report RESULTS_DIR [--out X.pdf]
[--title T]``; the report and its CLI live in :mod:`analysis.report` (no SUMO, no torch)."""

import sys

from analysis.report import main

if __name__ == "__main__":
    sys.exit(main())
