"""ACC-LC's longitudinal control: IDM with a kinematic emergency term, the acceleration for a
candidate lane (speed limits and curves ahead, leaders of that lane and overlapping ones,
cooperation, traffic lights and give-way lines), the hidden-vehicle cap and the acceleration of
a mandatory change waiting for a gap (see :mod:`agents.rules.acc_lc` for the rules).

``f`` is the feature dict of :func:`agents.rules.acc_lc_features.features`; every function is
vectorised over the A agents.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from agents.rules import acc_lc_kernel
from agents.rules.acc_lc_config import LANE_C as _C
from agents.rules.acc_lc_config import LANE_L as _L
from agents.rules.acc_lc_config import LANE_R as _R
from agents.rules.acc_lc_config import AccLcConfig
from mixed_traffic import compiled

Features = Mapping[str, np.ndarray]


def _idm(
    v: np.ndarray,
    v0: np.ndarray,
    gap: np.ndarray,
    dv: np.ndarray,
    c: AccLcConfig,
    s0: float | np.ndarray | None = None,
) -> np.ndarray:
    """IDM (or IIDM, ``c.iidm``) acceleration with the kinematic emergency term; dv = v -
    v_leader (closing speed), gap bumper gap [m] (inf = free); ``s0`` standstill gap (default
    ``c.s0``)."""
    s0 = c.s0 if s0 is None else s0
    v0 = np.maximum(v0, 0.1)
    s_star = s0 + np.maximum(0.0, v * c.T + v * dv / (2.0 * np.sqrt(c.a * c.b)))
    z = np.where(np.isfinite(gap), s_star / np.maximum(gap, 0.1), 0.0)
    acc = _iidm(v, v0, z, c) if c.iidm else c.a * (1.0 - (np.minimum(v, 2 * v0) / v0) ** 4 - z**2)
    # kinematic emergency: brake hard enough to stop behind where the leader could stop
    v_lead = np.maximum(v - dv, 0.0)
    room = np.maximum(gap - np.minimum(1.0, 0.5 * s0) + v_lead**2 / (2 * c.max_decel), 0.05)
    need = np.where(np.isfinite(gap), v**2 / (2 * room), 0.0)
    # blended in over ``emergency_span`` from ``emergency_decel``: a switch at one threshold
    # made steady following a noise-driven alternation of IDM's acceleration and hard braking
    r = np.clip((need - c.emergency_decel) / c.emergency_span, 0.0, 1.0)
    return np.minimum(acc, (1.0 - r) * acc - r * 1.2 * need)


def _iidm(v: np.ndarray, v0: np.ndarray, z: np.ndarray, c: AccLcConfig) -> np.ndarray:
    """Improved IDM (Treiber & Kesting 2013, §11.3.6): in equilibrium the gap is s0 + v T at
    every speed below v0, a constant time gap; ``z`` = desired / actual gap."""
    below = v <= v0
    a_free = np.where(below, c.a * (1.0 - (v / v0) ** 4),
                      -c.b * (1.0 - (v0 / np.maximum(v, 0.1)) ** (4.0 * c.a / c.b)))  # fmt: skip
    close = z >= 1.0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        soft = a_free * (1.0 - z ** (2.0 * c.a / np.maximum(a_free, 1e-9)))
    soft = np.where(a_free > 1e-9, soft, a_free)
    acc_below = np.where(close, c.a * (1.0 - z**2), soft)
    acc_above = np.where(close, a_free + c.a * (1.0 - z**2), a_free)
    return np.where(below, acc_below, acc_above)


class LaneCall(NamedTuple):
    """One request of :func:`lane_accels`: the acceleration if driving in lane column
    ``lane``."""

    lane: int
    memory: bool = True
    """False: the latest frame's leaders only (else every history frame, extrapolated)."""
    end_gap: np.ndarray | None = None
    """(A,) standstill gap to the virtual end-of-lane vehicle (default ``s0``)."""


