"""ACC-LC baseline: rule-based adaptive cruise + lane changing + lateral control (DESIGN §10).

It acts exactly like a learned policy, ``obs -> action`` through the env's parameterized action
space, from the observation only (DESIGN §6 layout, normalisation constants of
``mixed_traffic.sensing.observation``), vectorised over agents::

    pol = AccLcPolicy()
    decision, params = pol.act(obs_batch)   # obs_batch[key]: (A, ...) stacked observations
    actions = pol.actions(obs)              # {agent: {"decision", "params"}} convenience

``params`` (A, 3, 2) holds, for every decision (left change, follow, right change), the
(steering, accel_brake) that decision would execute; ``decision`` is chosen by the lane-change
rule and never a masked one.

Longitudinal (per candidate lane): IDM on the lane's front vehicle (bumper gap = front-bumper
distance - leader length) with a kinematic emergency term (the deceleration needed to stop behind
where the leader could stop, blended in as it grows from ``b`` to ``2 b``; a switch at ``b`` made
steady following alternate between accelerating and braking hard on sensor noise), the desired
speed 0.95 x the speed limit where the ego is (braking kinematically towards lower limits and
curves ahead), red / yellow lights as a
stopped leader at the stop line (yellow only if it can stop comfortably; the speeds of the turn
behind a stop line come from the route's speed-limit preview, ``limits``), a give-way line
(``give_way``: no yellow phase warns before SUMO closes it) approached at ``junction_speed`` on
roads under 20 m/s, vehicles of the neighbouring lanes that overlap the ego laterally (cut-ins,
or the ego straddling during its own change) as leaders too. The virtual stopped vehicle at the
end of a lane that must be left is a leader like any other. The light state is a majority over the
last three frames (misdetection filter). Cooperation: a vehicle ahead in a neighbouring lane
whose lateral offset points into our lane by ``signal_min`` (a waiting or starting change) is a
leader too when we can stop for it braking at most ``yield_decel`` and are farther behind it
than the rear gap its forced merge needs (``hv_s0``; nearer, waiting would deadlock both).
Hidden vehicles: the sensors report one front vehicle per lane, so one right ahead of a slower
neighbour (e.g. stuck half-way in a change into our lane) is invisible; slower neighbours are
passed no faster than a closing speed we could stop from (``hidden_decel``) before such a
vehicle.

Lane change (MOBIL-like): a change is safe if the target lane's rear vehicle keeps a gap of
``s0 + 0.6 s * v_rear`` plus a margin for its closing speed, and the front gap is enough for the
ego to follow without hard braking; discretionary when the IDM acceleration in the target lane
beats the current lane by a threshold (small keep-right bias), mandatory when the mask forbids
follow. A change already under way (offset and lateral velocity towards the target) continues
while it stays safe, otherwise the ego returns to its lane centre (abort). Discretionary
changes start only near the centre line. A mandatory change that waits for a gap stops
``end_wait`` before the lane's end (room to swing out), signals with ``signal_offset`` towards
the target lane (inside its own lane; neighbours yield to it, see above), accepts a forced gap
(the target lane's rear vehicle, assumed IDM, brakes moderately) and once under way creeps up
to ``end_s0`` before the end.

Lateral: a target offset (0 for follow, +-LANE_SHIFT for a change, relative to the current
lane; when the ego crosses into the target lane its offset is measured from the new lane and
"follow" centres it) -> a lateral velocity (rate-limited by a comfortable lateral acceleration)
-> a course angle (up to 60 deg at walking pace) -> steering with curvature feed-forward from
the waypoint orientations over the 5 m ahead (the env's bicycle model uses the same window; a
longer look-ahead averages an S-bend such as the lane-drop junction, which shifts every lane by
a width within 9 m, to zero) and a steering limit that bounds the lateral acceleration. The
current course is SUMO's heading, blended below 8 m/s into the measured lateral velocity
(SUMO's heading trails the path by a body length and lags far behind at walking pace).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from agents.rules import acc_lc_plan_kernel
from agents.rules.acc_lc_config import FOLLOW, LEFT, RIGHT, AccLcConfig
from agents.rules.acc_lc_config import LANE_C as _C
from agents.rules.acc_lc_config import LANE_L as _L
from agents.rules.acc_lc_config import LANE_R as _R
from agents.rules.acc_lc_features import features, lane_curvature
from agents.rules.acc_lc_lateral import follow_steering, forced_ok, lateral_bounds, safe, steer
from agents.rules.acc_lc_longitudinal import (
    LaneCall,
    hidden_cap,
    lane_accels,
    speed_cap,
    to_ab,
    wait_accel,
)
from agents.rules.obs_batch import stack_obs, to_actions
from agents.rules.rss import RssConfig, rss_caps
from mixed_traffic import compiled
from mixed_traffic.config import EnvConfig
from mixed_traffic.env.api import observation_space

__all__ = [
    "FOLLOW",
    "LEFT",
    "RIGHT",
    "AccLcConfig",
    "AccLcPlan",
    "AccLcPolicy",
    "lane_curvature",
]


@dataclass
class AccLcPlan:
    """ACC-LC's action and the checks behind it (A agents)."""

    decision: np.ndarray
    """(A,) int64 chosen decision."""
    params: np.ndarray
    """(A, 3, 2) float32 (steering, accel_brake) of every decision, in [-1, 1]."""
    features: dict[str, np.ndarray]
    """Decoded observation (SI units), see :func:`agents.rules.acc_lc_features.features`."""
    lateral_ok: np.ndarray
    """(A, 3) bool: moving towards the decision's lane is acceptable now (gap accepted;
    follow is always acceptable)."""
    lo: np.ndarray
    """(A,) lowest lateral target [m, current-lane frame] clear of vehicles alongside."""
    hi: np.ndarray
    """(A,) highest lateral target [m]."""
    config: AccLcConfig
    """The configuration the plan was made with."""
    _memo: dict = field(default_factory=dict, repr=False)

    def speed_cap(self, factor: float = 1.0) -> np.ndarray:
        """(A,) ACC-LC's speed cap [m/s²] towards ``factor`` x the limit
        (:func:`~agents.rules.acc_lc_longitudinal.speed_cap`), computed once per plan and
        factor: the driver's governor and the safety module both read it."""
        key = ("speed_cap", factor)
        if key not in self._memo:
            self._memo[key] = speed_cap(self.features, self.config, factor=factor)
        return self._memo[key]

    def rss_caps(self, rss: RssConfig) -> np.ndarray:
        """(A, 3) RSS-safe accelerations [m/s²] per lane column (:func:`agents.rules.rss.rss_caps`),
        computed once per plan and ``rss``."""
        if rss not in self._memo:
            self._memo[rss] = rss_caps(self.features, self.config, rss)
        return self._memo[rss]


