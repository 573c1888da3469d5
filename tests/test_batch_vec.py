"""The native vector env over batched worlds (issue 60): SB3's ``VecEnv`` API on real SUMO."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from mixed_traffic.benchmark import parallel_env, vec_env


def test_rows_are_the_copies_agents_and_end_together_at_the_horizon() -> None:
    venv = vec_env("ring-v2", copies=2, seed=0, episode_length=6.0)  # 12 decisions of 0.5 s
    try:
        obs = venv.reset()
        assert obs.shape == (2, 8) and obs.dtype == np.float32 and venv.active.all()
        assert venv.copy.tolist() == [0, 1]
        steps = 0
        for _ in range(12):
            obs, rewards, dones, infos = venv.step(np.zeros((2, 1)))
            steps += 1
            assert np.isfinite(rewards).all() and (rewards != 0).all()
            if dones.any():
                break
        assert steps == 12 and dones.all(), "both rows end at the horizon, together"
        assert all(i["TimeLimit.truncated"] and i["terminal_observation"].shape == (8,)
                   for i in infos)  # fmt: skip
        assert obs.shape == (2, 8) and venv.active.all(), "the batch reset"
    finally:
        venv.close()


def test_sb3_ppo_trains_on_it() -> None:
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    venv = VecMonitor(vec_env("ring-v2", copies=2, seed=1, episode_length=4.0))
    try:
        model = PPO("MlpPolicy", venv, n_steps=8, batch_size=8, n_epochs=1, seed=0, device="cpu")
        model.learn(32)
        assert model.num_timesteps >= 32
    finally:
        venv.close()


def test_bad_actions_are_named() -> None:
    venv = vec_env("ring-v2", copies=2, seed=0, episode_length=4.0)
    try:
        venv.reset()
        with pytest.raises(ValueError, match=r"non-finite actions for agent\(s\) \['av_1'\]"):
            venv.step(np.array([[0.0], [np.nan]]))
    finally:
        venv.close()


def test_a_batched_task_passes_the_parallel_api_test() -> None:
    env = parallel_env("ring-v2", copies=2, episode_length=5.0)
    try:
        parallel_api_test(env, num_cycles=40)
    finally:
        env.close()