def lane_accels(
    f: Features, c: AccLcConfig, calls: Sequence[LaneCall], offset: np.ndarray
) -> list[np.ndarray]:
    """(A,) acceleration per call, with the ego at lateral ``offset`` relative to the current
    lane (for the overlap test of neighbours): IDM towards the lane's desired speed, kinematic
    braking for lower limits ahead, the leaders (front vehicle of this lane and overlapping
    front vehicles of the others, every history frame) and the light. Compiled
    (:mod:`agents.rules.acc_lc_kernel`) unless ``compiled.enabled()`` is off."""
    run = _lane_accels_compiled if compiled.enabled() and len(f["v"]) else _lane_accels_reference
    return run(f, c, calls, offset)


def _lane_accels_compiled(
    f: Features, c: AccLcConfig, calls: Sequence[LaneCall], offset: np.ndarray
) -> list[np.ndarray]:
    """:func:`_lane_accels_reference` in two kernels around numpy's powers of the IDM: the
    free-road terms once per lane and agent, z's power only for the terms that read it."""
    v, A = f["v"], len(f["v"])
    lanes = np.array(sorted({q.lane for q in calls}), np.int64)
    K = f["h_dist"].shape[2]
    frames = np.array([K if q.memory else 1 for q in calls], np.int64)
    ends = np.array([np.zeros(A) if q.end_gap is None else q.end_gap for q in calls], np.float64)
    has_end = np.array([q.end_gap is not None for q in calls])
    lane = np.array([q.lane for q in calls], np.int64)
    # (A,) views of the ego row are strided: contiguous, one kernel specialisation for any A
    offset, wid = np.ascontiguousarray(offset), np.ascontiguousarray(f["wid"])
    gap, dv, s0, z, at, relevant, lim_now, a_lim, v0, stop_room = acc_lc_kernel.idm_inputs(
        v, offset, f["exists"], f["wp_speed"], f["wp_orient"], f["pv_speed"], f["pv_dist"],
        f["light_dist"], wid, f["h_dist"], f["h_len"], f["h_lat"], f["h_rel"], f["h_wid"],
        lanes, lane, frames, ends, has_end, c.speed_factor, c.limit_deadband, c.curve_accel,
        c.stop_margin, c.s0, c.lane_width_min, c.signal_min, c.yield_decel, c.hv_s0, c.T,
        2.0 * np.sqrt(c.a * c.b),
    )  # fmt: skip
    v0 = np.maximum(v0, 0.1)  # (L, A): _idm's, as _iidm's free-road terms below
    p3 = np.zeros(len(z))
    if c.iidm:
        below = v <= v0
        free = np.where(below, c.a * (1.0 - (v / v0) ** 4),
                        -c.b * (1.0 - (v0 / np.maximum(v, 0.1)) ** (4.0 * c.a / c.b)))  # fmt: skip
        soft = (below & (free > 1e-9)).ravel()[at] & ~(z >= 1.0)  # the terms that read z's power
        with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
            p3[soft] = z[soft] ** (2.0 * c.a / np.maximum(free, 1e-9)).ravel()[at[soft]]
    else:
        free = (np.minimum(v, 2 * v0) / v0) ** 4
    out = acc_lc_kernel.combine(
        gap, dv, s0, z, at, free.ravel(), p3, v0.ravel(), relevant, lim_now, a_lim, stop_room, v,
        f["v_mean"], f["light"], f["light_dist"], f["give_way"], f["signal_dist"], lanes, lane,
        frames, c.max_decel * 1.1, c.yellow_stop_decel, c.junction_speed, c.junction_speed**2,
        c.stop_margin, c.signal_sight_decel, c.iidm, c.a, 2 * c.max_decel, c.emergency_decel,
        c.emergency_span,
    )  # fmt: skip
    return list(out)


