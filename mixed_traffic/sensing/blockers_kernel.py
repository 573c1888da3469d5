"""``path_blockers`` (:mod:`.blockers`) and ``merge_leaders`` (:mod:`.merges`) as compiled
kernels, one agent at a time.

They loop over the (agent, candidate) pairs the numpy stages build as arrays, in the same
order (agents, then candidates by snapshot row; merges: path hops, then candidates), and keep
per agent the first pair of least gap, as the numpy ``lexsort`` does. Every floating-point
operation is numpy's, in its order (numba's ``cos``, ``sin`` and ``hypot`` equal numpy's here
bit for bit, checked on a million inputs), so the results are equal bit for bit
(tests/test_perception_kernel.py checks it on SUMO states). The numpy stages stay the reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import inline, njit


@inline
def _connection(lane, edge, conn_keys, conn_vals, n_edges):
    """``LaneGraph.connection`` of one lane and edge: the first lane row, -1 if none."""
    n = len(conn_keys)
    if lane < 0 or edge < 0 or n == 0:
        return -1
    key = lane * n_edges + edge
    i = np.searchsorted(conn_keys, key)
    if i < n and conn_keys[i] == key:
        return conn_vals[i]
    return -1


@inline
def _path(cur, pos, nxt, via, max_range, lane_next, lane_length, chain, chain_start, conn_keys,
          conn_vals, n_edges, hops, start):  # fmt: skip
    """``blockers.path_lanes`` of one agent on lane ``cur`` at ``pos`` [m]: fills ``hops`` and
    ``start`` (H,) (lanes, -1 padded; distance to their starts [m], +inf padded)."""
    H = len(hops)
    csafe = max(cur, 0)
    succ = np.int64(lane_next[csafe])
    conn = _connection(csafe, nxt, conn_keys, conn_vals, n_edges)
    if conn >= 0:
        succ = conn
    if via >= 0:
        succ = via
    if cur < 0:
        succ = -1
    ssafe = max(succ, 0)
    for h in range(H):
        if h == 0:
            lane, st = np.int64(cur), -pos
        else:
            lane = chain[ssafe, h - 1]
            st = (lane_length[csafe] - pos) + chain_start[ssafe, h - 1] if succ >= 0 else np.inf
        keep = lane >= 0 and st <= max_range and cur >= 0 and (h == 0 or succ >= 0)
        hops[h] = lane if keep else -1
        start[h] = st if keep else np.inf


@njit
def blockers(
    rows, vlane, lane_pos, length, width, heading, x, y, speed, junction, entry_junction,
    lane_next, lane_length, chain, chain_start, conn_keys, conn_vals, n_edges, wp_count,
    wp_offset, wp_xyz, wp_heading, next_edge, via, limit, max_range, spacing, sweep_margin,
):  # fmt: skip
    """``blockers.path_blockers`` (see there): the nearest vehicle across each agent's path.

    Args (A agents, N vehicles, L lanes, W waypoints): ``rows`` (A,) snapshot rows; the
    snapshot's (N,) ``vlane``, ``lane_pos`` [m], ``length`` [m], ``width`` [m], ``heading``
    [rad], ``x``, ``y`` [m], ``speed`` [m/s]; the lane graph's (L,) ``junction``,
    ``entry_junction``, (L, D) ``chain``, ``chain_start`` [m] and connection table; the map's
    (L,) ``lane_next``, ``lane_length`` [m], ``wp_count``, ``wp_offset``, (W, 3) ``wp_xyz``
    [m], (W,) ``wp_heading`` [rad]; (A,) ``next_edge`` and ``via`` (-1 none), ``limit`` [m]
    (+inf none); ``spacing`` the waypoint spacing [m].
    Returns (A,) int64 row (-1 none), (A,) gap [m] (+inf none), (A, 4) ``PATH_GEOMETRY``.
    """
    A, N, H = len(rows), len(vlane), chain.shape[1] + 1
    vehicle = np.full(A, -1, np.int64)
    best = np.full(A, np.inf)
    geom = np.zeros((A, 4))
    # candidates: on a junction lane, or leaving one with the rear still inside it
    cand = np.empty(N, np.int64)
    cl, cj = np.empty(N, np.int64), np.empty(N, np.int64)
    C = 0
    for v in range(N):
        ln = vlane[v]
        if ln < 0:
            continue
        j = entry_junction[ln] if lane_pos[v] < length[v] else junction[ln]
        if junction[ln] >= 0:
            j = junction[ln]
        if j >= 0:
            cand[C], cl[C], cj[C] = v, ln, j
            C += 1
    if A == 0 or C == 0:
        return vehicle, best, geom
    reach_c = np.hypot(length[cand[0]], width[cand[0]])
    for c in range(1, C):
        reach_c = max(reach_c, np.hypot(length[cand[c]], width[cand[c]]))
    reach_max = 0.5 * (reach_c + width.max())
    hops, start = np.empty(H, np.int64), np.empty(H)
    for a in range(A):
        row = rows[a]
        cur = vlane[row]
        csafe = max(cur, 0)
        cut = min(limit[a], max_range)
        to_junction = 0.0 if junction[csafe] >= 0 else lane_length[csafe] - lane_pos[row]
        if not (cur >= 0 and to_junction - reach_max <= cut + spacing):
            continue
        _path(cur, lane_pos[row], next_edge[a], via[a], max_range, lane_next, lane_length, chain,
              chain_start, conn_keys, conn_vals, n_edges, hops, start)  # fmt: skip
        r = 0.5 * width[row] + sweep_margin
        for c in range(C):
            v = cand[c]
            h1, h2, on = -1, -1, False
            for h in range(H):
                hj = junction[hops[h]] if hops[h] >= 0 else -1
                if hj >= 0 and hj == cj[c]:
                    h2 = h
                    if h1 < 0:
                        h1 = h
                on = on or hops[h] == cl[c]
            if h1 < 0 or on or v == row:
                continue
            half_l, half_w = 0.5 * length[v], 0.5 * width[v]
            reach = np.hypot(half_l, half_w) + r
            lo = max(start[h1] - reach, 0.0)
            hi = min(start[h2] + lane_length[hops[h2]] + reach, max_range)
            hi = min(hi, limit[a] + spacing)  # the first hit is at most spacing beyond the gap
            if lo <= hi:
                _pair(a, v, lo, hi, r, half_l, half_w, hops, start, heading, x, y, speed, length,
                      width, lane_length, wp_count, wp_offset, wp_xyz, wp_heading, spacing,
                      vehicle, best, geom)  # fmt: skip
    return vehicle, best, geom


@inline
def _pair(a, v, lo, hi, r, half_l, half_w, hops, start, heading, x, y, speed, length, width,
          lane_length, wp_count, wp_offset, wp_xyz, wp_heading, spacing, vehicle, best,
          geom):  # fmt: skip
    """Sample the path from ``lo`` to ``hi`` [m] at the waypoints; at the first sample within
    ``r`` of candidate ``v``'s body, its gap and geometry replace agent ``a``'s if nearer."""
    c, s = np.cos(heading[v]), np.sin(heading[v])
    cx = x[v] - half_l * c
    cy = y[v] - half_l * s
    H = len(hops)
    n = int(np.ceil((hi - lo) / spacing)) + 1  # covers every sample up to hi
    for i in range(n):
        d = lo + spacing * i
        if not d <= hi:
            break
        h = 0
        for hh in range(1, H):
            h += d >= start[hh]
        lane = hops[h]
        if lane < 0:
            continue
        q = d - start[h]
        if not q <= lane_length[lane] + 0.5 * spacing:
            continue
        k = min(max(np.int64(np.rint(q / spacing)), 0), wp_count[lane] - 1)
        wp = wp_offset[lane] + k
        dx = wp_xyz[wp, 0] - cx
        dy = wp_xyz[wp, 1] - cy
        out_l = max(abs(dx * c + dy * s) - half_l, 0.0)
        out_w = max(abs(dy * c - dx * s) - half_w, 0.0)
        if out_l * out_l + out_w * out_w < r * r:
            _meet(a, v, start[h] + k * spacing, wp, cx, cy, r, heading, speed, length, width,
                  wp_xyz, wp_heading, spacing, vehicle, best, geom)  # fmt: skip
            return


@inline
def _meet(a, v, dj, wj, cx, cy, r, heading, speed, length, width, wp_xyz, wp_heading, spacing,
          vehicle, best, geom):  # fmt: skip
    """``blockers._nearest`` for one hit: the path's frame at waypoint ``wj``, ``dj`` [m] along
    the path; agent ``a``'s blocker becomes ``v`` if its gap is smaller."""
    t = wp_heading[wj]
    rel = heading[v] - t
    ca, sa = abs(np.cos(rel)), abs(np.sin(rel))
    along = length[v] * ca + width[v] * sa
    across = length[v] * sa + width[v] * ca
    ex, ey = cx - wp_xyz[wj, 0], cy - wp_xyz[wj, 1]
    centre = ex * np.cos(t) + ey * np.sin(t)
    lateral = ey * np.cos(t) - ex * np.sin(t)
    # the body's near end, between the last sample that missed it and the hit's reach
    gap = max(min(max(dj + centre - 0.5 * along, dj - spacing), dj + r), 0.0)
    if gap < best[a]:
        vehicle[a], best[a] = v, gap
        geom[a, 0], geom[a, 1] = speed[v] * np.cos(rel), along
        geom[a, 2], geom[a, 3] = across, lateral


