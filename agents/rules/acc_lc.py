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
stopped leader at the stop line (yellow only if it can stop comfortably), a junction approach
speed at signalised stop lines (turn lanes behind a stop line are slow and the waypoints only
look 10 m ahead), vehicles of the neighbouring lanes that overlap the ego laterally (cut-ins, or
the ego straddling during its own change) as leaders too. The virtual stopped vehicle at the end
of a lane that must be left is a leader like any other. The light state is a majority over the
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

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mixed_traffic.config import SensorConfig, VehicleConfig
from mixed_traffic.env.api import (
    CURVATURE_WINDOW,
    DEAD_END_DISTANCE,
    EGO_SCALE,
    SPEED_SCALE,
    WAYPOINT_SCALE,
)

LEFT, FOLLOW, RIGHT = 0, 1, 2
#: lane columns in the observation (left, current, right)
_L, _C, _R = 0, 1, 2


@dataclass
class AccLcConfig:
    """Parameters of the rule-based driver (SI units)."""

    # the env's sensor ranges and vehicle limits (one source: mixed_traffic.config)
    lidar_range: float = SensorConfig.lidar_range
    camera_range: float = SensorConfig.camera_range
    wheelbase: float = VehicleConfig.wheelbase
    max_steer_deg: float = VehicleConfig.max_steer_deg
    max_accel: float = VehicleConfig.max_accel
    max_decel: float = VehicleConfig.max_decel
    # IDM
    a: float = 1.5
    b: float = 2.0
    T: float = 1.3
    s0: float = 3.0
    speed_factor: float = 0.95
    # lights and junctions
    yellow_stop_decel: float = 3.5
    stop_margin: float = 1.5
    junction_speed: float = 3.3
    curve_accel: float = 2.0
    # a target speed ahead this much below the present one is braked for kinematically [m/s]
    limit_deadband: float = 0.5
    # lane change
    lane_shift: float = 3.4
    lane_width_min: float = 3.2
    lc_threshold: float = 0.4
    keep_right_bias: float = 0.1
    rear_headway: float = 0.6
    rear_decel: float = 2.0
    lc_start_offset: float = 0.3
    # forced merge (mandatory change): the rear vehicle of the target lane, assumed to follow
    # IDM (hv parameters), may need to brake at most ``force_rear_decel`` for the ego
    force_rear_decel: float = 3.0
    force_front_decel: float = 3.0
    hv_a: float = 1.5
    hv_b: float = 2.0
    hv_T: float = 1.2
    hv_s0: float = 2.0
    # lateral envelope: clearance kept to vehicles alongside (longitudinal overlap)
    side_margin: float = 0.4
    side_long_margin: float = 2.0
    # hidden vehicle: one may sit right ahead of a slower visible neighbour (bumper gap
    # ``hidden_gap``) and pull into our lane; pass slow neighbours only as fast as we could stop
    hidden_gap: float = 1.0
    hidden_decel: float = 4.0
    # cooperation: a waiting mandatory changer signals with a lateral offset towards the target
    # lane; a vehicle ahead in a neighbouring lane offset towards us by ``signal_min`` is yielded
    # to (a leader) when we can stop for it braking at most ``yield_decel``
    signal_offset: float = 0.6
    signal_min: float = 0.4
    yield_decel: float = 2.5
    # a mandatory change waits this far before the end of its lane (room to swing out), and
    # creeps this close to it once the change is under way
    end_wait: float = 6.0
    # (the env ends a trip stuck within DEAD_END_DISTANCE of a dead end as a route deviation)
    end_s0: float = DEAD_END_DISTANCE + 0.5
    # lateral
    lat_accel: float = 2.0
    lat_speed: float = 1.0
    lat_gain: float = 0.8
    heading_gain: float = 1.0
    # in its lane (follow), the course is never steeper than one that can be turned straight
    # at this curvature [1/m] within the remaining offset: creeping in a queue, a course set
    # from the lateral speed alone reached 21 deg, and when the queue moved on the ego swung
    # past its lane centre into the next lane (a fixed small cap instead left egos straddling
    # two lanes when the queue stopped)
    follow_curvature: float = 0.1


@dataclass
class AccLcPlan:
    """ACC-LC's action and the checks behind it (A agents)."""

    decision: np.ndarray
    """(A,) int64 chosen decision."""
    params: np.ndarray
    """(A, 3, 2) float32 (steering, accel_brake) of every decision, in [-1, 1]."""
    features: dict[str, np.ndarray]
    """Decoded observation (SI units), see ``AccLcPolicy._features``."""
    lateral_ok: np.ndarray
    """(A, 3) bool: moving towards the decision's lane is acceptable now (gap accepted;
    follow is always acceptable)."""
    lo: np.ndarray
    """(A,) lowest lateral target [m, current-lane frame] clear of vehicles alongside."""
    hi: np.ndarray
    """(A,) highest lateral target [m]."""


