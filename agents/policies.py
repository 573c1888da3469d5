"""Policies that drive the env's agents from observations, by name or spec: auto, auto-raw,
acc-lc (``acc-lc:T=1.0,speed_factor=1.0``: :mod:`agents.rules.spec`), acc-lc-tuned, random, ...

Every policy maps a *batch* of observations (each key stacked over the A agents of a step) to
``(decision (A,), params (A, 3, 2))`` in one call, so inference is one batched pass per step.
``OBS_KEYS``, ``stack_obs`` and ``to_actions`` live in :mod:`agents.rules.obs_batch` (below every
policy, so ACC-LC does not import this module) and are re-exported here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from agents.rules.obs_batch import OBS_KEYS, stack_obs, to_actions
from agents.rules.spec import RULE_CONFIGS, PolicySpec, build_config, parse_policy
from mixed_traffic.config import EnvConfig
from mixed_traffic.schema import AUTO_POLICIES, STUDY_POLICIES

SHIPPED_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "auto.pt"
PPO_RING = SHIPPED_CHECKPOINT.parent / "ppo_ring.zip"
"""The shipped PPO policy of the benchmark's ring task (``--policy ppo-ring``)."""
AUTO_RING = SHIPPED_CHECKPOINT.parent / "auto_ring.pt"
"""RBP-DQN trained on the ring family alone (issue 43: ``auto-ring``)."""
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
    AUTO (auto, auto-raw), the shipped ring PPO (ppo-ring) or the study's
    ``STUDY_CHECKPOINTS/<name>.pt``; ``ValueError`` for ``ppo`` without a checkpoint."""
    if checkpoint is not None:
        return Path(checkpoint)
    if name == "ppo":
        raise ValueError("policy 'ppo' needs --checkpoint: a .zip written by "
                         "python -m mixed_traffic.benchmark.ppo")  # fmt: skip
    if name == "ppo-ring":
        return PPO_RING
    if name == "auto-ring":
        return AUTO_RING
    return SHIPPED_CHECKPOINT if name in AUTO_POLICIES else STUDY_CHECKPOINTS / f"{name}.pt"


def with_inputs(config: EnvConfig, name: str, checkpoint: str | Path | None = None) -> EnvConfig:
    """``config`` with the opt-in observation keys (``memory``, ``downstream``) that learned
    policy ``name`` was trained with switched on, as its checkpoint's training env had them;
    ``config`` itself for every other policy."""
    base = parse_policy(name).base
    if base not in AUTO_POLICIES and base not in STUDY_POLICIES:
        return config
    from agents.checkpoint import read_checkpoint

    meta = read_checkpoint(checkpoint_path(base, checkpoint))["meta"]
    trained = EnvConfig.from_dict(meta.get("env_base", {}))
    if trained.sensors.memory:
        sensors = replace(config.sensors, memory=True, memory_taus=trained.sensors.memory_taus)
        config = replace(config, sensors=sensors)
    if trained.v2x:
        config = replace(config, v2x=True, v2x_feed=trained.v2x_feed)
    return config


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
        family: str | None = None,
    ) -> None:
        """``dt``: the env's simulation step [s]; ``name``: the policy's (default auto, or
        auto-raw without the safety module); ``family``: the scenario family, for a policy
        that corrects ``acc-lc-tuned``."""
        from agents.checkpoint import load_driver
        from agents.rules.safety import SafetyModule

        path = Path(checkpoint) if checkpoint is not None else SHIPPED_CHECKPOINT
        self.checkpoint = path.resolve()
        self.name = name or ("auto" if safety else "auto-raw")
        self.driver = load_driver(path, dt, z=z, m=m, family=family)
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
                m: int | None = None, dt: float = 0.1, family: str | None = None) -> BatchPolicy:  # fmt: skip
    """A policy by name or spec (``acc-lc:T=1.0,speed_factor=1.0``, :mod:`agents.rules.spec`);
    ``z``/``m`` are the env's history and waypoint counts (checked for auto), ``dt`` the time
    between its decisions [s], ``family`` the scenario family (``acc-lc-tuned`` drives with its
    tuned parameters, and a learned policy's governor caps at that ACC-LC's speed). The policy's
    ``params`` are the parameters it resolved to (the records carry them)."""
    spec = parse_policy(name)
    base = spec.base
    if base == "random":
        return RandomPolicy(seed)
    if base in RULE_CONFIGS:
        return _rule(spec, dt, family)
    if base in ("ppo", "ppo-ring"):
        from agents.ppo_policy import PpoPolicy
        from agents.rules.tuned import cap_factor

        ppo = PpoPolicy(checkpoint_path(base, checkpoint), dt=dt, name=base)
        ppo.interface.cap_factor = cap_factor(family)
        return ppo
    if base in AUTO_POLICIES or base in STUDY_POLICIES:
        from agents.rules.tuned import cap_factor

        path = checkpoint_path(base, checkpoint)
        policy = AutoPolicy(path, z=z, m=m, safety=base != "auto-raw", dt=dt, name=base,
                            family=family)  # fmt: skip
        policy.driver.cap_factor = cap_factor(family)
        policy.params = {"speed_cap_factor": policy.driver.cap_factor}
        return policy
    raise ValueError(f"policy {base!r} drives no agent here (SUMO drives the AVs under it)")


def _rule(spec: PolicySpec, dt: float, family: str | None) -> BatchPolicy:
    """A rule-based policy (ACC-LC or Stern et al.'s) with the spec's parameters."""
    from agents.rules.acc_lc import AccLcPolicy
    from agents.rules.acc_lc_config import AccLcConfig, conservative
    from agents.rules.stern import FollowerStopper, PISaturation, SternConfig

    params, extra, checkpoint = spec.overrides, {}, None
    if spec.base == "acc-lc-tuned":
        from agents.rules.tuned import TUNED_FILE, tuned_params

        tuned = tuned_params(family)
        extra = {"tuned_for": tuned.pop("tuned_for")}
        checkpoint = TUNED_FILE
        params = {**tuned, **params}  # the spec's own fields win
    if spec.base.startswith("acc-lc"):
        start = conservative() if spec.base == "acc-lc-conservative" else AccLcConfig()
        policy: Any = AccLcPolicy(build_config(AccLcConfig, {**params, "dt": dt}, spec.base, start))
    else:
        cls = FollowerStopper if spec.base == "follower-stopper" else PISaturation
        policy = cls(build_config(SternConfig, {**params, "dt": dt}, spec.base))
    policy.name = str(spec)
    policy.params = {**params, **extra}
    policy.checkpoint = checkpoint  # a record names the file its parameters came from
    return policy
