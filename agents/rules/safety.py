"""Safety module: checks every learned action and falls back to the rule-based driver.

The paper's related work (§VI) notes that industrial driving stacks always place a safety module
behind the learned decision maker: it checks whether the action is safe and, if not, the vehicle
enters a safe mode in which a rule-based method computes the action. This is that module, with
ACC-LC (``agents.rules.acc_lc``) as the rule-based method. Per agent and step:

* **lateral** (safe mode): the learned (steering, accel) is held for ``horizon`` seconds in the
  env's kinematic bicycle model (``mixed_traffic.env.control``). If the predicted lateral offset
  leaves the corridor of the chosen decision and moves outwards, the agent takes ACC-LC's whole
  action (decision and parameters). The corridor is the current lane, plus the target lane when
  ACC-LC accepts the gap there, minus room kept clear of vehicles alongside. In its lane, the
  ego may also not drift outwards by more than ``drift_tolerance`` beyond where ACC-LC's
  steering would take it (the prediction's curvature is crude in S-bends). A mandatory
  change (the lane ends within ``observation.MANDATORY_DISTANCE`` and follow is masked) is
  always driven in safe mode: the learned policy missed such exits (route deviations).
* **longitudinal** (``SafetyConfig.longitudinal``, default ``rss``): the learned acceleration
  stands while it is RSS-safe (``agents.rules.rss``) behind every leader of the chosen
  decision's lane (the virtual vehicle at a lane's end is a stopped leader) and within ACC-LC's
  speed cap (limits and curves ahead, red and yellow lights, give-way lines). Above
  that it is capped, never below ACC-LC's own plus ``accel_tolerance``. The older ``clamp``
  held it to ACC-LC's plus ``accel_tolerance`` whenever ACC-LC braked, i.e. to ACC-LC's 1.4 s
  comfort gap: it changed 73-89 % of a learned policy's actions.

``AutoPolicy`` (``policies.py``) uses it unless built with ``safety=False`` (policy name
``auto-raw``). ``interventions`` counts the agent-steps it changed, which ``evaluate`` reports
as the ``sm_share`` metric.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from agents.rules.acc_lc import FOLLOW, LEFT, RIGHT, AccLcPlan, AccLcPolicy, lane_curvature
from agents.rules.rss import RssConfig
from mixed_traffic.config import VehicleConfig
from mixed_traffic.env.api import bicycle_rollout, to_accel_brake, to_physical


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds of the safety module."""

    horizon: float = 1.0
    """Time the learned steering and acceleration are held in the lateral prediction [s]."""
    dt: float = 0.1
    """Integration step of the prediction [s]."""
    lane_margin: float = 0.0
    """How far the ego's side may pass its lane's edge without a lane change [m] (0: two
    vehicles in neighbouring lanes, each at its edge, still clear each other)."""
    drift_tolerance: float = 0.3
    """How much farther from the lane centre than both now and ACC-LC's steering would take it
    the learned steering may take the ego within the horizon, in its lane [m]."""
    accel_tolerance: float = 0.3
    """How far the learned acceleration may exceed ACC-LC's when ACC-LC brakes [m/s²] (about
    the spread of ACC-LC's acceleration from sensor noise in steady following)."""
    longitudinal: str = "rss"
    """``rss``: the learned acceleration stands while it keeps an RSS-safe distance to every
    leader (``rss``) and stays within ACC-LC's speed cap (limits, curves, lights); ``clamp``:
    it may exceed ACC-LC's by at most ``accel_tolerance`` whenever ACC-LC brakes."""
    rss: RssConfig = field(default_factory=RssConfig)
    """The RSS rule's assumptions (``agents.rules.rss``)."""

    def __post_init__(self) -> None:
        if self.longitudinal not in ("rss", "clamp"):
            raise ValueError(
                f"SafetyConfig.longitudinal={self.longitudinal!r}; allowed 'rss' or 'clamp'"
            )


