"""Decision-level transitions (pure bookkeeping): one-step and n-step returns."""

from __future__ import annotations

import numpy as np
import pytest

from agents.collection.intervals import Intervals
from agents.rules.obs_batch import OBS_KEYS


def _obs(value: float) -> dict[str, np.ndarray]:
    """One agent's stacked observation, every key filled with ``value``."""
    return {k: np.full((1, 2), value, np.float32) for k in OBS_KEYS}


def _episode(n_step: int, terminal: bool) -> list[dict]:
    """Agent ``a`` decides at observations 0, 1, 2 (one step each, rewards 1, 2, 3), then its
    trip ends at observation 3. → the closed rows, in the order they left."""
    iv = Intervals(gamma_step=0.9, scale=1.0, bootstrap_arrival=True, n_step=n_step)
    label = (np.zeros(1, np.float32), np.zeros(1, np.int64), np.zeros((1, 3, 2), np.float32))
    out = []
    for t, r in enumerate((1.0, 2.0, 3.0)):
        out.append(iv.decide(["a"], _obs(t), np.array([0]), np.array([t % 3]),
                             np.zeros((1, 3, 2), np.float32), label))  # fmt: skip
        iv.reward(["a"], np.array([r], np.float32))
    out.append(iv.end(["a"], _obs(3), np.array([terminal]), np.array([False])))
    return [
        {"obs": float(b["obs"]["ego"][i, 0]), "next": float(b["next_obs"]["ego"][i, 0]),
         "reward": float(b["reward"][i]), "discount": float(b["discount"][i]),
         "done": float(b["done"][i]), "decision": int(b["decision"][i])}
        for b in out for i in range(len(b["reward"]))
    ]  # fmt: skip


def test_one_step_transitions_close_at_the_next_decision() -> None:
    rows = _episode(1, terminal=False)
    assert [(r["obs"], r["next"]) for r in rows] == [(0, 1), (1, 2), (2, 3)]
    assert [r["reward"] for r in rows] == [1.0, 2.0, 3.0]
    assert rows[0]["discount"] == pytest.approx(0.9) and {r["done"] for r in rows} == {0.0}


@pytest.mark.parametrize("terminal", [False, True])
def test_n_step_transitions_sum_discounted_rewards_and_flush_at_the_end(terminal: bool) -> None:
    rows = _episode(2, terminal)
    assert [(r["obs"], r["next"], r["decision"]) for r in rows] == [(0, 2, 0), (1, 3, 1),
                                                                    (2, 3, 2)]  # fmt: skip
    assert [r["reward"] for r in rows] == pytest.approx([1 + 0.9 * 2, 2 + 0.9 * 3, 3.0])
    assert [r["discount"] for r in rows] == pytest.approx([0.81, 0.81, 0.9])
    assert [r["done"] for r in rows] == [0.0, float(terminal), float(terminal)]


def test_n_step_must_be_positive() -> None:
    with pytest.raises(ValueError, match="n_step=0 must be >= 1"):
        Intervals(0.9, 1.0, True, n_step=0)
