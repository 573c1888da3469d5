"""Kept for the documented command ``python -m mixed_traffic.scenario --list``; scenarios live
in :mod:`mixed_traffic.world`."""

import sys

from mixed_traffic.experiments.scenarios import main

if __name__ == "__main__":
    sys.exit(main())