class SafetyModule:
    """Filters a batch of learned actions (see the module docstring)."""

    def __init__(
        self,
        config: SafetyConfig | None = None,
        rule: AccLcPolicy | None = None,
        vehicle: VehicleConfig | None = None,
    ) -> None:
        self.config = config or SafetyConfig()
        self.rule = rule or AccLcPolicy()
        self.vehicle = vehicle or VehicleConfig()
        self.interventions = {"lateral": 0, "longitudinal": 0}
        self.decisions = 0

    def predicted_offset(self, plan: AccLcPlan, steer: np.ndarray, accel: np.ndarray) -> np.ndarray:
        """(A,) lateral offset [m, current-lane frame] after holding the physical ``steer``
        [rad] and ``accel`` [m/s²] (A,) for ``horizon`` seconds."""
        c, f = self.config, plan.features
        steps = max(1, round(c.horizon / c.dt))
        return bicycle_rollout(f["v"], f["h"], f["d"], steer, accel, lane_curvature(f),
                               self.vehicle.wheelbase, c.dt, steps)  # fmt: skip

    def corridor(self, plan: AccLcPlan, decision: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(A,) lowest and highest lateral offset [m] the chosen decision may reach."""
        f, rc = plan.features, self.rule.c
        ar = np.arange(len(decision))
        half = 0.5 * rc.lane_width_min - 0.5 * f["wid"] + self.config.lane_margin
        ok = plan.lateral_ok[ar, decision]
        hi = half + np.where((decision == LEFT) & ok, rc.lane_shift, 0.0)
        lo = -half - np.where((decision == RIGHT) & ok, rc.lane_shift, 0.0)
        # vehicles alongside (ACC-LC's bounds keep a side margin; allow half of it)
        slack = 0.5 * rc.side_margin
        return np.maximum(lo, plan.lo - slack), np.minimum(hi, plan.hi + slack)

    def filter(
        self,
        obs: Mapping[str, np.ndarray],
        decision: np.ndarray,
        params: np.ndarray,
        plan: AccLcPlan | None = None,
    ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Learned ``decision`` (A,) and ``params`` (A, 3, 2) -> the safe ones and the
        per-agent flags ``{"lateral", "longitudinal"}`` (A,) bool of what was changed.
        ``plan``: ACC-LC's plan of these ``obs`` if the caller has it (else made here)."""
        plan = plan if plan is not None else self.rule.plan(obs)
        decision = np.asarray(decision, np.int64).copy()
        params = np.asarray(params, np.float32).copy()
        ar = np.arange(len(decision))
        steer, accel = to_physical(decision, params, self.vehicle)
        steer_rule, accel_rule = to_physical(decision, plan.params, self.vehicle)
        d_now = plan.features["d"]
        d_new = self.predicted_offset(plan, steer, accel)
        lo, hi = self.corridor(plan, decision)
        lateral = ((d_new > hi) & (d_new > d_now)) | ((d_new < lo) & (d_new < d_now))
        # staying in the lane: no drift outwards beyond where ACC-LC's steering would go (the
        # prediction's curvature is crude, e.g. in the S-bend of a lane drop; both share it)
        in_lane = (decision == FOLLOW) | ~plan.lateral_ok[ar, decision]
        d_rule = self.predicted_offset(plan, steer_rule, accel_rule)
        away = np.abs(d_new) - np.maximum(np.abs(d_rule), np.abs(d_now))
        lateral |= in_lane & (away > self.config.drift_tolerance)
        # a lane that must be left (follow masked): the learned policy misses the exit
        lateral |= ~plan.features["mask"][:, FOLLOW]
        decision[lateral] = plan.decision[lateral]
        params[lateral] = plan.params[lateral]
        # the others keep their decision; the acceleration is capped (not replaced by ACC-LC's:
        # its braking carries sensor noise, and replacing everything above it by it took
        # speed away on every noisy reading)
        cap = self.accel_cap(plan, decision, accel_rule)
        longitudinal = ~lateral & (accel > cap)
        ix = (ar[longitudinal], decision[longitudinal])
        params[ix + (1,)] = to_accel_brake(cap[longitudinal], self.vehicle)
        self.decisions += len(decision)
        self.interventions["lateral"] += int(lateral.sum())
        self.interventions["longitudinal"] += int(longitudinal.sum())
        return decision, params, {"lateral": lateral, "longitudinal": longitudinal}

    def accel_cap(
        self, plan: AccLcPlan, decision: np.ndarray, accel_rule: np.ndarray
    ) -> np.ndarray:
        """(A,) highest acceptable acceleration [m/s²] for the chosen ``decision``, given
        ACC-LC's ``accel_rule`` for it (see ``SafetyConfig.longitudinal``). Never below
        ACC-LC's plus the tolerance, so ACC-LC itself is never changed."""
        c = self.config
        rule_cap = accel_rule + c.accel_tolerance
        if c.longitudinal == "clamp":
            return np.where(accel_rule < 0, rule_cap, np.inf)
        a_rss = plan.rss_caps(c.rss)[np.arange(len(decision)), decision]
        static = plan.speed_cap() + c.accel_tolerance
        return np.maximum(rule_cap, np.minimum(static, a_rss))

    @property
    def shares(self) -> dict[str, float | None]:
        """``sm_lateral`` / ``sm_longitudinal``: share of agent-steps each check changed [%]."""
        n = self.decisions
        return {f"sm_{k}": 100.0 * v / n if n else None for k, v in self.interventions.items()}

    @property
    def share(self) -> float | None:
        """Share of agent-steps the module changed so far [%] (None before any)."""
        if not self.decisions:
            return None
        return 100.0 * sum(self.interventions.values()) / self.decisions
