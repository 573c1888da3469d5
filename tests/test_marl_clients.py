"""Outside MARL clients on real SUMO, through the one-line recipes of docs/marl.md: TorchRL's
``PettingZooWrapper`` and RLlib's ``ParallelPettingZooEnv`` (one PPO iteration)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mixed_traffic.env import parallel_env
from mixed_traffic.wrappers import FLAT_SIZE, FlatActionWrapper, FlatObservationWrapper

SMALL = dict(scenario="straight", density=40.0, penetration=0.1, episode_length=8.0)


def _flat_fleet(**kw):
    """The recipe: a constant agent set and flat Box observations and actions."""
    return FlatActionWrapper(FlatObservationWrapper(parallel_env(**SMALL, fixed_fleet=True, **kw)))


def test_torchrl_rolls_out_the_recipe() -> None:
    pz = pytest.importorskip("torchrl.envs.libs.pettingzoo")
    penv = _flat_fleet()
    try:
        env = pz.PettingZooWrapper(env=penv, use_mask=False)
        n = len(penv.possible_agents)
        td = env.rollout(30)
        assert td["av", "action"].shape == (30, n, FLAT_SIZE)
        obs = td["next", "av", "observation"]
        assert obs.shape[:2] == (30, n) and bool((obs.abs() <= 1).all())
        reward = td["next", "av", "reward"].numpy()
        assert np.isfinite(reward).all() and reward.std() > 0, "rewards reach TorchRL"
    finally:
        penv.close()


def test_rllib_trains_one_ppo_iteration_on_the_recipe() -> None:
    pytest.importorskip("ray.rllib")
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
    from ray.tune.registry import register_env

    register_env("mixed_traffic_flat", lambda _: ParallelPettingZooEnv(_flat_fleet()))
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        config = (
            PPOConfig()
            .environment("mixed_traffic_flat")
            .env_runners(num_env_runners=0)  # the env lives in this process
            .multi_agent(policies={"shared"}, policy_mapping_fn=lambda *_, **__: "shared")
            .training(train_batch_size_per_learner=160, minibatch_size=80, num_epochs=1)
        )
        algo = config.build_algo()
        try:
            result = algo.train()
        finally:
            algo.stop()
    finally:
        ray.shutdown()
    assert result["env_runners"]["num_env_steps_sampled_lifetime"] >= 160
    assert np.isfinite(result["learners"]["shared"]["total_loss"])


def _docs_block(needle: str) -> str:
    """The python block of docs/marl.md that contains ``needle``."""
    text = (Path(__file__).parents[1] / "docs" / "marl.md").read_text()
    return next(b.split("```")[0] for b in text.split("```python\n")[1:] if needle in b)


def test_the_batched_recipe_in_docs_runs() -> None:
    """The native vector env's block of docs/marl.md, executed as written, then trained."""
    pytest.importorskip("stable_baselines3")
    space: dict = {}
    exec(compile(_docs_block("vec_env("), "docs/marl.md", "exec"), space)
    model, venv = space["model"], space["venv"]
    try:
        assert venv.num_envs == 32 and model.n_steps * venv.num_envs == 2048
        model.learn(64)
        assert model.num_timesteps >= 64
    finally:
        venv.close()


def test_the_ppo_recipe_in_docs_runs() -> None:
    """The SB3 + SuperSuit recipe of docs/marl.md, executed as written."""
    pytest.importorskip("stable_baselines3")
    code = _docs_block("supersuit")
    space: dict = {}
    exec(compile(code, "docs/marl.md", "exec"), space)
    model = space["model"]
    assert model.num_timesteps >= 128 and model.observation_space.shape == (8,)
    assert len(model.ep_info_buffer) >= 1, "an episode of 30 s ended within 128 decisions"