@njit
def merges(
    rows, vlane, lane_pos, length, width, speed, exit_lane, to_exit, lane_next, lane_length,
    chain, chain_start, conn_keys, conn_vals, n_edges, next_edge, via, lead_gap, max_range,
):  # fmt: skip
    """``merges.merge_leaders`` (see there): the nearest vehicle merging into each agent's path.

    Args as :func:`blockers`, and ``exit_lane``, ``to_exit`` [m] (L,) (``merges.exit_table``),
    ``lead_gap`` (A,) [m] (+inf none). Returns (A,) int64 row (-1 none), (A,) gap [m] (+inf
    none), (A, 4) ``PATH_GEOMETRY``.
    """
    A, N, H = len(rows), len(vlane), chain.shape[1] + 1
    vehicle = np.full(A, -1, np.int64)
    best = np.full(A, np.inf)
    geom = np.zeros((A, 4))
    cand = np.empty(N, np.int64)
    C = 0
    for v in range(N):
        if vlane[v] >= 0 and exit_lane[vlane[v]] >= 0:
            cand[C] = v
            C += 1
    hops, start = np.empty(H, np.int64), np.empty(H)
    for a in range(A if C else 0):
        row = rows[a]
        _path(vlane[row], lane_pos[row], next_edge[a], via[a], max_range, lane_next, lane_length,
              chain, chain_start, conn_keys, conn_vals, n_edges, hops, start)  # fmt: skip
        for h in range(H):  # pairs in the numpy order: hops, then candidates by row
            if hops[h] < 0 or exit_lane[hops[h]] < 0:
                continue
            merge = start[h] + to_exit[hops[h]]  # the merge point along the agent's path
            for c in range(C):
                v = cand[c]
                if exit_lane[vlane[v]] != exit_lane[hops[h]]:
                    continue
                front = merge - (to_exit[vlane[v]] - lane_pos[v])
                on = False
                for hh in range(H):
                    on = on or hops[hh] == vlane[v]
                if not (front > 0 and not on and v != row and merge < lead_gap[a]):
                    continue
                gap = max(front - length[v], 0.0)
                if gap < best[a]:
                    vehicle[a], best[a] = v, gap
                    geom[a, 0], geom[a, 1], geom[a, 2] = speed[v], length[v], width[v]
    return vehicle, best, geom


