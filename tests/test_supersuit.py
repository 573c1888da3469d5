"""SuperSuit compatibility on real SUMO: black_death on the parallel env, and the env as a
(concatenated) vector env in fixed-fleet mode; plus the flat observation wrapper."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium import spaces

from mixed_traffic.env import parallel_env
from mixed_traffic.env.wrappers import FLAT_SIZE, FlatActionWrapper, FlatObservationWrapper

ss = pytest.importorskip("supersuit")

SMALL = dict(density=60.0, penetration=0.3, episode_length=20.0)


def _random_flat(agents, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {a: rng.uniform(-1, 1, FLAT_SIZE).astype(np.float32) for a in agents}


def test_flat_observation_round_trips_the_dict() -> None:
    e = FlatObservationWrapper(parallel_env(**SMALL))
    try:
        obs, _ = e.reset(seed=0)
        space = e.observation_space(e.possible_agents[0])
        dict_obs = {a: e.unwrapped._batches.last_obs(a) for a in obs}
        assert isinstance(space, spaces.Box) and space.dtype == np.float32
        assert obs and all(o.shape == space.shape and o.dtype == np.float32 for o in obs.values())
        for a, o in obs.items():
            back = spaces.unflatten(e.unwrapped.observation_space(a), o)
            for key, value in dict_obs[a].items():
                np.testing.assert_allclose(back[key], value, rtol=1e-6, atol=1e-7)
            np.testing.assert_array_equal(o[e.slices["action_mask"]], dict_obs[a]["action_mask"])
            assert space.contains(o)
    finally:
        e.close()


def test_black_death_runs_with_agents_leaving() -> None:
    env = ss.black_death_v3(FlatActionWrapper(FlatObservationWrapper(parallel_env(**SMALL))))
    rng = np.random.default_rng(0)
    try:
        obs, _ = env.reset(seed=1)
        shape = env.observation_space(env.possible_agents[0]).shape
        start = set(env.agents)
        gone: set[str] = set()
        for _ in range(60):
            # actions for every possible agent: black_death forwards those of the live ones
            obs, rew, term, trunc, info = env.step(_random_flat(env.possible_agents, rng))
            assert all(o.shape == shape for o in obs.values())
            live = set(env.unwrapped.agents)
            for a in gone & set(obs):  # a departed agent is black: zero obs, zero reward
                assert not obs[a].any() and rew[a] == 0.0
            gone |= start - live
            if not env.unwrapped.agents:
                break
        assert gone, "random driving should have ended some agents' trips"
        assert set(obs) >= start  # departed agents stay in the dicts
    finally:
        env.close()


@pytest.mark.parametrize("num_vec_envs", [1, 2])
def test_vec_env_with_fixed_fleet(num_vec_envs: int) -> None:
    base = FlatActionWrapper(FlatObservationWrapper(parallel_env(fixed_fleet=True, **SMALL)))
    n_agents = len(base.possible_agents)
    obs_dim = base.observation_space(base.possible_agents[0]).shape[0]
    venv = ss.pettingzoo_env_to_vec_env_v1(base)
    venv = ss.concat_vec_envs_v1(venv, num_vec_envs, num_cpus=0, base_class="gymnasium")
    rng = np.random.default_rng(0)
    n = n_agents * num_vec_envs
    try:
        obs, infos = venv.reset(seed=0)
        assert venv.num_envs == n
        assert obs.shape == (n, obs_dim) and obs.dtype == np.float32
        for _ in range(5):
            act = rng.uniform(-1, 1, (n, FLAT_SIZE)).astype(np.float32)
            obs, rew, term, trunc, infos = venv.step(act)
            assert obs.shape == (n, obs_dim)
            assert rew.shape == term.shape == trunc.shape == (n,)
            assert np.isfinite(obs).all() and np.isfinite(rew).all()
        assert np.abs(rew).sum() > 0  # the agents are really driving and rewarded
    finally:
        venv.close()
