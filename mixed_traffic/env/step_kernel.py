"""Compiled kernels of the env's per-step stages whose numpy versions stay the reference.

``event_codes``: the array part of the agents' terminal events (``termination``): off-road,
route deviation (with ``conn_to`` as a sorted key table), speed limit and the stop lines
crossed, fused into one pass. The floating-point operations and their order are those of the
numpy masks (the lane-width sums run in lane order, as ``np.sum`` does below 8 lanes), so the
results are equal bit for bit (tests/test_step_kernel.py checks it on SUMO states).

``reward_terms``: the reward's per-agent terms r1-r4 and r7 (``reward.reward_terms``) in one
pass; r1_ttc's logarithm stays numpy's (its SIMD ``log`` differs from libm's in the last bit),
so the kernel hands back the TTC ratios it applies to.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import clip, inline, njit

#: Codes of ``event_codes``: 0 = none, then ``TERMINAL_REASONS``' order from 1 (collision).
OFF_ROAD, ROUTE_DEVIATION, RED_LIGHT, SPEED_LIMIT = 2, 3, 4, 5


@njit
def event_codes(
    lane_width, lane_edge, lane_index, lane_length, lane_speed, edge_lanes, conn_keys,
    lane_prev, lateral, margin, edge, lane, lane_pos, routes, route_index, tolerance,
    dead_end, speed,
):  # fmt: skip
    """(codes (A,) int64, crossed (A,) bool) of the A agents judged after a step.

    ``codes``: the first of off-road, route deviation and speed limit that holds (the
    constants above, 0 = none; red lights are the caller's, from ``crossed``); ``crossed``:
    the agent left a normal edge's lane for a lane of another edge (``red_light_mask``).

    Args (L lanes, E edges, K lanes per edge, W route columns): the map's ``lane_width``,
    ``lane_length`` [m], ``lane_speed`` [m/s], ``lane_edge``, ``lane_index`` (L,) and
    ``edge_lanes`` (E, K); ``conn_keys`` sorted ``lane·E + next edge`` of ``conn_to``;
    ``lane_prev`` (A,) lane rows at t; ``lateral`` (A,) commanded offset from them [m];
    ``margin`` [m]; now (A,): ``edge``, ``lane`` rows, ``lane_pos`` [m], ``route_index``,
    ``speed`` [m/s]; ``routes`` (A, W) edge rows -1 padded; ``tolerance`` [-] over the limit;
    ``dead_end`` [m].
    """
    A, W = routes.shape
    E, K = edge_lanes.shape
    codes = np.zeros(A, np.int64)
    crossed = np.zeros(A, np.bool_)
    factor = 1.0 + tolerance
    for a in range(A):
        lp, ln, e = np.int64(lane_prev[a]), np.int64(lane[a]), np.int64(edge[a])
        # off-road: beyond the outer edge of the road of the lane at t
        off_road = False
        if lp >= 0:
            width, pe = lane_width[lp], lane_edge[lp]
            right, left = 0.5 * width, 0.5 * width
            if pe >= 0:
                idx = np.int64(lane_index[lp])
                below, above = 0.0, 0.0
                for k in range(K):  # in lane order, as np.sum below 8 lanes
                    row = edge_lanes[pe, k]
                    w = lane_width[max(row, 0)] if row >= 0 else 0.0
                    below += w * (k < idx)
                    above += w * (k > idx)
                right, left = below + 0.5 * width, above + 0.5 * width
            lat = lateral[a]
            off_road = (lat > left + margin) or (-lat > right + margin)
        # route deviation: off the route, or at a lane's end that cannot reach the next edge
        deviated = False
        if e >= 0:
            in_route = False
            for j in range(W):
                in_route |= routes[a, j] == e
            if not in_route:
                deviated = True
            elif ln >= 0:
                nxt_i = np.int64(route_index[a]) + 1
                nxt = routes[a, min(nxt_i, W - 1)] if nxt_i < W else np.int64(-1)
                if nxt >= 0 and (lane_length[ln] - lane_pos[a]) < dead_end:
                    key = ln * E + nxt
                    at = np.searchsorted(conn_keys, key)
                    deviated = at >= len(conn_keys) or conn_keys[at] != key
        if lp >= 0 and ln >= 0 and lp != ln:
            pe = lane_edge[lp]
            crossed[a] = pe >= 0 and lane_edge[ln] != pe
        # an unknown lane (-1) reads the last lane's limit, as numpy's indexing does
        over = speed[a] > lane_speed[ln] * factor
        if off_road:
            codes[a] = OFF_ROAD
        elif deviated:
            codes[a] = ROUTE_DEVIATION
        elif over:
            codes[a] = SPEED_LIMIT
    return codes, crossed


@njit
def reward_terms(
    front_distance, closing_speed, length, front_length, centre_distance, lane_width,
    terminal, speed, speed_limit, lane_changed, gap_new, gap_old, lidar_range, accel,
    prev_accel, rear_speed_prev, rear_speed_now, rear_same, ttc_threshold, terminal_penalty,
    gain, cap, acc_threshold, speed_drop, dt, min_gap,
):  # fmt: skip
    """(r1_ttc, r1_lane, r1_terminal, r2_speed, r2_lane_change, r3_comfort, r4_impact,
    r7_accel, ratio, hits): each term (A,) float64 as ``reward.reward_terms``'s, except
    r1_ttc, 0 where the caller puts max(-3, log(ratio)) (the ``hits`` agents whose TTC/G is
    in (0, 1), ``ratio`` (A,) there, -1 elsewhere). Inputs (A,) in the units of ``reward.reward_terms``;
    the config's scalars; ``min_gap`` [m] is ``reward.MIN_GAP``.
    """
    A = len(speed)
    r1_ttc, r1_lane, r1_terminal = np.zeros(A), np.empty(A), np.empty(A)
    r2_speed, r2_change, r3, r4, r7 = (
        np.empty(A),
        np.empty(A),
        np.empty(A),
        np.empty(A),
        np.empty(A),
    )
    ratio = np.full(A, -1.0)  # -1: no hit (a hit's ratio may underflow to 0)
    hits = 0
    big = np.finfo(np.float64).max  # np.nan_to_num's stand-in for inf
    for a in range(A):
        gap = front_distance[a] - 0.5 * (length[a] + front_length[a])
        closing = closing_speed[a]
        ttc = gap / closing if np.isfinite(gap) and closing > 0 else np.inf
        if ttc > 0 and ttc < ttc_threshold:
            ratio[a] = ttc / ttc_threshold
            hits += 1
        d = centre_distance[a]
        d = 0.0 if np.isnan(d) else big if d == np.inf else -big if d == -np.inf else d
        r1_lane[a] = -d / lane_width[a]
        r1_terminal[a] = terminal_penalty if terminal[a] else 0.0
        r2_speed[a] = speed[a] / speed_limit[a]
        change = _gap(gap_new[a], lidar_range, min_gap) / _gap(gap_old[a], lidar_range, min_gap)
        change -= 1.0
        if cap > 0:
            change = clip(change, -cap, cap)
        r2_change[a] = change * gain if lane_changed[a] else 0.0
        r3[a] = -abs(accel[a] - prev_accel[a]) / (2.0 * acc_threshold)
        dv = rear_speed_now[a] - rear_speed_prev[a]
        hit = rear_same[a] and np.isfinite(dv) and -dv > speed_drop
        r4[a] = dv / (2.0 * acc_threshold * dt) if hit else 0.0
        r7[a] = -abs(accel[a]) / acc_threshold
    return r1_ttc, r1_lane, r1_terminal, r2_speed, r2_change, r3, r4, r7, ratio, hits


@inline
def _gap(g, lidar_range, min_gap):
    """A bumper gap for the lane-change ratio [m]: none (NaN/inf) = the range, clipped."""
    return clip(g if np.isfinite(g) else lidar_range, min_gap, lidar_range)


def conn_keys(conn_to: dict, n_edges: int) -> np.ndarray:
    """Sorted int64 ``lane·n_edges + next edge`` of ``conn_to``'s keys (``event_codes``)."""
    keys = [lane * n_edges + nxt for lane, nxt in conn_to]
    return np.unique(np.array(keys, np.int64))


def warm() -> None:
    """Load the kernels (from the disk cache, else compile them) for the dtypes the env
    passes, on one agent of a one-lane map: a process that forks workers calls this once."""
    i64, i32, f = np.int64, np.int32, np.ones(1)
    event_codes(f, np.zeros(1, i32), np.zeros(1, np.int16), f, f, np.zeros((1, 1), i32),
                np.zeros(1, i64), np.zeros(1, i64), f, 0.3, np.zeros(1, i32), np.zeros(1, i32),
                f, np.zeros((1, 1), i64), np.zeros(1, i32), 0.1, 1.0, f)  # fmt: skip
    b = np.zeros(1, np.bool_)
    reward_terms(f, f, f, f, f, f, b, f, f, b, f, f, 50.0, f, f, f, f, b, 4.0, -20.0, 20.0, 0.0,
                 3.0, 1.0, 0.1, 0.5)  # fmt: skip
