"""The reward's traffic terms of :mod:`mixed_traffic.env.traffic_terms` as one compiled kernel.

Per agent it builds the route frame (``route_traffic.route_frame``), walks the vehicles the
numpy stages pair it with (``ring_pairs``: every vehicle, in row order; ``route_pairs``: each
route edge's window of the (edge, position)-sorted vehicles) and sums r5, r6 and r8 as it goes,
without the pair arrays. The floating-point operations and the order of every sum are those
of the numpy stages (``np.bincount`` adds in pair order; r6's followers in ``np.lexsort``'s
order), so the results are equal bit for bit (tests/test_fast_paths.py checks it on SUMO
states). The numpy stages stay the reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import inline, njit


@njit
def terms(
    rows, routes, route_len, lane, lane_pos, speed, accel, lane_index, route_index, edge_length,
    lane_speed, anchor_edge, anchor_offset, junction_keys, junction_len, n_edges, key_stride,
    key_shift, ring, upstream, downstream, followers, acc_threshold, desired,
):  # fmt: skip
    """(r5, r6, r8), each (A,) float64, of the agents at snapshot ``rows``.

    Args (A agents, W route columns, N vehicles, L lanes, E edges): ``rows`` (A,);
    ``routes`` (A, W) edge rows, ``route_len`` (A,) [edges]; the snapshot's per-vehicle
    arrays (N,) (``lane`` rows, ``lane_pos`` [m], ``speed`` [m/s], ``accel`` [m/s^2],
    ``lane_index``, ``route_index``); the map's ``edge_length`` (E,) [m] and ``lane_speed``
    (L,) [m/s]; ``route_traffic.map_tables``'s anchors (L,), junction table (K,), ``n_edges``,
    ``key_stride`` and ``key_shift`` [m]; ``ring``: pair every vehicle once on the loop;
    ``upstream`` / ``downstream`` the window [m]; ``followers`` [count] and ``acc_threshold``
    [m/s^2] of r6; ``desired`` (L,) r8's reference speed on each lane [m/s] (0 = its limit).
    """
    A, W = routes.shape
    edge, pos, ratio, target = _vehicles(lane, lane_pos, speed, anchor_edge, anchor_offset,
                                         lane_speed, desired)  # fmt: skip
    if ring:  # every vehicle is paired, in row order
        on, key = np.empty(0, np.int64), np.empty(0)
    else:
        on, key = _sorted(edge, pos, key_stride, key_shift)
    r5, r6, r8 = np.empty(A), np.empty(A), np.empty(A)
    edges, span, start = np.empty(W, np.int64), np.empty(W), np.empty(W)
    at = np.full(n_edges, np.nan)  # ring: start of each edge of the loop, nan off it
    # a ring's or a route column's follower candidates: vehicle, distance behind, pair index
    cand = np.empty(len(lane), np.int64), np.empty(len(lane)), np.empty(len(lane), np.int64)
    f = max(followers, 0)  # the nearest followers so far, as the candidates
    near = np.empty(f, np.int64), np.empty(f), np.empty(f, np.int64)
    for a in range(A):
        row = rows[a]
        k, ego = _frame(a, row, routes, route_len, route_index, edge, pos, edge_length,
                        junction_keys, junction_len, n_edges, edges, span, start)  # fmt: skip
        if ring:
            sums = _ring(row, k, ego, edges, start, edge, pos, at, ratio, target, lane_index,
                         upstream, cand, near)  # fmt: skip
        else:
            sums = _route(row, ego, edges, span, start, on, key, pos, key_stride, key_shift,
                          upstream, downstream, ratio, target, lane_index, cand, near)  # fmt: skip
        own = speed[row] / np.maximum(lane_speed[max(lane[row], 0)], 0.1)  # if off its route
        r5[a], r8[a] = _local_and_flow(sums, own)
        r6[a] = _comfort(near[0], sums[4], accel, acc_threshold)
    return r5, r6, r8


@inline
def _vehicles(lane, lane_pos, speed, anchor_edge, anchor_offset, lane_speed, desired):
    """(N,) the edge each vehicle counts on (-1 none), (N,) its position on it [m]
    (``route_traffic.positions``), and (N,) its speed and r8's reference speed as shares of
    its lane's limit (on an edge; once per vehicle, not per pair)."""
    n = len(lane)
    edge, pos = np.empty(n, np.int64), np.empty(n)
    ratio, target = np.zeros(n), np.zeros(n)
    for v in range(n):
        ln = lane[v]
        edge[v] = anchor_edge[ln] if ln >= 0 else -1
        pos[v] = lane_pos[v] + anchor_offset[max(ln, 0)]
        if edge[v] >= 0:
            limit = np.maximum(lane_speed[ln], 0.1)
            ratio[v] = speed[v] / limit
            target[v] = desired[ln] / limit if desired[ln] > 0 else 1.0
    return edge, pos, ratio, target


