"""The traffic along each agent's route: which vehicles are how far ahead or behind (ground truth).

A vehicle's *route distance* from an agent is the distance along the agent's route from the
agent's front bumper to the vehicle's front bumper [m], + ahead, over all lanes of the route's
edges and the junction lanes between them. Positions come from one snapshot and the HD map:
a vehicle on a junction lane counts on the next normal edge, as far before its start as the
junction lanes still ahead of it are long; an edge's successor on the route starts after the
edge's length plus the junction lanes of their connection.

Open roads pair each agent with the vehicles on the route edges around it, each occurrence of
an edge in the route once (``route_pairs``). On a ring (``world.ring``), every vehicle is
paired with every agent once, at a distance in [0, lap) (``ring_pairs``): a vehicle ``d`` ahead
is also ``lap - d`` behind, and ``d + k·lap`` ahead for every k. Both are vectorised over agents
and vehicles: no Python loop over either.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Junction lanes followed from a junction lane to the next normal lane.
MAX_JUNCTION_HOPS = 8


@dataclass(frozen=True)
class Pairs:
    """(agent, vehicle, route distance) triples, one per vehicle occurrence near an agent."""

    agent: np.ndarray
    """(P,) int64 index of the agent (into the ``rows`` it was built from)."""
    vehicle: np.ndarray
    """(P,) int64 snapshot row of the vehicle (the agent itself included, at distance 0)."""
    distance: np.ndarray
    """(P,) route distance [m], + ahead; on a ring in [0, lap)."""
    lap: np.ndarray
    """(A,) the ring's length along each agent's route [m]; inf on an open road."""


@dataclass(frozen=True)
class RouteFrame:
    """Each agent's route as distances from the start of its current edge (``route_frame``)."""

    edges: np.ndarray
    """(A, W) edge rows of the routes, -1 padded."""
    start: np.ndarray
    """(A, W) start of each route edge from the start of the agent's current route edge [m]."""
    span: np.ndarray
    """(A, W) length of each route edge plus the junction lanes to the next one [m]."""
    ego: np.ndarray
    """(A,) position of the agent's front bumper in this frame [m]."""
    current: np.ndarray
    """(A,) index of the agent's current (or last normal) edge in its route."""


class _MapTables:
    """Per-map lookups (built once per HD map, cached on it)."""

    def __init__(self, hd: HDMap) -> None:
        E = len(hd.edge_ids)
        self.n_edges = E
        self.anchor_edge, self.anchor_offset = _anchors(hd)
        best: dict[int, float] = {}
        for (lane, nxt), first in hd.conn_to.items():
            key = int(hd.lane_edge[lane]) * E + nxt
            length = _junction_length(hd, first)
            best[key] = min(best.get(key, np.inf), length)
        keys, vals = list(best), list(best.values())
        order = np.argsort(keys)
        self.junction_keys = np.asarray(keys, np.int64)[order]
        self.junction_len = np.asarray(vals, np.float64)[order]
        rows = np.maximum(hd.edge_lanes, 0)
        car = (hd.edge_lanes >= 0) & hd.lane_car[rows]
        self.edge_lanes = np.maximum(car.sum(axis=1), 1).astype(np.float64)
        """(E,) lanes cars may use per edge (at least 1) [count]."""
        self.edge_limit = np.where(car, hd.lane_speed[rows], 0.0).max(axis=1)
        """(E,) fastest car lane's speed limit per edge [m/s]."""
        slack = float(-self.anchor_offset.min(initial=0.0)) + 1.0
        self.key_shift = slack
        """Added to a position so that junction lanes before an edge stay >= 0 [m]."""
        self.key_stride = 2.0 * (float(hd.lane_length.max(initial=0.0)) + slack + 1.0)
        """Edge multiplier of the (edge, position) sort key of the vehicles [m]."""

    def junction(self, edge: np.ndarray, nxt: np.ndarray) -> np.ndarray:
        """(...) length of the junction lanes from ``edge`` into ``nxt`` [m], 0 if none."""
        key = np.asarray(edge, np.int64) * self.n_edges + np.asarray(nxt, np.int64)
        if not len(self.junction_keys):
            return np.zeros(key.shape)
        i = np.minimum(np.searchsorted(self.junction_keys, key), len(self.junction_keys) - 1)
        hit = (self.junction_keys[i] == key) & (np.asarray(edge) >= 0) & (np.asarray(nxt) >= 0)
        return np.where(hit, self.junction_len[i], 0.0)


