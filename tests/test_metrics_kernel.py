"""The metrics' compiled kernels (``mixed_traffic.env.metrics_kernel``) against the numpy
stages: the same SUMO episode with random actions, once per path, gives the same episode
metrics, flow diagnostics, trajectories and per-step infos, bit for bit."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from mixed_traffic import compiled
from mixed_traffic.env import metrics_kernel, parallel_env
from mixed_traffic.experiments.bench_env import bench_actions

needs_numba = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")


def _episode(scenario: str, penetration: float, steps: int, **kw: Any) -> dict[str, Any]:
    """Everything the metrics produce over ``steps`` steps of one seeded episode."""
    env = parallel_env(scenario=scenario, penetration=penetration, seed=5, trace=True, **kw)
    rng = np.random.default_rng(1)
    obs, _ = env.reset(seed=5)
    infos = []
    for _ in range(steps):
        if not env.agents:
            break
        obs, _, _, _, info = env.step(bench_actions(env, obs, env.action_space(None), rng))
        infos.append(info)
    flow = env._rec.flow  # per-vehicle figures: a last-bit slip in one vehicle's sums shows
    seen = list(flow._ids)
    out = {
        "travel_times": flow.vehicle_travel_times(),
        "delay_index": flow.delay_index(seen),
        "trip_delay_index": flow.trip_delay_index(seen),
        "free_flow_times": flow.free_flow_times(seen),
        "metrics": env.episode_metrics(),
        "flow": env.flow_diagnostics(),
        "traces": env.trajectories(),
        "infos": infos,
    }
    env.close()
    return out


def _same(a: Any, b: Any, where: str = "") -> None:
    """``a`` equals ``b``: floats bit for bit (any NaN equals any NaN), containers item by item."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), where
        for k in a:
            _same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, where
        if a.dtype.kind == "f":
            x, y = a.astype(np.float64).ravel(), b.astype(np.float64).ravel()
            nan = np.isnan(x)
            assert np.array_equal(nan, np.isnan(y)), where
            assert np.array_equal(x[~nan].view(np.int64), y[~nan].view(np.int64)), where
        else:
            assert np.array_equal(a, b), where
    elif isinstance(a, (float, np.floating)):
        assert isinstance(b, (float, np.floating)), where
        if math.isnan(a):
            assert math.isnan(b), where
        else:
            assert np.float64(a).view(np.int64) == np.float64(b).view(np.int64), (where, a, b)
    else:
        assert a == b, (where, a, b)


def _measured(metrics: dict[str, Any]) -> list[str]:
    """The metric keys with a finite value (the comparison has something to compare)."""
    return [k for k, v in metrics.items() if isinstance(v, float) and math.isfinite(v)]


@needs_numba
@pytest.mark.parametrize(
    ("scenario", "penetration", "steps", "kw"),
    [
        ("ring", 1 / 22, 300, {}),
        ("straight", 0.5, 950, {"density": 120.0}),
        ("merge", 0.3, 950, {}),
        ("urban", 0.3, 700, {}),
    ],
)
def test_metrics_kernel_equals_numpy(monkeypatch, scenario: str, penetration: float, steps: int,
                                     kw: dict) -> None:  # fmt: skip
    """Crossings (entries, exits, arrivals), delay indices, densities, speeds, the speed
    spread around the AVs and every step's infos, with random actions, bit for bit."""
    monkeypatch.setattr(compiled, "ENABLED", False)
    ref = _episode(scenario, penetration, steps, **kw)
    monkeypatch.setattr(compiled, "ENABLED", True)
    out = _episode(scenario, penetration, steps, **kw)
    _same(out, ref)
    # the compared values were measured, so a wrong kernel shows
    measured = _measured(ref["metrics"])
    for key in ("measured_density", "mean_speed", "speed_std_ahead", "speed_std_behind"):
        assert key in measured, (key, ref["metrics"])
    assert ref["flow"]["delay_index_mean"] is not None
    if scenario != "ring":  # vehicles crossed the segment (the ring has no end)
        assert ref["metrics"]["vehicles_crossed"] > 0 and ref["metrics"]["dt_tf"] is not None


@needs_numba
def test_metrics_warm_loads_the_kernels_the_env_calls() -> None:
    """``warm()`` (the sweep's fork server calls it) loads the specialisations a real episode
    uses, so forked cells add none."""
    metrics_kernel.warm()
    env = parallel_env(scenario="straight", density=120.0, penetration=0.5, seed=0)
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(60):
        obs, *_ = env.step(bench_actions(env, obs, env.action_space(None), rng, "keep"))
    env.close()
    for kernel in (metrics_kernel.flow_step, metrics_kernel.flow_gone,
                   metrics_kernel.ahead_behind_step, metrics_kernel.trips_add):  # fmt: skip
        assert len(kernel.signatures) == 1, kernel
