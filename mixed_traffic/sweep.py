"""Kept for the documented command ``python -m mixed_traffic.sweep``; the code lives in
:mod:`mixed_traffic.experiments.sweep`."""

import sys

from mixed_traffic.experiments.sweep import main

if __name__ == "__main__":
    sys.exit(main())
