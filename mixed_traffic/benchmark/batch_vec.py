"""A benchmark task as Stable-Baselines3's ``VecEnv`` over batched worlds: one row per
possible agent of ``copies`` copies of the task in one simulation, stepped with
``step_batch`` and observed with ``observation_batch`` (no per-agent dicts, no SuperSuit).

    from mixed_traffic.benchmark import vec_env
    venv = vec_env("ring-v2", copies=16, seed=0)   # 16 rings, one AV each: 16 rows

(``stable-baselines3``, the ``ppo`` extra, is imported here only.)

Each row observes the learner interface's 8 features (:mod:`agents.longitudinal`) and acts
with one acceleration in [-1, 1], held for the interface's ``hold`` env steps (one decision);
its reward is the task reward summed over them. A row whose agent is not on the road (it left,
or waits to re-enter with a fixed fleet) observes zeros, gets reward 0, and ``active`` (and its
``infos[i]["active"]``) is False: its actions are ignored. All rows end together at the task's
horizon (``TimeLimit.truncated``, the features there as ``terminal_observation``), and the
batch resets; a row whose agent's trip ends earlier (a collision on a ring) is done once, with
its last features.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnv

from agents.longitudinal import BOUND, N_FEATURES, LongitudinalConfig, LongitudinalInterface
from agents.rules.tuned import cap_factor
from mixed_traffic.benchmark.tasks import get_task
from mixed_traffic.env.parallel import MixedTrafficEnv


class BatchVecEnv(VecEnv):
    """SB3 ``VecEnv`` of a batched env through the learner interface (module docstring).

    Args:
        env: the env (``metrics=False`` for training), a fixed set of possible agents.
        interface: the learner interface (its ``dt`` the env's step).
    """

    def __init__(self, env: MixedTrafficEnv, interface: LongitudinalInterface) -> None:
        self.env, self.interface = env, interface
        self.render_mode = None  # SB3 warns where a VecEnv has none
        self._row = {a: i for i, a in enumerate(env.possible_agents)}
        n = len(self._row)
        super().__init__(n, spaces.Box(-BOUND, BOUND, (N_FEATURES,), np.float32),
                         spaces.Box(-1.0, 1.0, (1,), np.float32))  # fmt: skip
        self._obs = np.zeros((n, N_FEATURES), np.float32)
        self._actions = np.zeros(n)
        self.active = np.zeros(n, bool)
        """(n,) rows whose agent is on the road."""
        self.copy = env.agent_copy.copy()
        """(n,) the copy each row's agent drives in."""

    # ------------------------------------------------------------------ VecEnv
    def reset(self) -> np.ndarray:
        seed = self._seeds[0] if self._seeds and self._seeds[0] is not None else None
        self._seeds = []
        self.env.reset(seed=seed, options={"allow_no_agents": True})
        self.interface.reset()
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return self._observe()

    def step_async(self, actions: np.ndarray) -> None:
        actions = np.asarray(actions, np.float64).reshape(self.num_envs, -1)[:, 0]
        if not np.all(np.isfinite(actions[self.active])):
            bad = [
                a for a, i in self._row.items() if self.active[i] and not np.isfinite(actions[i])
            ]
            raise ValueError(f"non-finite actions for agent(s) {bad}")
        self._actions = actions

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:
        n, env = self.num_envs, self.env
        rewards, dones = np.zeros(n), np.zeros(n, bool)
        infos: list[dict[str, Any]] = [{} for _ in range(n)]
        for _ in range(self.interface.c.hold):
            rows = self._rows(self.interface.agents)
            out = env.step_batch(*self.interface.command(self._actions[rows]))
            got = self._rows(out.agents)
            rewards[got] += out.rewards
            for i in got[out.terminated]:  # a trip ended: done once, its last features
                dones[i], infos[i]["terminal_observation"] = True, self._obs[i].copy()
            if out.truncated.any() or env.sim_time >= env.config.episode_length - 1e-9:
                return self._horizon(rewards, dones, infos)
            obs = self._observe()  # once per env step: the interface's speed memory advances
        for i in range(n):
            infos[i]["active"] = bool(self.active[i])
        return obs, rewards, dones, infos

    def _horizon(self, rewards: np.ndarray, dones: np.ndarray,
                 infos: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict]]:  # fmt: skip
        """The step that reached the task's horizon: every row ends, the batch resets."""
        final = self._observe(ended=True)
        for i in np.flatnonzero(~dones):
            infos[i].update({"terminal_observation": final[i], "TimeLimit.truncated": True})
        obs = self.reset()
        for i in range(self.num_envs):
            infos[i]["active"] = bool(self.active[i])
        return obs, rewards, np.ones(self.num_envs, bool), infos

    def _observe(self, ended: bool = False) -> np.ndarray:
        """(n, 8) the features of every row (zeros where no agent is on the road); ``ended``:
        the last observations of the agents at the horizon."""
        agents = list(self.env.agents) if not ended else list(self.interface.agents)
        self._obs[:] = 0.0
        self.active[:] = False
        if agents:
            rows = self._rows(agents)
            self._obs[rows] = self.interface.observe(self.env.observation_batch(agents), agents)
            self.active[rows] = not ended
        return self._obs.copy()

    def _rows(self, agents: Sequence[str]) -> np.ndarray:
        return np.fromiter(map(self._row.__getitem__, agents), np.int64, len(agents))

    def close(self) -> None:
        self.env.close()

    # ------------------------------------------------------------------ the rest of VecEnv
    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices: Any = None, **kwargs: Any) -> list:
        result = getattr(self, method_name)(*args, **kwargs)
        return [result] * len(self._indices(indices))

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(self._indices(indices))

    def _indices(self, indices: Any) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)


def vec_env(task: str, copies: int = 1, split: str = "train", index: int = 0,
            **overrides: Any) -> BatchVecEnv:  # fmt: skip
    """``task``'s ``split`` config (``index``-th) as a ``BatchVecEnv`` of ``copies`` copies;
    ``overrides`` are ``EnvConfig`` fields (``seed``, ``episode_length``, ...). Roads run a
    fixed fleet (an AV that leaves re-enters upstream) so that rows keep their agents; a
    ring's AVs stay on their rings."""
    from mixed_traffic.benchmark import task_config

    config = task_config(task, split, index, copies=copies, **overrides)
    if config.scenario != "ring":
        config = replace(config, fixed_fleet=True)
    env = MixedTrafficEnv(config=config, metrics=False)  # rewards only
    interface = LongitudinalInterface(
        LongitudinalConfig(dt=env.config.step_length, **dict(get_task(task).learner))
    )
    interface.cap_factor = cap_factor(env.scenario.family)  # as in evaluation
    return BatchVecEnv(env, interface)
