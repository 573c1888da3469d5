"""The env's per-step kernels (``mixed_traffic.env.step_kernel``) against their numpy
references on real SUMO episodes with random actions (which crash, leave the road and run
red lights), bit for bit: each compiled stage on the inputs of every call, and whole episodes
with ``MIXED_TRAFFIC_KERNELS=numpy`` against the kernels."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from mixed_traffic import compiled
from mixed_traffic.env import reward, step_kernel, termination

from .conftest import STEP_CASES as CASES
from .conftest import STEP_IDS as IDS
from .conftest import random_episode, same_bits

needs_numba = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")


@needs_numba
def test_event_reasons_kernel_equals_numpy(monkeypatch) -> None:
    """``termination.event_reasons`` (off-road, route deviation, red light, speed limit) on
    every call of every case, kernel against numpy; the cases judge several kinds of terminal
    events (else the test could not fail)."""
    stage, events = termination.event_reasons, Counter()

    def both(*args):
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = stage(*args)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = stage(*args)
        same_bits(out, ref)
        events["calls"] += len(out)
        events.update(r for r in out.tolist() if r)
        return out

    monkeypatch.setattr(termination, "event_reasons", both)
    for kw, steps in CASES:
        before = events["calls"]
        random_episode(steps, action_seed=3, **kw)
        assert events["calls"] - before > steps // 2, f"the stage ran for the agents ({kw})"
    assert {"off_road", "route_deviation"} <= set(events), events
    assert len(set(events) - {"calls"}) >= 3, events


@needs_numba
def test_reward_terms_kernel_equals_numpy(monkeypatch) -> None:
    """``reward.reward_terms`` (r1-r4, r7) on every call of every case, kernel against numpy;
    every term is non-zero somewhere (else the test could not fail)."""
    stage, hits = reward.reward_terms, Counter()

    def both(cfg, dt, **kw):
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = stage(cfg, dt, **kw)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = stage(cfg, dt, **kw)
        assert list(out) == list(ref)
        same_bits(out, ref)
        hits.update(k for k, v in out.items() if np.any(v != 0))
        return out

    monkeypatch.setattr(reward, "reward_terms", both)
    for kw, steps in CASES:
        random_episode(steps, action_seed=3, **kw)
    names = ("r1_ttc", "r1_lane", "r1_terminal", "r2_speed", "r2_lane_change", "r3_comfort",
             "r4_impact", "r7_accel")  # fmt: skip
    assert set(names) <= set(hits), hits


@needs_numba
@pytest.mark.parametrize(("kw", "steps"), CASES, ids=IDS)
def test_episode_kernels_equal_numpy(monkeypatch, kw: dict, steps: int) -> None:
    """The same seeded episode with every numpy stage and with every kernel: observations,
    rewards, every named reward term, terminations, truncations and infos at every step, and
    the episode metrics at the end; some reward terms are not zero."""
    monkeypatch.setattr(compiled, "ENABLED", False)
    ref = random_episode(steps, action_seed=3, end_metrics=True, **kw)
    monkeypatch.setattr(compiled, "ENABLED", True)
    out = random_episode(steps, action_seed=3, end_metrics=True, **kw)
    assert len(out) == len(ref) > 10
    same_bits(out, ref)
    terms = [t for s in out[:-1] for i in s[4].values() for t in i.get("reward_terms", {}).values()]
    assert any(terms), "some reward terms were not zero"


@needs_numba
def test_warm_loads_one_signature_per_kernel() -> None:
    """``warm`` loads the specialisation a real env step uses (dtypes, layouts, flags)."""
    step_kernel.warm()
    random_episode(40, seed=0, policy="keep", scenario="ring", penetration=1 / 22)
    for kernel in (step_kernel.event_codes, step_kernel.reward_terms):
        assert len(kernel.signatures) == 1, kernel