def _lane_accels_reference(
    f: Features, c: AccLcConfig, calls: Sequence[LaneCall], offset: np.ndarray
) -> list[np.ndarray]:
    """The numpy reference of :func:`lane_accels`. Every IDM term of every call is one array:
    numpy's per-call overhead, not the arithmetic, dominated."""
    v = f["v"]
    lanes = sorted({q.lane for q in calls})
    limits = {ln: _speed_limits(f, c, np.where(f["exists"][:, ln], ln, _C), offset) for ln in lanes}
    stop_room = _stop_room(f, c)
    # IDM input columns (gap, closing speed, s0, v0): per lane its free road and light stop,
    # per call its leaders (A, 3 lane columns x K frames)
    leaders = [leader_inputs(f, c, q.lane, 1 if q.memory else -1, offset, q.end_gap) for q in calls]
    widths = [2] * len(lanes) + [x[0].shape[1] for x in leaders]
    ends = np.cumsum(widths)
    cols = np.empty((4, len(v), ends[-1]))

    def put(end: int, width: int, *values: float | np.ndarray) -> None:
        for k, x in enumerate(values):
            cols[k, :, end - width : end] = x

    for i, ln in enumerate(lanes):
        v0 = limits[ln][1][:, None]
        put(2 * i + 1, 1, np.inf, 0.0, c.s0, v0)
        put(2 * i + 2, 1, stop_room[:, None], v[:, None], c.s0, v0)
    for q, (gap, dv, s0, _), e, w in zip(calls, leaders, ends[len(lanes) :], widths[len(lanes) :]):
        put(e, w, gap, dv, s0, limits[q.lane][1][:, None])
    acc = _idm(v[:, None], cols[3], cols[0], cols[1], c, cols[2])
    base = {  # free road, kinematic braking for lower limits, light
        ln: np.minimum(
            np.minimum(acc[:, 2 * i], limits[ln][2]),
            _light_bound(f, c, limits[ln][0], acc[:, 2 * i + 1], stop_room),
        )
        for i, ln in enumerate(lanes)
    }
    return [
        np.minimum(base[q.lane], np.where(relevant, acc[:, e - w : e], np.inf).min(axis=1))
        for q, (*_, relevant), e, w in zip(calls, leaders, ends[len(lanes) :], widths[len(lanes) :])
    ]


def speed_cap(f: Features, c: AccLcConfig, horizon: float = 1.0, factor: float = 1.0) -> np.ndarray:
    """(A,) the largest acceleration [m/s²] that keeps the ego within ``factor`` x the speed
    limit of its lane, the curve and limit targets ahead and the traffic light: towards that
    speed where it is (or the curve's speed there) within ``horizon`` [s], ACC-LC's kinematic
    braking for lower targets ahead, its stop at a red or yellow light and its approach to a
    give-way line. ``factor`` 1 is the limit itself; a learned policy compared with an ACC-LC
    that aims at 0.95 of the limit is capped at ``factor`` 0.95 (agents.rules.tuned)."""
    ln = np.full(len(f["v"]), _C)
    lim_now, v0, a_lim = _speed_limits(f, c, ln, f["d"])
    cap = np.minimum((factor * v0 / c.speed_factor - f["v"]) / horizon, a_lim)
    return _light_accel(f, c, cap, v0, lim_now)


