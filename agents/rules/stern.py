"""The wave-dampening controllers of Stern et al. 2018 ("Dissipation of stop-and-go waves via
control of autonomous vehicles: Field experiments", Transp. Res. C 89): FollowerStopper and
the PI controller with saturation, as batch policies over the env's observations.

Both command a velocity v_cmd from the bumper gap Δx to the leader in the ego's lane, the
leader's speed v_lead and the AV's own speed v; the AV tracks it in one step (acceleration
(v_cmd − v)/dt within its limits and below ACC-LC's speed cap, so that it keeps the speed
limits, slows for lower ones ahead and stops at red lights as ACC-LC does). They are
longitudinal controllers: the lane is kept with ACC-LC's lateral control, and where the lane
must be left (follow masked) ACC-LC drives.

FollowerStopper: with Δv⁻ = min(v_lead − v, 0) and Δx_k = Δx⁰_k + (Δv⁻)² / (2 d_k), k = 1..3,
v_cmd is 0 below Δx_1, rises linearly to min(max(v_lead, 0), U) at Δx_2 and to U at Δx_3, and
is U beyond. Stern et al. set the desired speed U by hand (6.5-7.5 m/s on their ring); here U
is ``desired_speed`` if given, else the AV's own mean speed over the last ``window`` seconds
(as the PI controller estimates it), so that the controller needs no tuning per road.

PI with saturation: U is the AV's mean speed over ``window``; v_target = U + v_catch ·
clip((Δx − g_l) / (g_u − g_l), 0, 1); with Δx_s = max(2 (v_lead − v), 4 m), α = clip((Δx −
Δx_s) / γ, 0, 1) and β = 1 − α / 2, v_cmd ← β (α v_target + (1 − α) v_lead) + (1 − β) v_cmd.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from agents.rules.acc_lc import AccLcPolicy
from agents.rules.acc_lc_config import FOLLOW, check_rule_fields
from agents.rules.acc_lc_config import LANE_C as CURRENT
from mixed_traffic.config import VehicleConfig
from mixed_traffic.env.api import to_accel_brake


@dataclass(frozen=True)
class SternConfig:
    """Parameters of both controllers (Stern et al. 2018, §2)."""

    desired_speed: float = 0.0
    """FollowerStopper's U [m/s]; 0 = the AV's own mean speed over ``window``."""
    window: float = 38.0
    """Time over which the AV's mean speed U is taken [s]."""
    dx0: tuple[float, float, float] = (4.5, 5.25, 6.0)
    """FollowerStopper's gaps Δx⁰_1..3 at equal speeds [m]."""
    decel: tuple[float, float, float] = (1.5, 1.0, 0.5)
    """FollowerStopper's d_1..3, how the gaps widen when closing in [m/s²]."""
    v_catch: float = 1.0
    """PI: extra speed to close a large gap [m/s]."""
    gap_low: float = 7.0
    """PI: gap g_l from which the extra speed starts [m]."""
    gap_high: float = 30.0
    """PI: gap g_u at which the extra speed is full [m]."""
    gamma: float = 2.0
    """PI: width of the blend between the leader's speed and the target [m]."""
    safe_gap: float = 4.0
    """PI: smallest Δx_s [m]."""
    dt: float = 0.1
    """Time between decisions [s]."""

    def __post_init__(self) -> None:
        check_rule_fields(self, ("window", "gamma", "dt", "decel"))


class SpeedMemory:
    """Each agent's speeds over the last ``window`` seconds, and its last command."""

    def __init__(self, steps: int) -> None:
        self.steps = steps
        self.speeds: dict[str, list[float]] = {}
        self.command: dict[str, float] = {}

    def mean(self, agents: Sequence[str], v: np.ndarray) -> np.ndarray:
        """Add this step's speeds (A,) [m/s]; (A,) the mean over each agent's window."""
        alive = set(agents)
        for a in [a for a in self.speeds if a not in alive]:  # agents that left
            del self.speeds[a]
            self.command.pop(a, None)
        out = np.empty(len(agents))
        for i, (a, speed) in enumerate(zip(agents, v.tolist())):
            hist = self.speeds.setdefault(a, [])
            hist.append(speed)
            del hist[: max(0, len(hist) - self.steps)]
            out[i] = sum(hist) / len(hist)
        return out


