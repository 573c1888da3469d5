"""Kept for the documented command ``python -m mixed_traffic.study``; the code lives in
:mod:`mixed_traffic.experiments.study`."""

import sys

from mixed_traffic.experiments.study import main

if __name__ == "__main__":
    sys.exit(main())
