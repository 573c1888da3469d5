"""The feature stages of :meth:`mixed_traffic.sensing.observation.ObservationBuilder.build` as
one compiled kernel (the action mask, route hops, waypoints, speed-limit preview, signals,
vehicles, lights and masks of the current frame; the history shift stays in numpy).

It does per agent and lane column what the numpy stages do with whole arrays, in the same
floating-point operations and order, so the frames are equal bit for bit
(tests/test_observation_kernel.py checks it on SUMO states). The numpy stages stay the
reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import clip, inline, njit

_CURRENT = 1
#: ``sensing.camera.NO_LIGHT``.
_NO_LIGHT = -1


@inline
def _find(keys, vals, n_edges, lane, edge):
    """``LaneGraph._find`` of one (lane, edge): ``vals`` at the key, -1 where none."""
    n = len(keys)
    if n == 0 or lane < 0 or edge < 0:
        return -1
    key = lane * n_edges + edge
    i = np.searchsorted(keys, key)
    if i >= n:
        return -1
    return vals[i] if keys[i] == key else -1


@njit
def features(
    rows, lanes, nxt, after, lane_pos, z, heading, speed, ego_in, veh_in, found_in, light_state,
    light_dist, give_way, lane_length, lane_next, lane_edge, edge_lanes, lane_index, edge_length,
    lane_width, lane_advisory, wp_offset, wp_count, wp_xyz, wp_lane_index, wp_heading, wp_speed,
    ahead, exit_lane, exit_dist, drop_dist, drop_speed, conn_keys, conn_vals, tls_keys, tls_tl,
    graph_next, n_edges, has_tls, ego_scale, wp_scale, veh_scale, reach, camera_range,
    preview_range, speed_scale, spacing, short_edge, mandatory_distance,
):  # fmt: skip
    """The current frame of every agent.

    Args (A agents, N vehicles, L lanes, E edges, W waypoints, m waypoints per lane, k
    preview points): ``rows`` (A,) snapshot rows; ``lanes`` (A, 3) lane rows (-1 none);
    ``nxt``, ``after`` (A,) the next two route edges (-1 none); the snapshot's ``lane_pos``,
    ``z``, ``heading``, ``speed`` (N,); the sensed ``ego_in`` (A, 5), ``veh_in`` (A, 3, 2, 6),
    ``found_in`` (A, 3, 2) bool, ``light_state`` (A, 3), ``light_dist`` (A, 3) [m],
    ``give_way`` (A,); the map's lane (L,), edge (E, ...) and waypoint (W, ...) arrays,
    ``ahead`` (W, m), ``exit_lane``/``exit_dist`` (L,), the drop table (L, k); the lane
    graph's sorted connection and signal keys; the scales, ranges [m] and constants.
    Returns ``ego`` (A, 5), ``wp`` (A, 3, 4m), ``veh`` (A, 3, 12), ``lights`` (A, 3, 4) float64;
    ``limits`` (A, 3, k, 2), ``signals`` (A, 3) float32; ``give_way`` (A, 3), ``node``
    (A, 3, 3), ``act`` (A, 3) int8.
    """
    A, m, k = len(rows), ahead.shape[1], drop_dist.shape[1]
    ego = np.empty((A, 5))
    wp = np.empty((A, 3, 4 * m))
    veh = np.empty((A, 3, 12))
    lights = np.empty((A, 3, 4))
    limits = np.zeros((A, 3, k, 2), np.float32)
    signals = np.zeros((A, 3), np.float32)
    gw = np.zeros((A, 3), np.int8)
    node = np.zeros((A, 3, 3), np.int8)
    act = np.zeros((A, 3), np.int8)
    pos, via = np.empty(3), np.empty(3, np.int64)
    for a in range(A):
        r = rows[a]
        for f in range(5):
            ego[a, f] = clip(ego_in[a, f] / ego_scale[f], -1.0, 1.0)
        mandatory, end_dist = _action_mask(
            a, r, lanes, nxt, after, lane_pos, lane_length, lane_edge, edge_lanes, lane_index,
            edge_length, exit_lane, conn_keys, conn_vals, n_edges, short_edge,
            mandatory_distance, act,
        )  # fmt: skip
        cur = max(lanes[a, _CURRENT], 0)
        for c in range(3):
            ls = max(lanes[a, c], 0)
            pos[c] = lane_pos[r] * (lane_length[ls] / max(lane_length[cur], 1e-9))
            v = _find(conn_keys, conn_vals, n_edges, ls, nxt[a])
            via[c] = v if lanes[a, c] >= 0 else -1
        _waypoints(a, r, lanes, pos, via, z, heading, lane_index, wp_offset, wp_count, wp_xyz,
                   wp_lane_index, wp_heading, wp_speed, ahead, wp_scale, spacing, wp)  # fmt: skip
        _limits(a, lanes, pos, via, lane_length, lane_next, lane_advisory, drop_dist,
                drop_speed, preview_range, speed_scale, limits)  # fmt: skip
        if has_tls:
            _signals(a, lanes, pos, via, nxt, after, lane_length, exit_lane, exit_dist,
                     tls_keys, tls_tl, graph_next, n_edges, preview_range, signals)  # fmt: skip
        _vehicles(a, lanes, veh_in, found_in, mandatory, end_dist, speed[r], lane_width,
                  veh_scale, reach, veh, node)  # fmt: skip
        for c in range(3):
            on = light_state[a, c] != _NO_LIGHT
            for s in range(3):
                lights[a, c, s] = 1.0 if (light_state[a, c] == s) and on else 0.0
            x = light_dist[a, c] / camera_range if on else 0.0
            lights[a, c, 3] = clip(x, -reach, reach) if reach > 1.0 else clip(x, -1.0, 1.0)
            node[a, c, 0] = lanes[a, c] >= 0
            node[a, c, 2] = on and lanes[a, c] >= 0
        gw[a, _CURRENT] = give_way[a] and light_state[a, _CURRENT] != _NO_LIGHT
    return ego, wp, veh, lights, limits, signals, gw, node, act


@inline
def _action_mask(a, r, lanes, nxt, after, lane_pos, lane_length, lane_edge, edge_lanes,
                 lane_index, edge_length, exit_lane, conn_keys, conn_vals, n_edges, short_edge,
                 mandatory_distance, act):  # fmt: skip
    """``ObservationBuilder.action_mask`` of agent ``a`` into ``act[a]``; returns (mandatory,
    end_dist [m])."""
    cur = lanes[a, _CURRENT]
    csafe = max(cur, 0)
    edge = lane_edge[csafe] if cur >= 0 else -1
    ne, af = nxt[a], after[a]
    short = ne >= 0 and af >= 0 and edge_length[max(ne, 0)] < short_edge
    idx = np.int64(lane_index[csafe])
    left = right = cur_cont = False
    for j in range(edge_lanes.shape[1]):
        el = np.int64(edge_lanes[max(edge, 0), j])
        v = _find(conn_keys, conn_vals, n_edges, el, ne)
        through = True
        if short and v >= 0:  # ``_through_short_edge``
            vs = max(v, 0)
            land = v if lane_edge[vs] >= 0 else exit_lane[vs]
            through = _find(conn_keys, conn_vals, n_edges, land, af) >= 0
        cont = el >= 0 and edge >= 0 and ((v >= 0 and through) or ne < 0)
        left = left or (cont and j > idx)
        right = right or (cont and j < idx)
        cur_cont = cur_cont or (cont and j == idx)
    left = left and lanes[a, 0] >= 0
    right = right and lanes[a, 2] >= 0
    cur_cont = cur_cont or edge < 0
    end_dist = lane_length[csafe] - lane_pos[r]
    mandatory = (not cur_cont) and end_dist <= mandatory_distance and edge >= 0
    act[a, 0] = left
    act[a, 1] = (not mandatory) or not (left or right)
    act[a, 2] = right
    return mandatory, end_dist


@inline
def _waypoints(a, r, lanes, pos, via, z, heading, lane_index, wp_offset, wp_count, wp_xyz,
               wp_lane_index, wp_heading, wp_speed, ahead, wp_scale, spacing, wp):  # fmt: skip
    """``ObservationBuilder._waypoints`` of agent ``a`` into ``wp[a]`` (A, 3, 4m)."""
    m = ahead.shape[1]
    ego_idx = np.float64(lane_index[max(lanes[a, _CURRENT], 0)])
    for c in range(3):
        ls = max(lanes[a, c], 0)
        kk = np.int64(np.floor(pos[c] / spacing))
        w0 = wp_offset[ls] + min(max(kk, 0), wp_count[ls] - 1)
        left = wp_offset[ls] + wp_count[ls] - 1 - w0  # wps left on the lane
        succ = wp_offset[max(via[c], 0)]
        for j in range(m):
            w = ahead[w0, j]
            q = j - left - 1  # index into the successor's table
            if via[c] >= 0 and q >= 0:
                w = ahead[succ, min(max(q, 0), m - 1)]
            f = (
                wp_xyz[w, 2] - z[r],
                wp_lane_index[w] - ego_idx,
                np.pi - np.mod(np.pi - (wp_heading[w] - heading[r]), 2 * np.pi),
                np.float64(wp_speed[w]),
            )
            for i in range(4):
                x = clip(f[i] / wp_scale[4 * j + i], -1.0, 1.0)
                wp[a, c, 4 * j + i] = x if lanes[a, c] >= 0 else 0.0


@inline
def _limits(a, lanes, pos, via, lane_length, lane_next, lane_advisory, drop_dist, drop_speed,
            preview_range, speed_scale, limits):  # fmt: skip
    """``ObservationBuilder._limits`` (with ``preview.limit_preview``) of agent ``a`` into
    ``limits[a]`` (zeros where nothing is kept): the kept drops first, in table order."""
    k = drop_dist.shape[1]
    for c in range(3):
        ls = max(lanes[a, c], 0)
        hop = via[c] if via[c] >= 0 else (np.int64(lane_next[ls]) if lanes[a, c] >= 0 else -1)
        if lanes[a, c] < 0 or hop < 0:
            continue
        left = lane_length[ls] - pos[c]
        left = left if (left >= 0.0 or left != left) else 0.0  # np.maximum(left, 0.0)
        n = 0
        for i in range(k):
            d = drop_dist[hop, i] + left
            s = drop_speed[hop, i]
            if s < lane_advisory[ls] and d <= preview_range:  # kept
                if np.isfinite(d):
                    limits[a, c, n, 0] = d / preview_range
                    limits[a, c, n, 1] = s / speed_scale
                n += 1


@inline
def _lane_signal(tls_keys, tls_tl, graph_next, n_edges, lane, edge):
    """``camera.lane_signals`` light index of one lane into ``edge`` (-1 none)."""
    tl = _find(tls_keys, tls_tl, n_edges, lane, edge)
    if tl < 0:
        tl = _find(tls_keys, tls_tl, n_edges, lane, graph_next[max(lane, 0)])
    return tl


@inline
def _signals(a, lanes, pos, via, nxt, after, lane_length, exit_lane, exit_dist, tls_keys,
             tls_tl, graph_next, n_edges, rng, signals):  # fmt: skip
    """``ObservationBuilder._signals`` of agent ``a`` into ``signals[a]``."""
    for c in range(3):
        tl = _lane_signal(tls_keys, tls_tl, graph_next, n_edges, lanes[a, c], nxt[a])
        dist = lane_length[max(lanes[a, c], 0)] - pos[c]
        vs = max(via[c], 0)
        out = exit_lane[vs]
        beyond = -1 if via[c] < 0 else (out if out >= 0 else via[c])
        tl2 = _lane_signal(tls_keys, tls_tl, graph_next, n_edges, beyond, after[a])
        far = dist + (exit_dist[vs] if out >= 0 else 0.0) + lane_length[max(beyond, 0)]
        if tl < 0:
            dist = far if (tl2 >= 0 and beyond >= 0) else np.inf
        if lanes[a, c] >= 0 and dist <= rng:
            signals[a, c] = clip(dist / rng, 1e-4, 1.0)


@inline
def _vehicles(a, lanes, veh_in, found_in, mandatory, end_dist, ego_speed, lane_width, veh_scale,
              reach, veh, node):  # fmt: skip
    """``ObservationBuilder._vehicles`` of agent ``a`` into ``veh[a]`` and ``node[a, :, 1]``."""
    virt = mandatory and (not found_in[a, _CURRENT, 0] or end_dist < veh_in[a, _CURRENT, 0, 0])
    width = lane_width[max(lanes[a, _CURRENT], 0)]
    for c in range(3):
        for s in range(2):
            found = found_in[a, c, s]
            is_virt = virt and c == _CURRENT and s == 0
            for f in range(6):
                x = veh_in[a, c, s, f]
                if is_virt:  # the stopped vehicle at the lane's end
                    x = (end_dist, -ego_speed, 0.0, 0.0, width, 0.0)[f]
                x = x / veh_scale[f]
                x = clip(x, -reach, reach) if (f == 0 and reach > 1.0) else clip(x, -1.0, 1.0)
                veh[a, c, 6 * s + f] = x if (found or is_virt) else 0.0
            if found or is_virt:
                node[a, c, 1] = 1


def map_arrays(hd, graph, ahead, exits, drops) -> tuple:
    """The arguments of :func:`features` from ``lane_length`` to ``has_tls``: the arrays of
    the ``HDMap`` ``hd`` and its ``LaneGraph`` ``graph``, ``ahead`` (W, m) (``ahead_table``),
    ``exits`` (``merges.exit_table``) and ``drops`` (``preview.drop_table``)."""
    hd_names = ("lane_length", "lane_next", "lane_edge", "edge_lanes", "lane_index", "edge_length",
                "lane_width", "lane_advisory", "wp_offset", "wp_count", "wp_xyz", "wp_lane_index",
                "wp_heading", "wp_speed")  # fmt: skip
    g = graph
    return (*(getattr(hd, n) for n in hd_names), ahead, *exits, *drops, g.conn_keys, g.conn_vals,
            g.tls_keys, g.tls_tl, g.next_edge, g.n_edges, len(g.tls_ids) > 0)  # fmt: skip


def warm() -> None:
    """Load :func:`features` (from the disk cache, else compile it) for the dtypes and layouts
    ``ObservationBuilder.build`` passes, on a one-lane network: a process that forks workers
    calls this once, and they inherit the kernel."""
    i64, i32, i16, f8 = np.int64, np.int32, np.int16, np.float64
    one, lanes = np.zeros(1, f8), np.full((1, 3), -1, i64)
    table = np.zeros((1, 3), f8)
    features(
        np.zeros(1, i64), lanes, np.full(1, -1, i64), np.full(1, -1, i64), one, one, one, one,
        np.zeros((1, 5), f8), np.zeros((1, 3, 2, 6), f8), np.zeros((1, 3, 2), np.bool_),
        np.full((1, 3), -1, np.int8), np.zeros((1, 3), f8), np.zeros(1, np.bool_), one,
        np.full(1, -1, i32), np.zeros(1, i32), np.full((1, 3), -1, i32), np.zeros(1, i16), one,
        one, one, np.zeros(1, i64), np.ones(1, i64), np.zeros((1, 3), f8), np.zeros(1, i16),
        one, one, np.zeros((1, 10), i64), np.full(1, -1, i64), one, table, table,
        np.zeros(0, i64), np.zeros(0, i64), np.zeros(0, i64), np.zeros(0, i64),
        np.full(1, -1, i64), 1, False, np.ones(5), np.ones(40), np.ones(6), 1.0, 1.0, 1.0, 40.0,
        1.0, 20.0, 100.0,
    )  # fmt: skip
