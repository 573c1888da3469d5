"""Vectorised lookups over an HD map for the sensors: connections, signals, neighbour
lanes, predecessors and successor chains (``LaneGraph``, built once per map).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mixed_traffic.world.hdmap import HDMap

#: Lanes followed ahead (and behind) of a lane when looking for a leader (follower).
SEARCH_DEPTH = 4
#: Column of each lane in the (A, 3) lane arrays.
LEFT, CURRENT, RIGHT = 0, 1, 2


@dataclass
class LaneGraph:
    """Vectorised lookups over an HDMap, built once per map (``lane_graph(hdmap)``)."""

    n_edges: int
    conn_keys: np.ndarray
    """(C,) sorted keys lane * E + next_edge of ``hdmap.conn_to``."""
    conn_vals: np.ndarray
    """(C,) first lane row to take."""
    tls_keys: np.ndarray
    """(T,) sorted keys lane * E + next_edge of ``hdmap.tls_links``."""
    tls_tl: np.ndarray
    """(T,) index into ``tls_ids``."""
    tls_link: np.ndarray
    """(T,) link index within that light's state string."""
    tls_ids: list[str]
    pred: np.ndarray
    """(L,) one predecessor lane row (-1 if none)."""
    next_edge: np.ndarray
    """(L,) first normal edge reached by following primary successors (-1 if none)."""
    lane_offset_key: float
    """Multiplier of the lane row in the (lane, position) sort key [m]."""
    lane3: np.ndarray
    """(L, 3) (left neighbour, lane, right neighbour) of each lane row, -1 where none (a
    per-step ``neighbour_lane`` becomes one lookup)."""
    junction: np.ndarray
    """(L,) junction number of each internal lane, -1 for normal lanes."""
    entry_junction: np.ndarray
    """(L,) junction number at the start of each normal lane (the junction its incoming
    internal lanes belong to), -1 for internal lanes and lanes no junction feeds."""
    chain: np.ndarray
    """(L, SEARCH_DEPTH) the lane and its primary successors (``lane_next``), -1 padded."""
    chain_start: np.ndarray
    """(L, SEARCH_DEPTH) distance from the lane's start to the start of each of them [m]."""

    def connection(self, lane: np.ndarray, edge: np.ndarray) -> np.ndarray:
        """(...) first lane row of the connection lane -> edge, -1 if there is none."""
        found, i = self._find(self.conn_keys, lane, edge)
        if len(self.conn_vals) == 0:  # a network without junctions (a single edge)
            return np.full(found.shape, -1, dtype=np.int64)
        return np.where(found, self.conn_vals[np.minimum(i, len(self.conn_vals) - 1)], -1)

    def signal(self, lane: np.ndarray, edge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(...) light index into ``tls_ids`` and link index of lane -> edge (-1, -1 if none)."""
        if len(self.tls_keys) == 0:  # a network without signals: nothing to look up
            shape = np.broadcast_shapes(np.shape(lane), np.shape(edge))
            return np.full(shape, -1), np.full(shape, -1)
        found, i = self._find(self.tls_keys, lane, edge)
        i = np.minimum(i, len(self.tls_keys) - 1)
        return np.where(found, self.tls_tl[i], -1), np.where(found, self.tls_link[i], -1)

    def _find(self, keys: np.ndarray, lane: np.ndarray, edge: np.ndarray):
        lane = np.asarray(lane, dtype=np.int64)
        edge = np.asarray(edge, dtype=np.int64)
        key = lane * self.n_edges + edge
        i = np.searchsorted(keys, key)
        ok = (lane >= 0) & (edge >= 0) & (i < len(keys))
        found = (
            ok & (keys[np.minimum(i, max(len(keys) - 1, 0))] == key) if len(keys) else ok & False
        )
        return found, i


def lane_graph(hdmap: HDMap) -> LaneGraph:
    """The (cached) ``LaneGraph`` of ``hdmap``."""
    cached = hdmap.__dict__.get("_lane_graph")
    if cached is None:
        cached = _build_lane_graph(hdmap)
        hdmap.__dict__["_lane_graph"] = cached
    return cached


def _build_lane_graph(hd: HDMap) -> LaneGraph:
    E, L = len(hd.edge_ids), hd.n_lanes
    conn = sorted((a * E + b, c) for (a, b), c in hd.conn_to.items())
    names = sorted({t for t, _ in hd.tls_links.values()})
    tl_row = {t: i for i, t in enumerate(names)}
    tls = sorted((a * E + b, tl_row[t], k) for (a, b), (t, k) in hd.tls_links.items())
    # predecessor: prefer a straight-on (primary) link from a lane with the same index
    pred = np.full(L, -1, dtype=np.int64)
    for src in np.argsort(
        hd.lane_index != hd.lane_index[np.maximum(hd.lane_next, 0)], kind="stable"
    ):
        dst = hd.lane_next[src]
        if dst >= 0 and pred[dst] < 0:
            pred[dst] = src
    nxt_edge = np.full(L, -1, dtype=np.int64)
    lane = hd.lane_next.astype(np.int64)
    for _ in range(SEARCH_DEPTH):
        edge = np.where(lane >= 0, hd.lane_edge[np.maximum(lane, 0)], -1)
        nxt_edge = np.where((nxt_edge < 0) & (edge >= 0), edge, nxt_edge)
        lane = np.where(lane >= 0, hd.lane_next[np.maximum(lane, 0)], -1)
    return LaneGraph(
        n_edges=E,
        conn_keys=np.array([k for k, _ in conn], dtype=np.int64),
        conn_vals=np.array([v for _, v in conn], dtype=np.int64),
        tls_keys=np.array([k for k, _, _ in tls], dtype=np.int64),
        tls_tl=np.array([t for _, t, _ in tls], dtype=np.int64),
        tls_link=np.array([i for _, _, i in tls], dtype=np.int64),
        tls_ids=names,
        pred=pred,
        next_edge=nxt_edge,
        lane_offset_key=float(np.ceil(hd.lane_length.max()) + 10.0),
        lane3=np.stack([hd.neighbour_lane(np.arange(L), +1), np.arange(L),
                        hd.neighbour_lane(np.arange(L), -1)], axis=1).astype(np.int64),
        junction=(junction := _lane_junctions(hd)),
        entry_junction=_entry_junctions(hd, junction),
        **_successor_chains(hd),
    )  # fmt: skip


def _lane_junctions(hd: HDMap) -> np.ndarray:
    """(L,) junction number of each internal lane (-1 for normal lanes), from SUMO's internal
    lane ids ``:<junction>_<edge index>_<lane index>``."""
    names: dict[str, int] = {}
    out = np.full(hd.n_lanes, -1, dtype=np.int64)
    for row in np.flatnonzero(hd.lane_edge < 0).tolist():
        name = hd.lane_ids[row].lstrip(":").rsplit("_", 2)[0]
        out[row] = names.setdefault(name, len(names))
    return out


def _successor_chains(hd: HDMap) -> dict[str, np.ndarray]:
    """``chain`` and ``chain_start`` of ``LaneGraph``."""
    L = hd.n_lanes
    chain = np.full((L, SEARCH_DEPTH), -1, dtype=np.int64)
    start = np.full((L, SEARCH_DEPTH), np.inf)
    chain[:, 0], start[:, 0] = np.arange(L), 0.0
    for k in range(1, SEARCH_DEPTH):
        prev = chain[:, k - 1]
        nxt = np.where(prev >= 0, hd.lane_next[np.maximum(prev, 0)], -1)
        chain[:, k] = nxt
        start[:, k] = np.where(
            nxt >= 0, start[:, k - 1] + hd.lane_length[np.maximum(prev, 0)], np.inf
        )
    return {"chain": chain, "chain_start": start}


def _entry_junctions(hd: HDMap, junction: np.ndarray) -> np.ndarray:
    """(L,) junction of the internal lanes leading into each normal lane, -1 if none."""
    out = np.full(hd.n_lanes, -1, dtype=np.int64)
    src = np.flatnonzero((junction >= 0) & (hd.lane_next >= 0))
    dst = hd.lane_next[src].astype(np.int64)
    normal = hd.lane_edge[dst] >= 0
    out[dst[normal]] = junction[src[normal]]
    return out


def tls_ids(hdmap: HDMap) -> list[str]:
    """Traffic-light ids whose state strings ``Perception.sense`` expects, in this order."""
    return lane_graph(hdmap).tls_ids


def next_route_edge(routes: Sequence[Sequence[int]], route_index: np.ndarray) -> np.ndarray:
    """(A,) int64 edge row after the current one on each agent's route, -1 on the last edge.

    Args:
        routes: per agent, the edge rows of its route (``HDMap.edge_row`` of each edge id), or
            (A, W) such rows padded with -1 (the env's route table; one gather, no loop).
        route_index: (A,) index of the current (or last normal) edge within the route.
    """
    if isinstance(routes, np.ndarray):
        k = np.asarray(route_index, np.int64) + 1
        inside = (k >= 0) & (k < routes.shape[1])
        return np.where(inside, routes[np.arange(len(k)), np.clip(k, 0, routes.shape[1] - 1)], -1)
    nxt = (
        r[k] if 0 <= k < len(r) else -1
        for r, k in zip(routes, (np.asarray(route_index) + 1).tolist())
    )
    return np.fromiter(nxt, np.int64, len(routes))
