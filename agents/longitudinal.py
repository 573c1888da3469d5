"""The longitudinal interface of a learner that sets only the acceleration (as Flow's ring AV):
a compact observation of the lane ahead and behind, one action, and ACC-LC for everything else.

An outside RL library (``mixed_traffic.benchmark.ppo``) trains on it through
:class:`mixed_traffic.benchmark.interface.LongitudinalWrapper`, and the trained policy drives
through :class:`agents.ppo_policy.PpoPolicy`; both use this one class, so training and
evaluation see the same features and the same mapping.

Observation (A, 8) float32, from the env's (noisy, perceived) observation decoded by ACC-LC::

    0 v / 10 m/s                 own speed
    1 (v_lead - v) / 10 m/s      leader's relative speed (0 without a leader)
    2 gap / 50 m                 bumper gap to the leader, at most 2 (100 m; also without one)
    3 (v_rear - v) / 10 m/s      follower's relative speed (0 without a follower)
    4 rear gap / 50 m            gap to the follower, at most 2
    5 U / 10 m/s                 own mean speed over ``window`` (Stern et al.'s U)
    6 a_prev / accel_scale       the acceleration commanded last [m/s² / scale]
    7 cap / accel_scale          ACC-LC's speed cap: the road's rules (limit, lower limits
                                 ahead, red lights) as an acceleration bound, within [-1, 1]

Action: one number ``x`` in [-1, 1]: the acceleration ``x · accel_scale`` [m/s²] (with
``base="idm"`` added to the human model's IDM acceleration behind the perceived leader, so
that the zero action drives like a human and a policy learns a residual), bounded by
ACC-LC's speed cap (as FollowerStopper is), by the failsafe where ``reaction > 0`` and by the
vehicle's limits, held for ``hold`` env steps (the bounds are re-applied every env step). Lane
keeping, and driving wherever the lane must be left (follow masked), is ACC-LC's.

The failsafe is Flow's for its ring AV (SUMO's safe speed): the AV may not be faster than
Gipps's safe speed ``-b·τ + sqrt((b·τ)² + v_lead² + 2·b·(gap - s0))``, from which it can
still stop ``s0`` behind its (perceived) leader if both brake at the vehicle's ``max_decel`` b
after a reaction time τ.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from agents.rules.acc_lc import AccLcPolicy
from agents.rules.acc_lc_config import FOLLOW
from agents.rules.acc_lc_config import LANE_C as CURRENT
from agents.rules.acc_lc_features import features
from agents.rules.acc_lc_lateral import follow_steering, lateral_bounds
from agents.rules.acc_lc_longitudinal import speed_cap
from agents.rules.stern import SpeedMemory
from mixed_traffic.config import HumanConfig, VehicleConfig
from mixed_traffic.env.api import to_accel_brake

#: Feature names in observation order.
FEATURES = ("speed", "lead_rel_speed", "lead_gap", "rear_rel_speed", "rear_gap", "mean_speed",
            "last_accel", "speed_cap")  # fmt: skip
N_FEATURES = len(FEATURES)
#: Features are clipped to [-BOUND, BOUND].
BOUND = 5.0
#: What an action adds to (``LongitudinalConfig.base``).
BASES = ("none", "idm")


@dataclass(frozen=True)
class LongitudinalConfig:
    """The interface's constants (a checkpoint stores them; evaluation uses the stored ones)."""

    dt: float = 0.1
    """Env step [s]."""
    hold: int = 5
    """Env steps an action is held: the learner decides every ``hold · dt`` seconds."""
    window: float = 38.0
    """Time over which the own mean speed U is taken [s] (Stern et al. 2018)."""
    accel_scale: float = 3.0
    """Acceleration of action ±1 [m/s²]."""
    speed_scale: float = 10.0
    """Speed normalisation [m/s]."""
    gap_scale: float = 50.0
    """Gap normalisation [m]; gaps beyond 2 x this read as 2."""
    reaction: float = 0.0
    """Reaction time τ of the failsafe [s] (module docstring); 0 = no failsafe (the runs before
    ``ring-v2``)."""
    base: str = "none"
    """What the action adds to: none (it is the acceleration) | idm (the default human model's
    mean IDM, ``HumanConfig()``, with the limit as desired speed: the zero action follows like a
    human driver)."""
    standstill: float = 2.0
    """Gap s0 the failsafe keeps to a stopped leader [m] (the human model's; without it the
    safe speed lets a creeping AV close a noisy gap of centimetres)."""

    def __post_init__(self) -> None:
        for name in ("dt", "window", "accel_scale", "speed_scale", "gap_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LongitudinalConfig.{name}={getattr(self, name)!r} must be > 0")
        if not 0 <= self.reaction <= 10 or not 0 <= self.standstill <= 20:
            raise ValueError(f"LongitudinalConfig.reaction={self.reaction!r} / standstill="
                             f"{self.standstill!r}: must be in 0-10 s / 0-20 m")  # fmt: skip
        if self.base not in BASES:
            raise ValueError(f"LongitudinalConfig.base={self.base!r} not in {BASES}")
        if not (isinstance(self.hold, int) and 1 <= self.hold <= 100):
            raise ValueError(f"LongitudinalConfig.hold={self.hold!r} must be an integer in 1-100")


