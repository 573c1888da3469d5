"""``MixedTrafficEnv.step_batch`` (the runner's step, without the PettingZoo per-agent dicts)
against ``step`` on the same seeds and actions: the same observations, rewards, terminations,
events, agents entering and leaving, and episode metrics; and its bad input."""

from __future__ import annotations

import numpy as np
import pytest

from mixed_traffic.env import parallel_env

from .conftest import same_bits


def _actions(env, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random allowed decisions and params of the live agents (mostly following)."""
    mask = env.observation_batch()["action_mask"].astype(bool)
    a = len(mask)
    decision = np.where(rng.random(a) < 0.8, 1, rng.integers(0, 3, a))
    decision = np.where(mask[np.arange(a), decision], decision, 1)
    params = rng.uniform(-0.3, 0.6, (a, 3, 2)).astype(np.float32)
    return decision, params


@pytest.mark.parametrize(
    "kw",
    [dict(scenario="urban", penetration=0.4, episode_length=30.0),
     dict(scenario="straight", density=60.0, penetration=0.3, episode_length=40.0),
     dict(scenario="ring", fixed_fleet=True, penetration=0.2, episode_length=20.0)],
    ids=["urban", "straight", "ring-fixed-fleet"],
)  # fmt: skip
def test_step_batch_equals_step(kw: dict) -> None:
    envs = [parallel_env(seed=5, **kw) for _ in range(2)]
    try:
        for e in envs:
            e.reset(seed=5)
        rng = np.random.default_rng(0)
        seen = {"entered": 0, "ended": 0, "steps": 0}
        while envs[0].agents:
            agents = list(envs[0].agents)
            assert envs[1].agents == agents
            same_bits(envs[0].observation_batch(), envs[1].observation_batch(), "obs")
            decision, params = _actions(envs[0], rng)
            actions = {a: {"decision": int(d), "params": p}
                       for a, d, p in zip(agents, decision, params)}  # fmt: skip
            _, rew, term, trunc, infos = envs[0].step(actions)
            out = envs[1].step_batch(decision, params)
            assert out.agents == agents
            assert out.rewards.tolist() == [rew[a] for a in agents]
            assert out.terminated.tolist() == [term[a] for a in agents]
            assert out.truncated.tolist() == [trunc[a] for a in agents]
            assert out.events == [infos[a]["event"] if a in infos else "" for a in agents]
            entered = [a for a, i in infos.items() if i["event"] == "entered"]
            assert sorted(out.entered) == sorted(entered)
            assert envs[1].agents == envs[0].agents
            seen["entered"] += len(out.entered)
            seen["ended"] += int(out.terminated.sum())
            seen["steps"] += 1
        assert envs[1]._phase == envs[0]._phase == "ended"
        same_bits(envs[0].episode_metrics(), envs[1].episode_metrics(), "metrics")
        assert seen["steps"] > 100
        if not kw.get("fixed_fleet"):
            assert seen["entered"] > 0 and seen["ended"] > 0, seen
    finally:
        for e in envs:
            e.close()


def test_step_batch_rejects_bad_input() -> None:
    e = parallel_env(scenario="straight", density=60.0, penetration=0.3, episode_length=10.0)
    with pytest.raises(RuntimeError, match="before reset"):
        e.step_batch(np.zeros(0, np.int64), np.zeros((0, 3, 2)))
    try:
        e.reset(seed=0)
        n, start = len(e.agents), e.sim_time
        good = np.ones(n, np.int64), np.zeros((n, 3, 2))
        with pytest.raises(ValueError, match=rf"decision \({n},\) integers"):
            e.step_batch(np.ones(n + 1, np.int64), good[1])
        with pytest.raises(ValueError, match="integers"):
            e.step_batch(np.ones(n), good[1])
        bad = good[1].copy()
        bad[n - 1, 1, 1] = np.nan
        with pytest.raises(ValueError, match=rf"agent '{e.agents[n - 1]}'.*not finite"):
            e.step_batch(good[0], bad)
        bad[n - 1, 1, 1] = 3.0
        with pytest.raises(ValueError, match=rf"agent '{e.agents[n - 1]}'"):
            e.step_batch(good[0], bad)
        assert e.sim_time == start, "a rejected step must not advance the simulation"
        e.step_batch(*good)
    finally:
        e.close()
