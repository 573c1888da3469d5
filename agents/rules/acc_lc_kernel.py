"""ACC-LC's candidate-lane accelerations (:func:`agents.rules.acc_lc_longitudinal.lane_accels`)
as two compiled kernels around numpy's powers, and the RSS caps (:func:`rss_caps`).

``idm_inputs`` builds, per agent, what the numpy stages build with whole arrays: each lane's
speed limits (curves, limits and the preview ahead) and every call's leaders (overlap,
cooperation, the virtual end-of-lane vehicle), as one entry per IDM term ACC-LC reads (gap,
closing speed, standstill gap and the IDM's z). The IDM's powers stay numpy's: its vectorised
``power`` differs from libm's (the only one a kernel can call) in the last bit; IIDM's free-road
terms are taken once per lane and agent, z's power only for the terms that read it. ``combine``
then computes each term's acceleration (IDM or IIDM, the kinematic emergency term), bounds each
lane by its limits and light and takes every call's minimum over its leaders. The kernels do the
numpy stages' floating-point operations in the same order, so the results are equal bit for bit
(tests/test_acc_lc_kernel.py checks it on SUMO states); the numpy stages stay the reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import clip, inline, maximum, minimum, njit

_L, _C, _R = 0, 1, 2
_TWO_PI = 2 * np.pi


@inline
def _limits(a, ln, v, offset, wp_speed, wp_orient, pv_speed, pv_dist, sf, deadband, curve_accel,
            spd, target):  # fmt: skip
    """(lim_now, v0, a_lim) of agent ``a`` in lane column ``ln`` (``_speed_limits``);
    ``spd`` and ``target`` (m,) are scratch."""
    m, k = wp_speed.shape[2], pv_speed.shape[2]
    lowest = np.inf
    for j in range(m):
        s = wp_speed[a, ln, j]
        spd[j] = s if s > 0.5 else np.inf
        lowest = minimum(lowest, spd[j])
    lim = spd[0] if np.isfinite(spd[0]) else lowest
    lim = lim if np.isfinite(lim) else 13.9
    w = min(5, m - 1) if m > 1 else 1
    hi = max(m - 1 - w, 0)
    ins = abs(offset[a]) + 0.3
    for j in range(m):
        j0 = min(max(j - w // 2, 0), hi)
        j1 = min(j0 + w, m - 1)
        o = wp_orient[a, ln, j1] - wp_orient[a, ln, j0] + np.pi
        kap = abs(o % _TWO_PI - np.pi) / w
        v_curve = np.sqrt(curve_accel / maximum(kap, 1e-4))
        inside = maximum(1.0 - kap * ins, 0.3)
        target[j] = minimum(sf * spd[j], v_curve) * inside
    v0 = minimum(sf * lim, target[0])
    va = v[a]
    a_lim = np.inf
    for j in range(m):
        lower = (target[j] < target[0] - deadband) and (target[j] < va)
        need = (target[j] * target[j] - va * va) / (2 * (j + 1.0)) if lower else np.inf
        a_lim = minimum(a_lim, need)
    for j in range(k):
        pv_t, pv_d = sf * pv_speed[a, ln, j], pv_dist[a, ln, j]
        far = (pv_t < va) and (pv_d > float(m))
        need = (pv_t * pv_t - va * va) / (2 * pv_d) if far else np.inf
        a_lim = minimum(a_lim, need)
    return lim, v0, 1.3 * a_lim if a_lim < 0 else np.inf


@njit
def idm_inputs(
    v, offset, exists, wp_speed, wp_orient, pv_speed, pv_dist, light_dist, wid, h_dist, h_len,
    h_lat, h_rel, h_wid, lanes, call_lane, call_frames, call_end, has_end, sf, deadband,
    curve_accel, stop_margin, s0, lane_width, signal_min, yield_decel, hv_s0, T, den,
):  # fmt: skip
    """The IDM's inputs of ``lane_accels`` for A agents, one entry per IDM term it needs.

    Args: the features (``v``, ``offset``, ``wid``, ``light_dist`` ... as in
    :mod:`agents.rules.acc_lc_features`; history arrays (A, 3, K)); ``lanes`` (L,) the sorted
    lane columns called; per call (Q,) its lane column, frames (K or 1) and whether it has an
    end gap, ``call_end`` (Q, A) [m]; the config's scalars (``den`` = 2 sqrt(a b)).
    Returns per entry (U,), agent by agent (per lane its free road and light stop, then each
    call's relevant leaders): gap [m], closing speed [m/s], standstill gap [m], the IDM's
    ``z`` (desired over actual gap) and the flat index ``i A + a`` of its lane and agent into
    (L, A) arrays; then ``relevant`` (A, 3 Σ frames) which leader columns are entries;
    ``lim_now``, ``a_lim`` and ``v0`` (L, A) [m/s, m/s², m/s]; ``stop_room`` (A,) [m].
    """
    A, K = h_dist.shape[0], h_dist.shape[2]
    L, Q = len(lanes), len(call_lane)
    W = 3 * int(call_frames.sum())
    cap = A * (2 * L + W)
    gap_e, dv_e, s0_e, z_e = np.empty(cap), np.empty(cap), np.empty(cap), np.empty(cap)
    at_e = np.empty(cap, np.int64)
    relevant = np.zeros((A, W), np.bool_)
    lim_now, a_lim, v0 = np.empty((L, A)), np.empty((L, A)), np.empty((L, A))
    stop_room = np.empty(A)
    spd, target = np.empty(wp_speed.shape[2]), np.empty(wp_speed.shape[2])
    u = 0
    for a in range(A):
        va = v[a]
        stop_room[a] = maximum(light_dist[a, _C] - stop_margin, 0.05)
        for i in range(L):
            ln = lanes[i] if exists[a, lanes[i]] else _C
            lim_now[i, a], v0[i, a], a_lim[i, a] = _limits(
                a, ln, v, offset, wp_speed, wp_orient, pv_speed, pv_dist, sf, deadband,
                curve_accel, spd, target)  # fmt: skip
            # the free road, and the stop before the light
            gap_e[u], dv_e[u], s0_e[u], z_e[u], at_e[u] = np.inf, 0.0, s0, 0.0, i * A + a
            room = stop_room[a]
            gap_e[u + 1], dv_e[u + 1], s0_e[u + 1], at_e[u + 1] = room, va, s0, i * A + a
            z_e[u + 1] = _z(va, va, room, s0, T, den)
            u += 2
        col = 0
        for q in range(Q):
            lane, first = call_lane[q], K - call_frames[q]
            at = np.searchsorted(lanes, lane) * A + a
            for j in range(3):
                for kk in range(first, K):
                    rel, gap = _leader(a, lane, j, kk, offset, exists, wid, h_dist, h_len, h_lat,
                                       h_rel, h_wid, lane_width, signal_min, yield_decel, hv_s0)  # fmt: skip
                    relevant[a, col] = rel
                    col += 1
                    if rel:
                        end = has_end[q] and j == _C and h_len[a, j, kk] < 0.1
                        s0_u = call_end[q, a] if end else s0
                        gap_e[u], dv_e[u], s0_e[u], at_e[u] = gap, -h_rel[a, j, kk], s0_u, at
                        z_e[u] = _z(va, dv_e[u], gap, s0_u, T, den)
                        u += 1
    return (gap_e[:u], dv_e[:u], s0_e[:u], z_e[:u], at_e[:u], relevant, lim_now, a_lim, v0,
            stop_room)  # fmt: skip


@inline
def _z(v, dv, gap, s0, T, den):
    """The IDM's desired over actual gap (``_idm``'s ``z``); 0 on a free road."""
    s_star = s0 + maximum(0.0, v * T + v * dv / den)
    return s_star / maximum(gap, 0.1) if np.isfinite(gap) else 0.0


@inline
def _idm_acc(v, v0, z, p3, free, gap, dv, s0, iidm, a_max, max_decel_2, e_decel, e_span):  # fmt: skip
    """``_idm``'s acceleration of one entry from its ``z``, ``free`` (IIDM's free-road
    acceleration of its lane, else IDM's (v / v0)⁴) and ``p3`` (z ** (2 a / free), numpy's)."""
    if iidm:
        close = z >= 1.0
        if v <= v0:
            soft = free * (1.0 - p3) if free > 1e-9 else free
            acc = a_max * (1.0 - z * z) if close else soft
        else:
            acc = free + a_max * (1.0 - z * z) if close else free
    else:
        acc = a_max * (1.0 - free - z * z)
    # the kinematic emergency term
    v_lead = maximum(v - dv, 0.0)
    room = maximum(gap - minimum(1.0, 0.5 * s0) + v_lead * v_lead / max_decel_2, 0.05)
    need = v * v / (2 * room) if np.isfinite(gap) else 0.0
    r = clip((need - e_decel) / e_span, 0.0, 1.0)
    return minimum(acc, (1.0 - r) * acc - r * 1.2 * need)


@inline
def _leader(a, lane, j, kk, offset, exists, wid, h_dist, h_len, h_lat, h_rel, h_wid, lane_width,
            signal_min, yield_decel, hv_s0):  # fmt: skip
    """(is a leader, bumper gap [m]) of agent ``a``'s history vehicle (``j``, ``kk``) when
    driving in lane column ``lane`` (``leader_inputs``): the lane's own, the others' on
    lateral overlap, and neighbours to yield to."""
    dist = h_dist[a, j, kk]
    gap = dist - h_len[a, j, kk]
    lat = abs(h_lat[a, j, kk] + float(j - _C) * -lane_width - offset[a])
    half = 0.5 * (wid[a] + h_wid[a, j, kk]) + 0.4
    if j == _C:
        half = half + (0.6 if lane != _C else 0.0)
    rel = np.isfinite(dist) and (lat < half or j == lane) and (exists[a, j] or j == _C)
    if lane == _C and j != _C and not rel:
        rel = _yields(dist, gap, h_lat[a, j, kk], h_rel[a, j, kk], j, signal_min, yield_decel,
                      hv_s0)  # fmt: skip
    return rel, gap


@njit
def rss_caps(v, offset, exists, wid, h_dist, h_len, h_lat, h_rel, h_wid, lane_width, signal_min,
             yield_decel, hv_s0, rho, rho_sq4, ego_decel, lead_2, min_gap):  # fmt: skip
    """(A, 3) ``rss.rss_caps``: per lane column the lowest RSS-safe acceleration [m/s²] behind
    the leaders of every history frame (inf = none); ``rho`` the response time [s],
    ``rho_sq4`` = rho² / 4, ``lead_2`` twice the leader's braking, as ``rss_accel``."""
    A, K = h_dist.shape[0], h_dist.shape[2]
    out = np.empty((A, 3))
    for a in range(A):
        for lane in range(3):
            cap = np.inf
            for j in range(3):
                for kk in range(K):
                    rel, gap = _leader(a, lane, j, kk, offset, exists, wid, h_dist, h_len, h_lat,
                                       h_rel, h_wid, lane_width, signal_min, yield_decel, hv_s0)  # fmt: skip
                    if rel:
                        v_lead = maximum(v[a] - -h_rel[a, j, kk], 0.0)
                        room = gap - min_gap + v_lead * v_lead / lead_2
                        disc = rho_sq4 + 2 * (room - v[a] * rho / 2) / ego_decel
                        x = ego_decel * (-rho / 2 + np.sqrt(disc)) if disc >= 0 else 0.0
                        cap = minimum(cap, (maximum(x, 0.0) - v[a]) / rho if disc >= 0 else -np.inf)
            out[a, lane] = cap
    return out


