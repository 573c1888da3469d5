"""The pass rules of issue 43's acceptance checks (pure statistics on synthetic episodes)."""

from __future__ import annotations

import pandas as pd
import pytest

from mixed_traffic.experiments.acceptance import (
    AcceptanceConfig,
    dt_tf_rows,
    eval_rows,
    ring_rows,
    wave_rows,
)


def _half(gain: float, sm: float = 2.0, collisions: float = 0.0, kept: float = 0.2) -> pd.DataFrame:
    """Four paired seeds; AUTO's AvgDT-A is ``gain`` % below the tuned ACC-LC's, with seed
    noise, and auto-mean's ``kept`` of that gain; the default ACC-LC is 10 % slower than the
    tuned one."""
    rows = []
    for seed, acc in enumerate([80.0, 76.0, 78.0, 82.0]):
        noise = 0.2 * (seed % 2 - 0.5)
        for policy, slower in (("acc-lc-tuned", 1.0), ("acc-lc", 1.1)):
            rows.append({"policy": policy, "seed": seed, "avg_dt_a": acc * slower, "avg_at_c": 0.1,
                         "sm_share": None, "terminal_collision": 0.0})  # fmt: skip
        rows.append({"policy": "auto", "seed": seed, "avg_dt_a": acc * (1 - (gain + noise) / 100),
                     "avg_at_c": 0.1, "sm_share": sm, "terminal_collision": collisions})  # fmt: skip
        rows.append({"policy": "auto-mean", "seed": seed, "avg_at_c": 0.1,
                     "avg_dt_a": acc * (1 - kept * (gain + noise) / 100)})  # fmt: skip
    return pd.DataFrame(rows)


RAW = pd.DataFrame(
    [{"policy": "auto-raw", "seed": 0, "av_trips": 1000.0, "terminal_off_road": 1.0}]
)


TUNED = "acc-lc-tuned"


def _passed(rows: list[dict]) -> dict[str, bool]:
    return {r["check"]: r["pass"] for r in rows}


def test_a_clear_gain_passes_and_a_small_one_does_not() -> None:
    assert _passed(eval_rows("x", _half(4.0), RAW, TUNED)) == {
        "dt_gain": True, "auto_mean": True, "at_c": True, "terminal": True, "sm_share": True,
        "raw_terminal": True,
    }  # fmt: skip
    assert not _passed(eval_rows("x", _half(1.0), RAW, TUNED))["dt_gain"]  # significant but < 3 %
    # over the default ACC-LC the same AUTO gains about 13 %: shown, not what is checked
    row = eval_rows("x", _half(1.0), RAW, TUNED)[0]
    assert "over acc-lc-tuned" in row["value"] and "over acc-lc +10." in row["value"]


def test_a_gain_that_a_constant_keeps_is_not_behaviour() -> None:
    assert not _passed(eval_rows("x", _half(4.0, kept=0.8), RAW, TUNED))["auto_mean"]
    assert _passed(eval_rows("x", _half(4.0, kept=0.4), RAW, TUNED))["auto_mean"]
    assert not _passed(eval_rows("x", _half(-1.0, kept=0.0), RAW, TUNED))["auto_mean"]  # no gain


@pytest.mark.parametrize(
    ("kw", "raw_events", "failing"),
    [({"sm": 12.0}, 1.0, "sm_share"), ({"collisions": 1.0}, 1.0, "terminal"),
     ({}, 3.0, "raw_terminal")],
)  # fmt: skip
def test_safety_limits(kw: dict, raw_events: float, failing: str) -> None:
    raw = RAW.assign(terminal_off_road=raw_events)  # 0.1 % passes, 0.3 % does not
    passed = _passed(eval_rows("x", _half(4.0, **kw), raw, TUNED))
    assert [k for k, ok in passed.items() if not ok] == [failing]


def _ring(std: float, speed: float, behind: float = 0.1) -> pd.DataFrame:
    """Two rings x three seeds: the AV's ring at ``std`` and ``speed`` [m/s], all human at 2.5
    and 2.0, FollowerStopper at 0.4 and 2.4; the AV's wake ``behind`` against 0.3 ahead."""
    return pd.DataFrame([
        {"policy": p, "seed": s, "ring": length, "speed_std": v + 0.01 * s, "mean_speed": m,
         "speed_std_ahead": 0.3, "speed_std_behind": behind}
        for length in (210.0, 280.0) for s in range(3)
        for p, v, m in (("auto", std, speed), ("idm", 2.5, 2.0), ("follower-stopper", 0.4, 2.4))
    ])  # fmt: skip


def _wave(std: float, fuel: float, dt_tf: float) -> pd.DataFrame:
    """AUTO's ratios to all human (std 4, fuel 8, DT-TF 100) on three seeds."""
    return pd.DataFrame([{"policy": p, "seed": s, "speed_std": 4.0 * r[0], "fuel": 8.0 * r[1],
                          "dt_tf": 100.0 * r[2]}
                         for s in range(3)
                         for p, r in (("auto", (std, fuel, dt_tf)), ("idm", (1, 1, 1)))])  # fmt: skip


def test_ring_and_wave_rows() -> None:
    assert _passed(ring_rows(_ring(1.0, 2.6)) + wave_rows(_wave(0.7, 0.9, 1.01))) == {
        "ring_std": True, "ring_speed": True, "ring_wake": True, "wave": True,
    }  # fmt: skip
    assert not _passed(ring_rows(_ring(1.3, 2.6)))["ring_std"]  # 1.3 > 2.5 / 2
    slow = _passed(ring_rows(_ring(1.0, 2.2, behind=0.5)))
    assert not slow["ring_speed"] and not slow["ring_wake"]  # slower than FollowerStopper
    for bad in ((0.9, 0.9, 1.01), (0.7, 0.97, 1.01), (0.7, 0.9, 1.05)):  # each bound alone
        assert not _passed(wave_rows(_wave(*bad)))["wave"]
    nan = _ring(1.0, 2.6).assign(speed_std=float("nan"))
    assert not _passed(ring_rows(nan))["ring_std"]  # no measurement never passes


def test_checks_are_named_groups() -> None:
    assert AcceptanceConfig(checks=("ring",)).checks == ("ring",)
    with pytest.raises(ValueError, match="--checks ring sail: choose from"):
        AcceptanceConfig(checks=("ring", "sail"))


def test_dt_tf_rows() -> None:
    full = pd.DataFrame([{"policy": p, "seed": s, "dt_tf": v + s}
                         for s in range(3) for p, v in (("auto", 70.0), ("idm", 72.0))])  # fmt: skip
    assert _passed(dt_tf_rows(full))["dt_tf"]
    slower = full.assign(dt_tf=full["dt_tf"] + 5.0 * (full["policy"] == "auto"))
    assert not _passed(dt_tf_rows(slower))["dt_tf"]  # 3 s/km slower than all human
    assert not _passed(dt_tf_rows(full.assign(dt_tf=float("nan"))))["dt_tf"]
