"""ACC-LC's lateral part: steering towards a lateral target, the gap checks of a lane change
(safe, relaxed for one under way, forced for a mandatory one) and the lateral bounds that keep
clear of vehicles alongside (see :mod:`agents.rules.acc_lc` for the rules).

``f`` is the feature dict of :func:`agents.rules.acc_lc_features.features`; every function is
vectorised over the A agents.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from agents.rules.acc_lc_config import AccLcConfig
from agents.rules.acc_lc_features import lane_curvature

Features = Mapping[str, np.ndarray]


def steer(
    f: Features, c: AccLcConfig, target: np.ndarray, curvature: float | None = None
) -> np.ndarray:
    """(A,) steering in [-1, 1] towards the lateral ``target`` [m]; with a ``curvature``
    [1/m], the course is one that turns straight at it before reaching the target."""
    v = f["v"]
    vs = np.maximum(v, 0.5)
    err = target - f["d"]
    mag = np.minimum.reduce(
        [np.full_like(err, c.lat_speed), c.lat_gain * np.abs(err), np.sqrt(1.6 * np.abs(err))]
    )
    vl_des = np.sign(err) * mag
    h = _current_course(f, c, v, vs)
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
    # a step of dt corrects at most half the course error (the command is held for the step:
    # at SUMO's 0.5 s steps the full gain overshoots and the ego weaves)
    gain = np.minimum(c.heading_gain * np.minimum(1.0, 8.0 / vs), 0.5 * c.wheelbase / (vs * c.dt))
    fb = np.clip(gain * (chi - h), -lim, lim)
    steer = ff + fb
    return np.clip(steer / np.deg2rad(c.max_steer_deg), -1.0, 1.0)


def _current_course(f: Features, c: AccLcConfig, v: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """(A,) current course [rad]: SUMO's heading trails the lateral path by a body length, so
    at low speed (a lane change from standstill) it lags the course far behind and the ego
    overshoots into the next lane; there the measured lateral velocity is used. So it is
    where the two disagree by more than ``heading_trust``: SUMO's heading is the chord of
    the body along its lane, which on a junction lane that shifts sideways or turns
    sharply points where the car is not going (SUMO's cross: 50 deg off while the car went
    straight on), and steering against it built up a yaw that carried the AV into the next
    lane after the junction."""
    chi_meas = np.arcsin(np.clip(f["vlat_hist"] / vs, -0.9, 0.9))
    slow = np.clip((8.0 - v) / 4.0, 0.0, 1.0)
    off = np.clip(np.abs(f["h"] - chi_meas) / c.heading_trust - 1.0, 0.0, 1.0)
    wgt = np.maximum(slow, off)
    return wgt * chi_meas + (1.0 - wgt) * f["h"]


def safe(f: Features, c: AccLcConfig, side: int, relaxed: bool) -> np.ndarray:
    """(A,) a change into lane column ``side`` is safe: the target lane's rear vehicle keeps
    ``s0 + rear_headway * v_rear`` plus a margin for its closing speed, and the ego can follow
    its front vehicle without hard braking (``relaxed``: half those gaps, for a change under
    way)."""
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


def forced_ok(f: Features, c: AccLcConfig, side: int) -> np.ndarray:
    """(A,) a forced (cooperative) merge into ``side`` is acceptable: the target lane's rear
    vehicle, following IDM with the ego as its leader, brakes at most ``force_rear_decel``,
    and the ego can follow the target lane's front vehicle braking at most
    ``force_front_decel``; both bumper gaps stay positive with a margin."""
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


def lateral_bounds(f: Features, c: AccLcConfig) -> tuple[np.ndarray, np.ndarray]:
    """(A,) lowest / highest allowed lateral target (current-lane frame): a vehicle
    alongside (longitudinal overlap plus a margin) in any lane column, e.g. one straddling
    into the lane we change to from the other side, bounds the lateral motion towards it."""
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
    # at an angle to the lane the ego reaches sideways with its corners: two AVs changing into
    # one lane from both sides met at +-15 deg with their centres 1.8 m apart (SUMO's grid6).
    # (Only its own: a neighbour's heading is SUMO's drawing, and a long one's far corner is
    # not beside us; counting them pushed an AV into the other lane beside a truck.)
    course = _current_course(f, c, f["v"], np.maximum(f["v"], 0.5))
    reach = 0.5 * f["len"] * np.sin(np.minimum(np.abs(course), c.max_body_yaw))
    H = half + c.side_margin + reach[:, None, None]
    hi = np.where(beside & (y > d), y - H, np.inf).min(axis=(1, 2))
    lo = np.where(beside & (y <= d), y + H, -np.inf).max(axis=(1, 2))
    # never off the road to keep clear: squeezed against a road edge by a neighbour in a
    # queue, an AV steered hard into the kerb at walking pace and left the road (A10KW)
    edge = 0.5 * (c.lane_width_min - f["wid"])
    hi = np.maximum(hi, np.where(f["exists"][:, 2], -np.inf, -edge))
    lo = np.minimum(lo, np.where(f["exists"][:, 0], np.inf, edge))
    squeezed = lo > hi
    mid = 0.5 * (np.where(squeezed, lo, 0.0) + np.where(squeezed, hi, 0.0))
    return np.where(squeezed, mid, lo), np.where(squeezed, mid, hi)


def follow_steering(f: Features, c: AccLcConfig, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(A,) steering that keeps the lane centre (clipped to the lateral bounds ``[lo, hi]``
    [m]), along the lane's curvature."""
    return steer(f, c, np.clip(np.zeros(len(f["v"])), lo, hi), c.follow_curvature)