class AccLcPolicy:
    """Rule-based ACC + lane change + lateral controller over stacked observations."""

    def __init__(self, config: AccLcConfig | None = None, **kwargs) -> None:
        self.c = config if config is not None else AccLcConfig(**kwargs)

    def _features(self, ob: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The decoded observation (:func:`agents.rules.acc_lc_features.features`)."""
        return features(ob, self.c)

    def _lateral_bounds(self, f: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Lateral bounds (:func:`agents.rules.acc_lc_lateral.lateral_bounds`)."""
        return lateral_bounds(f, self.c)

    def act(
        self, obs_batch: Mapping[str, np.ndarray], agents: Sequence[str] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Decisions (A,) int64 and params (A, 3, 2) float32 for stacked observations (of
        ``agents``; ACC-LC keeps no memory per agent)."""
        plan = self.plan(obs_batch)
        return plan.decision, plan.params

    def plan(self, obs_batch: Mapping[str, np.ndarray]) -> AccLcPlan:
        """The action of :meth:`act` with the checks behind it (for the safety module)."""
        c = self.c
        f = features(obs_batch, c)
        A = len(f["v"])
        mand = ~f["mask"][:, FOLLOW]
        la = _lane_accels(f, c, mand)
        decision, go_l, go_r, *accels = _decision(f, c, mand, la)
        # keep clear laterally of vehicles alongside (simultaneous changes into one lane)
        lo, hi = lateral_bounds(f, c)
        params = _params(f, c, _targets(c, mand, go_l, go_r), accels, lo, hi)
        lateral_ok = np.stack([go_l, np.ones(A, bool), go_r], axis=1)
        return AccLcPlan(decision, params, f, lateral_ok, lo, hi, c)

    def actions(self, obs: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, dict]:
        """``{agent: obs}`` -> ``{agent: {"decision": int, "params": (3, 2)}}``."""
        agents = list(obs)
        if not agents:
            return {}
        return to_actions(agents, *self.act(stack_obs(obs, agents)))


def warm() -> None:
    """Load the compiled kernels of :meth:`AccLcPolicy.plan` (from the disk cache, else compile
    them) for the dtypes and layouts a real plan passes, on a zero observation: a process that
    forks workers calls this once, and they inherit the kernels."""
    space = observation_space(EnvConfig())
    plan = AccLcPolicy().plan(
        {k: np.zeros((1, *s.shape), s.dtype) for k, s in space.spaces.items()}
    )
    plan.rss_caps(RssConfig())


# ---------------------------------------------------------------------- steps of plan()
Features = Mapping[str, np.ndarray]


class _Checks(NamedTuple):
    """Lane-change checks per side (A,) bool, each already limited to allowed decisions."""

    safe_l: np.ndarray
    """The gap to the left is accepted now."""
    safe_r: np.ndarray
    cont_l: np.ndarray
    """The relaxed check for a change under way to the left."""
    cont_r: np.ndarray
    going_l: np.ndarray
    """A change to the left is under way (offset and lateral motion towards it)."""
    going_r: np.ndarray


class _LaneAccels(NamedTuple):
    """(A,) candidate-lane accelerations: the incentive's (latest frame, ``now_*``) and the
    executed rows' (every history frame; ``fc`` is the current lane with the creep gap)."""

    now_c: np.ndarray
    now_l: np.ndarray
    now_r: np.ndarray
    f: np.ndarray
    l: np.ndarray  # noqa: E741
    r: np.ndarray
    fc: np.ndarray


def _lane_accels(f: Features, c: AccLcConfig, mand: np.ndarray) -> _LaneAccels:
    """All seven candidate-lane accelerations of one plan, in one :func:`lane_accels` call."""
    creep = np.where(mand, c.end_s0, c.s0)
    calls = [LaneCall(_C, False), LaneCall(_L, False), LaneCall(_R, False)]
    calls += [LaneCall(_C, True, np.where(mand, c.end_wait, c.s0))]
    calls += [LaneCall(lane, True, creep) for lane in (_L, _R, _C)]
    return _LaneAccels(*lane_accels(f, c, calls, f["d"]))


def _decision(f: Features, c: AccLcConfig, mand: np.ndarray, la: _LaneAccels) -> tuple:
    """(decision (A,) int64, go_l, go_r (A,) bool, accelerations (A,) [m/s²] of the follow,
    left and right rows); compiled (:mod:`agents.rules.acc_lc_plan_kernel`) unless
    ``compiled.enabled()`` is off."""
    run = _decision_compiled if compiled.enabled() and len(f["v"]) else _decision_reference
    return run(f, c, mand, la)


def _decision_reference(f: Features, c: AccLcConfig, mand: np.ndarray, la: _LaneAccels) -> tuple:
    """The numpy reference of :func:`_decision`."""
    ck = _change_checks(f, c, mand)
    go_l, go_r = _go(f, c, mand, ck)
    return (_decide(f, c, mand, ck, la), go_l, go_r,
            *_executed_accels(f, c, mand, ck, go_l, go_r, la))  # fmt: skip


def _decision_compiled(f: Features, c: AccLcConfig, mand: np.ndarray, la: _LaneAccels) -> tuple:
    """:func:`_decision_reference` in one kernel (contiguous inputs: one specialisation)."""
    cc = np.ascontiguousarray
    return acc_lc_plan_kernel.decision(
        f["v"], cc(f["d"]), cc(f["len"]), cc(f["vlat_hist"]), cc(f["vdist"]), cc(f["vrel"]),
        cc(f["vlen"]), cc(f["exists"]), cc(f["mask"]), cc(mand), *(cc(x) for x in la),
        c.s0, c.rear_headway, 2 * c.rear_decel, 2 * c.b, c.signal_offset, c.lc_start_offset,
        c.lc_threshold, c.keep_right_bias, c.hv_s0, c.hv_T, c.hv_a,
        2 * np.sqrt(c.hv_a * c.hv_b), np.sqrt(1.0 + c.force_rear_decel / c.hv_a),
        c.force_rear_decel, c.force_front_decel, c.a, c.hidden_gap, 2 * c.hidden_decel,
    )  # fmt: skip


def _change_checks(f: Features, c: AccLcConfig, mand: np.ndarray) -> _Checks:
    """The gap checks and whether a change is under way (``mand``: follow is masked)."""
    d = f["d"]
    mask = f["mask"]
    safe_l = safe(f, c, _L, relaxed=False) & mask[:, LEFT]
    safe_r = safe(f, c, _R, relaxed=False) & mask[:, RIGHT]
    cont_l = safe(f, c, _L, relaxed=True) & mask[:, LEFT]
    cont_r = safe(f, c, _R, relaxed=True) & mask[:, RIGHT]
    vlat = f["vlat_hist"]
    # a change under way: offset and lateral motion towards that side (beyond the signal
    # offset of a waiting mandatory change)
    start = np.where(mand, c.signal_offset + 0.15, c.lc_start_offset)
    going_l = (d > start) & (vlat > 0.1)
    going_r = (d < -start) & (vlat < -0.1)
    return _Checks(safe_l, safe_r, cont_l, cont_r, going_l, going_r)


def _decide(
    f: Features, c: AccLcConfig, mand: np.ndarray, ck: _Checks, la: _LaneAccels
) -> np.ndarray:
    """(A,) int64 decision: a wanted discretionary change, a change under way that stays
    safe, a mandatory change's side; never a masked decision."""
    d = f["d"]
    mask = f["mask"]
    A = len(d)
    centred = np.abs(d) < c.lc_start_offset
    want_l, want_r = _wanted(f, c, ck, centred, la)
    decision = np.full(A, FOLLOW, dtype=np.int64)
    decision[want_r] = RIGHT
    decision[want_l] = LEFT
    decision[ck.going_l & ck.cont_l] = LEFT
    decision[ck.going_r & ck.cont_r] = RIGHT
    # mandatory: pick an allowed side, preferring the one that is safe now
    m_l = mand & mask[:, LEFT] & (~mask[:, RIGHT] | ck.safe_l | ~ck.safe_r)
    decision[mand & ~m_l & mask[:, RIGHT]] = RIGHT
    decision[m_l] = LEFT
    # never a masked decision
    bad = ~mask[np.arange(A), decision]
    if bad.any():
        first = np.argmax(mask, axis=1)
        decision = np.where(bad & mask[:, FOLLOW], FOLLOW, np.where(bad, first, decision))
    return decision


def _wanted(
    f: Features, c: AccLcConfig, ck: _Checks, centred: np.ndarray, la: _LaneAccels
) -> tuple[np.ndarray, np.ndarray]:
    """(A,) discretionary changes wanted to the left / right (the better side if both)."""
    # incentive (MOBIL-like, without politeness towards followers beyond the safety test),
    # from the latest frame only (remembered leaders cap the executed accelerations but
    # must not make the current lane look worse and trigger changes)
    inc_l = la.now_l - la.now_c - c.lc_threshold
    inc_r = la.now_r - la.now_c - c.lc_threshold
    inc_r = inc_r + c.keep_right_bias
    want_l = ck.safe_l & centred & (inc_l > 0) & (f["v"] > 3.0)
    want_r = ck.safe_r & centred & (inc_r > 0) & (f["v"] > 3.0)
    both = want_l & want_r
    want_l &= ~both | (inc_l > inc_r)
    want_r &= ~(both & (inc_l > inc_r))
    return want_l, want_r


def _go(
    f: Features, c: AccLcConfig, mand: np.ndarray, ck: _Checks
) -> tuple[np.ndarray, np.ndarray]:
    """(A,) a change row shifts the lateral target (left / right) only while it is safe (a
    mandatory change that is not safe yet holds the lane and waits); a mandatory change also
    accepts a forced (cooperative) gap."""
    mask = f["mask"]
    forced_l = mand & forced_ok(f, c, _L) & mask[:, LEFT]
    forced_r = mand & forced_ok(f, c, _R) & mask[:, RIGHT]
    go_l = np.where(ck.going_l, ck.cont_l, ck.safe_l) | forced_l
    go_r = np.where(ck.going_r, ck.cont_r, ck.safe_r) | forced_r
    return go_l, go_r


def _targets(
    c: AccLcConfig, mand: np.ndarray, go_l: np.ndarray, go_r: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(A,) lateral targets [m] of the left / right change rows; a waiting mandatory change
    signals (offset towards the target lane, inside its own)."""
    t_l = np.where(go_l, c.lane_shift, np.where(mand, c.signal_offset, 0.0))
    t_r = np.where(go_r, -c.lane_shift, np.where(mand, -c.signal_offset, 0.0))
    return t_l, t_r


def _executed_accels(
    f: Features,
    c: AccLcConfig,
    mand: np.ndarray,
    ck: _Checks,
    go_l: np.ndarray,
    go_r: np.ndarray,
    la: _LaneAccels,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A,) accelerations of the follow, left and right rows."""
    acc_f, acc_l, acc_r = la.f, la.l, la.r
    # while changing, the current lane's leaders still count (min of both lanes)
    # mandatory change waiting for a gap: match the target lane (stay behind its front
    # vehicle) and let a rear vehicle that is about alongside pass
    wait_l = wait_accel(f, c, _L, acc_f)
    wait_r = wait_accel(f, c, _R, acc_f)
    # (a mandatory change under way may creep towards the end of its lane to swing out)
    norm_l = np.where(go_l, np.minimum(acc_l, la.fc), acc_f)
    norm_r = np.where(go_r, np.minimum(acc_r, la.fc), acc_f)
    acc_l = np.where(mand & ~(go_l & (ck.safe_l | ck.going_l & ck.cont_l)), wait_l, norm_l)
    acc_r = np.where(mand & ~(go_r & (ck.safe_r | ck.going_r & ck.cont_r)), wait_r, norm_r)
    cap = hidden_cap(f, c)
    acc_f, acc_l, acc_r = (np.minimum(x, cap) for x in (acc_f, acc_l, acc_r))
    return acc_f, acc_l, acc_r


def _params(
    f: Features,
    c: AccLcConfig,
    targets: tuple[np.ndarray, np.ndarray],
    accels: tuple[np.ndarray, np.ndarray, np.ndarray],
    lo: np.ndarray,
    hi: np.ndarray,
) -> np.ndarray:
    """(A, 3, 2) float32 (steering, accel_brake) per decision: the lateral targets (left,
    right; follow centres) clipped to ``[lo, hi]``, the accelerations (follow, left, right)."""
    A = len(f["v"])
    t_l, t_r = targets
    acc_f, acc_l, acc_r = accels
    t_l = np.clip(t_l, lo, hi)
    t_r = np.clip(t_r, lo, hi)
    params = np.empty((A, 3, 2), dtype=np.float32)
    params[:, FOLLOW, 0] = follow_steering(f, c, lo, hi)
    params[:, LEFT, 0] = steer(f, c, t_l)
    params[:, RIGHT, 0] = steer(f, c, t_r)
    params[:, FOLLOW, 1] = to_ab(acc_f, c)
    params[:, LEFT, 1] = to_ab(acc_l, c)
    params[:, RIGHT, 1] = to_ab(acc_r, c)
    return params