@njit
def take_nearer(vehicle, distance, lead_gap, b_row, b_gap, b_geom, m_row, m_gap, m_geom, s_row,
                s_gap, s_geom):  # fmt: skip
    """``neighbours._in_the_way``'s choice: of the blocker (``b_``), merge leader (``m_``) and
    straddler (``s_``), in this order, each (A,) row, gap [m] and (A, 4) geometry, one nearer
    than the lane leader's ``lead_gap`` (A,) [m] (and the ones before) replaces the current
    lane's front vehicle in ``vehicle`` / ``distance`` (A, 3, 2) (in place). Returns
    ``on_path`` (A,) bool and its ``PATH_GEOMETRY`` (A, 4)."""
    A = len(lead_gap)
    on_path = np.zeros(A, np.bool_)
    geom = np.zeros((A, 4))
    for a in range(A):
        best = lead_gap[a]
        for row, gap, other in ((b_row, b_gap, b_geom), (m_row, m_gap, m_geom),
                                (s_row, s_gap, s_geom)):  # fmt: skip
            if row[a] >= 0 and gap[a] < best:
                vehicle[a, 1, 0] = row[a]
                distance[a, 1, 0] = gap[a] + other[a, 1]
                geom[a, :] = other[a, :]
                best = gap[a]
                on_path[a] = True
    return on_path, geom


def warm() -> None:
    """Load :func:`blockers` and :func:`merges` (from the disk cache, else compile them) for
    the dtypes ``blockers.path_blockers`` and ``merges.merge_leaders`` pass, on an empty
    network: a process that forks workers calls this once, and they inherit the kernels."""
    i64, i32 = np.int64, np.int32
    one, row, lane32 = np.zeros(1), np.zeros(1, i64), np.full(1, -1, i32)
    chain, chain_start = np.full((1, 4), -1, i64), np.zeros((1, 4))
    blockers(row, lane32, one, one, one, one, one, one, one, row, row, lane32, one, chain,
             chain_start, row, row, 1, row, row, np.zeros((1, 3)), one, row, row, one, 1.0, 1.0,
             0.5)  # fmt: skip
    merges(row, lane32, one, one, one, one, row, one, lane32, one, chain, chain_start, row, row,
           1, row, row, one, 1.0)  # fmt: skip
    rows, geom = np.full(1, -1, i64), np.zeros((1, 4))
    take_nearer(np.zeros((1, 3, 2), i64), np.zeros((1, 3, 2)), one, rows, one, geom, rows, one,
                geom, rows, one, geom)  # fmt: skip
