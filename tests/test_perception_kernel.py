"""The perception stage's compiled kernels (``mixed_traffic.sensing.blockers_kernel``) against
their numpy references on real SUMO states, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic import compiled
from mixed_traffic.sensing import blockers, merges, neighbours

from .conftest import random_episode

needs_numba = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")

CASES = [("ring", 1 / 22, 80), ("straight", 0.5, 80), ("merge", 0.3, 100), ("urban", 0.3, 120)]


def _same_bits(out: tuple, ref: tuple) -> None:
    """Equal dtypes and bits (``np.array_equal`` alone takes -0.0 for 0.0)."""
    assert len(out) == len(ref)
    for k, (x, y) in enumerate(zip(out, ref)):
        assert x.dtype == y.dtype and x.shape == y.shape, k
        if x.dtype == np.float64:
            x, y = x.view(np.int64), y.view(np.int64)
        assert np.array_equal(x, y), k


def _both(monkeypatch, fn, found: list):
    """``fn`` run with the numpy stages and with the kernels on the same inputs, compared."""

    def both(*args, **kw):
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = fn(*args, **kw)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = fn(*args, **kw)
        _same_bits(out, ref)
        found.append(int((ref[0] >= 0).sum()))
        return out

    return both


@needs_numba
@pytest.mark.parametrize(("scenario", "penetration", "steps"), CASES)
def test_blockers_and_merges_kernels_equal_numpy(monkeypatch, scenario: str, penetration: float,
                                                 steps: int) -> None:  # fmt: skip
    """Every agent's blocker across its path and merge leader, with random actions (lane
    changes, junction turns, stops and crashes), bit for bit; with the lane leader's gap as
    the limit (as ``find_neighbours`` passes it) and without any limit."""
    found_b, found_m = [], []
    path_blockers = _both(monkeypatch, blockers.path_blockers, found_b)
    merge_leaders = _both(monkeypatch, merges.merge_leaders, found_m)

    def blockers_twice(snap, hdmap, rows, max_range, next_edge, limit, via):
        path_blockers(snap, hdmap, rows, max_range, next_edge, None, via)
        return path_blockers(snap, hdmap, rows, max_range, next_edge, limit, via)

    def merges_twice(snap, hdmap, rows, max_range, next_edge, via, lead_gap):
        merge_leaders(snap, hdmap, rows, max_range, next_edge, via, None)
        return merge_leaders(snap, hdmap, rows, max_range, next_edge, via, lead_gap)

    monkeypatch.setattr(neighbours, "path_blockers", blockers_twice)
    monkeypatch.setattr(neighbours, "merge_leaders", merges_twice)
    random_episode(steps, scenario=scenario, penetration=penetration)
    assert len(found_b) >= 2 * steps // 2 and len(found_m) == len(found_b), "the stages ran"
    if scenario == "urban":
        assert sum(found_b) > 0, "some blocker across a junction was found"
        assert sum(found_m) > 0, "some merge leader was found"
    if scenario == "merge":  # the ramp's junction: a vehicle crossing the path ahead
        assert sum(found_b) > 0, "some blocker was found"


@needs_numba
def test_blockers_kernel_warm_loads_the_specialisation_the_env_calls() -> None:
    """``warm()`` loads the specialisations a real step uses, so forked cells add none."""
    from mixed_traffic.sensing import blockers_kernel

    blockers_kernel.warm()
    random_episode(1, seed=0, policy="keep", scenario="urban", penetration=0.3)
    assert len(blockers_kernel.blockers.signatures) == 1
    assert len(blockers_kernel.merges.signatures) == 1
    assert len(blockers_kernel.take_nearer.signatures) == 1


@needs_numba
@pytest.mark.parametrize(("scenario", "penetration", "steps"), CASES)
def test_in_the_way_kernel_equals_numpy(monkeypatch, scenario: str, penetration: float,
                                        steps: int) -> None:  # fmt: skip
    """The choice among blocker, merge leader and straddler (``take_nearer``) and its in-place
    update of the lane leader, bit for bit, on the same inputs."""
    taken = []
    in_the_way = neighbours._in_the_way

    def both(snap, hdmap, rows, vehicle, distance, *args):
        v_ref, d_ref = vehicle.copy(), distance.copy()
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = in_the_way(snap, hdmap, rows, v_ref, d_ref, *args)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = in_the_way(snap, hdmap, rows, vehicle, distance, *args)
        _same_bits((*out, vehicle, distance), (*ref, v_ref, d_ref))
        taken.append(int(ref[0].sum()))
        return out

    monkeypatch.setattr(neighbours, "_in_the_way", both)
    random_episode(steps, scenario=scenario, penetration=penetration)
    assert len(taken) >= steps // 2, "the stage ran"
    if scenario in ("merge", "urban"):
        assert sum(taken) > 0, "some vehicle in the way replaced a lane leader"
