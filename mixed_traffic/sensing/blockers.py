"""Vehicles across the ego's path: on another (junction) lane whose body comes within half
the ego's width of the path ahead (``path_blockers``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.sensing import blockers_kernel
from mixed_traffic.sensing.lane_graph import LaneGraph, lane_graph
from mixed_traffic.world.hdmap import SPACING, HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Geometry of a vehicle on the ego's path (``path_blockers``), in the path's frame at the point
#: where the path meets it: speed along the path [m/s], extent of its body along the path [m]
#: and across it [m], offset of its centre from the path, + = left [m].
PATH_GEOMETRY = ("speed", "along", "across", "lateral")
#: Added to the agent's half width when testing bodies against its path [m]: in a turn its
#: body (a rectangle behind the front bumper, as SUMO checks collisions) sweeps wider.
SWEEP_MARGIN = 0.5


def path_lanes(
    hdmap: HDMap, lane: np.ndarray, pos: np.ndarray, max_range: float,
    next_edge: np.ndarray | None, via: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(A, H) lanes of each ego's path ahead from ``lane`` at ``pos`` (then the successors
    ``find_neighbours`` follows, while they start within ``max_range``), -1 padded; and (A, H)
    the distance from the ego's front bumper to each lane's start [m] (+inf where padded).
    ``via``: (A,) lane the current lane leads into as SUMO chose it where the lane fans out
    (-1: the map's connection to ``next_edge``)."""
    g = lane_graph(hdmap)
    cur = np.asarray(lane, dtype=np.int64)
    csafe = np.maximum(cur, 0)
    succ = hdmap.lane_next[csafe].astype(np.int64)
    if next_edge is not None:
        conn = g.connection(csafe, np.asarray(next_edge))
        succ = np.where(conn >= 0, conn, succ)
    if via is not None:
        succ = np.where(via >= 0, via, succ)
    succ = np.where(cur >= 0, succ, -1)
    ssafe = np.maximum(succ, 0)
    hops = np.concatenate([cur[:, None], g.chain[ssafe]], axis=1)
    start = np.concatenate(
        [-pos[:, None], (hdmap.lane_length[csafe] - pos)[:, None] + g.chain_start[ssafe]], axis=1
    )
    start[:, 1:][succ < 0] = np.inf
    keep = (hops >= 0) & (start <= max_range)
    keep[:, 1:] &= (succ >= 0)[:, None]
    keep &= (cur >= 0)[:, None]
    return np.where(keep, hops, -1), np.where(keep, start, np.inf)


