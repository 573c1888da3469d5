"""The benchmark's learner interface as a PettingZoo wrapper: each agent observes
``Box(-5, 5, (8,))`` and acts with ``Box(-1, 1, (1,))`` (:mod:`agents.longitudinal`).

One wrapper step holds the actions for ``hold`` env steps (lane keeping re-planned every env
step) and returns the summed rewards; it ends early when an agent finishes, so the returned
dicts are always those of the last env step. ``infos`` pass through unchanged (the reward terms
of the last env step).

    from mixed_traffic.benchmark import parallel_env
    from mixed_traffic.benchmark.interface import LongitudinalWrapper
    env = LongitudinalWrapper(parallel_env("ring-v2", fixed_fleet=True))
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo.utils.env import ParallelEnv
from pettingzoo.utils.wrappers import BaseParallelWrapper

from agents.longitudinal import BOUND, N_FEATURES, LongitudinalConfig, LongitudinalInterface
from agents.rules.obs_batch import stack_obs, to_actions


class LongitudinalWrapper(BaseParallelWrapper):
    """Compact observations and one acceleration per agent (module docstring)."""

    def __init__(self, env: ParallelEnv, config: LongitudinalConfig | None = None) -> None:
        super().__init__(env)
        dt = env.unwrapped.config.step_length
        self.interface = LongitudinalInterface(config or LongitudinalConfig(dt=dt))
        if abs(self.interface.c.dt - dt) > 1e-9:
            raise ValueError(f"LongitudinalConfig.dt={self.interface.c.dt} is not the env's "
                             f"step_length={dt}")  # fmt: skip
        self._obs_space = spaces.Box(-BOUND, BOUND, (N_FEATURES,), np.float32)
        self._act_space = spaces.Box(-1.0, 1.0, (1,), np.float32)
        self._agents: list[str] = []

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Box:
        return self._act_space

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs, infos = self.env.reset(seed=seed, options=options)
        self.interface.reset()
        return self._features(obs), infos

    def step(self, actions: dict[str, Any]):
        held = {a: float(np.asarray(actions[a], np.float64).reshape(-1)[0])
                for a in self._agents if a in actions}  # fmt: skip
        missing = [a for a in self._agents if a not in held]
        if missing:
            raise ValueError(f"no action for live agent(s) {missing}")
        total: dict[str, float] = defaultdict(float)
        for _ in range(self.interface.c.hold):
            x = np.array([held.get(a, 0.0) for a in self.interface.agents])
            decision, params = self.interface.command(x)
            live = [i for i, a in enumerate(self.interface.agents) if a in self._agents]
            acts = to_actions(self._agents, decision[live], params[live])
            obs, rew, term, trunc, infos = self.env.step(acts)
            for a, r in rew.items():
                total[a] += float(r)
            feats = self._features(obs)
            if not self.env.agents or any(term.values()) or any(trunc.values()):
                break
        return feats, {a: total[a] for a in rew}, term, trunc, infos

    def _features(self, obs: dict[str, dict]) -> dict[str, np.ndarray]:
        """Per-agent features of every agent in ``obs`` (a finished one's last observation)."""
        self._agents = [a for a in obs if a in self.env.agents]
        if not obs:
            return {}
        agents = list(obs)
        return dict(zip(agents, self.interface.observe(stack_obs(obs, agents), agents)))