@inline
def _yields(dist, gap, lat, rel, j, signal_min, yield_decel, hv_s0):  # fmt: skip
    """``_yield_to`` of one neighbour in side column ``j``."""
    towards = lat * float(j - _C) > signal_min
    close = maximum(-rel, 0.0)
    can = close * close / (2 * maximum(gap - 1.0, 0.1)) <= yield_decel
    return np.isfinite(dist) and towards and (gap > hv_s0) and can


@njit
def combine(
    gap, dv, s0, z, at, free, p3, v0, relevant, lim_now, a_lim, stop_room, v, v_mean, light,
    light_dist, give_way, signal_dist, lanes, call_lane, call_frames, max_decel_stop,
    yellow_stop_decel, vj, vj2, stop_margin, signal_sight_decel, iidm, a_max, max_decel_2,
    e_decel, e_span,
):  # fmt: skip
    """(Q, A) each call's acceleration [m/s²] from :func:`idm_inputs`' entries (``free`` and
    ``v0`` (L, A) flat, ``p3`` (U,) numpy's powers): the lane's free road bounded by its limits
    ahead and its light (``_light_bound``), and the call's relevant leaders."""
    A, L, Q = len(v), len(lanes), len(call_lane)
    out = np.empty((Q, A))
    base = np.empty(L)
    u = 0
    for a in range(A):
        va = v[a]
        unseen = _unseen(a, v_mean, light, signal_dist, stop_margin, signal_sight_decel)
        for i in range(L):
            road = _idm_acc(va, v0[at[u]], z[u], p3[u], free[at[u]], gap[u], dv[u], s0[u], iidm,
                            a_max, max_decel_2, e_decel, e_span)  # fmt: skip
            u += 1
            stop = _idm_acc(va, v0[at[u]], z[u], p3[u], free[at[u]], gap[u], dv[u], s0[u], iidm,
                            a_max, max_decel_2, e_decel, e_span)  # fmt: skip
            u += 1
            bound = _light(a, lim_now[i, a], stop, stop_room[a], v, light, light_dist,
                           give_way, max_decel_stop, yellow_stop_decel, vj, vj2)  # fmt: skip
            base[i] = minimum(minimum(road, a_lim[i, a]), minimum(bound, unseen))
        col = 0
        for q in range(Q):
            lead = np.inf
            for _ in range(3 * call_frames[q]):
                if relevant[a, col]:
                    lead = minimum(lead, _idm_acc(va, v0[at[u]], z[u], p3[u], free[at[u]],
                                                  gap[u], dv[u], s0[u], iidm, a_max,
                                                  max_decel_2, e_decel, e_span))  # fmt: skip
                    u += 1
                col += 1
            out[q, a] = minimum(base[np.searchsorted(lanes, call_lane[q])], lead)
    return out


