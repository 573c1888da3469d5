"""The pass rules of issue 22's acceptance checks (pure statistics on synthetic episodes)."""

from __future__ import annotations

import pandas as pd
import pytest

from mixed_traffic.experiments.acceptance import eval_rows, flow_rows


def _half(gain: float, sm: float = 2.0, collisions: float = 0.0) -> pd.DataFrame:
    """Four paired seeds; AUTO's AvgDT-A is ``gain`` % below the tuned ACC-LC's, with seed
    noise; the default ACC-LC is 10 % slower than the tuned one."""
    rows = []
    for seed, acc in enumerate([80.0, 76.0, 78.0, 82.0]):
        noise = 0.2 * (seed % 2 - 0.5)
        for policy, slower in (("acc-lc-tuned", 1.0), ("acc-lc", 1.1)):
            rows.append({"policy": policy, "seed": seed, "avg_dt_a": acc * slower, "avg_at_c": 0.1,
                         "sm_share": None, "terminal_collision": 0.0})  # fmt: skip
        rows.append({"policy": "auto", "seed": seed, "avg_dt_a": acc * (1 - (gain + noise) / 100),
                     "avg_at_c": 0.1, "sm_share": sm, "terminal_collision": collisions})  # fmt: skip
    return pd.DataFrame(rows)


RAW = pd.DataFrame(
    [{"policy": "auto-raw", "seed": 0, "av_trips": 1000.0, "terminal_off_road": 1.0}]
)


TUNED = "acc-lc-tuned"


def _passed(rows: list[dict]) -> dict[str, bool]:
    return {r["check"]: r["pass"] for r in rows}


def test_a_clear_gain_passes_and_a_small_one_does_not() -> None:
    assert _passed(eval_rows("x", _half(4.0), RAW, TUNED)) == {
        "dt_gain": True, "at_c": True, "terminal": True, "sm_share": True, "raw_terminal": True,
    }  # fmt: skip
    assert not _passed(eval_rows("x", _half(1.0), RAW, TUNED))["dt_gain"]  # significant but < 3 %
    # over the default ACC-LC the same AUTO gains about 13 %: shown, not what is checked
    row = eval_rows("x", _half(1.0), RAW, TUNED)[0]
    assert "over acc-lc-tuned" in row["value"] and "over acc-lc +10." in row["value"]


@pytest.mark.parametrize(
    ("kw", "raw_events", "failing"),
    [({"sm": 12.0}, 1.0, "sm_share"), ({"collisions": 1.0}, 1.0, "terminal"),
     ({}, 3.0, "raw_terminal")],
)  # fmt: skip
def test_safety_limits(kw: dict, raw_events: float, failing: str) -> None:
    raw = RAW.assign(terminal_off_road=raw_events)  # 0.1 % passes, 0.3 % does not
    passed = _passed(eval_rows("x", _half(4.0, **kw), raw, TUNED))
    assert [k for k, ok in passed.items() if not ok] == [failing]


def test_flow_rows() -> None:
    full = pd.DataFrame([{"policy": p, "seed": s, "dt_tf": v + s}
                         for s in range(3) for p, v in (("auto", 70.0), ("idm", 72.0))])  # fmt: skip
    ring = pd.DataFrame([{"policy": p, "seed": s, "speed_std": v}
                         for s in range(3) for p, v in (("auto", 1.3), ("idm", 2.5),
                                                        ("follower-stopper", 0.4))])  # fmt: skip
    assert _passed(flow_rows(full, ring)) == {"dt_tf": True, "ring": False}  # 1.3 > 2.5 / 2
    assert _passed(flow_rows(full, ring.replace(1.3, 1.2)))["ring"]
    nan = full.assign(dt_tf=float("nan"))
    assert not _passed(flow_rows(nan, ring))["dt_tf"]  # no measurement never passes
