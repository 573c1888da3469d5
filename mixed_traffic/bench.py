"""Kept for the documented command ``python -m mixed_traffic.bench``; the code lives in
:mod:`mixed_traffic.experiments.bench`."""

import sys

from mixed_traffic.experiments.bench import main

if __name__ == "__main__":
    sys.exit(main())
