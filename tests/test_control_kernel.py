"""The controller's kernel (``mixed_traffic.env.control_kernel``) against its numpy reference
on real SUMO episodes with random actions (steering, lane changes, braking), bit for bit:
``BicycleController.compute`` on the inputs and state of every call (whole episodes with every
kernel against every numpy stage: tests/test_step_kernel.py)."""

from __future__ import annotations

import copy
from collections import Counter

import numpy as np
import pytest

from mixed_traffic import compiled
from mixed_traffic.env import action, control, control_kernel, space_time, truth
from mixed_traffic.env import parallel as env_parallel

from .conftest import STEP_CASES as CASES
from .conftest import random_episode, same_bits

needs_numba = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")


def _state(ctl: control.BicycleController) -> tuple[np.ndarray, ...]:
    return ctl.v.copy(), ctl.psi.copy(), ctl.body_offset.copy(), ctl.length.copy()


def _set_state(ctl: control.BicycleController, state: tuple[np.ndarray, ...]) -> None:
    ctl.v, ctl.psi, ctl.body_offset, ctl.length = (x.copy() for x in state)


@needs_numba
def test_compute_kernel_equals_numpy(monkeypatch) -> None:
    """``BicycleController.compute`` (the bicycle model's Frenet step, the body offset and the
    state it writes back) on every call of every case, kernel against numpy from the same
    state; the course clip, braking to a stop and curved lanes happen (else the test could
    not fail)."""
    stage, seen = control.BicycleController.compute, Counter()

    def both(self, ids, steer, accel, lane, lane_pos, lateral):
        before = _state(self)
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = stage(self, ids, steer, accel, lane, lane_pos, lateral)
        after = _state(self)
        _set_state(self, before)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = stage(self, ids, steer, accel, lane, lane_pos, lateral)
        same_bits(vars(out), vars(ref))
        same_bits(_state(self), after)
        seen["calls"] += len(ids)
        seen["clipped"] += int(np.sum(np.abs(out.course) >= control.MAX_COURSE))
        seen["stopped"] += int(np.sum(self.v[self.rows(ids)] == 0.0))
        seen["curved"] += int(np.sum(self.curvature(lane, lane_pos) != 0.0))
        seen["moved_left"] += int(np.sum(out.lateral_move > 0.01))
        seen["moved_right"] += int(np.sum(out.lateral_move < -0.01))
        return out

    monkeypatch.setattr(control.BicycleController, "compute", both)
    for kw, steps in CASES:
        before = seen["calls"]
        random_episode(steps, action_seed=3, **kw)
        assert seen["calls"] - before > steps // 2, f"the stage ran for the agents ({kw})"
    assert all(
        seen[k] > 0 for k in ("clipped", "stopped", "curved", "moved_left", "moved_right")
    ), seen


@needs_numba
def test_action_kernels_equal_numpy(monkeypatch) -> None:
    """``action.allowed_decisions`` and ``action.to_physical`` on every call of every case,
    kernel against numpy; forbidden decisions, throttle, braking and steering both ways
    happen (else the test could not fail)."""
    allowed, physical, seen = action.allowed_decisions, action.to_physical, Counter()

    def both_allowed(decision, mask):
        # the random actions respect the masks: the other decisions, too, on the same masks
        for shift in (1, 2, 0):
            monkeypatch.setattr(compiled, "ENABLED", False)
            ref = allowed((decision + shift) % 3, mask)
            monkeypatch.setattr(compiled, "ENABLED", True)
            out = allowed((decision + shift) % 3, mask)
            same_bits(out, ref)
            seen["replaced"] += int(out[1].sum())
            seen["replaced_not_follow"] += int(np.sum(out[1] & (out[0] != 1)))
        seen["not_follow"] += int(np.sum(out[0] != 1))
        return out

    def both_physical(decision, params, vehicle):
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = physical(decision, params, vehicle)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = physical(decision, params, vehicle)
        same_bits(out, ref)
        seen["calls"] += len(decision)
        seen["left"] += int(np.sum(out[0] > 0))
        seen["right"] += int(np.sum(out[0] < 0))
        seen["throttle"] += int(np.sum(out[1] > 0))
        seen["brake"] += int(np.sum(out[1] < 0))
        return out

    monkeypatch.setattr(env_parallel, "allowed_decisions", both_allowed)
    monkeypatch.setattr(env_parallel, "to_physical", both_physical)
    for kw, steps in CASES:
        before = seen["calls"]
        random_episode(steps, action_seed=3, **kw)
        assert seen["calls"] - before > steps // 2, f"the stages ran for the agents ({kw})"
    assert all(seen[k] > 0 for k in ("replaced", "replaced_not_follow", "not_follow", "left", "right", "throttle",
                                     "brake")), seen  # fmt: skip


