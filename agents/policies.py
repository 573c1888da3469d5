"""Policies that drive the env's agents from observations, by name: auto, auto-raw, acc-lc,
random.

Every policy maps a *batch* of observations (each key stacked over the A agents of a step) to
``(decision (A,), params (A, 3, 2))`` in one call, so inference is one batched pass per step.
``OBS_KEYS``, ``stack_obs`` and ``to_actions`` live in :mod:`agents.rules.obs_batch` (below every
policy, so ACC-LC does not import this module) and are re-exported here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Protocol

import numpy as np

from agents.rules.obs_batch import OBS_KEYS, stack_obs, to_actions
from mixed_traffic.schema import STUDY_POLICIES

SHIPPED_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "auto.pt"
STUDY_CHECKPOINTS = SHIPPED_CHECKPOINT.parent / "study"
"""Checkpoints of the study policies (``mixed_traffic.schema.STUDY_POLICIES``), <name>.pt."""

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


def checkpoint_path(name: str, checkpoint: str | Path | None = None) -> Path:
    """The weights learned policy ``name`` runs: ``checkpoint`` if given, else the shipped
    AUTO (auto, auto-raw) or the study's ``STUDY_CHECKPOINTS/<name>.pt``."""
    if checkpoint is not None:
        return Path(checkpoint)
    return SHIPPED_CHECKPOINT if name in ("auto", "auto-raw") else STUDY_CHECKPOINTS / f"{name}.pt"


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
        name: str | None = None,
    ) -> None:
        """``dt``: the env's simulation step [s]; ``name``: the policy's (default auto, or
        auto-raw without the safety module)."""
        from agents.checkpoint import load_driver
        from agents.rules.safety import SafetyModule

        path = Path(checkpoint) if checkpoint is not None else SHIPPED_CHECKPOINT
        self.checkpoint = path.resolve()
        self.name = name or ("auto" if safety else "auto-raw")
        self.driver = load_driver(path, dt, z=z, m=m)
        self.safety = SafetyModule(rule=self.driver.teacher) if safety else None

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
        from agents.rules.acc_lc_config import AccLcConfig, conservative

        base = conservative() if name == "acc-lc-conservative" else AccLcConfig()
        return AccLcPolicy(replace(base, dt=dt))
    if name in ("auto", "auto-raw"):
        return AutoPolicy(checkpoint, z=z, m=m, safety=name == "auto", dt=dt)
    if name in STUDY_POLICIES:  # trained by mixed_traffic.study, behind the safety module
        return AutoPolicy(checkpoint_path(name, checkpoint), z=z, m=m, dt=dt, name=name)
    if name in ("follower-stopper", "pi-saturation"):
        from agents.rules.stern import FollowerStopper, PISaturation, SternConfig

        cls = FollowerStopper if name == "follower-stopper" else PISaturation
        return cls(SternConfig(dt=dt))
    raise ValueError(f"unknown policy {name!r}; choose from auto, auto-raw, acc-lc, "
                     "acc-lc-conservative, random, follower-stopper, pi-saturation, "
                     f"{', '.join(STUDY_POLICIES)}")  # fmt: skip