def _speed_limits(
    f: Features, c: AccLcConfig, ln: np.ndarray, offset: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A,) speed limit where the ego is, IDM's desired speed ``v0`` and the kinematic
    acceleration ``a_lim`` for lower targets ahead (inf = none) in lane columns ``ln``."""
    v = f["v"]
    ar = np.arange(len(v))
    # speed limit: lowest ahead, and braking towards lower limits ahead
    spd = f["wp_speed"][ar, ln]  # (A, m)
    spd = np.where(spd > 0.5, spd, np.inf)
    lim_now = np.where(np.isfinite(spd[:, 0]), spd[:, 0], np.min(spd, axis=1))
    lim_now = np.where(np.isfinite(lim_now), lim_now, 13.9)
    v0 = c.speed_factor * lim_now
    dist_wp = np.arange(spd.shape[1], dtype=np.float64) + 1.0
    target = _curve_target(f, c, ar, ln, spd, offset)
    # the target where the ego is now is IDM's desired speed, whose free-road term is smooth
    # in the noisy speed reading; braking to it over the 1 m to the first waypoint turned
    # every reading above it into a hard brake. Kinematic braking only for lower targets.
    v0 = np.minimum(v0, target[:, 0])
    lower = (target < target[:, :1] - c.limit_deadband) & (target < v[:, None])
    need = np.where(lower, (target**2 - v[:, None] ** 2) / (2 * dist_wp), np.inf)
    # the preview's drops beyond the waypoints (a junction's turn speed), braked for alike
    pv_t, pv_d = c.speed_factor * f["pv_speed"][ar, ln], f["pv_dist"][ar, ln]  # (A, k)
    far = (pv_t < v[:, None]) & (pv_d > dist_wp[-1])
    need_pv = np.where(far, (pv_t**2 - v[:, None] ** 2) / (2 * np.where(far, pv_d, 1.0)), np.inf)
    need = np.concatenate([need, need_pv], axis=1)
    a_lim = np.min(need, axis=1)
    a_lim = np.where(a_lim < 0, 1.3 * a_lim, np.inf)
    return lim_now, v0, a_lim


def _curve_target(
    f: Features,
    c: AccLcConfig,
    ar: np.ndarray,
    ln: np.ndarray,
    spd: np.ndarray,
    offset: np.ndarray,
) -> np.ndarray:
    """(A, m) target speed at each waypoint: the speed limit ``spd`` bounded by the curves
    (lateral acceleration bound, and the along-lane speed SUMO reports grows by
    1 / (1 - kappa * d) on the inside of a curve)."""
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
    return np.minimum(c.speed_factor * spd, v_curve) * inside


def leader_inputs(
    f: Features,
    c: AccLcConfig,
    lane: int,
    frames: int,
    offset: np.ndarray,
    end_gap: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IDM inputs (A, 3 K) behind the front vehicles of every lane column when driving in
    ``lane`` (``frames`` 1: every history frame, -1: the latest only): bumper gap (inf where
    not a leader), closing speed, standstill gap, and which are leaders: those of the lane
    itself, of the others on lateral overlap, and neighbours to yield to."""
    kk = slice(None) if frames > 0 else slice(-1, None)
    dist = f["h_dist"][:, :, kk]  # (A, 3, K)
    gap = dist - f["h_len"][:, :, kk]
    # lateral position of the other vehicles relative to the current lane centre
    shift = (np.arange(3) - _C) * -c.lane_width_min  # left column = +width
    lat = np.abs(f["h_lat"][:, :, kk] + shift[:, None] - offset[:, None, None])
    half = 0.5 * (f["wid"][:, None, None] + f["h_wid"][:, :, kk]) + 0.4
    # moving to another lane: the current lane's leader matters while we overlap it
    half[:, _C] += 0.6 if lane != _C else 0.0
    overlap = lat < half
    overlap[:, lane] = True
    # own lane of the lane column: the chosen lane; others only on overlap
    present = f["exists"].copy()
    present[:, _C] = True
    relevant = np.isfinite(dist) & overlap & present[:, :, None]
    if lane == _C:
        relevant[:, [_L, _R]] |= _yield_to(f, c, kk, dist, gap)[:, [_L, _R]]
    s0 = np.full(dist.shape, c.s0)
    if end_gap is not None:
        s0[:, _C] = np.where(f["h_len"][:, _C, kk] < 0.1, end_gap[:, None], c.s0)
    A = len(dist)
    return (
        np.where(relevant, gap, np.inf).reshape(A, -1),
        -f["h_rel"][:, :, kk].reshape(A, -1),
        s0.reshape(A, -1),
        relevant.reshape(A, -1),
    )


def _yield_to(
    f: Features, c: AccLcConfig, kk: slice, dist: np.ndarray, gap: np.ndarray
) -> np.ndarray:
    """(A, 3, K) cooperation: yield to a neighbour ahead signalling a change into our lane
    (meaningful in the side columns), unless we are already closer than the rear gap its
    forced merge needs (then waiting deadlocks both; passing lets it merge behind us)."""
    side = (np.arange(3) - _C)[:, None]
    towards = f["h_lat"][:, :, kk] * side > c.signal_min
    close = np.maximum(-f["h_rel"][:, :, kk], 0.0)
    can = close**2 / (2 * np.maximum(gap - 1.0, 0.1)) <= c.yield_decel
    return np.isfinite(dist) & towards & (gap > c.hv_s0) & can


def _stop_room(f: Features, c: AccLcConfig) -> np.ndarray:
    """(A,) room [m] to stop before the current lane's light (its stop line less the margin)."""
    return np.maximum(f["light_dist"][:, _C] - c.stop_margin, 0.05)