@needs_numba
def test_front_view_kernel_equals_numpy(monkeypatch) -> None:
    """``truth.FrontView`` (the reward's, the AV metrics' and the step memory's) on every
    call of every case, kernel against numpy; agents with and without a front vehicle,
    overlapping ones (gap < 0) and closing ones happen (else the test could not fail)."""
    init, seen = truth.FrontView.__init__, Counter()
    names = ("exists", "distance", "length", "closing", "gap")

    def both(self, snap, frame, k, r):
        monkeypatch.setattr(compiled, "ENABLED", False)
        init(self, snap, frame, k, r)
        ref = {n: getattr(self, n) for n in names}
        monkeypatch.setattr(compiled, "ENABLED", True)
        init(self, snap, frame, k, r)
        same_bits({n: getattr(self, n) for n in names}, ref)
        seen["calls"] += len(k)
        seen["front"] += int(self.exists.sum())
        seen["no_front"] += int((~self.exists).sum())
        seen["overlap"] += int(np.sum(self.gap < 0))
        seen["closing"] += int(np.sum(self.exists & (self.closing > 0)))

    monkeypatch.setattr(truth.FrontView, "__init__", both)
    for kw, steps in CASES:
        before = seen["calls"]
        random_episode(steps, action_seed=3, **kw)
        assert seen["calls"] - before > steps, f"the stage ran for the agents ({kw})"
    assert all(seen[k] > 0 for k in ("front", "no_front", "overlap", "closing")), seen


@needs_numba
def test_edie_add_kernel_equals_numpy(monkeypatch) -> None:
    """``space_time.SpaceTimeField.add`` on every call of every case, kernel against numpy
    from the same field (a deep copy): the grid, moments and traces after it; vehicles
    outside the segment and several vehicles in one cell happen (else the test could not
    fail)."""
    add, seen = space_time.SpaceTimeField.add, Counter()

    def both(self, t, s, v, copy_of=None):
        ref = copy.deepcopy(self)
        monkeypatch.setattr(compiled, "ENABLED", False)
        add(ref, t, s, v, copy_of)
        monkeypatch.setattr(compiled, "ENABLED", True)
        add(self, t, s, v, copy_of)
        same_bits(vars(self), vars(ref))
        if self._steps:
            inside = s[~np.isnan(s)]
            seen["calls"] += 1
            seen["outside"] += int(np.isnan(s).sum())
            cells = (inside // space_time.DX).astype(np.int64)
            seen["shared_cell"] += len(cells) - len(np.unique(cells))

    monkeypatch.setattr(space_time.SpaceTimeField, "add", both)
    for kw, steps in CASES:
        before = seen["calls"]
        random_episode(steps, action_seed=3, **kw)
        assert seen["calls"] - before > steps // 2, f"the stage ran ({kw})"
    assert seen["outside"] > 0 and seen["shared_cell"] > 0, seen


@needs_numba
def test_warm_loads_one_signature_per_kernel() -> None:
    """``warm`` loads the specialisation a real env step uses (dtypes, layouts, flags)."""
    control_kernel.warm()
    random_episode(40, seed=0, policy="keep", scenario="ring", penetration=1 / 22)
    kernels = (control_kernel.frenet_compute, control_kernel.allowed, control_kernel.physical,
               control_kernel.front_view, control_kernel.edie_add)  # fmt: skip
    for kernel in kernels:
        assert len(kernel.signatures) == 1, kernel


@needs_numba
def test_rollout_kernel_equals_numpy(monkeypatch) -> None:
    """The safety module's predicted offsets (``control.bicycle_rollout``) on every call of
    AUTO episodes, kernel against the step loop, and on random states that clip the course and
    brake to a stop (pure math)."""
    import agents.rules.safety as safety
    from mixed_traffic.config import EnvConfig
    from mixed_traffic.experiments.runner import run_episode

    seen = Counter()

    def both(v, psi, d, steer, accel, kappa, wheelbase, dt, steps):
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = control.bicycle_rollout(v, psi, d, steer, accel, kappa, wheelbase, dt, steps)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = control.bicycle_rollout(v, psi, d, steer, accel, kappa, wheelbase, dt, steps)
        same_bits(out, ref)
        seen["calls"] += len(v)
        seen["steered"] += int(np.sum(np.abs(steer) > 0.01))
        return out

    monkeypatch.setattr(safety, "bicycle_rollout", both)
    for scenario in ("urban", "merge"):
        cfg = EnvConfig(scenario=scenario, penetration=0.3, episode_length=15.0)
        assert run_episode(cfg, "auto", 0.0)["status"] == "ok"
    assert seen["calls"] > 500 and seen["steered"] > 0
    rng = np.random.default_rng(0)
    n = 2000
    v, psi, d = rng.uniform(0, 30, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-3, 3, n)
    steer, accel, kappa = rng.uniform(-0.6, 0.6, n), rng.uniform(-9, 3, n), rng.normal(0, 0.05, n)
    both(v, psi, d, steer, accel, kappa, 2.7, 0.1, 10)
    clipped = np.abs(psi + np.arctan(0.5 * np.tan(steer))) > control.MAX_COURSE
    assert clipped.any() and (v + 10 * 0.1 * accel < 0).any()
