"""The neighbour search of :mod:`mixed_traffic.sensing.neighbours` as one compiled kernel.

It does, per agent and lane column, what the numpy stages do with whole arrays (same lane,
the nearer of two side by side, successor and predecessor lanes, the range, and the
straddlers), in the same floating-point operations and order, so the results are equal bit
for bit (tests/test_fast_paths.py checks it on SUMO states). The numpy stages stay the reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import inline, njit

_LEFT, _CURRENT, _RIGHT = 0, 1, 2
_SIDES = ((_LEFT, 1.0), (_RIGHT, -1.0))


@njit
def search(
    rows, lanes, pos, order, key, s_pos, start, rank, succ, prev, lane_length, lane_next, pred,
    lane_width, lane_pos, lateral, length, width, offset_key, max_range, search_depth,
    straddle_depth, straddle_margin,
):  # fmt: skip
    """Front/rear vehicles of every agent's (left, current, right) lanes, and straddlers.

    Args (A agents, N vehicles, M on lanes, L lanes): ``rows`` (A,) snapshot rows;
    ``lanes`` (A, 3) lane rows (-1 none); ``pos`` (A, 3) the ego's position projected onto
    them [m]; the lane sort (``order``, ``key``, ``s_pos`` (M,), ``start`` (L+1,), ``rank``
    (N,)); ``succ`` (A, 3) first successor lanes (route-aware), ``prev`` (A, 3) first
    predecessors; the map's lane arrays (L,); the snapshot's per-vehicle arrays (N,).
    Returns ``i`` (A, 3) the sorted index each search started from, ``vehicle`` (A, 3, 2),
    ``distance`` (A, 3, 2) [m], and the straddler's row, gap [m] and lateral offset [m] (A,).
    """
    A, n = len(rows), len(order)
    i = np.zeros((A, 3), np.int64)
    vehicle = np.full((A, 3, 2), -1, np.int64)
    distance = np.empty((A, 3, 2))
    best = np.full(A, -1, np.int64)
    best_gap = np.full(A, np.inf)
    best_lat = np.zeros(A)
    for a in range(A):
        for c in range(3):
            i[a, c] = np.searchsorted(key, max(lanes[a, c], 0) * offset_key + pos[a, c])
        cur = lanes[a, _CURRENT]
        i[a, _CURRENT] = rank[rows[a]] if cur >= 0 else 0
        front, fdist, rear, rdist = _same_lane(a, i, lanes, pos, order, s_pos, start)
        if n:
            _nearer(a, rows, lanes, pos, order, s_pos, start, i, 1, front, fdist, lane_pos,
                    lateral, length, lane_width)  # fmt: skip
            _nearer(a, rows, lanes, pos, order, s_pos, start, i, -1, rear, rdist, lane_pos,
                    lateral, length, lane_width)  # fmt: skip
            for c in range(3):
                has = lanes[a, c] >= 0
                ls = max(lanes[a, c], 0)
                off = lane_length[ls] - pos[a, c] if has else np.inf
                back = pos[a, c] if has else np.inf
                front[c], fdist[c] = _ahead(rows[a], succ[a, c], off, front[c], fdist[c], order,
                                            s_pos, start, lane_length, lane_next, max_range,
                                            search_depth)  # fmt: skip
                rear[c], rdist[c] = _behind(rows[a], prev[a, c], back, rear[c], rdist[c], order,
                                            s_pos, start, lane_length, pred, max_range,
                                            search_depth)  # fmt: skip
        for c in range(3):
            f_in = front[c] >= 0 and fdist[c] <= max_range
            r_in = rear[c] >= 0 and -rdist[c] <= max_range
            vehicle[a, c, 0] = front[c] if f_in else -1
            vehicle[a, c, 1] = rear[c] if r_in else -1
            distance[a, c, 0] = fdist[c] if f_in else np.inf
            distance[a, c, 1] = rdist[c] if r_in else -np.inf
        if n:
            best[a], best_gap[a], best_lat[a] = _straddler(
                a, rows, lanes, i, pos, order, s_pos, start, lane_width, lateral, length, width,
                max_range, straddle_depth, straddle_margin,
            )  # fmt: skip
    return i, vehicle, distance, best, best_gap, best_lat


@inline
def _same_lane(a, i, lanes, pos, order, s_pos, start):
    """(front, fdist, rear, rdist) (3,) of agent ``a`` on each lane column."""
    n = len(order)
    front, rear = np.full(3, -1, np.int64), np.full(3, -1, np.int64)
    fdist, rdist = np.full(3, np.inf), np.full(3, -np.inf)
    for c in range(3):
        has = lanes[a, c] >= 0
        ls = max(lanes[a, c], 0)
        fi = i[a, c] + (1 if c == _CURRENT else 0)
        ri = i[a, c] - 1
        if n and has and fi < start[ls + 1]:
            j = min(fi, n - 1)
            front[c], fdist[c] = order[j], s_pos[j] - pos[a, c]
        if n and has and ri >= start[ls]:
            j = min(max(ri, 0), n - 1)
            rear[c], rdist[c] = order[j], s_pos[j] - pos[a, c]
    return front, fdist, rear, rdist


@inline
def _nearer(a, rows, lanes, pos, order, s_pos, start, i, step, veh, dist, lane_pos, lateral,
            length, lane_width):  # fmt: skip
    """Of two vehicles side by side on a neighbour lane, the laterally nearer (in place)."""
    n = len(order)
    cur = max(lanes[a, _CURRENT], 0)
    ego = lateral[rows[a]]
    for c, side in _SIDES:
        ln = max(lanes[a, c], 0)
        j = i[a, c] + (step if step > 0 else -2)  # front: after the first; rear: before it
        ok = veh[c] >= 0 and j >= start[ln] and j < start[ln + 1]
        j = min(max(j, 0), n - 1)
        v, w = max(veh[c], 0), order[j]
        lead = w if step > 0 else v
        ok = ok and abs(s_pos[j] - lane_pos[v]) < length[lead]
        shift = side * 0.5 * (lane_width[cur] + lane_width[ln])
        ok = ok and abs(lateral[w] + shift - ego) < abs(lateral[v] + shift - ego)
        if ok:
            veh[c], dist[c] = w, s_pos[j] - pos[a, c]


@inline
def _ahead(row, succ, off, front, fdist, order, s_pos, start, lane_length, lane_next, max_range,
           depth):  # fmt: skip
    """The first vehicle on the successor lanes, when the lane has no front vehicle."""
    n = len(order)
    for _ in range(depth):
        if not (front < 0 and succ >= 0 and off <= max_range):
            break
        first = start[succ]
        j = min(first, n - 1)
        if start[succ + 1] - first > 0 and order[j] != row:
            front, fdist = order[j], off + s_pos[j]
        off = off + lane_length[succ]
        succ = lane_next[succ]
    return front, fdist


@inline
def _behind(row, prev, back, rear, rdist, order, s_pos, start, lane_length, pred, max_range,
            depth):  # fmt: skip
    """The last vehicle on the predecessor lanes, when the lane has no rear vehicle."""
    for _ in range(depth):
        if not (rear < 0 and prev >= 0 and back <= max_range):
            break
        last = max(start[prev + 1] - 1, 0)
        if start[prev + 1] - start[prev] > 0 and order[last] != row:
            rear, rdist = order[last], -(back + lane_length[prev] - s_pos[last])
        back = back + lane_length[prev]
        prev = pred[prev]
    return rear, rdist


@inline
def _straddler(a, rows, lanes, i, pos, order, s_pos, start, lane_width, lateral, length, width,
               max_range, depth, margin):  # fmt: skip
    """The nearest vehicle ahead on a neighbour lane overlapping the ego laterally: its row
    (-1 none), bumper gap [m] and centre offset in the ego lane's frame [m]."""
    n, ego = len(order), rows[a]
    best, best_gap, best_lat = -1, np.inf, 0.0
    w_cur = lane_width[max(lanes[a, _CURRENT], 0)]
    for c, side in _SIDES:
        ok_lane = lanes[a, c] >= 0 and lanes[a, _CURRENT] >= 0
        ls = max(lanes[a, c], 0)
        shift = side * 0.5 * (w_cur + lane_width[ls])
        for k in range(depth):
            idx = i[a, c] + k
            j = min(idx, n - 1)
            v = order[j]
            y = lateral[v] + shift
            d = s_pos[j] - pos[a, c]
            half = 0.5 * (width[v] + width[ego]) + margin
            gap = d - length[v]
            if (ok_lane and idx < start[ls + 1] and d <= max_range
                    and abs(y - lateral[ego]) < half and gap < best_gap):  # fmt: skip
                best, best_gap, best_lat = v, gap, y
    return best, best_gap, best_lat


def warm() -> None:
    """Load :func:`search` (from the disk cache, else compile it) for the dtypes
    ``neighbours.find_neighbours`` passes, on an empty network: a process that forks workers
    calls this once, and they inherit the kernel (a first call costs about 0.5 s)."""
    i64, i32 = np.int64, np.int32
    one, lanes = np.zeros(1), np.full((1, 3), -1, i64)
    search(np.zeros(1, i64), lanes, np.zeros((1, 3)), np.zeros(0, i64), np.zeros(0), np.zeros(0),
           np.zeros(2, i64), np.zeros(1, i64), lanes, lanes, one, np.zeros(1, i32),
           np.zeros(1, i64), one, one, one, one, one, 1.0, 1.0, 3, 3, 0.2)  # fmt: skip
