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
* **longitudinal** (a clamp): when ACC-LC brakes for the chosen decision's lane (a leader, a red
  light, a lower speed limit or a curve ahead, a lane end), the learned acceleration is clamped
  to at most ACC-LC's plus ``accel_tolerance``. Otherwise the learned acceleration stands.

``AutoPolicy`` (``policies.py``) uses it unless built with ``safety=False`` (policy name
``auto-raw``). ``interventions`` counts the agent-steps it changed, which ``evaluate`` reports
as the ``sm_share`` metric.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from agents.rules.acc_lc import FOLLOW, LEFT, RIGHT, AccLcPlan, AccLcPolicy, lane_curvature
from mixed_traffic.config import VehicleConfig
from mixed_traffic.env.api import bicycle_frenet_step, to_accel_brake, to_physical


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
        kappa = lane_curvature(f)
        v, psi, d = f["v"], f["h"], f["d"].copy()
        for _ in range(max(1, round(c.horizon / c.dt))):
            v, _, dd, psi, _ = bicycle_frenet_step(
                v, psi, d, steer, accel, kappa, self.vehicle.wheelbase, c.dt
            )
            d = d + dd
        return d

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
        self, obs: Mapping[str, np.ndarray], decision: np.ndarray, params: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Learned ``decision`` (A,) and ``params`` (A, 3, 2) -> the safe ones and the
        per-agent flags ``{"lateral", "longitudinal"}`` (A,) bool of what was changed."""
        plan = self.rule.plan(obs)
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
        # the others keep their decision: clamp the acceleration where ACC-LC brakes (a clamp,
        # not a switch to ACC-LC's value: its braking carries sensor noise, and replacing
        # everything above it by it took speed away on every noisy reading)
        cap = accel_rule + self.config.accel_tolerance
        longitudinal = ~lateral & (accel_rule < 0) & (accel > cap)
        ix = (ar[longitudinal], decision[longitudinal])
        params[ix + (1,)] = to_accel_brake(cap[longitudinal], self.vehicle)
        self.decisions += len(decision)
        self.interventions["lateral"] += int(lateral.sum())
        self.interventions["longitudinal"] += int(longitudinal.sum())
        return decision, params, {"lateral": lateral, "longitudinal": longitudinal}

    @property
    def share(self) -> float | None:
        """Share of agent-steps the module changed so far [%] (None before any)."""
        if not self.decisions:
            return None
        return 100.0 * sum(self.interventions.values()) / self.decisions
