"""ACC-LC's compiled lane accelerations (agents/rules/acc_lc_kernel.py) and observation decoding
(agents/rules/acc_lc_features_kernel.py) against the numpy references on real SUMO states, bit
for bit."""

from __future__ import annotations

import numpy as np
import pytest

import agents.rules.acc_lc as acc_lc
from agents.rules import acc_lc_features as feat
from agents.rules import acc_lc_longitudinal as lon
from agents.rules import rss as acc_lc_rss
from agents.rules.acc_lc_config import AccLcConfig
from mixed_traffic import compiled
from mixed_traffic.config import EnvConfig
from mixed_traffic.env.api import observation_space
from mixed_traffic.experiments.runner import run_episode

from .conftest import same_bits

pytestmark = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")


@pytest.mark.parametrize(
    ("scenario", "policy", "weather"),
    [("ring", "acc-lc", "normal"), ("straight", "acc-lc-tuned", "normal"),
     ("merge", "acc-lc", "normal"), ("urban", "acc-lc", "fog"), ("urban", "auto", "normal")],
)  # fmt: skip
def test_lane_accels_kernel_equals_numpy(monkeypatch, scenario: str, policy: str,
                                         weather: str) -> None:  # fmt: skip
    """Every call of a whole episode (leaders in every lane column, mandatory changes with
    their end gap, lights, give-way lines, fog's unseen signals; AUTO's teacher too), the
    decoded features and the lane accelerations."""
    seen = {"agents": 0, "leaders": 0, "bounded": 0, "decoded": 0, "capped": 0}

    def decode(ob, c):
        ref = feat._features_reference(ob, c)
        out = feat._features_compiled(ob, c)
        same_bits(ref, out, "features")
        seen["decoded"] += len(out["v"])
        return out

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
    monkeypatch.setattr(acc_lc, "features", decode)

    def caps(f, c, rss):
        monkeypatch.setattr(compiled, "ENABLED", False)
        ref = acc_lc_rss.rss_caps(f, c, rss)
        monkeypatch.setattr(compiled, "ENABLED", True)
        out = acc_lc_rss.rss_caps(f, c, rss)
        same_bits(ref, out, "rss_caps")
        seen["capped"] += int(np.isfinite(out).sum())
        return out

    monkeypatch.setattr(acc_lc, "rss_caps", caps)
    cfg = EnvConfig(scenario=scenario, penetration=0.3, episode_length=25.0, weather=weather)
    assert run_episode(cfg, policy, 0.0)["status"] == "ok"
    assert seen["agents"] > 250 and seen["leaders"] > 0 and seen["decoded"] == seen["agents"]
    assert seen["bounded"] > 0 or scenario != "urban", "the urban run met lights"
    assert seen["capped"] > 0 or policy != "auto", "AUTO's governor and safety read RSS caps"


@pytest.mark.parametrize("history", [2, 5, 9, 20])
def test_features_kernel_sums_and_signed_zeros(history: int) -> None:
    """Pure math: the decoding kernel equals numpy on random observations full of ties, signed
    zeros, NaN and full-scale lengths, for histories below and above numpy's 8-term block sum."""
    from dataclasses import replace

    cfg = EnvConfig()
    space = observation_space(replace(cfg, sensors=replace(cfg.sensors, history=history)))
    rng = np.random.default_rng(history)
    values = np.array([0.0, -0.0, 1.0, 0.3, -0.2, 0.6, 1e-7, 0.9999995, 2.0, np.nan])
    for dt in (0.05, 0.1, 0.2):
        ob = {}
        for k, s in space.spaces.items():
            if s.dtype == np.int8:
                ob[k] = rng.integers(0, 2, (9, *s.shape)).astype(np.int8)
            else:
                draw = rng.choice(values, (9, *s.shape)) * rng.uniform(0.5, 1.5, (9, *s.shape))
                ob[k] = draw.astype(s.dtype)
        ob["ego"][..., 4] = rng.uniform(-1.5, 1.5, ob["ego"][..., 4].shape)  # lane switches
        c = AccLcConfig(dt=dt)
        same_bits(feat._features_reference(ob, c), feat._features_compiled(ob, c), f"dt={dt}")


def test_pairwise_sum_is_numpys() -> None:
    """Pure math: the kernel's row sum is numpy's ``sum`` of a float64 row, bit for bit, below
    and above its 8-term block and for rows of -0.0."""
    from agents.rules.acc_lc_features_kernel import _pairwise_sum

    rng = np.random.default_rng(0)
    for n in range(51):
        for x in (rng.normal(size=n) * 10.0 ** rng.integers(-8, 8, n), np.full(n, -0.0)):
            assert np.array(_pairwise_sum(x, n)).tobytes() == np.array(x.sum()).tobytes(), n


def test_kernel_off_runs_the_reference(monkeypatch) -> None:
    """``MIXED_TRAFFIC_KERNELS=numpy`` runs the numpy stages."""
    called = []
    monkeypatch.setattr(lon, "_lane_accels_reference", lambda *a: called.append(a) or [])
    monkeypatch.setattr(compiled, "ENABLED", False)
    lon.lane_accels({"v": np.zeros(2)}, None, [], np.zeros(2))
    assert len(called) == 1


def test_warm_loads_the_kernels_a_plan_calls() -> None:
    """``warm()`` (the sweep's fork server calls it) loads the specialisations that ACC-LC's and
    AUTO's episodes use, so forked cells compile none. (A test worker may hold others from
    earlier tests: the check is that the episodes add none.)"""
    from agents.rules import acc_lc_features_kernel, acc_lc_kernel, acc_lc_plan_kernel

    acc_lc.warm()
    kernels = [acc_lc_kernel.idm_inputs, acc_lc_kernel.combine, acc_lc_kernel.rss_caps,
               acc_lc_features_kernel.decode, acc_lc_plan_kernel.decision]  # fmt: skip
    warmed = [len(k.signatures) for k in kernels]
    assert min(warmed) >= 1
    for policy in ("acc-lc", "auto"):
        cfg = EnvConfig(scenario="straight", penetration=0.3, episode_length=2.0)
        assert run_episode(cfg, policy, 0.0)["status"] == "ok"
    assert [len(k.signatures) for k in kernels] == warmed
