"""Golden records: five reference episodes (AUTO on straight and merge, the tuned rule at 100 %,
FollowerStopper on the ring, ACC-LC on urban; 40 s each) must keep their metrics bit for bit
across revisions, unless a change means to move them (then say so and regenerate the file with
the code of the change: ``tests/golden/records.json``). Written by the code before batched
worlds (issue 60), so it also checks that one copy runs exactly as an env without copies."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.runner import run_episode

pytestmark = pytest.mark.slow

GOLDEN = json.loads((Path(__file__).parent / "golden" / "records.json").read_text())
SKIP = {"avg_it"}  # wall-clock time


def _same(a: object, b: object) -> bool:
    """Equal values, NaN equal to NaN, floats bit for bit."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(map(_same, a, b))
    return a == b


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_reference_episodes_keep_their_records(name: str) -> None:
    case = GOLDEN[name]
    record = run_episode(EnvConfig(seed=3, episode_length=40.0, **case["config"]), case["policy"],
                         10.0)  # fmt: skip
    for part in ("metrics", "diagnostics"):
        for key, want in case[part].items():
            if key not in SKIP:
                got = record[part].get(key)
                assert _same(got, want), f"{name}: {part}.{key} = {got!r}, golden {want!r}"
