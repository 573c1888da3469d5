"""Vehicles merging into the ego's path: on another junction lane that ends on the same lane as
one of the path's junction lanes (``merge_leaders``).

Two junction lanes that merge run side by side until they meet at the end. A vehicle on the
other one is not yet on the ego's path (``path_blockers`` finds bodies only where they touch
it), but it will be: whoever is nearer the merge point goes first, as in SUMO's zipper and
priority merges. Its place on the ego's path is where it will be once merged: the merge point
less its remaining distance to it.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.sensing import blockers_kernel
from mixed_traffic.sensing.blockers import kernel_array, path_lanes
from mixed_traffic.sensing.lane_graph import lane_graph
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot


def exit_table(hd: HDMap) -> tuple[np.ndarray, np.ndarray]:
    """(L,) the normal lane each junction lane leads into (-1 for normal lanes and dead ends)
    and (L,) the distance from the junction lane's start to it [m]. Cached."""
    cached = hd.__dict__.get("_exit_table")
    if cached is not None:
        return cached
    g = lane_graph(hd)
    internal = g.junction >= 0
    lane = np.arange(hd.n_lanes)
    dist = np.zeros(hd.n_lanes)
    out = np.full(hd.n_lanes, -1, dtype=np.int64)
    live = internal.copy()
    for _ in range(8):  # junction lanes split at internal junctions come in short chains
        dist[live] += hd.lane_length[lane[live]]
        lane = np.where(live, hd.lane_next[lane], lane).astype(np.int64)
        done = live & ((lane < 0) | (g.junction[np.maximum(lane, 0)] < 0))
        out[done & (lane >= 0)] = lane[done & (lane >= 0)]
        live &= ~done
        if not live.any():
            break
    cached = (out, dist)
    hd.__dict__["_exit_table"] = cached
    return cached


def merge_leaders(
    snap: TrafficSnapshot,
    hdmap: HDMap,
    rows: np.ndarray,
    max_range: float,
    next_edge: np.ndarray | None = None,
    via: np.ndarray | None = None,
    lead_gap: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest vehicle ahead of each agent that merges into its path at a junction.

    Candidates are vehicles on junction lanes that are not on the agent's path but lead into
    the same normal lane as one of the path's junction lanes. One is ahead when its front is
    nearer that merge point than the agent's front; its bumper gap is then (merge point of the
    agent - the candidate's remaining distance) - its length, at least 0 (side by side, it
    goes first). With ``lead_gap`` (A,) [m], the bumper gap to the agent's lane leader (+inf:
    none), only merge points before that leader's rear count: a vehicle merging in enters the
    path there, so it cannot come between the agent and a leader that has not passed the
    merge point yet (issue 42: on SUMO's ``cross``, a truck about to merge hid a car queued at
    a red light in front of the agent, which drove into the car).
    """
    rows = np.asarray(rows, dtype=np.int64)
    A = len(rows)
    exit_lane, to_exit = exit_table(hdmap)
    if compiled.enabled():
        g = lane_graph(hdmap)
        return blockers_kernel.merges(
            np.ascontiguousarray(rows), snap.lane, snap.lane_pos, snap.length, snap.width,
            snap.speed, exit_lane, to_exit, hdmap.lane_next, hdmap.lane_length, g.chain,
            g.chain_start, g.conn_keys, g.conn_vals, g.n_edges,
            kernel_array(next_edge, A, np.int64, -1), kernel_array(via, A, np.int64, -1),
            kernel_array(lead_gap, A, np.float64, np.inf), float(max_range),
        )  # fmt: skip
    none = (np.full(A, -1, dtype=np.int64), np.full(A, np.inf), np.zeros((A, 4)))
    vlane = snap.lane.astype(np.int64)
    cand = np.flatnonzero((vlane >= 0) & (exit_lane[np.maximum(vlane, 0)] >= 0))
    if A == 0 or len(cand) == 0:
        return none
    c_exit = exit_lane[vlane[cand]]
    c_rem = to_exit[vlane[cand]] - snap.lane_pos[cand]  # front's distance to the merge point
    order = np.argsort(c_exit, kind="stable")
    cand, c_exit, c_rem = cand[order], c_exit[order], c_rem[order]
    cur = vlane[rows]
    hops, start = path_lanes(hdmap, cur, snap.lane_pos[rows], max_range, next_edge, via)
    hsafe = np.maximum(hops, 0)
    h_exit = np.where(hops >= 0, exit_lane[hsafe], -1)  # (A, H)
    # the merge point, measured from the agent's front along its path; one per exit lane
    h_merge = start + to_exit[hsafe]
    lo = np.searchsorted(c_exit, h_exit, "left")
    hi = np.searchsorted(c_exit, h_exit, "right")
    n = np.where(h_exit >= 0, hi - lo, 0)
    if not n.any():
        return none
    ai, hi_ = np.nonzero(n)
    counts = n[ai, hi_]
    pa = np.repeat(ai, counts)  # (P,) agent index
    ph = np.repeat(hi_, counts)
    first = np.repeat(lo[ai, hi_], counts)
    pc = first + np.arange(len(pa)) - np.repeat(np.cumsum(counts) - counts, counts)
    v = cand[pc]
    front = h_merge[pa, ph] - c_rem[pc]  # the candidate's front along the agent's path
    on_path = (hops[pa] == vlane[v][:, None]).any(axis=1)
    ahead = (front > 0) & ~on_path & (v != rows[pa])
    if lead_gap is not None:
        ahead &= h_merge[pa, ph] < np.asarray(lead_gap, np.float64)[pa]
    if not ahead.any():
        return none
    pa, v, front = pa[ahead], v[ahead], front[ahead]
    gap = np.maximum(front - snap.length[v], 0.0)
    vehicle, best, geom = none
    order = np.lexsort((gap, pa))
    pick = order[np.r_[True, pa[order][1:] != pa[order][:-1]]]
    a = pa[pick]
    vehicle[a], best[a] = v[pick], gap[pick]
    geom[a] = np.stack([snap.speed[v], snap.length[v], snap.width[v], np.zeros(len(v))], axis=1)[
        pick
    ]
    return vehicle, best, geom