def map_tables(hd: HDMap) -> _MapTables:
    """The (cached) per-map tables of ``hd``."""
    cached = hd.__dict__.get("_route_traffic")
    if cached is None:
        cached = hd.__dict__["_route_traffic"] = _MapTables(hd)
    return cached


def _junction_length(hd: HDMap, lane: int) -> float:
    """Length of the junction lanes from ``lane`` (a connection's first lane) to a normal lane [m]."""
    total = 0.0
    for _ in range(MAX_JUNCTION_HOPS):
        if lane < 0 or hd.lane_edge[lane] >= 0:
            break
        total += float(hd.lane_length[lane])
        lane = int(hd.lane_next[lane])
    return total


def _anchors(hd: HDMap) -> tuple[np.ndarray, np.ndarray]:
    """(L,) the normal edge each lane's vehicles count on, -1 if none, and (L,) the offset of
    the lane's start from that edge's start [m]: 0 on a normal lane, minus the length of the
    junction lanes up to the edge on a junction lane."""
    edge = hd.lane_edge.astype(np.int64).copy()
    offset = np.zeros(hd.n_lanes)
    todo = np.flatnonzero(edge < 0)
    lane, run = todo.copy(), np.zeros(len(todo))
    for _ in range(MAX_JUNCTION_HOPS):
        if not len(todo):
            break
        run += hd.lane_length[lane]
        lane = hd.lane_next[lane].astype(np.int64)
        dead = lane < 0
        hit = ~dead & (hd.lane_edge[np.maximum(lane, 0)] >= 0)
        edge[todo[hit]] = hd.lane_edge[lane[hit]]
        offset[todo[hit]] = -run[hit]
        keep = ~dead & ~hit
        todo, lane, run = todo[keep], lane[keep], run[keep]
    return edge, offset


def positions(hd: HDMap, snap: TrafficSnapshot) -> tuple[np.ndarray, np.ndarray]:
    """(N,) the edge each vehicle counts on (-1 none) and (N,) its front bumper's position
    from that edge's start [m] (< 0 on the junction lanes before it)."""
    t = map_tables(hd)
    lane = snap.lane.astype(np.int64)
    safe = np.maximum(lane, 0)
    edge = np.where(lane >= 0, t.anchor_edge[safe], -1)
    return edge, snap.lane_pos + t.anchor_offset[safe]


def route_frame(hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray, routes: np.ndarray,
                route_len: np.ndarray) -> RouteFrame:  # fmt: skip
    """Each agent's route measured from the start of its current route edge.

    Args:
        rows: (A,) snapshot rows of the agents.
        routes: (A, W) their routes' edge rows, -1 padded.
        route_len: (A,) their routes' lengths [edges].
    """
    t = map_tables(hd)
    A, W = routes.shape
    edges = np.where(np.arange(W) < np.asarray(route_len)[:, None], routes, -1)
    nxt = np.concatenate([edges[:, 1:], np.full((A, 1), -1)], axis=1)
    span = np.where(edges >= 0, hd.edge_length[np.maximum(edges, 0)] + t.junction(edges, nxt), 0.0)
    cum = np.concatenate([np.zeros((A, 1)), np.cumsum(span, axis=1)[:, :-1]], axis=1)
    k = np.clip(snap.route_index[rows].astype(np.int64), 0, W - 1)
    start = cum - cum[np.arange(A), k][:, None]
    ego_edge, ego_pos = positions(hd, snap)
    ego_edge, ego_pos = ego_edge[rows], ego_pos[rows]
    k1 = np.minimum(k + 1, W - 1)
    # on the junction after its edge an agent counts on the route's next edge
    ahead = (ego_edge != edges[np.arange(A), k]) & (ego_edge == edges[np.arange(A), k1])
    ego = np.where(ahead, start[np.arange(A), k1] + ego_pos, ego_pos)
    return RouteFrame(edges, start, span, ego, k)


