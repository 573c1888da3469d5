"""Kept for the documented command ``python -m mixed_traffic.compare``; the code lives in
:mod:`mixed_traffic.experiments.compare`."""

import sys

from mixed_traffic.experiments.compare import main

if __name__ == "__main__":
    sys.exit(main())
