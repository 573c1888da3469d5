"""Policies that drive the env's agents from observations, by name: auto, auto-raw, acc-lc,
random.

Every policy maps a *batch* of observations (each key stacked over the A agents of a step) to
``(decision (A,), params (A, 3, 2))`` in one call, so inference is one batched pass per step.
``OBS_KEYS``, ``stack_obs`` and ``to_actions`` live in :mod:`agents.rules.obs_batch` (below every
policy, so ACC-LC does not import this module) and are re-exported here.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from agents.rules.obs_batch import OBS_KEYS, stack_obs, to_actions

SHIPPED_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "auto.pt"

__all__ = [
    "OBS_KEYS",
    "SHIPPED_CHECKPOINT",
    "AutoPolicy",
    "BatchPolicy",
    "RandomPolicy",
    "make_policy",
    "stack_obs",
    "to_actions",
]


class BatchPolicy(Protocol):
    name: str

    def act(
        self, obs: dict[str, np.ndarray], agents: Sequence[str] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """obs (A, ...) per key of the ``agents`` (ids, for policies with a memory per agent)
        -> (decision (A,) int, params (A, 3, 2) float in [-1, 1])."""


class RandomPolicy:
    """Uniform random parameters and a uniformly random *allowed* decision."""

    name = "random"

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)

    def act(
        self, obs: dict[str, np.ndarray], agents: Sequence[str] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        mask = obs["action_mask"].astype(bool)
        a = len(mask)
        scores = self.rng.random((a, 3)) + mask  # any allowed decision beats every masked one
        return scores.argmax(axis=1), self.rng.uniform(-1, 1, (a, 3, 2)).astype(np.float32)


class AutoPolicy:
    """The AUTO agent (LCA + RBP-DQN actor/critic) from a checkpoint, greedy, deciding every
    decision interval of its checkpoint (``agents.driver``), behind the safety module
    (``agents.rules.safety``) unless ``safety=False`` (name ``auto-raw``)."""

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        z: int | None = None,
        m: int | None = None,
        safety: bool = True,
        dt: float = 0.1,
    ) -> None:
        """``dt``: the env's simulation step [s]."""
        from agents.checkpoint import load_driver
        from agents.rules.safety import SafetyModule

        path = Path(checkpoint) if checkpoint is not None else SHIPPED_CHECKPOINT
        self.checkpoint = path.resolve()
        self.name = "auto" if safety else "auto-raw"
        self.driver = load_driver(path, dt, z=z, m=m)
        self.safety = SafetyModule() if safety else None

    def act(
        self, obs: dict[str, np.ndarray], agents: Sequence[str] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        names = list(agents) if agents is not None else [str(i) for i in range(len(obs["ego"]))]
        cmd = self.driver.act(obs, names)
        decision, params = cmd.decision, cmd.params
        if self.safety is not None:
            decision, params, _ = self.safety.filter(obs, decision, params, self.driver.plan)
        return decision, params


def make_policy(name: str, *, seed: int = 0, checkpoint: str | Path | None = None, z: int | None = None,
                m: int | None = None, dt: float = 0.1) -> BatchPolicy:  # fmt: skip
    """A policy by name; ``z``/``m`` are the env's history and waypoint counts (checked for
    auto), ``dt`` the time between its decisions [s]."""
    if name == "random":
        return RandomPolicy(seed)
    if name in ("acc-lc", "acc-lc-conservative"):
        from agents.rules.acc_lc import AccLcPolicy
        from agents.rules.acc_lc_config import conservative

        return AccLcPolicy(conservative() if name == "acc-lc-conservative" else None)
    if name in ("auto", "auto-raw"):
        return AutoPolicy(checkpoint, z=z, m=m, safety=name == "auto", dt=dt)
    if name in ("follower-stopper", "pi-saturation"):
        from agents.rules.stern import FollowerStopper, PISaturation, SternConfig

        cls = FollowerStopper if name == "follower-stopper" else PISaturation
        return cls(SternConfig(dt=dt))
    raise ValueError(f"unknown policy {name!r}; choose from auto, auto-raw, acc-lc, "
                     "acc-lc-conservative, random, follower-stopper, pi-saturation")  # fmt: skip
