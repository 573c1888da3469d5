"""Kept for the documented command ``python -m mixed_traffic.train``; the code lives in
:mod:`mixed_traffic.experiments.train`."""

import sys

from mixed_traffic.experiments.train import main

if __name__ == "__main__":
    sys.exit(main())