@inline
def _sorted(edge, pos, key_stride, key_shift):
    """The vehicles on an edge (M,) sorted by their (edge, position) key, and (M,) the keys,
    as ``route_traffic.route_pairs`` sorts them (stable)."""
    m = 0
    for v in range(len(edge)):
        m += edge[v] >= 0
    on, key = np.empty(m, np.int64), np.empty(m)
    m = 0
    for v in range(len(edge)):
        if edge[v] >= 0:
            on[m], key[m] = v, edge[v] * key_stride + (pos[v] + key_shift)
            m += 1
    order = np.argsort(key, kind="mergesort")  # stable, as numpy's kind="stable"
    return on[order], key[order]


@inline
def _frame(a, row, routes, route_len, route_index, edge, pos, edge_length, junction_keys,
           junction_len, n_edges, edges, span, start):  # fmt: skip
    """Agent ``a``'s route frame (``route_traffic.route_frame``) into ``edges``, ``span`` and
    ``start`` (W,); returns its current route column and its position in the frame [m]."""
    W = len(edges)
    for j in range(W):
        edges[j] = routes[a, j] if j < route_len[a] else -1
    cum = 0.0  # np.cumsum adds in order
    for j in range(W):
        e, nxt = edges[j], edges[j + 1] if j + 1 < W else -1
        span[j] = edge_length[max(e, 0)] + _junction(e, nxt, junction_keys, junction_len,
                                                     n_edges) if e >= 0 else 0.0  # fmt: skip
        start[j] = cum
        cum += span[j]
    k = min(max(route_index[row], 0), W - 1)
    origin = start[k]
    for j in range(W):
        start[j] = start[j] - origin
    k1 = min(k + 1, W - 1)
    # on the junction after its edge an agent counts on the route's next edge
    if edge[row] != edges[k] and edge[row] == edges[k1]:
        return k, start[k1] + pos[row]
    return k, pos[row]


@inline
def _junction(e, nxt, junction_keys, junction_len, n_edges):
    """Length of the junction lanes from edge ``e`` into ``nxt`` [m], 0 if none
    (``_MapTables.junction``)."""
    n = len(junction_keys)
    if n == 0:
        return 0.0
    key = np.int64(e) * n_edges + nxt
    i = min(np.searchsorted(junction_keys, key), n - 1)
    if junction_keys[i] == key and e >= 0 and nxt >= 0:
        return junction_len[i]
    return 0.0


@inline
def _ring(row, k, ego, edges, start, edge, pos, at, ratio, target, lane_index, upstream, cand,
          near):  # fmt: skip
    """The sums (``_add``) and followers kept (``_offer``) over every vehicle on the loop at
    its distance ahead in [0, lap) (``ring_pairs``), in row order."""
    W = len(edges)
    n, s_ratio, s_square, s_target, m = 0, 0.0, 0.0, 0.0, 0
    stop = -1  # where the current edge comes again: the loop's end
    for j in range(k + 1, W):
        if edges[j] == edges[k]:
            stop = j
            break
    if stop < 0:  # no loop: no pairs (lap = inf)
        return n, s_ratio, s_square, s_target, 0
    lap = start[stop]
    for j in range(k, stop):
        if edges[j] >= 0:
            at[edges[j]] = start[j]  # a repeated edge: the later column, as numpy assigns
    for v in range(len(edge)):
        if edge[v] < 0 or lap == 0.0:  # np.mod(x, 0) is nan: no pair
            continue
        dist = (at[edge[v]] + pos[v] - ego) % lap  # Python's (and np.mod's) sign rule
        if np.isfinite(dist):
            behind = lap - dist if dist > 0 else 0.0  # one d ahead is lap - d behind
            m = _candidate(cand, m, v, behind, n, row, lane_index, upstream)
            n, s_ratio, s_square, s_target = _add(ratio[v], target[v], n, s_ratio, s_square,
                                                  s_target)  # fmt: skip
    for j in range(k, stop):
        if edges[j] >= 0:
            at[edges[j]] = np.nan
    return n, s_ratio, s_square, s_target, _offer(cand, m, near, 0)