def lane_curvature(f: Mapping[str, np.ndarray]) -> np.ndarray:
    """(A,) curvature of the current lane where the ego is [1/m, + = left], from the waypoint
    orientations (``AccLcPolicy._features``) over the env's ``CURVATURE_WINDOW``; 0 where the
    lane is missing."""
    o = f["wp_orient"][:, _C]
    w = min(CURVATURE_WINDOW, o.shape[1] - 1)
    kappa = (o[:, w] - o[:, 0]) / max(w, 1)
    return np.where(f["exists"][:, _C], kappa, 0.0)


def _idm(v, v0, gap, dv, c: AccLcConfig, s0=None):
    """IDM acceleration; dv = v - v_leader (closing speed), gap bumper gap [m] (inf = free);
    ``s0`` standstill gap (default ``c.s0``)."""
    s0 = c.s0 if s0 is None else s0
    v0 = np.maximum(v0, 0.1)
    free = 1.0 - (np.minimum(v, 2 * v0) / v0) ** 4
    s_star = s0 + np.maximum(0.0, v * c.T + v * dv / (2.0 * np.sqrt(c.a * c.b)))
    inter = np.where(np.isfinite(gap), (s_star / np.maximum(gap, 0.1)) ** 2, 0.0)
    acc = c.a * (free - inter)
    # kinematic emergency: brake hard enough to stop behind where the leader could stop
    v_lead = np.maximum(v - dv, 0.0)
    room = np.maximum(gap - np.minimum(1.0, 0.5 * s0) + v_lead**2 / (2 * c.max_decel), 0.05)
    need = np.where(np.isfinite(gap), v**2 / (2 * room), 0.0)
    # blended in from the comfortable decel to twice it: a switch at one threshold made
    # steady following a noise-driven alternation of IDM's acceleration and hard braking
    r = np.clip((need - c.b) / c.b, 0.0, 1.0)
    return np.minimum(acc, (1.0 - r) * acc - r * 1.2 * need)


