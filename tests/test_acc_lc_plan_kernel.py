"""ACC-LC's compiled lane-change decision (agents/rules/acc_lc_plan_kernel.py) against the numpy
reference on real SUMO states, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

import agents.rules.acc_lc as acc_lc
from mixed_traffic import compiled
from mixed_traffic.config import EnvConfig
from mixed_traffic.experiments.runner import run_episode

pytestmark = pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")


def _same(x: np.ndarray, y: np.ndarray) -> bool:
    """Equal dtypes and bits (-0.0 differs from 0.0, NaNs of one payload are equal)."""
    x, y = np.asarray(x), np.asarray(y)
    if x.dtype != y.dtype or x.shape != y.shape:
        return False
    if x.dtype == np.float64:
        return np.array_equal(x.view(np.int64), y.view(np.int64))
    return np.array_equal(x, y)


@pytest.mark.parametrize(
    ("scenario", "policy", "weather"),
    [("ring", "acc-lc", "normal"), ("ring", "acc-lc-tuned", "normal"),
     ("straight", "acc-lc", "normal"), ("straight", "acc-lc-tuned", "normal"),
     ("merge", "acc-lc", "normal"), ("merge", "acc-lc-tuned", "normal"),
     ("urban", "acc-lc", "normal"), ("urban", "acc-lc-tuned", "normal"),
     ("urban", "acc-lc", "fog"), ("urban", "acc-lc-tuned", "fog"),
     ("urban", "auto", "normal")],
)  # fmt: skip
def test_decision_kernel_equals_numpy(monkeypatch, scenario: str, policy: str,
                                      weather: str) -> None:  # fmt: skip
    """Every call of a whole episode: the decision, the go rows and the executed
    accelerations (discretionary and mandatory changes, unsafe gaps, waiting changes)."""
    seen = {"agents": 0, "changes": 0, "go": 0, "unsafe": 0, "mand": 0}

    def both(f, c, mand, la):
        ref = acc_lc._decision_reference(f, c, mand, la)
        out = acc_lc._decision_compiled(f, c, mand, la)
        assert len(ref) == len(out) == 6
        for x, y in zip(ref, out):
            assert _same(x, y)
        ck = acc_lc._change_checks(f, c, mand)
        side = f["exists"][:, [0, 2]] & f["mask"][:, [0, 2]]
        seen["agents"] += len(f["v"])
        seen["changes"] += int((out[0] != acc_lc.FOLLOW).sum())
        seen["go"] += int((out[1] | out[2]).sum())
        seen["unsafe"] += int((side & ~np.stack([ck.safe_l, ck.safe_r], 1)).sum())
        seen["mand"] += int(mand.sum())
        return out

    monkeypatch.setattr(acc_lc, "_decision", both)
    cfg = EnvConfig(scenario=scenario, penetration=0.3, episode_length=25.0, weather=weather)
    assert run_episode(cfg, policy, 0.0)["status"] == "ok"
    assert seen["agents"] > 250, seen
    # (the ring has one lane: no change to check there; on the straight road few are wanted)
    assert scenario == "ring" or min(seen["go"], seen["unsafe"]) > 0, seen
    assert seen["changes"] > 0 or scenario in ("ring", "straight"), seen
    assert seen["mand"] > 0 or scenario != "merge", "the merge run had mandatory changes"


def test_episode_records_equal_without_kernels(monkeypatch) -> None:
    """A whole episode's record with the numpy stages equals the kernels' (timing aside)."""
    cfg = EnvConfig(scenario="merge", penetration=0.3, episode_length=25.0)

    def record(switch: str) -> dict:
        monkeypatch.setattr(compiled, "ENABLED", switch == "numba")
        rec = dict(run_episode(cfg, "acc-lc", 0.0))
        rec.pop("created", None), rec.pop("wall_time", None)
        rec["metrics"] = {k: v for k, v in rec.get("metrics", {}).items() if k != "avg_it"}
        return rec

    assert record("numpy") == record("numba")


def test_kernel_off_runs_the_reference(monkeypatch) -> None:
    """``MIXED_TRAFFIC_KERNELS=numpy`` runs the numpy stages."""
    called = []
    monkeypatch.setattr(acc_lc, "_decision_reference", lambda *a: called.append(a) or ())
    monkeypatch.setattr(compiled, "ENABLED", False)
    acc_lc._decision({"v": np.zeros(2)}, None, np.zeros(2, bool), None)
    assert len(called) == 1


def test_warm_loads_the_decision_kernel() -> None:
    """``warm()`` loads the one specialisation a real episode uses."""
    from agents.rules import acc_lc_plan_kernel

    acc_lc.warm()
    cfg = EnvConfig(scenario="merge", penetration=0.3, episode_length=2.0)
    assert run_episode(cfg, "acc-lc", 0.0)["status"] == "ok"
    assert len(acc_lc_plan_kernel.decision.signatures) == 1
