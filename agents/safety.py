"""Safety module: checks every learned action and falls back to the rule-based driver.

The paper's related work (§VI) notes that industrial driving stacks always place a safety module
behind the learned decision maker: it checks whether the action is safe and, if not, the vehicle
enters a safe mode in which a rule-based method computes the action. This is that module, with
ACC-LC (``agents.acc_lc``) as the rule-based method. Per agent and step:

* **lateral** (safe mode): the learned (steering, accel) is held for ``horizon`` seconds in the
  env's kinematic bicycle model (``mixed_traffic.control``). If the predicted lateral offset
  leaves the corridor of the chosen decision and moves outwards, the agent takes ACC-LC's whole
  action (decision and parameters). The corridor is the current lane, plus the target lane when
  ACC-LC accepts the gap there, minus room kept clear of vehicles alongside. In its lane, the
  ego may also not drift outwards by more than ``drift_tolerance`` beyond where ACC-LC's
  steering would take it (the prediction's curvature is crude in S-bends). A mandatory
  change (the lane ends within ``observation.MANDATORY_DISTANCE`` and follow is masked) is
  always driven in safe mode: the learned policy missed such exits (route deviations).
* **longitudinal** (a cap): when ACC-LC brakes for the chosen decision's lane (a leader, a red
  light, a lower speed limit or a curve ahead, a lane end), the learned acceleration may not
  exceed ACC-LC's. Otherwise the learned acceleration stands.

``AutoPolicy`` (``policies.py``) uses it unless built with ``safety=False`` (policy name
``auto-raw``). ``interventions`` counts the agent-steps it changed, which ``evaluate`` reports
as the ``sm_share`` metric.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from agents.acc_lc import _C, FOLLOW, LEFT, RIGHT, AccLcPlan, AccLcPolicy
from mixed_traffic.config import VehicleConfig
from mixed_traffic.control import bicycle_frenet_step


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
    accel_tolerance: float = 0.1
    """Learned acceleration above ACC-LC's braking that is still accepted [m/s²]."""


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

    def _accel(self, ab: np.ndarray) -> np.ndarray:
        """accel_brake in [-1, 1] -> [m/s²] (as ``mixed_traffic.action``)."""
        return np.where(ab > 0, ab * self.vehicle.max_accel, ab * self.vehicle.max_decel)

    def predicted_offset(self, plan: AccLcPlan, steer: np.ndarray, ab: np.ndarray) -> np.ndarray:
        """(A,) lateral offset [m, current-lane frame] after holding ``steer``/``ab`` (A,) in
        [-1, 1] for ``horizon`` seconds."""
        c, f = self.config, plan.features
        o = f["wp_orient"][:, _C]
        w = min(5, o.shape[1] - 1)
        kappa = np.where(f["exists"][:, _C], (o[:, w] - o[:, 0]) / max(w, 1), 0.0)
        delta = steer * np.deg2rad(self.vehicle.max_steer_deg)
        acc = self._accel(ab)
        v, psi, d = f["v"], f["h"], f["d"].copy()
        for _ in range(max(1, round(c.horizon / c.dt))):
            v, _, dd, psi, _ = bicycle_frenet_step(
                v, psi, d, delta, acc, kappa, self.vehicle.wheelbase, c.dt
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
        row = params[ar, decision]
        d_now = plan.features["d"]
        d_new = self.predicted_offset(plan, row[:, 0], row[:, 1])
        lo, hi = self.corridor(plan, decision)
        lateral = ((d_new > hi) & (d_new > d_now)) | ((d_new < lo) & (d_new < d_now))
        # staying in the lane: no drift outwards beyond where ACC-LC's steering would go (the
        # prediction's curvature is crude, e.g. in the S-bend of a lane drop; both share it)
        in_lane = (decision == FOLLOW) | ~plan.lateral_ok[ar, decision]
        rule = plan.params[ar, decision]
        d_rule = self.predicted_offset(plan, rule[:, 0], rule[:, 1])
        away = np.abs(d_new) - np.maximum(np.abs(d_rule), np.abs(d_now))
        lateral |= in_lane & (away > self.config.drift_tolerance)
        # a lane that must be left (follow masked): the learned policy misses the exit
        lateral |= ~plan.features["mask"][:, FOLLOW]
        decision[lateral] = plan.decision[lateral]
        params[lateral] = plan.params[lateral]
        # longitudinal cap for the (possibly replaced) decision
        ab, ab_rule = params[ar, decision, 1], plan.params[ar, decision, 1]
        a, a_rule = self._accel(ab), self._accel(ab_rule)
        longitudinal = ~lateral & (a_rule < 0) & (a > a_rule + self.config.accel_tolerance)
        params[ar[longitudinal], decision[longitudinal], 1] = ab_rule[longitudinal]
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