@inline
def _light(a, lim_now, a_stop, room, v, light, light_dist, give_way, max_decel_stop,
           yellow_stop_decel, vj, vj2):  # fmt: skip
    """``_light_bound`` of agent ``a`` without the unseen signal's bound."""
    va, st, ld = v[a], light[a, _C], light_dist[a, _C]
    need_stop = va * va / (2 * room)
    stop = (st == 0 and need_stop < max_decel_stop) or (st == 1 and need_stop < yellow_stop_decel)
    a_stop = minimum(a_stop, -need_stop * 1.1 if need_stop > 1.0 else a_stop)
    bound = a_stop if stop else np.inf
    a_j = (vj2 - va * va) / (2 * maximum(ld - 1.0, 0.5)) if va > vj else np.inf
    if st >= 0 and np.isfinite(ld) and give_way[a] and lim_now < 20.0:
        bound = minimum(bound, a_j)
    return bound


@inline
def _unseen(a, v_mean, light, signal_dist, stop_margin, signal_sight_decel):  # fmt: skip
    """``_unseen_signal_bound`` of agent ``a``."""
    sig = signal_dist[a]
    need = v_mean[a] * v_mean[a] / (2 * maximum(sig - stop_margin, 0.05))
    if light[a, _C] < 0 and np.isfinite(sig) and need >= signal_sight_decel:
        return -need
    return np.inf
