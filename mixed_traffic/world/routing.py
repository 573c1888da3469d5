"""Fastest free-flow paths over an ``HDMap``'s edges, for placement and fleet trips.

A city's placement asks for a path from every lane to each of its destinations: thousands.
One backward Dijkstra per destination (cached on the map) gives every edge's time to go; a
path then follows, from the lane, the successor that keeps the least time to go.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Mapping
from typing import TypeVar

import numpy as np

from mixed_traffic.world.hdmap import UTURN_PENALTY, HDMap

T = TypeVar("T")
TIE = 1e-9
"""Paths whose times differ by less than this share are equally fast [-] (sums of the same
edge times in another order differ in the last bits)."""


def fastest_path(hd: HDMap, lane: int, destination: int) -> list[int] | None:
    """Edge rows from ``lane``'s edge to ``destination`` with the least free-flow travel time
    whose first junction is one ``lane`` connects through (None: there is none); of equally
    fast paths, the one with the lowest edge rows first. A turnaround costs ``UTURN_PENALTY``
    more: drivers turn around where nothing else leads on, not to save a block."""
    e = int(hd.lane_edge[lane])
    togo, path = time_to(hd, destination), [e]
    options = hd.lane_exits.get(lane, ())
    for _ in range(len(hd.edge_ids)):  # each step gets an edge closer; a path has no repeat
        if e == destination:
            return path
        cost = {n: step_cost(hd, e, n) + togo[n] for n in options}
        best = min(cost.values(), default=np.inf)
        if not np.isfinite(best):
            return None
        e = min(n for n, c in cost.items() if c <= best * (1 + TIE))
        path.append(e)
        options = hd.edge_successors.get(e, ())
    return path if e == destination else None


def step_cost(hd: HDMap, e: int, n: int) -> float:
    """Free-flow time of entering edge ``n`` from edge ``e`` [s], a turnaround's penalty
    included."""
    return float(hd.edge_free_time[n]) + (UTURN_PENALTY if (e, n) in hd.edge_uturns else 0.0)


def time_to(hd: HDMap, destination: int) -> np.ndarray:
    """(E,) least free-flow time from the end of each edge to the end of ``destination`` [s]
    (inf: no path), by Dijkstra backwards over the edge graph; cached on ``hd``."""
    cached = hd.__dict__.setdefault("_time_to", {})
    if destination not in cached:
        before = _predecessors(hd)
        togo = np.full(len(hd.edge_ids), np.inf)
        heap = [(0.0, destination)]
        while heap:
            t, n = heapq.heappop(heap)
            if t >= togo[n]:
                continue
            togo[n] = t
            for e in before.get(n, ()):
                c = t + step_cost(hd, e, n)
                if c < togo[e]:
                    heapq.heappush(heap, (c, e))
        cached[destination] = togo
    return cached[destination]


def _predecessors(hd: HDMap) -> dict[int, list[int]]:
    """Edge row -> edge rows that reach it through one junction (cached on ``hd``)."""
    if "_predecessors" not in hd.__dict__:
        hd.__dict__["_predecessors"] = predecessors(hd.edge_successors)
    return hd.__dict__["_predecessors"]


def predecessors(succ: Mapping[T, Iterable[T]]) -> dict[T, list[T]]:
    """The graph ``succ`` (node -> successors) turned around: node -> its predecessors."""
    out: dict[T, list[T]] = {}
    for e, nxt in succ.items():
        for n in nxt:
            out.setdefault(n, []).append(e)
    return out
