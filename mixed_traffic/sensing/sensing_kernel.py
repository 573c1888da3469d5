"""The per-step sensor stages of :mod:`mixed_traffic.sensing.perception` as compiled kernels:
the neighbour search's set-up (``neighbours._setup``: lane sort, query lanes, successors), the
weather's ranges and noise (``noise.within_range``, ``noise.degrade``), the camera's traffic
lights (``camera.traffic_lights``), the LiDAR's vehicle features (``lidar.vehicle_features``)
and the GNSS's ego features (``gnss.ego_features``).

Each does per element what the numpy stage does with whole arrays, in the same floating-point
operations and order, so the results are equal bit for bit (tests/test_sensing_kernel.py checks
it on SUMO states). The random draws stay in numpy (the env's generator, same order and sizes);
only the arithmetic on them is here. The numpy stages stay the reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import inline, maximum, njit

_CURRENT = 1
_NO_LIGHT = -1


@inline
def _wrap(a):
    """``geometry.wrap_angle`` of one angle [rad] (numpy's ``np.mod``, checked bit for bit)."""
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


@inline
def _cut(vehicle, distance, light_state, light_dist, lidar_reach, camera_reach):
    """The vehicles and lights within reach (``noise.within_range`` without the features):
    ``vehicle`` (A, 3, 2) rows (-1 beyond), ``distance`` (A, 3, 2) [m] (+-inf beyond),
    ``state`` (A, 3) int8 and ``ldist`` (A, 3) [m] (NO_LIGHT / +inf beyond)."""
    A = vehicle.shape[0]
    v_out = np.empty((A, 3, 2), np.int64)
    d_out = np.empty((A, 3, 2))
    state = np.empty((A, 3), np.int8)
    ldist = np.empty((A, 3))
    for a in range(A):
        for c in range(3):
            for s in range(2):
                seen = vehicle[a, c, s] >= 0 and np.abs(distance[a, c, s]) <= lidar_reach
                v_out[a, c, s] = vehicle[a, c, s] if seen else -1
                d_out[a, c, s] = distance[a, c, s] if seen else (np.inf if s == 0 else -np.inf)
            lit = light_dist[a, c] <= camera_reach
            state[a, c] = light_state[a, c] if lit else _NO_LIGHT
            ldist[a, c] = light_dist[a, c] if lit else np.inf
    return v_out, d_out, state, ldist


@njit
def within_range(vehicles, vehicle, distance, light_state, light_dist, lidar_reach, camera_reach):
    """``noise.within_range``: the frame's arrays without what lies beyond the reaches.

    Args (A agents): ``vehicles`` (A, 3, 2, F) features; ``vehicle`` (A, 3, 2) int64 rows
    (-1 none); ``distance`` (A, 3, 2) [m]; ``light_state`` (A, 3) int8; ``light_dist`` (A, 3)
    [m]; ``lidar_reach`` and ``camera_reach`` the detection ranges [m].
    Returns ``vehicle``, ``distance``, ``vehicles`` (0 beyond), ``light_state`` and
    ``light_dist`` within reach, shapes and dtypes as given.
    """
    v_out, d_out, state, ldist = _cut(vehicle, distance, light_state, light_dist, lidar_reach,
                                      camera_reach)  # fmt: skip
    veh = np.zeros(vehicles.shape)
    for a in range(vehicles.shape[0]):
        for c in range(3):
            for s in range(2):
                if v_out[a, c, s] >= 0:
                    veh[a, c, s, :] = vehicles[a, c, s, :]
    return v_out, d_out, veh, state, ldist


@njit
def degrade(
    vehicles, vehicle, distance, ego, light_state, light_dist, z_veh, z_ego, u_light, shift,
    z_ldist, lidar_reach, camera_reach, rel_noise, misdetect, veh_floor, ego_floor, ego_noisy,
):  # fmt: skip
    """``noise.degrade`` on numpy's draws (``noise.noise_draws``): ranges, noise, misdetection.

    Args (A agents, F = 6 vehicle and E = 5 ego features): the truth's ``vehicles``
    (A, 3, 2, F), ``vehicle`` (A, 3, 2) int64, ``distance`` (A, 3, 2) [m], ``ego`` (A, E),
    ``light_state`` (A, 3) int8, ``light_dist`` (A, 3) [m]; the draws ``z_veh`` (A, 3, 2, F),
    ``z_ego`` (A, E), ``u_light`` (A, 3), ``shift`` (A, 3) int64, ``z_ldist`` (A, 3); the
    reaches [m], the weather's ``rel_noise`` and ``misdetect`` probability, and the noise
    floors (F,), (E,) and ``ego_noisy`` (E,) multipliers.
    Returns the sensed ``vehicle``, ``distance``, ``vehicles``, ``ego``, ``light_state`` (int8)
    and ``light_dist``.
    """
    v_out, dist, state, _ = _cut(vehicle, distance, light_state, light_dist, lidar_reach,
                                 camera_reach)  # fmt: skip
    A, F = vehicles.shape[0], vehicles.shape[3]
    veh = np.zeros(vehicles.shape)
    for a in range(A):
        for c in range(3):
            for s in range(2):
                if v_out[a, c, s] < 0:
                    continue
                for k in range(F):
                    x = vehicles[a, c, s, k]
                    # the numpy stage's in-place order: ((|x| + floor) * rel) * z + x
                    veh[a, c, s, k] = (np.abs(x) + veh_floor[k]) * rel_noise * z_veh[a, c, s, k] + x
                dist[a, c, s] = veh[a, c, s, 0]
    E = ego.shape[1]
    ego_out = np.empty((A, E))
    for a in range(A):
        for k in range(E):
            x = ego[a, k]
            ego_out[a, k] = x + ego_noisy[k] * rel_noise * (np.abs(x) + ego_floor[k]) * z_ego[a, k]
    ldist = np.empty((A, 3))
    for a in range(A):
        for c in range(3):
            st = state[a, c]
            if st != _NO_LIGHT and u_light[a, c] < misdetect:
                st = np.int8((np.int64(st) + shift[a, c]) % 3)
            state[a, c] = st
            d = light_dist[a, c] * (1.0 + rel_noise * z_ldist[a, c])
            # np.maximum(d, 0.0): d where d >= 0 or NaN (it propagates NaN, keeps -0.0)
            ldist[a, c] = np.inf if st == _NO_LIGHT else (d if d >= 0.0 or d != d else 0.0)
    return v_out, dist, veh, ego_out, state, ldist


@njit
def vehicle_features(rows, vehicle, distance, on_path, path_geometry, speed, heading, length,
                     width, lateral):  # fmt: skip
    """``lidar.vehicle_features``: (A, 3, 2, 6) ``VEHICLE_FEATURES`` of the neighbours, 0 where
    missing; the current lane's leader in the path's frame where ``on_path`` (A,) bool.

    Args (A agents, N vehicles): ``rows`` (A,) int64; ``vehicle`` (A, 3, 2) int64 (-1 none);
    ``distance`` (A, 3, 2) [m]; ``path_geometry`` (A, 4) ``PATH_GEOMETRY``; the snapshot's
    ``speed`` [m/s], ``heading`` [rad], ``length``, ``width``, ``lateral`` [m] (N,).
    """
    A = len(rows)
    feats = np.zeros((A, 3, 2, 6))
    for a in range(A):
        e = rows[a]
        for c in range(3):
            for s in range(2):
                o = vehicle[a, c, s]
                if o < 0:
                    continue
                f = feats[a, c, s]
                f[0] = distance[a, c, s]
                if c == _CURRENT and s == 0 and on_path[a]:
                    g = path_geometry[a]
                    f[1], f[3], f[4], f[5] = g[0] - speed[e], g[1], g[2], g[3]
                else:
                    f[1], f[3], f[4], f[5] = speed[o] - speed[e], length[o], width[o], lateral[o]
                f[2] = _wrap(heading[o] - heading[e])
    return feats


@njit
def ego_features(rows, lane, lane_pos, heading, speed, length, width, lateral, wp_offset, wp_count,
                 wp_heading, spacing):  # fmt: skip
    """``gnss.ego_features``: (A, 5) ``EGO_FEATURES``, the heading relative to the lane's
    waypoint below the front bumper (``HDMap.waypoint_at``, waypoints ``spacing`` [m] apart).

    Args (A agents, N vehicles, L lanes, W waypoints): ``rows`` (A,) int64; the snapshot's
    ``lane`` (N,) and per-vehicle floats (N,); the map's ``wp_offset``, ``wp_count`` (L,) and
    ``wp_heading`` (W,) [rad].
    """
    A = len(rows)
    out = np.empty((A, 5))
    for a in range(A):
        r = rows[a]
        ln = max(np.int64(lane[r]), 0)
        k = np.int64(np.floor(lane_pos[r] / spacing))
        k = min(max(k, 0), np.int64(wp_count[ln]) - 1)  # np.clip: maximum, then minimum
        wp = np.int64(wp_offset[ln]) + k
        rel = _wrap(heading[r] - wp_heading[wp]) if lane[r] >= 0 else 0.0
        out[a, 0], out[a, 1], out[a, 2] = speed[r], rel, length[r]
        out[a, 3], out[a, 4] = width[r], lateral[r]
    return out


@inline
def _connection(lane, edge, conn_keys, conn_vals, n_edges):
    """``LaneGraph.connection`` of one lane row and edge row: the first lane row of the
    connection, -1 if there is none."""
    C = len(conn_keys)
    if C == 0 or lane < 0 or edge < 0:
        return -1
    key = lane * n_edges + edge
    i = np.searchsorted(conn_keys, key)
    if i >= C or conn_keys[i] != key:
        return -1
    return np.int64(conn_vals[i])


@njit
def lane_sort(lane, lane_pos, n_lanes, offset_key):
    """``neighbours._sort_by_lane``: the vehicles on lanes sorted (stably) by lane * offset_key +
    position. Args (N vehicles): ``lane`` (N,) lane rows (-1 off-lane), ``lane_pos`` (N,) [m].
    Returns ``order`` (M,) rows, ``key`` (M,), ``pos`` (M,) [m], ``start`` (L+1,) and ``rank``
    (N,) (-1 off-lane), as ``neighbours._Sorted``."""
    N = len(lane)
    key_all = np.empty(N)
    n_on = 0
    for r in range(N):
        key_all[r] = np.int64(lane[r]) * offset_key + lane_pos[r]
        n_on += lane[r] >= 0
    on = np.empty(n_on, np.int64)
    m = 0
    for r in range(N):
        if lane[r] >= 0:
            on[m] = r
            m += 1
    order = on[np.argsort(key_all[on], kind="mergesort")]  # stable, as numpy's "stable"
    key = key_all[order]
    start = np.searchsorted(key, np.arange(n_lanes + 1) * offset_key - 1e-3)
    rank = np.full(N, -1, np.int64)
    for j in range(len(order)):
        rank[order[j]] = j
    return order, key, lane_pos[order], start, rank


@njit
def query_lanes(rows, lane, lane_pos, lane3, lane_length, lane_next, pred, conn_keys, conn_vals,
                n_edges, next_edge, via):  # fmt: skip
    """``neighbours._query_lanes``, ``_successors`` and the predecessors: per agent (A) and
    column (left, current, right), the lane row (-1 none), the agent's position projected on
    it [m] (0 where none), the lane it continues into (towards ``next_edge`` (A,) where it
    connects, ``via`` (A,) for the current lane where >= 0, else ``lane_next``) and its
    predecessor ``pred`` (-1 where none). All (A, 3); rows int64.
    """
    A = len(rows)
    lanes = np.empty((A, 3), np.int64)
    pos = np.empty((A, 3))
    succ = np.empty((A, 3), np.int64)
    prev = np.empty((A, 3), np.int64)
    for a in range(A):
        r = rows[a]
        cur = np.int64(lane[r])
        cs = max(cur, 0)
        denom = maximum(lane_length[cs], 1e-9)
        for c in range(3):
            ln = lane3[cs, c] if cur >= 0 else -1
            ls = max(ln, 0)
            lanes[a, c] = ln
            pos[a, c] = lane_pos[r] * (lane_length[ls] / denom) if ln >= 0 else 0.0
            conn = _connection(ls, next_edge[a], conn_keys, conn_vals, n_edges)
            succ[a, c] = conn if conn >= 0 else np.int64(lane_next[ls])
            prev[a, c] = pred[ls] if ln >= 0 else -1
        if via[a] >= 0:
            succ[a, _CURRENT] = via[a]
    return lanes, pos, succ, prev


@inline
def _signal(lane, edge, tls_keys, tls_tl, tls_link, n_edges):
    """``LaneGraph.signal`` of one lane row and edge row: light and link index, (-1, -1) if
    the link lane -> edge has no signal."""
    T = len(tls_keys)
    if T == 0 or lane < 0 or edge < 0:
        return -1, -1
    key = lane * n_edges + edge
    i = np.searchsorted(tls_keys, key)
    if i >= T or tls_keys[i] != key:
        return -1, -1
    return tls_tl[i], tls_link[i]


@njit
def traffic_lights(rows, lanes, next_edge, lane_pos, lane_length, tls_keys, tls_tl, tls_link,
                   n_edges, lane_next_edge, chars, offsets, code):  # fmt: skip
    """``camera.traffic_lights``: (A, 3) int8 state code and (A, 3) stop-line distance [m] of
    the signal at the end of each lane column (NO_LIGHT and +inf where none).

    Args (A agents): ``rows`` (A,) int64; ``lanes`` (A, 3) int64 (-1 none); ``next_edge`` (A,)
    route edge rows; the snapshot's ``lane_pos`` (N,) [m]; the map's ``lane_length`` (L,) [m];
    the graph's signal table (``tls_keys``, ``tls_tl``, ``tls_link`` (T,)) and
    ``lane_next_edge`` (L,); ``chars`` the light state strings' uint8 characters, one after
    another from ``offsets`` (one per light); ``code`` (256,) int8 state code per character.
    """
    A, n_chars = len(rows), len(chars)
    state = np.empty((A, 3), np.int8)
    dist = np.empty((A, 3))
    for a in range(A):
        denom = maximum(lane_length[max(lanes[a, _CURRENT], 0)], 1e-9)
        for c in range(3):
            ln = lanes[a, c]
            ls = max(ln, 0)
            # the link into the route's next edge, else the lane's own way on
            tl, link = _signal(ln, next_edge[a], tls_keys, tls_tl, tls_link, n_edges)
            if tl < 0:
                tl, link = _signal(ln, lane_next_edge[ls], tls_keys, tls_tl, tls_link, n_edges)
            flat = offsets[max(tl, 0)] + link
            if tl >= 0 and link >= 0 and flat < n_chars:
                state[a, c] = code[chars[flat]]
                d = lane_length[ls] - lane_pos[rows[a]] * (lane_length[ls] / denom)
                dist[a, c] = maximum(d, 0.0)
            else:
                state[a, c] = _NO_LIGHT
                dist[a, c] = np.inf
    return state, dist


def warm() -> None:
    """Load the kernels (from the disk cache, else compile them) for the dtypes and layouts
    the env passes, on one agent with nothing around: a process that forks workers calls this
    once, and they inherit the kernels."""
    i64, f8 = np.int64, np.float64
    vehicles, vehicle = np.zeros((1, 3, 2, 6)), np.full((1, 3, 2), -1, i64)
    distance, ego, ones = np.zeros((1, 3, 2)), np.zeros((1, 5)), np.zeros(1)
    state, ldist = np.full((1, 3), _NO_LIGHT, np.int8), np.full((1, 3), np.inf)
    within_range(vehicles, vehicle, distance, state, ldist, 1.0, 1.0)
    degrade(vehicles, vehicle, distance, ego, state, ldist, np.zeros((1, 3, 2, 6)),
            np.zeros((1, 5)), np.zeros((1, 3)), np.ones((1, 3), i64), np.zeros((1, 3)), 1.0, 1.0,
            0.1, 0.1, np.zeros(6), np.zeros(5), np.zeros(5))  # fmt: skip
    rows, lane3 = np.zeros(1, i64), np.full((1, 3), -1, i64)
    chars = np.frombuffer(b"r", np.uint8)  # read-only, as the env's
    traffic_lights(rows, lane3, rows, ones, ones, np.zeros(1, i64), np.zeros(1, i64),
                   np.zeros(1, i64), 1, rows, chars, np.zeros(2, i64), np.zeros(256, np.int8))  # fmt: skip
    lane_sort(np.zeros(1, np.int32), ones, 1, 1.0)
    query_lanes(rows, np.zeros(1, np.int32), ones, lane3, ones, np.zeros(1, np.int32),
                np.zeros(1, i64), np.zeros(0, i64), np.zeros(0, i64), 1, rows, rows)  # fmt: skip
    vehicle_features(rows, vehicle, distance, np.zeros(1, bool), np.zeros((1, 4)), ones, ones,
                     ones, ones, ones)  # fmt: skip
    ego_features(rows, np.zeros(1, np.int32), ones, ones, ones, ones, ones, ones,
                 np.zeros(1, i64), np.ones(1, i64), np.zeros(1, f8), 1.0)  # fmt: skip
