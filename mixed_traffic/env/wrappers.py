"""Wrappers for libraries without hybrid (Dict) action spaces.

``FlatActionWrapper`` turns the parameterized action ``Dict(decision=Discrete(3),
params=Box(-1, 1, (3, 2)))`` into one ``Box(-1, 1, (9,), float32)`` per agent::

    flat[0:3]  decision scores: decision = argmax(flat[0:3]) (ties -> the lowest index,
               i.e. left change before follow before right change)
    flat[3:9]  params row-major: (steer_left, ab_left, steer_follow, ab_follow, steer_right, ab_right)

so ``params = flat[3:9].reshape(3, 2)``. ``flat_to_dict`` is the pure mapping; it raises
``ValueError`` on a wrong shape or non-finite values (bounds are checked by the env).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo.utils.env import ParallelEnv
from pettingzoo.utils.wrappers import BaseParallelWrapper

from mixed_traffic.env.action import N_DECISIONS, N_PARAMS

FLAT_SIZE = N_DECISIONS + N_DECISIONS * N_PARAMS  # 9


def flat_action_space() -> spaces.Box:
    """``Box(-1, 1, (9,), float32)``: 3 decision scores then the (3, 2) params row-major."""
    return spaces.Box(-1.0, 1.0, (FLAT_SIZE,), np.float32)


def flat_to_dict(flat: Any, agent: str = "?") -> dict[str, Any]:
    """(9,) flat action -> ``{"decision": int, "params": (3, 2) float32}``."""
    arr = np.asarray(flat, dtype=np.float64)
    if arr.shape != (FLAT_SIZE,):
        raise ValueError(
            f"flat action of agent {agent!r} has shape {arr.shape}, expected ({FLAT_SIZE},): "
            "3 decision scores then 6 params"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"flat action of agent {agent!r} contains non-finite values: {arr}")
    return {
        "decision": int(np.argmax(arr[:N_DECISIONS])),
        "params": arr[N_DECISIONS:].reshape(N_DECISIONS, N_PARAMS).astype(np.float32),
    }


def dict_to_flat(action: dict[str, Any]) -> np.ndarray:
    """Inverse view: one-hot decision score (+1 chosen, -1 others) followed by the params."""
    scores = -np.ones(N_DECISIONS, np.float32)
    scores[int(action["decision"])] = 1.0
    return np.concatenate([scores, np.asarray(action["params"], np.float32).reshape(-1)])


class FlatActionWrapper(BaseParallelWrapper):
    """PettingZoo parallel wrapper exposing ``flat_action_space()`` for every agent.

    Works with any ``ParallelEnv`` whose agents take the parameterized Dict action; observations,
    rewards and infos pass through unchanged.
    """

    def __init__(self, env: ParallelEnv) -> None:
        super().__init__(env)
        self._flat_space = flat_action_space()

    def action_space(self, agent: str) -> spaces.Box:
        return self._flat_space

    def step(self, actions: dict[str, Any]):
        return self.env.step({a: flat_to_dict(v, a) for a, v in actions.items()})


class FlatObservationWrapper(BaseParallelWrapper):
    """PettingZoo parallel wrapper giving each agent one flat ``Box`` observation (float32).

    The Dict observation is flattened with ``gymnasium.spaces.flatten`` in the Dict space's
    (sorted) key order (``action_mask, [downstream,] ego, give_way, lanes, lights, limits,
    node_mask, signals, vehicles``; ``downstream`` with ``v2x=True``); ``slices[key]`` is the
    part of the vector holding ``key`` (e.g. ``obs[..., w.slices["action_mask"]]`` is the
    (3,) action mask). Needed by SuperSuit's ``black_death_v3`` and vector envs.
    """

    def __init__(self, env: ParallelEnv) -> None:
        super().__init__(env)
        agent = env.possible_agents[0]
        self._dict_space = env.observation_space(agent)
        flat = spaces.flatten_space(self._dict_space)
        self._flat_space = spaces.Box(
            flat.low.astype(np.float32), flat.high.astype(np.float32), dtype=np.float32
        )
        self.slices: dict[str, slice] = {}
        start = 0
        for key, sub in self._dict_space.spaces.items():
            size = spaces.flatdim(sub)
            self.slices[key] = slice(start, start + size)
            start += size

    def observation_space(self, agent: str) -> spaces.Box:
        return self._flat_space

    def _flat(self, obs: dict[str, Any]) -> dict[str, np.ndarray]:
        space = self._dict_space
        return {a: spaces.flatten(space, o).astype(np.float32) for a, o in obs.items()}

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs, infos = self.env.reset(seed=seed, options=options)
        return self._flat(obs), infos

    def step(self, actions: dict[str, Any]):
        obs, rew, term, trunc, infos = self.env.step(actions)
        return self._flat(obs), rew, term, trunc, infos
