"""ACC-LC's view of the observation (:func:`agents.rules.acc_lc_features.features`) as one
compiled kernel.

:func:`decode` does per agent what the numpy stages do with whole arrays: the ego features and
the lateral-velocity history, the waypoints and the limit preview, the neighbours of the latest
frame, the front vehicles of the history frames and the lights. It does their floating-point
operations in the same order, sums included (:func:`_pairwise_sum` is numpy's summation of a
float64 row), so the results equal the numpy stages' bit for bit
(tests/test_acc_lc_features_kernel.py checks it on SUMO states); those stay the reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import inline, maximum, njit


@inline
def _pairwise_sum(x, n):
    """numpy's ``add.reduce`` of the float64 row ``x[:n]`` (n <= 128): a plain sum below 8
    terms, else eight interleaved partial sums (``pairwise_sum`` in numpy's loops)."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += x[i]
        return res
    r0, r1, r2, r3 = x[0], x[1], x[2], x[3]
    r4, r5, r6, r7 = x[4], x[5], x[6], x[7]
    i = 8
    while i < n - n % 8:
        r0 += x[i]
        r1 += x[i + 1]
        r2 += x[i + 2]
        r3 += x[i + 3]
        r4 += x[i + 4]
        r5 += x[i + 5]
        r6 += x[i + 6]
        r7 += x[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += x[i]
        i += 1
    return 0.0 + res  # the reduction starts from add's identity: -0.0 sums to 0.0


@inline
def _length(norm, long_length, scale):
    """``acc_lc_features._length`` of one normalised length."""
    return long_length if norm >= 1.0 - 1e-6 else norm * scale


@inline
def _light(a, lane, lights, z, F, camera_range, light, light_dist):
    """``_light_features`` of agent ``a``'s lane column ``lane``: the majority state of the
    last ``F`` frames with a detection and its distance."""
    r = y = g = 0
    any_det = last_det = False
    for t in range(z - F, z):
        l0, l1, l2 = np.float64(lights[a, lane, t, 0]), np.float64(lights[a, lane, t, 1]), np.float64(lights[a, lane, t, 2])  # fmt: skip
        det = ((0.0 + l0) + l1) + l2 > 0.5
        any_det = any_det or det
        last_det = det
        r += l0 > 0.5
        y += l1 > 0.5
        g += l2 > 0.5
    best = 0 if (r >= y and r >= g) else (1 if y >= g else 2)
    light[a, lane] = best if any_det else -1
    now = np.float64(lights[a, lane, z - 1, 3]) * camera_range
    before = np.float64(lights[a, lane, z - 2, 3]) * camera_range
    if last_det:
        light_dist[a, lane] = now
    elif any_det:
        light_dist[a, lane] = before
    else:
        light_dist[a, lane] = np.inf


@njit
def decode(ego, lanes, veh, lights, node_mask, action_mask, limits, signals, give_way, dt,
           long_length, preview_range, camera_range, ego_scale, wp_scale, nb_scale, speed_scale):  # fmt: skip
    """The features of ``acc_lc_features.features`` from the observation's arrays (A, ...)
    (``nb_scale`` (6,): the neighbour columns' scales), in the order of its dict."""
    A, z = ego.shape[0], ego.shape[1]
    m, k = lanes.shape[3] // 4, limits.shape[2]
    K = min(veh.shape[2], 1 + int(0.8 / dt + 1e-9))
    F = min(3, z)  # light frames of the majority vote
    v, h, ln, wid, d = np.empty(A), np.empty(A), np.empty(A), np.empty(A), np.empty(A)
    v_mean, vlat = np.empty(A), np.empty(A)
    wp_speed, wp_orient = np.empty((A, 3, m)), np.empty((A, 3, m))
    pv_dist, pv_speed = np.empty((A, 3, k)), np.empty((A, 3, k))
    present = np.empty((A, 3, 2), np.bool_)
    vdist, vrel, vlen = np.empty((A, 3, 2)), np.empty((A, 3, 2)), np.empty((A, 3, 2))
    vwid, vlat_n = np.empty((A, 3, 2)), np.empty((A, 3, 2))
    h_dist, h_rel, h_len = np.empty((A, 3, K)), np.empty((A, 3, K)), np.empty((A, 3, K))
    h_wid, h_lat = np.empty((A, 3, K)), np.empty((A, 3, K))
    exists, mask = np.empty((A, 3), np.bool_), np.empty((A, 3), np.bool_)
    light, light_dist = np.empty((A, 3), np.int64), np.empty((A, 3))
    signal_dist, gw = np.empty(A), np.empty(A, np.bool_)
    row, dh = np.empty(z), np.empty(z)
    valid, hvalid = np.empty(z, np.bool_), np.empty(K, np.bool_)
    far = (np.inf, -np.inf)
    for a in range(A):
        # ego, the mean speed over the observed frames and the lateral velocity
        e0 = np.float64(ego[a, z - 1, 0]) * ego_scale[0]
        v[a] = maximum(e0, 0.0)
        h[a] = np.float64(ego[a, z - 1, 1]) * ego_scale[1]
        ln[a] = _length(np.float64(ego[a, z - 1, 2]), long_length, ego_scale[2])
        wid[a] = np.float64(ego[a, z - 1, 3]) * ego_scale[3]
        d[a] = np.float64(ego[a, z - 1, 4]) * ego_scale[4]
        n_valid = 0
        for t in range(z):
            valid[t] = ego[a, t, 2] > 0
            n_valid += valid[t]
            s = maximum(np.float64(ego[a, t, 0]) * ego_scale[0], 0.0)
            row[t] = s if valid[t] else 0.0
            dh[t] = np.float64(ego[a, t, 4]) * ego_scale[4]
        v_mean[a] = _pairwise_sum(row, z) / max(n_valid, 1)
        k0 = max(0, z - 3)
        n_ok = 0
        for t in range(k0, z - 1):
            diff = dh[t + 1] - dh[t]
            ok = valid[t + 1] and valid[t] and abs(diff) < 1.5
            n_ok += ok
            row[t - k0] = diff if ok else 0.0
        vlat[a] = _pairwise_sum(row, z - 1 - k0) / max(n_ok, 1) / dt
        # history frames since the last lane switch (a jump of the offset)
        later = False
        hvalid[K - 1] = valid[z - 1]
        for j in range(K - 2, -1, -1):
            later = later or abs(dh[z - K + j + 1] - dh[z - K + j]) >= 1.5
            hvalid[j] = (not later) and valid[z - K + j]
        for lane in range(3):
            for j in range(m):
                wp_speed[a, lane, j] = np.float64(lanes[a, lane, z - 1, 4 * j + 3]) * wp_scale[3]
                wp_orient[a, lane, j] = np.float64(lanes[a, lane, z - 1, 4 * j + 2]) * wp_scale[2]
            for j in range(k):
                dist, spd = np.float64(limits[a, lane, j, 0]), np.float64(limits[a, lane, j, 1])
                pv_dist[a, lane, j] = dist * preview_range if spd > 0 else np.inf
                pv_speed[a, lane, j] = spd * speed_scale if spd > 0 else np.inf
            for side in range(2):
                o = 6 * side
                wd = np.float64(veh[a, lane, z - 1, o + 4]) * nb_scale[4]
                present[a, lane, side] = wd > 0
                dist = np.float64(veh[a, lane, z - 1, o]) * nb_scale[0]
                vdist[a, lane, side] = dist if wd > 0 else far[side]
                vrel[a, lane, side] = np.float64(veh[a, lane, z - 1, o + 1]) * nb_scale[1]
                vlen[a, lane, side] = _length(
                    np.float64(veh[a, lane, z - 1, o + 3]), long_length, ego_scale[2]
                )
                vwid[a, lane, side] = wd
                vlat_n[a, lane, side] = np.float64(veh[a, lane, z - 1, o + 5]) * nb_scale[5]
            for j in range(K):
                t = z - K + j
                dist = np.float64(veh[a, lane, t, 0]) * nb_scale[0]
                rel = np.float64(veh[a, lane, t, 1]) * nb_scale[1]
                wd = np.float64(veh[a, lane, t, 4]) * nb_scale[4]
                age = np.float64(K - 1 - j) * dt
                h_dist[a, lane, j] = dist + rel * age if (wd > 0 and hvalid[j]) else np.inf
                h_rel[a, lane, j] = rel
                h_len[a, lane, j] = _length(
                    np.float64(veh[a, lane, t, 3]), long_length, ego_scale[2]
                )
                h_wid[a, lane, j] = wd
                h_lat[a, lane, j] = np.float64(veh[a, lane, t, 5]) * nb_scale[5]
            exists[a, lane] = node_mask[a, lane, 0] > 0
            mask[a, lane] = action_mask[a, lane] > 0
            _light(a, lane, lights, z, F, camera_range, light, light_dist)
        sig = np.float64(signals[a, 1])
        signal_dist[a] = sig * preview_range if sig > 0 else np.inf
        gw[a] = give_way[a, 1] > 0
    return (v, h, ln, wid, d, v_mean, vlat, wp_speed, wp_orient, pv_dist, pv_speed, present,
            vdist, vrel, vlen, vwid, vlat_n, h_dist, h_rel, h_len, h_wid, h_lat, exists, mask,
            light, light_dist, signal_dist, gw)  # fmt: skip