def _light_accel(
    f: Features, c: AccLcConfig, acc: np.ndarray, v0: np.ndarray, lim_now: np.ndarray
) -> np.ndarray:
    """``acc`` (A,) bounded by :func:`_light_bound`."""
    room = _stop_room(f, c)
    a_stop = _idm(f["v"], v0, room, f["v"], c)
    return np.minimum(acc, _light_bound(f, c, lim_now, a_stop, room))


def _light_bound(
    f: Features, c: AccLcConfig, lim_now: np.ndarray, a_stop: np.ndarray, stop_room: np.ndarray
) -> np.ndarray:
    """(A,) acceleration bound (inf = none) of the traffic light or give-way line of the
    current lane (a change does not escape it) and of the approach speed at a give-way line;
    ``a_stop`` is IDM's acceleration behind a stopped vehicle at ``stop_room``. (The speeds of
    a turn behind a signal come from the route's preview.)"""
    v = f["v"]
    ld = f["light_dist"][:, _C]
    st = f["light"][:, _C]
    need_stop = v**2 / (2 * stop_room)
    stop = ((st == 0) & (need_stop < c.max_decel * 1.1)) | (
        (st == 1) & (need_stop < c.yellow_stop_decel)
    )
    a_stop = np.minimum(a_stop, np.where(need_stop > 1.0, -need_stop * 1.1, a_stop))
    bound = np.where(stop, a_stop, np.inf)
    # a give-way line may close at any moment: approach it at ``junction_speed`` (in town: a
    # ramp's merge on a fast road is taken at speed)
    vj = c.junction_speed
    a_j = np.where(v > vj, (vj**2 - v**2) / (2 * np.maximum(ld - 1.0, 0.5)), np.inf)
    line = (st >= 0) & np.isfinite(ld) & f["give_way"] & (lim_now < 20.0)
    bound = np.where(line, np.minimum(bound, a_j), bound)
    return np.minimum(bound, _unseen_signal_bound(f, c))


def _unseen_signal_bound(f: Features, c: AccLcConfig) -> np.ndarray:
    """(A,) acceleration bound (inf = none) towards a signal the HD map shows on the current
    lane whose state the camera does not show: brake at what stopping at its line needs once
    that exceeds ``signal_sight_decel``. Without it, ACC-LC reached a red first seen at the
    fog camera's 30 m at 15.7 m/s and could not stop (urban-grid3x3, fog)."""
    sig = f["signal_dist"]
    unseen = (f["light"][:, _C] < 0) & np.isfinite(sig)
    need = f["v_mean"] ** 2 / (2 * np.maximum(sig - c.stop_margin, 0.05))
    return np.where(unseen & (need >= c.signal_sight_decel), -need, np.inf)


def hidden_cap(f: Features, c: AccLcConfig) -> np.ndarray:
    """(A,) acceleration cap for passing slower neighbours: the sensors report one front
    vehicle per lane, so a vehicle right ahead of it (e.g. stuck half-way in a change into
    our lane) is hidden; keep the closing speed to it, and to the visible one while its rear
    is still ahead (its lateral offset may be misread), stoppable at ``hidden_decel``."""
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


def wait_accel(f: Features, c: AccLcConfig, side: int, acc_cur: np.ndarray) -> np.ndarray:
    """(A,) acceleration of a mandatory change waiting for (or forcing into) a gap: aim at
    the slot between the target lane's front and rear vehicles when it is long enough
    (match their speed, centre the slack), else let the rear vehicle pass; never beyond the
    current lane's own limits (``acc_cur``: its leaders and the lane's end)."""
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


def to_ab(acc: np.ndarray, c: AccLcConfig) -> np.ndarray:
    """Physical acceleration [m/s²] (A,) -> the normalised accel_brake in [-1, 1]."""
    return np.clip(np.where(acc > 0, acc / c.max_accel, acc / c.max_decel), -1.0, 1.0)


def from_ab(ab: np.ndarray, c: AccLcConfig) -> np.ndarray:
    """Normalised accel_brake in [-1, 1] (A,) -> the physical acceleration [m/s²]."""
    return np.where(ab > 0, ab * c.max_accel, ab * c.max_decel)
