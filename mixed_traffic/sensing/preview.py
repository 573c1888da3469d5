"""Speed-limit preview along the route: where the limit ahead drops (an HD-map lookup).

The waypoints see ``sensors.waypoints`` metres ahead, too short to slow down for a junction's
turn speed (netconvert limits a turn's internal lane to the speed its radius allows, but a
hand-drawn junction may keep the road's limit). The limit of a lane here is its advisory
speed (``HDMap.lane_advisory``: the speed limit, lower where a bend allows less). The
preview lists, per lane column, the first K points within ``sensors.preview_range`` metres
where that limit drops below every limit before it. Those are the only limits a braking
vehicle can be bound by: a later, higher limit is always reached in time if the earlier, lower
one is, whatever the deceleration. The first hop follows the agent's route (the lane's
connection to its next route edge), later hops the primary successors, as the waypoints do.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.world.hdmap import HDMap

#: Lane hops followed when building a lane's table (short OSM edges need many).
MAX_HOPS = 64


def drop_table(hd: HDMap, k: int, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Per lane row, from the lane's start along primary successors: the lane itself, then
    the first ``k - 1`` points within ``reach`` [m] where the limit drops below every one
    before it. Returns (L, k) distances [m] (inf = none) and (L, k) limits [m/s]. Cached."""
    cache = hd.__dict__.setdefault("_drop_tables", {})
    if (k, reach) in cache:
        return cache[(k, reach)]
    L = hd.n_lanes
    dist = np.full((L, k), np.inf)
    speed = np.zeros((L, k))
    rows = np.arange(L)
    limit = hd.lane_advisory
    dist[:, 0], speed[:, 0] = 0.0, limit
    count = np.ones(L, np.int64)
    lowest = limit.astype(np.float64)
    prev, d = rows, np.zeros(L)
    for _ in range(MAX_HOPS):
        d = d + hd.lane_length[prev]
        cur = hd.lane_next[prev].astype(np.int64)
        live = (cur >= 0) & (d <= reach) & (count < k)
        if not live.any():
            break
        drop = live & (limit[np.maximum(cur, 0)] < lowest)
        i = rows[drop]
        dist[i, count[i]], speed[i, count[i]] = d[i], limit[cur[i]]
        lowest[i], count[i] = speed[i, count[i]], count[i] + 1
        prev = np.where(live, cur, prev)
        d = np.where(live, d, np.inf)
    cache[(k, reach)] = dist, speed
    return dist, speed


def limit_preview(
    hd: HDMap, lanes: np.ndarray, pos: np.ndarray, via: np.ndarray, k: int, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """(A, 3, k) distance [m] (inf = none) and limit [m/s] of the drops ahead of the ego.

    Args:
        lanes: (A, 3) lane rows of the lane columns (-1 = none).
        pos: (A, 3) ego position projected onto each column's lane [m].
        via: (A, 3) the lane each column continues into at its end (-1 = dead end).
    """
    ok = (lanes >= 0) & (via >= 0)
    dist, speed = drop_table(hd, k, reach)
    safe = np.maximum(lanes, 0)
    left = np.maximum(hd.lane_length[safe] - pos, 0.0)  # (A, 3) to the lane's end
    d = dist[np.maximum(via, 0)] + left[..., None]  # (A, 3, k)
    s = speed[np.maximum(via, 0)]
    # the via table starts at its own limit; keep what drops below this lane's
    keep = ok[..., None] & (s < hd.lane_advisory[safe][..., None]) & (d <= reach)
    order = np.argsort(~keep, axis=-1, kind="stable")  # kept first, in distance order
    d = np.where(keep, d, np.inf)
    s = np.where(keep, s, 0.0)
    return np.take_along_axis(d, order, -1), np.take_along_axis(s, order, -1)
