"""The opt-in ``memory`` key: slow summaries of an agent's own and its leader's speed and its
last command, checked against the observations it was built from (real SUMO)."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from mixed_traffic.config import EnvConfig, SensorConfig
from mixed_traffic.env import parallel_env
from mixed_traffic.sensing.memory import SPEED_SCALE, SPREAD_SCALE
from mixed_traffic.sensing.observation import observation_space

SENSORS = SensorConfig(memory=True, memory_taus=(2.0, 10.0), noise=False)


def _ema(x: np.ndarray, alpha: float) -> tuple[float, float]:
    """Exponential mean and spread of the series ``x``, from its first value."""
    mean, var = x[0], 0.0
    for v in x[1:]:
        d = v - mean
        mean += alpha * d
        var = (1 - alpha) * (var + alpha * d * d)
    return mean, np.sqrt(var)


def test_the_key_is_opt_in_and_bad_time_constants_are_named() -> None:
    assert "memory" not in observation_space(EnvConfig()).spaces
    assert observation_space(EnvConfig(sensors=SENSORS))["memory"].shape == (12,)
    with pytest.raises(ValueError, match=r"SensorConfig\.memory_taus=\(0\.0,\)"):
        SensorConfig(memory_taus=(0.0,))


def test_summaries_follow_the_observed_speeds_and_the_last_command() -> None:
    env = parallel_env(config=EnvConfig(scenario="ring", ring_vehicles=22, penetration=1 / 22,
                                        episode_length=40.0, sensors=SENSORS, seed=2))  # fmt: skip
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=2)
    (agent,) = env.agents
    own, lead, memory = [], [], []
    try:
        for _ in range(300):
            o = obs[agent]
            own.append(o["ego"][-1, 0] * 40.0)
            lead.append(own[-1] + o["vehicles"][1, -1, 1] * 40.0)  # current lane, front
            assert o["node_mask"][1, 1]  # the ring's leader is always seen
            memory.append(o["memory"])
            params = np.zeros((3, 2), np.float32)
            params[1, 1] = rng.uniform(-0.3, 0.3)
            obs, *_ = env.step({agent: {"decision": 1, "params": params}})
        m = obs[agent]["memory"]
        np.testing.assert_allclose(m[8:11], [0, 1, 0])  # the last command: follow
        assert m[11] == pytest.approx(params[1, 1], abs=1e-6)
    finally:
        env.close()
    own, lead, m = np.array(own), np.array(lead), memory[-1]
    assert own.std() > 0.1  # the speed varied: the check can tell the time constants apart
    for j, tau in enumerate(SENSORS.memory_taus):
        mean, spread = _ema(own, 0.1 / tau)
        assert m[j] * SPEED_SCALE == pytest.approx(mean, abs=1e-3)
        assert m[2 + j] * SPREAD_SCALE == pytest.approx(spread, abs=1e-3)
        # the leader's starts at the agent's own speed, then follows the leader's
        mean, spread = _ema(np.concatenate([own[:1], lead]), 0.1 / tau)
        assert m[4 + j] * SPEED_SCALE == pytest.approx(mean, abs=1e-3)
        assert m[6 + j] * SPREAD_SCALE == pytest.approx(spread, abs=1e-3)
    assert m[0] != pytest.approx(m[1], abs=1e-4)  # two time constants, two means


def test_parallel_api_with_memory() -> None:
    env = parallel_env(config=EnvConfig(scenario="straight", density=60.0, penetration=0.2,
                                        episode_length=6.0, sensors=SENSORS))  # fmt: skip
    try:
        parallel_api_test(env, num_cycles=40)
    finally:
        env.close()