class _SternPolicy:
    """ACC-LC's lateral control with a Stern velocity law; subclasses give ``v_cmd``."""

    name = ""

    def __init__(self, config: SternConfig | None = None, vehicle: VehicleConfig | None = None):
        self.c = config or SternConfig()
        self.vehicle = vehicle or VehicleConfig()
        self.rule = AccLcPolicy(dt=self.c.dt)
        self.memory = SpeedMemory(max(1, round(self.c.window / self.c.dt)))

    def act(self, obs: Mapping[str, np.ndarray], agents: Sequence[str] | None = None):
        """Batched (A, ...) observations of ``agents`` -> (decision (A,), params (A, 3, 2))."""
        plan = self.rule.plan(obs)
        f = plan.features
        n = len(f["v"])
        agents = list(agents) if agents is not None else [str(i) for i in range(n)]
        v = f["v"]
        lead = f["present"][:, CURRENT, 0]
        gap = np.where(lead, f["vdist"][:, CURRENT, 0] - f["vlen"][:, CURRENT, 0], np.inf)
        v_lead = np.where(lead, v + f["vrel"][:, CURRENT, 0], np.inf)
        u = self.memory.mean(agents, v)
        v_cmd = self.command(agents, np.maximum(gap, 0.0), v, v_lead, u)
        # the road's rules bound the law as they bound ACC-LC: the speed limit here and the
        # lower ones ahead (a slow zone), red lights and give-way lines
        accel = np.minimum((v_cmd - v) / self.c.dt, plan.speed_cap())
        accel = np.clip(accel, -self.vehicle.max_decel, self.vehicle.max_accel)
        follow = f["mask"][:, FOLLOW]
        decision = np.where(follow, FOLLOW, plan.decision)
        params = np.array(plan.params, np.float32, copy=True)
        rows = np.flatnonzero(follow)
        params[rows, FOLLOW, 1] = to_accel_brake(accel[rows], self.vehicle)
        return decision, params

    def command(self, agents, gap, v, v_lead, u) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


class FollowerStopper(_SternPolicy):
    """FollowerStopper (module docstring)."""

    name = "follower-stopper"

    def command(self, agents: Sequence[str], gap: np.ndarray, v: np.ndarray,
                v_lead: np.ndarray, u: np.ndarray) -> np.ndarray:  # fmt: skip
        """(A,) commanded speed [m/s] from gaps [m] and speeds [m/s] (A,)."""
        c = self.c
        target = np.full_like(v, c.desired_speed) if c.desired_speed > 0 else u
        closing = np.minimum(np.where(np.isfinite(v_lead), v_lead - v, 0.0), 0.0)
        dx1, dx2, dx3 = (x0 + closing**2 / (2.0 * d) for x0, d in zip(c.dx0, c.decel))
        slow = np.minimum(np.maximum(np.where(np.isfinite(v_lead), v_lead, target), 0.0), target)
        with np.errstate(invalid="ignore"):  # 0 x inf without a leader: target is selected
            ramp1 = slow * (gap - dx1) / (dx2 - dx1)
            ramp2 = slow + (target - slow) * (gap - dx2) / (dx3 - dx2)
        return np.select([gap <= dx1, gap <= dx2, gap <= dx3], [0.0, ramp1, ramp2], target)


class PISaturation(_SternPolicy):
    """PI controller with saturation (module docstring)."""

    name = "pi-saturation"

    def command(self, agents: Sequence[str], gap: np.ndarray, v: np.ndarray,
                v_lead: np.ndarray, u: np.ndarray) -> np.ndarray:  # fmt: skip
        """(A,) commanded speed [m/s] from gaps [m] and speeds [m/s] (A,)."""
        c = self.c
        free = ~np.isfinite(v_lead)
        v_lead = np.where(free, u, v_lead)
        target = u + c.v_catch * np.clip((gap - c.gap_low) / (c.gap_high - c.gap_low), 0.0, 1.0)
        safe = np.maximum(2.0 * (v_lead - v), c.safe_gap)
        alpha = np.where(free, 1.0, np.clip((gap - safe) / c.gamma, 0.0, 1.0))
        beta = 1.0 - 0.5 * alpha
        last = np.array([self.memory.command.get(a, s) for a, s in zip(agents, v.tolist())])
        cmd = beta * (alpha * target + (1.0 - alpha) * v_lead) + (1.0 - beta) * last
        self.memory.command.update(zip(agents, cmd.tolist()))
        return cmd