class AccLcPolicy:
    """Rule-based ACC + lane change + lateral controller over stacked observations."""

    def __init__(self, config: AccLcConfig | None = None, **kwargs) -> None:
        self.c = config if config is not None else AccLcConfig(**kwargs)

    # ------------------------------------------------------------------ features
    def _features(self, ob: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        c = self.c
        ego = np.asarray(ob["ego"], np.float64)  # (A, z, 5)
        lanes = np.asarray(ob["lanes"], np.float64)  # (A, 3, z, 4m)
        veh = np.asarray(ob["vehicles"], np.float64)  # (A, 3, z, 12)
        lights = np.asarray(ob["lights"], np.float64)  # (A, 3, z, 4)
        A = ego.shape[0]
        e = ego[:, -1] * EGO_SCALE
        f = {"v": np.maximum(e[:, 0], 0.0), "h": e[:, 1], "len": e[:, 2], "wid": e[:, 3]}
        f["d"] = e[:, 4]
        # lateral offset history, unwrapped across lane switches (jumps > 1.5 m)
        dh = ego[:, :, 4] * EGO_SCALE[4]
        valid = ego[:, :, 2] > 0
        k = max(0, ego.shape[1] - 3)
        diffs = np.diff(dh[:, k:], axis=1)
        ok = valid[:, k + 1 :] & valid[:, k:-1] & (np.abs(diffs) < 1.5)
        f["vlat_hist"] = np.where(ok, diffs, 0.0).sum(1) / np.maximum(ok.sum(1), 1) / 0.1
        m = lanes.shape[-1] // 4
        wp = lanes[:, :, -1].reshape(A, 3, m, 4) * WAYPOINT_SCALE
        f["wp_speed"] = wp[..., 3]  # (A, 3, m)
        f["wp_orient"] = wp[..., 2]
        vv = veh[:, :, -1].reshape(A, 3, 2, 6)
        scale = np.array([c.lidar_range, SPEED_SCALE, np.pi, 10.0, 5.0, 2.0])
        vv = vv * scale
        present = vv[..., 4] > 0
        f["present"] = present
        f["vdist"] = np.where(present, vv[..., 0], np.array([np.inf, -np.inf]))
        f["vrel"] = vv[..., 1]
        f["vlen"] = vv[..., 3]
        f["vwid"] = vv[..., 4]
        f["vlat"] = vv[..., 5]
        # front vehicles of the last K frames (object permanence: a leader hidden behind a
        # nearer vehicle of the same lane, or gone into a junction lane the ego does not
        # follow, is extrapolated from its last sighting), only since the last lane switch
        K = min(5, veh.shape[2])
        hv = veh[:, :, -K:, :6] * scale  # (A, 3, K, 6)
        age = (K - 1 - np.arange(K)) * 0.1
        hp = hv[..., 4] > 0
        jump = np.abs(np.diff(dh[:, -K:], axis=1)) >= 1.5  # (A, K-1)
        since = np.flip(np.cumsum(np.flip(jump, 1), axis=1), 1) == 0  # no switch after k
        hvalid = np.concatenate([since, np.ones((A, 1), bool)], axis=1) & valid[:, -K:]
        hp &= hvalid[:, None, :]
        f["h_dist"] = np.where(hp, hv[..., 0] + hv[..., 1] * age, np.inf)
        f["h_rel"], f["h_len"] = hv[..., 1], hv[..., 3]
        f["h_wid"], f["h_lat"] = hv[..., 4], hv[..., 5]
        nm = np.asarray(ob["node_mask"])
        f["exists"] = nm[:, :, 0] > 0
        f["mask"] = np.asarray(ob["action_mask"]) > 0
        # lights: majority of the last 3 frames with a detection
        lt = lights[:, :, -3:]
        det = lt[..., :3].sum(-1) > 0.5
        votes = (lt[..., :3] > 0.5).sum(2)  # (A, 3, 3) counts of r/y/g
        state = np.where(det.any(2), votes.argmax(-1), -1)
        f["light"] = state
        f["light_dist"] = np.where(
            det[..., -1], lights[:, :, -1, 3] * c.camera_range, np.where(det.any(2), 0, np.inf)
        )
        # fall back to the last detected distance when the latest frame lost the light
        last = lights[:, :, -2, 3] * c.camera_range
        f["light_dist"] = np.where(~det[..., -1] & det.any(2), last, f["light_dist"])
        return f

    # ------------------------------------------------------------------ longitudinal
    def _lane_accel(
        self, f, lane: int, offset: np.ndarray, memory: bool = True, end_gap=None
    ) -> np.ndarray:
        """(A,) acceleration if driving in lane column ``lane`` (with the ego at lateral
        ``offset`` relative to the current lane, for the overlap test of neighbours);
        ``end_gap`` (A,) standstill gap to the virtual end-of-lane vehicle (default ``s0``)."""
        c = self.c
        v = f["v"]
        ln = np.where(f["exists"][:, lane], lane, _C)
        ar = np.arange(len(v))
        # speed limit: lowest ahead, and braking towards lower limits ahead
        spd = f["wp_speed"][ar, ln]  # (A, m)
        spd = np.where(spd > 0.5, spd, np.inf)
        lim_now = np.where(np.isfinite(spd[:, 0]), spd[:, 0], np.min(spd, axis=1))
        lim_now = np.where(np.isfinite(lim_now), lim_now, 13.9)
        v0 = c.speed_factor * lim_now
        dist_wp = np.arange(spd.shape[1], dtype=np.float64) + 1.0
        # curves: lateral acceleration bound, and the along-lane speed SUMO reports grows by
        # 1 / (1 - kappa * d) on the inside of a curve
        o = f["wp_orient"][ar, ln]
        # curvature over a 5 m window: internal (junction) lanes are coarse polylines whose
        # orientation jumps by ~0.5 rad at a vertex, which per metre would read as a sharp bend
        mw = o.shape[1]
        w = min(5, mw - 1) if mw > 1 else 1
        j0 = np.clip(np.arange(mw) - w // 2, 0, max(mw - 1 - w, 0))
        j1 = np.minimum(j0 + w, mw - 1)
        kap = np.abs((o[:, j1] - o[:, j0] + np.pi) % (2 * np.pi) - np.pi) / w
        v_curve = np.sqrt(c.curve_accel / np.maximum(kap, 1e-4))
        inside = np.maximum(1.0 - kap * (np.abs(offset)[:, None] + 0.3), 0.3)
        target = np.minimum(c.speed_factor * spd, v_curve) * inside
        # the target where the ego is now is IDM's desired speed, whose free-road term is smooth
        # in the noisy speed reading; braking to it over the 1 m to the first waypoint turned
        # every reading above it into a hard brake. Kinematic braking only for lower targets.
        v0 = np.minimum(v0, target[:, 0])
        lower = (target < target[:, :1] - c.limit_deadband) & (target < v[:, None])
        need = np.where(lower, (target**2 - v[:, None] ** 2) / (2 * dist_wp), np.inf)
        a_lim = np.min(need, axis=1)
        a_lim = np.where(a_lim < 0, 1.3 * a_lim, np.inf)
        acc = _idm(v, v0, np.full_like(v, np.inf), np.zeros_like(v), c)
        acc = np.minimum(acc, a_lim)
        # leaders: front vehicle of this lane and overlapping front vehicles of the others
        # (every history frame, extrapolated to now: shape (A, K))
        kk = slice(None) if memory else slice(-1, None)
        for j in (_L, _C, _R):
            dist = f["h_dist"][:, j, kk]
            gap = dist - f["h_len"][:, j, kk]
            # lateral position of the other vehicle relative to the current lane centre
            shift = (j - _C) * -c.lane_width_min  # left column = +width
            lat_o = f["h_lat"][:, j, kk] + shift
            lat_ego = offset[:, None]
            half = 0.5 * (f["wid"][:, None] + f["h_wid"][:, j, kk]) + 0.4
            if j == lane:
                relevant = np.isfinite(dist)
            else:
                relevant = np.isfinite(dist) & (np.abs(lat_o - lat_ego) < half)
            # own lane of the lane column: the chosen lane; others only on overlap
            relevant &= (f["exists"][:, j] | (j == _C))[:, None]
            if j != lane and lane != _C and j == _C:
                # moving to another lane: the current lane's leader matters while we overlap it
                relevant = np.isfinite(dist) & (np.abs(lat_o - lat_ego) < half + 0.6)
            if lane == _C and j != _C:
                # cooperation: yield to a neighbour ahead signalling a change into our lane,
                # unless we are already closer than the rear gap its forced merge needs (then
                # waiting deadlocks both; passing lets it merge behind us)
                towards = f["h_lat"][:, j, kk] * (j - _C) > c.signal_min
                close = np.maximum(-f["h_rel"][:, j, kk], 0.0)
                can = close**2 / (2 * np.maximum(gap - 1.0, 0.1)) <= c.yield_decel
                relevant |= np.isfinite(dist) & towards & (gap > c.hv_s0) & can
            vk = v[:, None]
            s0 = c.s0
            if end_gap is not None and j == _C:
                s0 = np.where(f["h_len"][:, j, kk] < 0.1, end_gap[:, None], c.s0)
            rel = -f["h_rel"][:, j, kk]
            a_j = _idm(vk, v0[:, None], np.where(relevant, gap, np.inf), rel, c, s0)
            acc = np.minimum(acc, np.where(relevant, a_j, np.inf).min(axis=1))
        # traffic light of the current lane (a change does not escape the light)
        ld = f["light_dist"][:, _C]
        st = f["light"][:, _C]
        stop_room = np.maximum(ld - c.stop_margin, 0.05)
        need_stop = v**2 / (2 * stop_room)
        stop = ((st == 0) & (need_stop < c.max_decel * 1.1)) | (
            (st == 1) & (need_stop < c.yellow_stop_decel)
        )
        a_stop = _idm(v, v0, stop_room, v, c)
        a_stop = np.minimum(a_stop, np.where(need_stop > 1.0, -need_stop * 1.1, a_stop))
        acc = np.where(stop, np.minimum(acc, a_stop), acc)
        # junction approach speed at a signalised stop line (turns behind it are slow)
        lightish = (st >= 0) & np.isfinite(ld)
        # (the waypoints see only 10 m ahead along the primary successor, not the route's turn;
        # the tightest turns of the urban nets are limited to ~3.6 m/s)
        vj = np.minimum(c.junction_speed, v0)
        a_j = np.where(v > vj, (vj**2 - v**2) / (2 * np.maximum(ld - 1.0, 0.5)), np.inf)
        acc = np.where(lightish & (lim_now < 20.0), np.minimum(acc, a_j), acc)
        return acc

    def _hidden_cap(self, f) -> np.ndarray:
        """(A,) acceleration cap for passing slower neighbours: the sensors report one front
        vehicle per lane, so a vehicle right ahead of it (e.g. stuck half-way in a change into
        our lane) is hidden; keep the closing speed to it, and to the visible one while its rear
        is still ahead (its lateral offset may be misread), stoppable at ``hidden_decel``."""
        c = self.c
        v = f["v"]
        cap = np.full_like(v, np.inf)
        for j in (_L, _R):
            fd = f["vdist"][:, j, 0]
            v_o = np.maximum(v + f["vrel"][:, j, 0], 0.0)
            rear = fd - f["vlen"][:, j, 0]
            room = np.minimum(fd + c.hidden_gap, np.where(rear > 0, rear, np.inf)) - 0.5
            v_max = v_o + np.sqrt(2 * c.hidden_decel * np.maximum(room, 0.0))
            on = f["exists"][:, j] & np.isfinite(fd) & (f["vlen"][:, j, 0] > 0.1)
            # (tracked within 0.25 s: the bound tightens as fast as we close in)
            cap = np.where(on, np.minimum(cap, 4.0 * (v_max - v)), cap)
        return cap

    # ------------------------------------------------------------------ lateral
    def _steer(self, f, target: np.ndarray, curvature: float | None = None) -> np.ndarray:
        """(A,) steering in [-1, 1] towards the lateral ``target`` [m]; with a ``curvature``
        [1/m], the course is one that turns straight at it before reaching the target."""
        c = self.c
        v = f["v"]
        vs = np.maximum(v, 0.5)
        err = target - f["d"]
        mag = np.minimum.reduce(
            [np.full_like(err, c.lat_speed), c.lat_gain * np.abs(err), np.sqrt(1.6 * np.abs(err))]
        )
        vl_des = np.sign(err) * mag
        # current course: SUMO's heading trails the lateral path by a body length, so at low
        # speed (a lane change from standstill) it lags the course far behind and the ego
        # overshoots into the next lane; there the measured lateral velocity is used
        chi_meas = np.arcsin(np.clip(f["vlat_hist"] / vs, -0.9, 0.9))
        wgt = np.clip((8.0 - v) / 4.0, 0.0, 1.0)
        h = wgt * chi_meas + (1.0 - wgt) * f["h"]
        vl_now = vs * np.sin(h)
        vl = np.clip(vl_des, vl_now - c.lat_accel * 0.25, vl_now + c.lat_accel * 0.25)
        # (up to 60 deg at walking pace: a change from standstill at a lane's end has little room)
        chi = np.arcsin(np.clip(vl / vs, -0.87, 0.87))
        if curvature is not None:
            # a course chi straightens out at curvature k over about chi²/(2k) of offset
            chi_max = np.sqrt(2.0 * curvature * np.abs(err))
            chi = np.clip(chi, -chi_max, chi_max)
        # lane curvature here, from the current lane's waypoint orientations (relative to ego
        # heading), over the 5 m window the env's bicycle model uses: a longer look-ahead
        # averages an S-bend (the lane-drop junction shifts every lane by one width within
        # 9 m) to zero and the ego lags a whole lane behind its lane
        ff = np.arctan(c.wheelbase * lane_curvature(f))
        lim = np.arctan(c.wheelbase * c.lat_accel / vs**2)
        fb = np.clip(c.heading_gain * (chi - h) * np.minimum(1.0, 8.0 / vs), -lim, lim)
        steer = ff + fb
        return np.clip(steer / np.deg2rad(c.max_steer_deg), -1.0, 1.0)

    def _to_ab(self, acc: np.ndarray) -> np.ndarray:
        c = self.c
        return np.clip(np.where(acc > 0, acc / c.max_accel, acc / c.max_decel), -1.0, 1.0)

    # ------------------------------------------------------------------ lane change
    def _safe(self, f, side: int, relaxed: bool) -> np.ndarray:
        c = self.c
        v = f["v"]
        # rear vehicle of the target lane
        rd = -f["vdist"][:, side, 1]  # positive distance behind (front bumpers)
        rgap = rd - f["len"]
        v_rear = np.maximum(v + f["vrel"][:, side, 1], 0.0)
        closing = np.maximum(f["vrel"][:, side, 1], 0.0)
        req_r = c.s0 + c.rear_headway * v_rear + closing**2 / (2 * c.rear_decel)
        if relaxed:
            req_r = 0.5 * req_r
        rear_ok = ~np.isfinite(rd) | (rgap > req_r)
        # front vehicle of the target lane
        fd = f["vdist"][:, side, 0]
        fgap = fd - f["vlen"][:, side, 0]
        fclose = np.maximum(-f["vrel"][:, side, 0], 0.0)
        req_f = c.s0 + 0.5 * v + fclose**2 / (2 * c.b)
        if relaxed:
            req_f = 0.5 * req_f
        front_ok = ~np.isfinite(fd) | (fgap > req_f)
        return f["exists"][:, side] & rear_ok & front_ok

    def _forced_ok(self, f, side: int) -> np.ndarray:
        """(A,) a forced (cooperative) merge into ``side`` is acceptable: the target lane's rear
        vehicle, following IDM with the ego as its leader, brakes at most ``force_rear_decel``,
        and the ego can follow the target lane's front vehicle braking at most
        ``force_front_decel``; both bumper gaps stay positive with a margin."""
        c = self.c
        v = f["v"]
        rd = -f["vdist"][:, side, 1]
        rgap = rd - f["len"]
        v_r = np.maximum(v + f["vrel"][:, side, 1], 0.0)
        s_star = c.hv_s0 + v_r * c.hv_T + v_r * (v_r - v) / (2 * np.sqrt(c.hv_a * c.hv_b))
        s_star = np.maximum(s_star, c.hv_s0)
        acc_r = c.hv_a * (1.0 - (s_star / np.maximum(rgap, 0.1)) ** 2)
        # (kinematic alternative: the rear vehicle can stop behind the ego at that rate)
        kin = (v_r - v) ** 2 / (2 * np.maximum(rgap - c.hv_s0, 0.1)) <= c.force_rear_decel
        rear_ok = ~np.isfinite(rd) | (
            ((acc_r >= -c.force_rear_decel) | kin) & (rgap > c.hv_s0 + 0.3 * v_r)
        )
        fd = f["vdist"][:, side, 0]
        fgap = fd - f["vlen"][:, side, 0]
        fclose = np.maximum(-f["vrel"][:, side, 0], 0.0)
        front_ok = ~np.isfinite(fd) | (
            (fgap > 1.5 + 0.3 * v)
            & (fclose**2 / (2 * np.maximum(fgap - 1.0, 0.1)) <= c.force_front_decel)
        )
        return f["exists"][:, side] & rear_ok & front_ok

    def _wait_accel(self, f, side: int, acc_cur) -> np.ndarray:
        """(A,) acceleration of a mandatory change waiting for (or forcing into) a gap: aim at
        the slot between the target lane's front and rear vehicles when it is long enough
        (match their speed, centre the slack), else let the rear vehicle pass; never beyond the
        current lane's own limits (``acc_cur``: its leaders and the lane's end)."""
        c = self.c
        v = f["v"]
        fd, rd = f["vdist"][:, side, 0], -f["vdist"][:, side, 1]
        has_f, has_r = np.isfinite(fd), np.isfinite(rd)
        fgap = np.where(has_f, fd - f["vlen"][:, side, 0], 1e3)
        rgap = np.where(has_r, rd - f["len"], 1e3)
        v_f = np.maximum(v + f["vrel"][:, side, 0], 0.0)
        v_r = np.maximum(v + f["vrel"][:, side, 1], 0.0)
        need_r = (c.hv_s0 + c.hv_T * v_r) / np.sqrt(1.0 + c.force_rear_decel / c.hv_a) + 0.5
        need_f = 1.5 + 0.3 * v
        slack = fgap + rgap - need_r - need_f
        fits = slack > 0
        e = fgap - (need_f + 0.5 * np.minimum(slack, 20.0))  # > 0: too far back
        v_ref = np.where(has_f, v_f, np.where(has_r, v_r + 1.0, v))
        acc_gap = 0.4 * e + 1.0 * (v_ref - v)
        acc_pass = 1.0 * (np.maximum(v_r - 2.0, 0.0) - v)
        acc = np.clip(np.where(fits, acc_gap, acc_pass), -c.force_front_decel, c.a)
        return np.minimum(acc, acc_cur)

    def _lateral_bounds(self, f) -> tuple[np.ndarray, np.ndarray]:
        """(A,) lowest / highest allowed lateral target (current-lane frame): a vehicle
        alongside (longitudinal overlap plus a margin) in any lane column, e.g. one straddling
        into the lane we change to from the other side, bounds the lateral motion towards it."""
        c = self.c
        d = f["d"][:, None, None]
        shift = np.array([1.0, 0.0, -1.0])[None, :, None] * c.lane_width_min
        y = f["vlat"] + shift  # (A, 3, 2) relative to the current lane centre
        dist = f["vdist"]
        close_f = np.maximum(-f["vrel"][:, :, 0], 0.0)
        close_r = np.maximum(f["vrel"][:, :, 1], 0.0)
        lm = c.side_long_margin
        ahead = (dist[:, :, 0] - f["vlen"][:, :, 0]) < lm + close_f
        behind = (-dist[:, :, 1] - f["len"][:, None]) < lm + close_r
        along = np.stack([ahead, behind], axis=2) & f["present"] & (f["vlen"] > 0.1)
        half = 0.5 * (f["wid"][:, None, None] + f["vwid"])
        # only vehicles beside us (already overlapping laterally is the longitudinal case)
        beside = along & (np.abs(y - d) > half - 0.2)
        H = half + c.side_margin
        hi = np.where(beside & (y > d), y - H, np.inf).min(axis=(1, 2))
        lo = np.where(beside & (y <= d), y + H, -np.inf).max(axis=(1, 2))
        squeezed = lo > hi
        mid = 0.5 * (np.where(squeezed, lo, 0.0) + np.where(squeezed, hi, 0.0))
        return np.where(squeezed, mid, lo), np.where(squeezed, mid, hi)

    def act(self, obs_batch: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Decisions (A,) int64 and params (A, 3, 2) float32 for stacked observations."""
        plan = self.plan(obs_batch)
        return plan.decision, plan.params

    def plan(self, obs_batch: Mapping[str, np.ndarray]) -> AccLcPlan:
        """The action of :meth:`act` with the checks behind it (for the safety module)."""
        c = self.c
        f = self._features(obs_batch)
        A = len(f["v"])
        d = f["d"]
        mask = f["mask"]
        # accelerations and steering per decision
        mand = ~mask[:, FOLLOW]
        creep = np.where(mand, c.end_s0, c.s0)
        acc_f = self._lane_accel(f, _C, d, end_gap=np.where(mand, c.end_wait, c.s0))
        acc_l = self._lane_accel(f, _L, d, end_gap=creep)
        acc_r = self._lane_accel(f, _R, d, end_gap=creep)
        safe_l = self._safe(f, _L, relaxed=False) & mask[:, LEFT]
        safe_r = self._safe(f, _R, relaxed=False) & mask[:, RIGHT]
        cont_l = self._safe(f, _L, relaxed=True) & mask[:, LEFT]
        cont_r = self._safe(f, _R, relaxed=True) & mask[:, RIGHT]
        vlat = f["vlat_hist"]
        # a change under way: offset and lateral motion towards that side (beyond the signal
        # offset of a waiting mandatory change)
        start = np.where(mand, c.signal_offset + 0.15, c.lc_start_offset)
        going_l = (d > start) & (vlat > 0.1)
        going_r = (d < -start) & (vlat < -0.1)
        centred = np.abs(d) < c.lc_start_offset
        # incentive (MOBIL-like, without politeness towards followers beyond the safety test),
        # from the latest frame only (remembered leaders cap the executed accelerations but
        # must not make the current lane look worse and trigger changes)
        now_f = self._lane_accel(f, _C, d, memory=False)
        inc_l = self._lane_accel(f, _L, d, memory=False) - now_f - c.lc_threshold
        inc_r = self._lane_accel(f, _R, d, memory=False) - now_f - c.lc_threshold
        inc_r = inc_r + c.keep_right_bias
        want_l = safe_l & centred & (inc_l > 0) & (f["v"] > 3.0)
        want_r = safe_r & centred & (inc_r > 0) & (f["v"] > 3.0)
        both = want_l & want_r
        want_l &= ~both | (inc_l > inc_r)
        want_r &= ~(both & (inc_l > inc_r))
        decision = np.full(A, FOLLOW, dtype=np.int64)
        decision[want_r] = RIGHT
        decision[want_l] = LEFT
        decision[going_l & cont_l] = LEFT
        decision[going_r & cont_r] = RIGHT
        # mandatory: pick an allowed side, preferring the one that is safe now
        m_l = mand & mask[:, LEFT] & (~mask[:, RIGHT] | safe_l | ~safe_r)
        decision[mand & ~m_l & mask[:, RIGHT]] = RIGHT
        decision[m_l] = LEFT
        # never a masked decision
        bad = ~mask[np.arange(A), decision]
        if bad.any():
            first = np.argmax(mask, axis=1)
            decision = np.where(bad & mask[:, FOLLOW], FOLLOW, np.where(bad, first, decision))
        # params per decision: a change row shifts the lateral target only while it is safe
        # (a mandatory change that is not safe yet holds the lane and waits)
        # a mandatory change also accepts a forced (cooperative) gap
        forced_l = mand & self._forced_ok(f, _L) & mask[:, LEFT]
        forced_r = mand & self._forced_ok(f, _R) & mask[:, RIGHT]
        go_l = np.where(going_l, cont_l, safe_l) | forced_l
        go_r = np.where(going_r, cont_r, safe_r) | forced_r
        # a waiting mandatory change signals (offset towards the target lane, inside its own)
        t_l = np.where(go_l, c.lane_shift, np.where(mand, c.signal_offset, 0.0))
        t_r = np.where(go_r, -c.lane_shift, np.where(mand, -c.signal_offset, 0.0))
        # while changing, the current lane's leaders still count (min of both lanes)
        # mandatory change waiting for a gap: match the target lane (stay behind its front
        # vehicle) and let a rear vehicle that is about alongside pass
        wait_l = self._wait_accel(f, _L, acc_f)
        wait_r = self._wait_accel(f, _R, acc_f)
        # (a mandatory change under way may creep towards the end of its lane to swing out)
        acc_fc = self._lane_accel(f, _C, d, end_gap=creep)
        norm_l = np.where(go_l, np.minimum(acc_l, acc_fc), acc_f)
        norm_r = np.where(go_r, np.minimum(acc_r, acc_fc), acc_f)
        acc_l = np.where(mand & ~(go_l & (safe_l | going_l & cont_l)), wait_l, norm_l)
        acc_r = np.where(mand & ~(go_r & (safe_r | going_r & cont_r)), wait_r, norm_r)
        cap = self._hidden_cap(f)
        acc_f, acc_l, acc_r = (np.minimum(x, cap) for x in (acc_f, acc_l, acc_r))
        # keep clear laterally of vehicles alongside (simultaneous changes into one lane)
        lo, hi = self._lateral_bounds(f)
        t_f = np.clip(np.zeros(A), lo, hi)
        t_l = np.clip(t_l, lo, hi)
        t_r = np.clip(t_r, lo, hi)
        params = np.empty((A, 3, 2), dtype=np.float32)
        params[:, FOLLOW, 0] = self._steer(f, t_f, c.follow_curvature)
        params[:, LEFT, 0] = self._steer(f, t_l)
        params[:, RIGHT, 0] = self._steer(f, t_r)
        params[:, FOLLOW, 1] = self._to_ab(acc_f)
        params[:, LEFT, 1] = self._to_ab(acc_l)
        params[:, RIGHT, 1] = self._to_ab(acc_r)
        lateral_ok = np.stack([go_l, np.ones(A, bool), go_r], axis=1)
        return AccLcPlan(decision, params, f, lateral_ok, lo, hi)

    def actions(self, obs: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, dict]:
        """``{agent: obs}`` -> ``{agent: {"decision": int, "params": (3, 2)}}``."""
        from agents.policies import stack_obs, to_actions

        agents = list(obs)
        if not agents:
            return {}
        return to_actions(agents, *self.act(stack_obs(obs, agents)))


def _run_episode(scenario, density, penetration, seconds, seed, weather="normal", verbose=False):
    from mixed_traffic.env import parallel_env

    e = parallel_env(
        scenario=scenario,
        density=density,
        penetration=penetration,
        episode_length=seconds,
        seed=seed,
        weather=weather,
    )
    try:
        obs, _ = e.reset(seed=seed)
        pol = AccLcPolicy()
        events: dict[str, int] = {}
        decisions = np.zeros(3, np.int64)
        while e.agents:
            act = pol.actions({a: obs[a] for a in e.agents})
            for a in act.values():
                decisions[a["decision"]] += 1
            obs, _, term, _, info = e.step(act)
            for a, t in term.items():
                ev = info.get(a, {}).get("event", "")
                if t and ev and ev != "arrived":
                    events[ev] = events.get(ev, 0) + 1
                    if verbose:
                        print("event", a, ev)
        m = e.episode_metrics()
    finally:
        e.close()
    return m, events, decisions


def safety_matrix(
    scenarios=(
        "straight", "straight-eval", "highway", "highway-eval", "bottleneck",
        "bottleneck-eval", "merge", "merge-eval", "urban", "urban-eval",
    ),
    densities=(60, 120, 180),
    penetrations=(0.2, 0.5, 1.0),
    seconds: float = 120.0,
    seed: int = 0,
    weather: str = "normal",
) -> list[dict]:  # fmt: skip
    """Run ACC-LC over scenarios x densities x penetrations and print a safety table."""
    rows = []
    hdr = (
        f"{'scenario':16s} {'dens':>4s} {'pen':>4s} {'coll':>4s} {'events':24s} {'trips':>5s} "
        f"{'rc':>5s} {'vel_A':>6s} {'vel_C':>6s}"
    )
    print(hdr, flush=True)
    for sc in scenarios:
        for dn in densities:
            for p in penetrations:
                m, ev, _ = _run_episode(sc, dn, p, seconds, seed, weather)
                row = {"scenario": sc, "density": dn, "penetration": p, "events": ev, **m}
                rows.append(row)
                evs = ",".join(f"{k}:{v}" for k, v in sorted(ev.items())) or "-"
                print(
                    f"{sc:16s} {dn:4d} {p:4.1f} {int(m.get('collisions') or 0):4d} {evs:24s} "
                    f"{int(m.get('av_trips') or 0):5d} {_fmt(m.get('route_completion'))} "
                    f"{_fmt(m.get('avg_vel_a'))} {_fmt(m.get('avg_vel_c'))}",
                    flush=True,
                )
    return rows


def _fmt(x) -> str:
    return f"{x:6.2f}" if isinstance(x, (int, float)) else f"{'-':>6s}"