@inline
def _route(row, ego, edges, span, start, on, key, pos, key_stride, key_shift, upstream,
           downstream, ratio, target, lane_index, cand, near):  # fmt: skip
    """The sums (``_add``) and followers kept (``_offer``) over the vehicles on each route edge
    within ``upstream`` behind and ``downstream`` ahead (``route_pairs``), edge by edge in
    route order, each by position."""
    n, s_ratio, s_square, s_target, nf = 0, 0.0, 0.0, 0.0, 0
    for j in range(len(edges)):
        e = edges[j]
        lo = start[j] - ego
        hi = start[j] + span[j] - ego
        before = span[j - 1] if j > 0 else 0.0  # junction slack
        if not (e >= 0 and hi >= -upstream and lo - before <= downstream):
            continue
        base = e * key_stride
        left = np.searchsorted(key, base + np.maximum(-upstream - lo + key_shift, 0.0))
        right = np.searchsorted(
            key, base + np.minimum(downstream - lo + key_shift, key_stride), side="right"
        )
        m = 0
        for i in range(left, right):
            v = on[i]
            dist = lo + pos[v]
            if dist >= -upstream and dist <= downstream:  # float edges of the ranges
                m = _candidate(cand, m, v, -dist, n, row, lane_index, upstream)
                n, s_ratio, s_square, s_target = _add(ratio[v], target[v], n, s_ratio,
                                                      s_square, s_target)  # fmt: skip
        nf = _offer(cand, m, near, nf)
    return n, s_ratio, s_square, s_target, nf


@inline
def _add(ratio, target, n, s_ratio, s_square, s_target):
    """The agent's pair count and sums of the speed shares, of their squared shortfalls and
    of the reference shares, with one more pair (in pair order, as ``np.bincount`` adds)."""
    d = ratio - target
    return n + 1, s_ratio + ratio, s_square + d * d, s_target + target  # numpy's x**2: x * x


@inline
def _candidate(cand, m, v, behind, index, row, lane_index, upstream):
    """Appends pair ``index`` (vehicle ``v``, ``behind`` [m] behind the agent at ``row``) to
    the ``m`` candidates if it is a follower; returns their number. Without a branch: the
    lane test is a coin toss, which a branch mispredicts half the time."""
    cand[0][m], cand[1][m], cand[2][m] = v, behind, index
    follows = (v != row) & (behind > 0) & (behind <= upstream) & (lane_index[v] == lane_index[row])
    return m + follows


@inline
def _offer(cand, m, near, nf):
    """Offers the ``m`` candidates to the ``nf`` followers kept in ``near``; returns how many
    are kept. Last first: pairs come by position, farthest behind first, so most of them are
    then appended or refused at the first comparison."""
    for c in range(m - 1, -1, -1):
        nf = _keep_nearest(near, nf, cand[0][c], cand[1][c], cand[2][c])
    return nf


@inline
def _keep_nearest(near, nf, v, behind, index):
    """Inserts pair ``index`` (vehicle ``v``, ``behind`` [m]) into the ``nf`` nearest followers
    (``near``: vehicles, distances, pair indices), which stay in ``np.lexsort``'s order (by
    distance, then pair index) and at most ``len(near[0])``; returns how many are kept."""
    size = len(near[0])
    if size == 0 or (nf == size and not _before(behind, index, near[1][-1], near[2][-1])):
        return nf
    p = nf
    while p > 0 and _before(behind, index, near[1][p - 1], near[2][p - 1]):
        p -= 1
    for i in range(min(nf, size - 1), p, -1):
        near[0][i], near[1][i], near[2][i] = near[0][i - 1], near[1][i - 1], near[2][i - 1]
    near[0][p], near[1][p], near[2][p] = v, behind, index
    return min(nf + 1, size)


@inline
def _before(behind, index, other_behind, other_index):
    """Pair (``behind``, ``index``) comes before the other in ``np.lexsort``'s (stable) order."""
    return behind < other_behind or (behind == other_behind and index < other_index)


@inline
def _local_and_flow(sums, own):
    """r5 (``own``, the agent's speed share, without pairs) and r8 (0 without pairs)
    from the agent's ``sums`` (``_add``; ``traffic_terms``, ``uniform_flow_reward``)."""
    n, s_ratio, s_square, s_target = sums[0], sums[1], sums[2], sums[3]
    if n == 0:
        return own, 0.0
    rms = np.sqrt(s_square / n)
    return s_ratio / n, np.maximum(0.0, 1.0 - rms / np.maximum(s_target / n, 1e-9))


@inline
def _comfort(near_v, nf, accel, acc_threshold):
    """r6: -mean (a / acc_threshold)^2 over the ``nf`` followers kept, nearest first."""
    total = 0.0
    for i in range(nf):
        q = accel[near_v[i]] / acc_threshold
        total += q * q
    return -total / max(nf, 1)


def warm() -> None:
    """Load :func:`terms` (from the disk cache, else compile it) for the dtypes
    ``traffic_terms`` passes, on one vehicle with no map: a process that forks workers calls
    this once, and they inherit the kernel."""
    i64, i32 = np.int64, np.int32
    one = np.zeros(1)
    terms(np.zeros(1, i64), np.full((1, 1), -1, i64), np.zeros(1, i64), np.full(1, -1, i32),
          one, one, one, np.zeros(1, np.int16), np.zeros(1, i32), one, one, np.zeros(1, i64),
          one, np.zeros(0, i64), np.zeros(0), 1, 1.0, 0.0, False, 1.0, 1.0, 1, 1.0, one)  # fmt: skip
