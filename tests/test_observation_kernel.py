"""The compiled observation frame (``sensing.observation_kernel``) against the numpy stages of
``ObservationBuilder`` on real SUMO states, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic import compiled
from mixed_traffic.config import SensorConfig
from mixed_traffic.sensing import observation, observation_kernel
from mixed_traffic.sensing.observation import ObservationBuilder

from .conftest import random_episode

needs_numba = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")

#: The frame's parts in the order ``ObservationBuilder._frame`` returns them.
PARTS = ("ego", "lanes", "vehicles", "lights", "limits", "signals", "give_way", "node_mask",
         "action_mask")  # fmt: skip
#: Distances beyond 1 (the detection range scaled up) and a long preview.
FAR = SensorConfig(range_factor=1.5, preview_range=600.0)


def _identical(out: tuple[np.ndarray, ...], ref: tuple[np.ndarray, ...]) -> None:
    """Equal dtypes, shapes and bytes (so -0.0 differs from 0.0 and NaN equals NaN)."""
    assert len(out) == len(ref) == len(PARTS)
    for name, x, y in zip(PARTS, out, ref):
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(np.ascontiguousarray(x).view(np.uint8),
                              np.ascontiguousarray(y).view(np.uint8)), name  # fmt: skip


@needs_numba
@pytest.mark.parametrize(
    ("scenario", "kw", "steps"),
    [("ring", {"penetration": 1 / 22}, 80),
     ("straight", {"penetration": 0.5, "density": 120.0}, 80),
     ("merge", {"penetration": 0.3}, 80),
     ("urban", {"penetration": 0.3}, 100),
     ("urban", {"penetration": 0.3, "weather": "fog"}, 60),
     ("urban-eval", {"penetration": 0.3, "sensors": FAR}, 60),
     ("merge", {"penetration": 0.3, "sensors": FAR}, 60)],
)  # fmt: skip
def test_observation_kernel_equals_numpy(monkeypatch, scenario: str, kw: dict,
                                         steps: int) -> None:  # fmt: skip
    """Every agent's frame (action mask with mandatory changes, route hops, waypoints past
    lane ends, limit preview, signals, the virtual end-of-lane vehicle, lights, masks), with
    random actions, in fog and with distances beyond 1 (``range_factor``), bit for bit. With
    ``FAR``, every next edge counts as short (no scenario has one under ``SHORT_EDGE``) and
    signals a lane further on are in range."""
    calls = []
    if kw.get("sensors") is FAR:
        monkeypatch.setattr(observation, "SHORT_EDGE", 1e4)
    compiled_frame = ObservationBuilder._frame_compiled

    def both(self, *args):
        ref = ObservationBuilder._frame(self, *args)  # the stage below the history: no state
        out = compiled_frame(self, *args)
        _identical(out, ref)
        calls.append(len(out[0]))
        return out

    monkeypatch.setattr(compiled, "ENABLED", True)
    monkeypatch.setattr(ObservationBuilder, "_frame_compiled", both)
    random_episode(steps, scenario=scenario, **kw)
    assert sum(calls) > steps, "the kernel ran for the agents"


@needs_numba
def test_observation_kernel_switch_off(monkeypatch) -> None:
    """``MIXED_TRAFFIC_KERNELS=numpy`` builds the frame with the numpy stages."""
    monkeypatch.setattr(compiled, "ENABLED", False)

    def fail(*args):
        raise AssertionError("the kernel ran")

    monkeypatch.setattr(ObservationBuilder, "_frame_compiled", fail)
    random_episode(1, seed=0, policy="keep", scenario="ring", penetration=1 / 22)


@needs_numba
def test_observation_warm_loads_the_kernel_the_env_calls(monkeypatch) -> None:
    """``warm()`` (the sweep's fork server calls it) loads the specialisation a real step uses,
    so forked cells add none."""
    monkeypatch.setattr(compiled, "ENABLED", True)
    observation_kernel.warm()
    random_episode(1, seed=0, policy="keep", scenario="ring", penetration=1 / 22)
    assert len(observation_kernel.features.signatures) == 1