def path_blockers(
    snap: TrafficSnapshot,
    hdmap: HDMap,
    rows: np.ndarray,
    max_range: float,
    next_edge: np.ndarray | None = None,
    limit: np.ndarray | None = None,
    via: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest vehicle across each agent's path ahead, on a lane the path does not follow.

    The path is the agent's lane from its front bumper on, then the successors
    ``find_neighbours`` follows (route-aware first hop), up to ``max_range``. Candidates are the
    vehicles on internal lanes of the junctions the path crosses, and those that left such a
    junction by less than their length (a vehicle on a lane of the path is found by the lane
    search). The path is sampled at the HD map's 1 m waypoints (only around the candidate's
    junction); a candidate blocks it where its body (a rectangle behind its front bumper) comes
    within half the agent's width of a sample. Vectorised over (agent, candidate) pairs that
    share a junction, times samples.

    Args:
        limit: optional (A,) bumper gap [m] beyond which blockers are not wanted (the lane
            leader's: ``find_neighbours`` passes it, which spares the test for most agents).
    Returns:
        (A,) snapshot row of the nearest blocker (-1 if none); (A,) bumper gap [m] >= 0 along
        the path from the agent's front bumper to where the path meets its body (+inf if none);
        (A, 4) its ``PATH_GEOMETRY`` (0 where none).
    """
    rows = np.asarray(rows, dtype=np.int64)
    if compiled.enabled():
        return _compiled(snap, hdmap, rows, max_range, next_edge, limit, via)
    A = len(rows)
    none = (np.full(A, -1, dtype=np.int64), np.full(A, np.inf), np.zeros((A, 4)))
    cand = _candidates(snap, lane_graph(hdmap))
    if A == 0 or len(cand[0]) == 0:
        return none
    sub = _near_a_junction(snap, hdmap, rows, cand[0], max_range, limit)
    if len(sub) == 0:
        return none
    pairs = _pairs(snap, hdmap, rows, sub, cand, max_range, next_edge, limit, via)
    if pairs is None:
        return none
    hit = _hits(snap, hdmap, pairs)
    if hit is None:
        return none
    return _nearest(snap, hdmap, rows, sub, pairs, *hit, none)


def kernel_array(x: np.ndarray | None, n: int, dtype: type, missing: float) -> np.ndarray:
    """(n,) contiguous writeable copy of ``x`` as ``dtype`` for a kernel (``missing`` everywhere
    when None): one specialisation whatever the caller passes (numba types read-only and
    non-contiguous arrays apart)."""
    if x is None:
        return np.full(n, missing, dtype=dtype)
    return np.array(np.broadcast_to(np.asarray(x, dtype=dtype), (n,)))


def _compiled(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, max_range: float,
              next_edge: np.ndarray | None, limit: np.ndarray | None,
              via: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """:func:`path_blockers` as one compiled kernel (:func:`.blockers_kernel.blockers`)."""
    g, A = lane_graph(hdmap), len(rows)
    return blockers_kernel.blockers(
        np.ascontiguousarray(rows), snap.lane, snap.lane_pos, snap.length, snap.width,
        snap.heading, snap.x, snap.y, snap.speed, g.junction, g.entry_junction, hdmap.lane_next,
        hdmap.lane_length, g.chain, g.chain_start, g.conn_keys, g.conn_vals, g.n_edges,
        hdmap.wp_count, hdmap.wp_offset, hdmap.wp_xyz, hdmap.wp_heading,
        kernel_array(next_edge, A, np.int64, -1), kernel_array(via, A, np.int64, -1),
        kernel_array(limit, A, np.float64, np.inf), float(max_range), SPACING, SWEEP_MARGIN,
    )  # fmt: skip


def _candidates(snap: TrafficSnapshot, g: LaneGraph) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vehicles on internal lanes, or leaving a junction with the rear still inside it: their
    (C,) snapshot rows, lane rows and junction numbers."""
    vlane = snap.lane.astype(np.int64)
    cand = np.flatnonzero(vlane >= 0)
    cl = vlane[cand]
    cj = np.where(snap.lane_pos[cand] < snap.length[cand], g.entry_junction[cl], g.junction[cl])
    cj = np.where(g.junction[cl] >= 0, g.junction[cl], cj)
    return cand[cj >= 0], cl[cj >= 0], cj[cj >= 0]


def _near_a_junction(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, cand: np.ndarray,
                     max_range: float, limit: np.ndarray | None) -> np.ndarray:  # fmt: skip
    """Indices into ``rows`` of the agents whose path reaches a junction before their limit:
    from a normal lane, the next junction begins at the lane's end; on an internal lane, here."""
    g = lane_graph(hdmap)
    reach_max = 0.5 * (np.hypot(snap.length[cand], snap.width[cand]).max() + snap.width.max())
    cut = max_range if limit is None else np.minimum(np.asarray(limit, np.float64), max_range)
    cur = snap.lane.astype(np.int64)[rows]
    csafe = np.maximum(cur, 0)
    to_junction = np.where(
        g.junction[csafe] >= 0, 0.0, hdmap.lane_length[csafe] - snap.lane_pos[rows]
    )
    return np.flatnonzero((cur >= 0) & (to_junction - reach_max <= cut + SPACING))


class _Pairs(NamedTuple):
    """(agent, candidate) pairs that share a junction, with the window of the path to sample."""

    ai: np.ndarray
    """(P,) index into ``sub`` (the agents near a junction)."""
    v: np.ndarray
    """(P,) snapshot row of the candidate."""
    lo: np.ndarray
    """(P,) start of the window along the path [m]."""
    hi: np.ndarray
    """(P,) end of the window along the path [m]."""
    r: np.ndarray
    """(P,) the agent's half width [m]."""
    half_l: np.ndarray
    """(P,) half the candidate's length [m]."""
    half_w: np.ndarray
    """(P,) half the candidate's width [m]."""
    hops: np.ndarray
    """(P, H) lanes of the agent's path, -1 padded."""
    st: np.ndarray
    """(P, H) distance from the agent's front bumper to each lane's start [m]."""


def _pairs(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, sub: np.ndarray,
           cand: tuple[np.ndarray, np.ndarray, np.ndarray], max_range: float,
           next_edge: np.ndarray | None, limit: np.ndarray | None,
           via: np.ndarray | None = None) -> _Pairs | None:  # fmt: skip
    """Pairs of an agent in ``sub`` and a candidate on a junction its path crosses (not on a
    lane of the path, not itself), and the window of its path around that junction: the
    junction's lanes, +- the body's reach."""
    g = lane_graph(hdmap)
    cand, cl, cj = cand
    cur = snap.lane.astype(np.int64)[rows]
    nxt = None if next_edge is None else np.asarray(next_edge)[sub]
    vsub = None if via is None else np.asarray(via)[sub]
    hops, start = path_lanes(hdmap, cur[sub], snap.lane_pos[rows[sub]], max_range, nxt, vsub)
    hj = np.where(hops >= 0, g.junction[np.maximum(hops, 0)], -1)  # (a, H)
    match = (hj[:, :, None] == cj[None, None, :]) & (hj >= 0)[:, :, None]  # (a, H, C)
    pair = match.any(axis=1)
    pair &= ~(hops[:, :, None] == cl[None, None, :]).any(axis=1)  # not on a lane of the path
    pair &= cand[None, :] != rows[sub, None]
    ai, ci = np.nonzero(pair)  # ai: index into sub
    if len(ai) == 0:
        return None
    m = match[ai, :, ci]  # (P, H)
    H = m.shape[1]
    h1 = np.argmax(m, axis=1)
    h2 = H - 1 - np.argmax(m[:, ::-1], axis=1)
    v = cand[ci]
    half_l, half_w = 0.5 * snap.length[v], 0.5 * snap.width[v]
    r = 0.5 * snap.width[rows[sub[ai]]] + SWEEP_MARGIN  # the agent's half width, and more
    reach = np.hypot(half_l, half_w) + r
    st = start[ai]  # (P, H)
    lo = np.maximum(st[np.arange(len(ai)), h1] - reach, 0.0)
    hi = st[np.arange(len(ai)), h2] + hdmap.lane_length[hops[ai, h2]] + reach
    hi = np.minimum(hi, max_range)
    if limit is not None:  # the first hit is at most SPACING beyond the gap
        hi = np.minimum(hi, np.asarray(limit, dtype=np.float64)[sub[ai]] + SPACING)
    near = lo <= hi
    if not near.any():
        return None
    return _Pairs(ai[near], v[near], lo[near], hi[near], r[near], half_l[near], half_w[near],
                  hops[ai][near], st[near])  # fmt: skip


def _hits(snap: TrafficSnapshot, hdmap: HDMap, pp: _Pairs):
    """Sample each pair's window at the waypoints and test the candidate's body against the
    agent's half width. Returns None without any hit, else (hit (P, S) bool, sample hop
    (P, S), waypoint (P, S), waypoint index on its lane (P, S), body centre x and y (P,))."""
    n = int(np.ceil(np.max(pp.hi - pp.lo, initial=0.0) / SPACING)) + 1
    d = pp.lo[:, None] + SPACING * np.arange(n)[None, :]  # (P, S)
    h = np.zeros(d.shape, dtype=np.int64)  # hop of each sample
    for hh in range(1, pp.st.shape[1]):
        h += d >= pp.st[:, hh, None]
    lane = np.take_along_axis(pp.hops, h, axis=1)
    lsafe = np.maximum(lane, 0)
    q = d - np.take_along_axis(pp.st, h, axis=1)  # position on that lane
    k = np.clip(np.rint(q / SPACING).astype(np.int64), 0, hdmap.wp_count[lsafe] - 1)
    wp = hdmap.wp_offset[lsafe] + k
    ok = (lane >= 0) & (d <= pp.hi[:, None]) & (q <= hdmap.lane_length[lsafe] + 0.5 * SPACING)
    # ---- the body: rectangle behind the front bumper, in its own frame
    c, s = np.cos(snap.heading[pp.v]), np.sin(snap.heading[pp.v])
    cx = snap.x[pp.v] - pp.half_l * c
    cy = snap.y[pp.v] - pp.half_l * s
    dx = hdmap.wp_xyz[wp, 0] - cx[:, None]
    dy = hdmap.wp_xyz[wp, 1] - cy[:, None]
    out_l = np.maximum(np.abs(dx * c[:, None] + dy * s[:, None]) - pp.half_l[:, None], 0.0)
    out_w = np.maximum(np.abs(dy * c[:, None] - dx * s[:, None]) - pp.half_w[:, None], 0.0)
    hit = ok & (out_l**2 + out_w**2 < (pp.r * pp.r)[:, None])
    if not hit.any(axis=1).any():
        return None
    return hit, h, wp, k, cx, cy


def _nearest(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, sub: np.ndarray,
             pp: _Pairs, hit: np.ndarray, h: np.ndarray, wp: np.ndarray, k: np.ndarray,
             cx: np.ndarray, cy: np.ndarray, none: tuple):  # fmt: skip
    """Where the path meets each blocker (the first hit sample, in the path's frame there),
    and the nearest blocker per agent: ``none`` filled in."""
    p = np.flatnonzero(hit.any(axis=1))
    j = np.argmax(hit[p], axis=1)
    ai, v, wj = pp.ai[p], pp.v[p], wp[p, j]
    dj = np.take_along_axis(pp.st[p], h[p, j][:, None], axis=1)[:, 0] + k[p, j] * SPACING
    t = hdmap.wp_heading[wj]
    rel = snap.heading[v] - t
    ca, sa = np.abs(np.cos(rel)), np.abs(np.sin(rel))
    along = snap.length[v] * ca + snap.width[v] * sa
    across = snap.length[v] * sa + snap.width[v] * ca
    ex, ey = cx[p] - hdmap.wp_xyz[wj, 0], cy[p] - hdmap.wp_xyz[wj, 1]
    centre = ex * np.cos(t) + ey * np.sin(t)
    lateral = ey * np.cos(t) - ex * np.sin(t)
    # the body's near end, between the last sample that missed it and the hit's reach
    gap = np.maximum(np.clip(dj + centre - 0.5 * along, dj - SPACING, dj + pp.r[p]), 0.0)
    order = np.lexsort((gap, ai))
    first = order[np.r_[True, ai[order][1:] != ai[order][:-1]]]
    vehicle, best, geom = none
    a = sub[ai[first]]
    vehicle[a] = v[first]
    best[a] = gap[first]
    geom[a] = np.stack([snap.speed[v] * np.cos(rel), along, across, lateral], axis=1)[first]
    return vehicle, best, geom
