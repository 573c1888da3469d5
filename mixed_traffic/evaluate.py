"""Kept for the documented command ``python -m mixed_traffic.evaluate``; the code lives in
:mod:`mixed_traffic.experiments.evaluate`."""

import sys

from mixed_traffic.experiments.evaluate import main

if __name__ == "__main__":
    sys.exit(main())