def route_pairs(hd: HDMap, snap: TrafficSnapshot, frame: RouteFrame, behind: float,
                ahead: float) -> Pairs:  # fmt: skip
    """Every vehicle on the route edges of each agent between ``behind`` [m] behind and
    ``ahead`` [m] ahead of it, once per occurrence of its edge in the route."""
    A = len(frame.ego)
    edge, pos = positions(hd, snap)
    lo, hi = frame.start - frame.ego[:, None], frame.start + frame.span - frame.ego[:, None]
    before = np.concatenate([np.zeros((A, 1)), frame.span[:, :-1]], axis=1)  # junction slack
    near = (frame.edges >= 0) & (hi >= -behind) & (lo - before <= ahead)
    ea, ej = np.nonzero(near)
    e, base = frame.edges[ea, ej], lo[ea, ej]
    # vehicles sorted by (edge, position): each entry's window is one searchsorted range
    t = map_tables(hd)
    on = np.flatnonzero(edge >= 0)
    key = edge[on] * t.key_stride + (pos[on] + t.key_shift)
    order = np.argsort(key, kind="stable")
    on, key = on[order], key[order]
    left = np.searchsorted(key, e * t.key_stride + np.maximum(-behind - base + t.key_shift, 0.0))
    right = np.searchsorted(
        key, e * t.key_stride + np.minimum(ahead - base + t.key_shift, t.key_stride), side="right"
    )
    n = np.maximum(right - left, 0)
    k = np.repeat(np.arange(len(e)), n)
    within = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    veh = on[left[k] + within]
    dist = base[k] + pos[veh]
    keep = (dist >= -behind) & (dist <= ahead)  # float edges of the ranges
    return Pairs(ea[k][keep], veh[keep], dist[keep], np.full(A, np.inf))


def ring_pairs(hd: HDMap, snap: TrafficSnapshot, frame: RouteFrame) -> Pairs:
    """Every vehicle with every agent once, at its distance ahead on the loop, in [0, lap).

    The loop is the agents' route up to where its current edge comes again (a ring's route
    repeats the loop); a vehicle off the loop is left out."""
    A, W = frame.edges.shape
    edge, pos = positions(hd, snap)
    idx, k = np.arange(A), frame.current
    cur = frame.edges[idx, k]
    cols = np.arange(W)[None, :]
    again = (frame.edges == cur[:, None]) & (cols > k[:, None])
    nxt = np.where(again.any(axis=1), np.argmax(again, axis=1), -1)
    lap = np.where(nxt >= 0, frame.start[idx, np.maximum(nxt, 0)], np.inf)
    # start of each edge's first occurrence from the current one on, per agent: (A, E)
    E = len(hd.edge_ids)
    in_lap = (
        (cols >= k[:, None]) & (cols < np.where(nxt >= 0, nxt, W)[:, None]) & (frame.edges >= 0)
    )
    start = np.full((A, E), np.nan)
    ia, ij = np.nonzero(in_lap)
    start[ia, frame.edges[ia, ij]] = frame.start[ia, ij]
    ok = edge >= 0
    rel = start[:, np.maximum(edge, 0)] + pos[None, :] - frame.ego[:, None]  # (A, N)
    rel = np.where(ok[None, :] & np.isfinite(lap)[:, None], rel, np.nan)
    dist = np.mod(rel, lap[:, None])
    ai, vi = np.nonzero(np.isfinite(dist))
    return Pairs(ai, vi, dist[ai, vi], lap)


def lane_metres(
    hd: HDMap, frame: RouteFrame, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(A, S) lane-metres of each agent's route between ``lo`` and ``hi`` [m] ahead of it
    ((S,) or (A, S) each; route edge lengths plus the junctions after them, times the edges'
    car lanes), and (A, S) the speed limit averaged over that length [m/s] (nan where there
    is no road)."""
    t = map_tables(hd)
    a = frame.start - frame.ego[:, None]  # (A, W)
    b = a + frame.span
    lo3 = np.reshape(lo, (-1, 1, np.shape(lo)[-1]))
    hi3 = np.reshape(hi, (-1, 1, np.shape(hi)[-1]))
    over = np.clip(np.minimum(b[..., None], hi3) - np.maximum(a[..., None], lo3), 0.0, None)
    over = np.where((frame.edges >= 0)[..., None], over, 0.0)  # (A, W, S)
    e = np.maximum(frame.edges, 0)
    metres = over.sum(axis=1)
    limit = (over * t.edge_limit[e][..., None]).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_limit = np.where(metres > 0, limit / metres, np.nan)
    return (over * t.edge_lanes[e][..., None]).sum(axis=1), mean_limit
