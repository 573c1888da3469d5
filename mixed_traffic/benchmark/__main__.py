"""``python -m mixed_traffic.benchmark``: the benchmark table (see ``benchmark.table``)."""

import sys

from mixed_traffic.benchmark.table import main

sys.exit(main())
