"""ACC-LC's compiled lane accelerations (agents/rules/acc_lc_kernel.py) against the numpy
reference on real SUMO states, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

import agents.rules.acc_lc as acc_lc
from agents.rules import acc_lc_longitudinal as lon
from mixed_traffic import compiled
from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.runner import run_episode

pytestmark = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")


@pytest.mark.parametrize(
    ("scenario", "policy", "weather"),
    [("ring", "acc-lc", "normal"), ("straight", "acc-lc-tuned", "normal"),
     ("merge", "acc-lc", "normal"), ("urban", "acc-lc", "fog"), ("urban", "auto", "normal")],
)  # fmt: skip
def test_lane_accels_kernel_equals_numpy(monkeypatch, scenario: str, policy: str,
                                         weather: str) -> None:  # fmt: skip
    """Every call of a whole episode (leaders in every lane column, mandatory changes with
    their end gap, lights, give-way lines, fog's unseen signals; AUTO's teacher too)."""
    seen = {"agents": 0, "leaders": 0, "bounded": 0}

    def both(f, c, calls, offset):
        ref = lon._lane_accels_reference(f, c, calls, offset)
        out = lon._lane_accels_compiled(f, c, calls, offset)
        for x, y in zip(ref, out):
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True)
        seen["agents"] += len(f["v"])
        seen["leaders"] += int(np.isfinite(f["h_dist"]).sum())
        seen["bounded"] += int(np.isfinite(f["light_dist"]).sum())
        return out

    monkeypatch.setattr(acc_lc, "lane_accels", both)
    cfg = EnvConfig(scenario=scenario, penetration=0.3, episode_length=25.0, weather=weather)
    assert run_episode(cfg, policy, 0.0)["status"] == "ok"
    assert seen["agents"] > 250 and seen["leaders"] > 0
    assert seen["bounded"] > 0 or scenario != "urban", "the urban run met lights"


def test_kernel_off_runs_the_reference(monkeypatch) -> None:
    """``MIXED_TRAFFIC_KERNELS=numpy`` runs the numpy stages."""
    called = []
    monkeypatch.setattr(lon, "_lane_accels_reference", lambda *a: called.append(a) or [])
    monkeypatch.setenv(compiled.SWITCH, "numpy")
    lon.lane_accels({"v": np.zeros(2)}, None, [], np.zeros(2))
    assert len(called) == 1


def test_warm_loads_the_kernels_a_plan_calls() -> None:
    """``warm()`` (the sweep's fork server calls it) loads the specialisations a real episode
    uses, so forked cells add none."""
    from agents.rules import acc_lc_kernel

    acc_lc.warm()
    cfg = EnvConfig(scenario="straight", penetration=0.3, episode_length=2.0)
    assert run_episode(cfg, "acc-lc", 0.0)["status"] == "ok"
    assert len(acc_lc_kernel.idm_inputs.signatures) == 1
    assert len(acc_lc_kernel.combine.signatures) == 1