class _Plan(NamedTuple):
    features: dict[str, np.ndarray]
    decision: np.ndarray
    """(A,) ACC-LC's decision (follow wherever it is allowed)."""
    params: np.ndarray
    """(A, 3, 2) float32 with ACC-LC's follow steering (its whole plan where follow is masked)."""
    cap: np.ndarray
    """(A,) The acceleration bound [m/s²]: ACC-LC's speed cap and the failsafe."""
    base: np.ndarray
    """(A,) The acceleration the action adds to [m/s²] (``LongitudinalConfig.base``)."""


class LongitudinalInterface:
    """Features for a batch of agents, and their env actions from the learner's accelerations.

    Call :meth:`observe` once per env step (it advances each agent's speed memory), then
    :meth:`command` with the held actions of the same agents.
    """

    def __init__(self, config: LongitudinalConfig | None = None,
                 vehicle: VehicleConfig | None = None,
                 human: HumanConfig | None = None) -> None:  # fmt: skip
        self.c = config or LongitudinalConfig()
        self.vehicle = vehicle or VehicleConfig()
        self.human = human or HumanConfig()
        self.rule = AccLcPolicy(dt=self.c.dt)
        self._memory = SpeedMemory(max(1, round(self.c.window / self.c.dt)))
        self._plan: _Plan | None = None
        self._agents: list[str] = []
        self.cap_factor = 1.0
        """Speed cap as a share of the limit (a learned policy caps where the tuned ACC-LC
        aims: ``agents.rules.tuned.cap_factor``)."""

    @property
    def agents(self) -> list[str]:
        """The agents last observed, in feature row order."""
        return self._agents

    def reset(self) -> None:
        """Forget every agent (a new episode)."""
        self._memory = SpeedMemory(self._memory.steps)
        self._plan, self._agents = None, []

    def observe(self, obs: Mapping[str, np.ndarray], agents: Sequence[str]) -> np.ndarray:
        """Stacked (A, ...) env observations of ``agents`` -> (A, 8) float32 features."""
        self._agents = list(agents)
        self._plan = plan = self._lane_keeping(obs)
        f, c = plan.features, self.c
        v = f["v"]
        mean = self._memory.mean(self._agents, v)
        out = np.zeros((len(v), N_FEATURES))
        for col, k in ((1, 0), (3, 1)):  # leader, follower
            present = f["present"][:, CURRENT, k]
            dist = np.abs(f["vdist"][:, CURRENT, k])
            gap = dist - (f["vlen"][:, CURRENT, 0] if k == 0 else f["len"])
            out[:, col] = np.where(present, f["vrel"][:, CURRENT, k], 0.0) / c.speed_scale
            out[:, col + 1] = np.where(present, np.clip(gap, 0.0, None), np.inf) / c.gap_scale
        out[:, 0] = v / c.speed_scale
        out[:, 5] = mean / c.speed_scale
        last = self._memory.command  # the last command of each agent still present
        out[:, 6] = [last.get(a, 0.0) / c.accel_scale for a in self._agents]
        out[:, 7] = np.clip(plan.cap, -c.accel_scale, c.accel_scale) / c.accel_scale
        out[:, (2, 4)] = np.minimum(out[:, (2, 4)], 2.0)
        return np.clip(out, -BOUND, BOUND).astype(np.float32)

    def command(self, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(A,) actions in [-1, 1] of the agents last observed -> (decision (A,), params
        (A, 3, 2)): follow at the bounded acceleration, or ACC-LC's action where follow is
        masked."""
        plan = self._plan
        if plan is None:
            raise RuntimeError("LongitudinalInterface.command before observe")
        x = np.asarray(action, np.float64).reshape(-1)
        if x.shape != (len(self._agents),) or not np.all(np.isfinite(x)):
            raise ValueError(f"longitudinal actions {x!r}: expected {len(self._agents)} finite "
                             "values, one per observed agent")  # fmt: skip
        accel = np.minimum(np.clip(x, -1.0, 1.0) * self.c.accel_scale + plan.base, plan.cap)
        accel = np.clip(accel, -self.vehicle.max_decel, self.vehicle.max_accel)
        follow = plan.features["mask"][:, FOLLOW]
        decision = np.where(follow, FOLLOW, plan.decision)
        params = plan.params.copy()
        rows = np.flatnonzero(follow)
        params[rows, FOLLOW, 1] = to_accel_brake(accel[rows], self.vehicle)
        self._memory.command.update(zip(self._agents, accel.tolist()))
        return decision, params

    def _failsafe(self, f: dict[str, np.ndarray]) -> np.ndarray:
        """(A,) the acceleration [m/s²] that reaches Gipps's safe speed in one env step
        (+inf without a leader)."""
        b, tau = self.vehicle.max_decel, self.c.reaction
        present, gap, lead = _leader(f)
        room = np.maximum(gap - self.c.standstill, 0.0)
        safe = -b * tau + np.sqrt((b * tau) ** 2 + lead**2 + 2 * b * room)
        return np.where(present, (safe - f["v"]) / self.c.dt, np.inf)

    def _base(self, f: dict[str, np.ndarray]) -> np.ndarray:
        """(A,) the acceleration the action adds to [m/s²]: 0, or the human model's mean IDM
        (Treiber's, desired speed the lane's limit) behind the perceived leader."""
        if self.c.base == "none":
            return np.zeros(len(f["v"]))
        _, gap, lead = _leader(f)  # gap inf without a leader: IDM's free road
        limit = f["wp_speed"][:, CURRENT, 0]
        v0 = np.where(limit > 0.5, limit, 13.9) * self.cap_factor
        return self.human.idm_accel(f["v"], lead, gap, v0)

    def _lane_keeping(self, obs: Mapping[str, np.ndarray]) -> _Plan:
        """ACC-LC's lane keeping and speed cap; its whole plan only where follow is masked."""
        c = self.rule.c
        f = features(obs, c)
        cap = speed_cap(f, c, factor=self.cap_factor)
        if self.c.reaction > 0:
            cap = np.minimum(cap, self._failsafe(f))
        base = self._base(f)
        if not f["mask"][:, FOLLOW].all():
            plan = self.rule.plan(obs)
            return _Plan(f, plan.decision, np.array(plan.params, np.float32), cap, base)
        lo, hi = lateral_bounds(f, c)
        params = np.zeros((len(f["v"]), 3, 2), np.float32)
        params[:, FOLLOW, 0] = follow_steering(f, c, lo, hi)
        return _Plan(f, np.full(len(f["v"]), FOLLOW), params, cap, base)


def _leader(f: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A,) whether a leader is perceived in the lane, the bumper gap to it [m] and its speed
    [m/s] (inf and 0 without one)."""
    present = f["present"][:, CURRENT, 0]
    gap = np.abs(f["vdist"][:, CURRENT, 0]) - f["vlen"][:, CURRENT, 0]
    lead = np.maximum(f["v"] + f["vrel"][:, CURRENT, 0], 0.0)
    return present, np.where(present, gap, np.inf), np.where(present, lead, 0.0)
