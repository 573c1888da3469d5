"""Compiled kernel of the controller's per-step arithmetic (``control``), whose numpy version
stays the reference.

``frenet_compute``: ``BicycleController.compute`` after the steering's side-slip angle in one
pass over the agents: the bicycle model's Frenet step (``control.bicycle_frenet_step``), the
SUMO body-offset update, the state write-back and the command's arrays. The side-slip angle
``β = arctan(l_r / L · tan δ)`` and the predicted heading ``arctan2(body, length)`` stay
numpy's (its SIMD ``tan``/``arctan``/``arctan2`` differ from libm's in the last bit); ``sin``
and ``cos`` match. The floating-point operations and their order are those of the numpy
expressions, so the results are equal bit for bit (tests/test_control_kernel.py checks it on
SUMO episodes).

``allowed`` and ``physical``: the action stage's ``allowed_decisions`` (masked decisions
replaced) and ``to_physical`` (executed row -> steering angle and acceleration), one pass each.

``front_view``: ``truth.FrontView``'s arrays (the ground-truth front vehicle of each agent and
its bumper gap), one pass instead of a dozen numpy temporaries (the env builds it three times a
step).

``edie_add``: ``space_time.SpaceTimeField.add``'s two ``np.add.at`` into one time row of the
Edie grid, in vehicle order as ``np.add.at`` adds (the speed moments' pairwise sums stay
numpy's).
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import clip, inline, maximum, minimum, njit


@njit
def frenet_compute(v, psi, body, length, r, lateral, accel, kappa, beta, lr, dt, max_course):
    """(speed, lateral_move, intended_lateral, course, body_new), each (A,) float64, of the A
    agents at state rows ``r``; writes their new speed, yaw and body offset into ``v``,
    ``psi`` and ``body`` (the controller's state arrays) in place.

    Args:
        v, psi, body, length: (N,) the controller's state: CoG speed [m/s], yaw relative to the
            lane [rad], SUMO's front-rear lateral offset [m], vehicle length [m].
        r: (A,) int64 state rows of the agents.
        lateral, accel, kappa, beta: (A,) lateral offset now [m], acceleration [m/s²], lane
            curvature [1/m] and the side-slip angle β [rad] (numpy's).
        lr: distance rear axle - CoG [m]; dt: step [s]; max_course: course clip [rad].

    Returns:
        ``speed`` along the lane (ds/dt) [m/s], ``lateral_move`` dd [m], ``intended_lateral``
        = lateral + dd [m], ``course`` ψ_mid + β [rad] and the new ``body`` offset [m] (for the
        caller's ``arctan2``).
    """
    A = len(r)
    speed, move, intended = np.empty(A), np.empty(A), np.empty(A)
    course_out, body_out = np.empty(A), np.empty(A)
    for a in range(A):
        k = r[a]
        d = lateral[a]
        v_new, psi_new, course, scale = _frenet(v[k], psi[k], d, accel[a], kappa[a], beta[a], lr,
                                                dt, max_course)  # fmt: skip
        ds = v_new * np.cos(course) * scale * dt
        dd = v_new * np.sin(course) * dt
        # SUMO's rear point trails the front's lateral path (control's module docstring)
        body_new = body[k] * (1.0 - minimum(ds / length[k], 1.0)) + dd
        v[k], psi[k], body[k] = v_new, psi_new, body_new
        speed[a], move[a], intended[a] = ds / dt, dd, d + dd
        course_out[a], body_out[a] = course, body_new
    return speed, move, intended, course_out, body_out


@njit
def frenet_rollout(v, psi, d, accel, kappa, beta, lr, dt, steps, max_course):
    """(A,) lateral offset [m] after ``steps`` Frenet steps of ``control.bicycle_frenet_step``
    from ``v``, ``psi``, ``d`` (A,) holding ``accel`` with side-slip angle ``beta`` (numpy's)
    on curvature ``kappa`` (``control.bicycle_rollout``'s kernel; inputs are not written)."""
    A = len(v)
    out = np.empty(A)
    for a in range(A):
        va, pa, da = v[a], psi[a], d[a]
        for _ in range(steps):
            va, pa, course, _ = _frenet(va, pa, da, accel[a], kappa[a], beta[a], lr, dt,
                                        max_course)  # fmt: skip
            da = da + va * np.sin(course) * dt
        out[a] = da
    return out


@inline
def _frenet(v, psi, d, accel, kap, b, lr, dt, max_course):
    """One agent's ``bicycle_frenet_step`` up to its course: (new speed, new yaw, course, the
    along-lane scale 1 / (1 - κ d)), the operations in the numpy step's order."""
    v_new = maximum(v + accel * dt, 0.0)
    yaw_rate = v_new * np.sin(b) / lr
    scale = 1.0 / maximum(1.0 - kap * d, 0.1)
    s_dot0 = v_new * np.cos(clip(psi + b, -max_course, max_course)) * scale
    psi_new = psi + (yaw_rate - kap * s_dot0) * dt
    psi_new = clip(psi_new + b, -max_course, max_course) - b
    course = clip(0.5 * (psi + psi_new) + b, -max_course, max_course)
    return v_new, psi_new, course, scale


@njit
def allowed(decision, mask):
    """(executed (A,) int64, replaced (A,) bool) of ``action.allowed_decisions``.

    Args:
        decision: (A,) int64 in [-3, 3) (negative counts from the end, as numpy's indexing).
        mask: (A, 3) int8 action masks, non-zero = allowed.
    """
    A = len(decision)
    out, replaced = np.empty(A, np.int64), np.empty(A, np.bool_)
    for a in range(A):
        d = _decision_col(decision[a])
        forbidden = mask[a, d] == 0
        fallback = np.int64(0)  # np.argmax of a row with nothing allowed
        if mask[a, 1] != 0:
            fallback = np.int64(1)
        else:
            for k in range(3):
                if mask[a, k] != 0:
                    fallback = np.int64(k)
                    break
        out[a] = fallback if forbidden else decision[a]
        replaced[a] = forbidden
    return out, replaced


@njit
def physical(decision, params, steer_scale, max_accel, max_decel):
    """(steer (A,) [rad], accel (A,) [m/s²]) of ``action.to_physical``.

    Args:
        decision: (A,) int64 in [-3, 3); params: (A, 3, 2) float64 normalised (steering,
            accel_brake); steer_scale: max steering angle [rad]; max_accel, max_decel [m/s²].
    """
    A = len(decision)
    steer, accel = np.empty(A), np.empty(A)
    for a in range(A):
        d = _decision_col(decision[a])
        steer[a] = params[a, d, 0] * steer_scale
        ab = params[a, d, 1]
        accel[a] = ab * max_accel if ab > 0 else ab * max_decel
    return steer, accel


@njit
def front_view(vehicle, distance, features, speed, length, k, r, lane):
    """(exists (A,) bool, distance, length, closing, gap (A,) float64) of ``truth.FrontView``.

    Args:
        vehicle, distance: (M, 3, 2) the ground-truth neighbour rows and distances [m]
            (``Neighbours``; [..., 0] = front); features: (M, 3, V, F) the ground-truth
            vehicle features (slot 0 = front; feature 1 its relative speed [m/s], 3 its length
            [m]); speed, length: (N,) the snapshot's [m/s], [m]; k: (A,) truth rows;
            r: (A,) snapshot rows; lane: the current lane's column (``lane_graph.CURRENT``).
    """
    A = len(k)
    exists = np.empty(A, np.bool_)
    dist, flen, closing, gap = np.empty(A), np.empty(A), np.empty(A), np.empty(A)
    for a in range(A):
        i = k[a]
        e = vehicle[i, lane, 0] >= 0
        d = distance[i, lane, 0]
        other = features[i, lane, 0, 3] if e else 0.0
        exists[a], dist[a], flen[a] = e, d, other
        closing[a] = -features[i, lane, 0, 1] if e else speed[r[a]]
        gap[a] = abs(d) - 0.5 * (length[r[a]] + other)  # sensing.geometry.bumper_gap
    return exists, dist, flen, closing, gap


@njit
def edie_add(dist, time, row, s, v, dt, dx, copy, width, last):
    """Add the vehicles inside the segment to time row ``row`` of the Edie grid in place.

    Args:
        dist, time: (T, C·width) distance driven [m] and time spent [s] per cell, copy c's
            cells from column c·width.
        row: the step's time bin; s: (N,) position along its copy's segment [m], NaN outside;
        v: (N,) speed [m/s]; dt: step [s]; dx: cell length [m]; copy: (N,) int64 each
        vehicle's copy; width: columns per copy; last: (C,) int64 each copy's last column.
    """
    for n in range(len(s)):
        x = s[n]
        if x != x:  # outside the segment
            continue
        q = x // dx
        # numpy's float -> int64 cast on x86 gives INT64_MIN for NaN/out of range: clipped to 0
        col = np.int64(q) if q >= -9.2e18 and q < 9.2e18 else np.int64(0)
        c = copy[n]
        col = min(max(col, 0), last[c]) + c * width
        dist[row, col] += v[n] * dt
        time[row, col] += dt


@inline
def _decision_col(d):
    """The column numpy's indexing reads for decision ``d`` of 3 (IndexError outside)."""
    if d < -3 or d >= 3:
        raise IndexError("decision outside the action space")
    return d + 3 if d < 0 else d


def warm() -> None:
    """Load the kernels (from the disk cache, else compile it) for the dtypes and layouts the
    env passes, on one agent: a process that forks workers calls this once."""
    f, r = np.ones(1), np.zeros(1, np.int64)
    frenet_compute(f.copy(), f.copy(), f.copy(), f.copy(), r, f, f, f, f, 1.5, 0.1, 1.3)
    frenet_rollout(f, f, f, f, f, f, 1.5, 0.1, 10, 1.3)
    allowed(r, np.ones((1, 3), np.int8))
    physical(r, np.zeros((1, 3, 2)), 1.0, 3.0, 6.0)
    i = np.zeros((1, 3, 2), np.int64)
    front_view(i, np.zeros((1, 3, 2)), np.zeros((1, 3, 2, 6)), f, f, r, r, 0)
    one = np.zeros(1, np.int64)
    edie_add(np.zeros((1, 1)), np.zeros((1, 1)), 0, f, f, 0.1, 10.0, one, 1, one)
