"""Where vehicles can be placed at reset, and how fast they may depart, so that SUMO inserts
every one of them at t = 0 (it refuses a vehicle that would have to change lanes before its
next junction, brake for its leader, or could not slow down for a slower lane or a lane end).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from mixed_traffic.config import HumanConfig
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.routing import fastest_path
from mixed_traffic.world.scenario import Route

DEPART_SHARE = 0.95
"""Placed vehicles depart at most at this share of their desired speed [-] (measured: SUMO
refuses some that depart at their desired speed on a lane they must leave soon, "too many lane
changes required", but not at 0.95 of it)."""


def lane_route(hd: HDMap, lane: int, route: Route, edge: str) -> tuple[str, ...] | None:
    """The edges of ``route`` from ``edge`` on, if a vehicle on ``lane`` can follow them without
    changing lanes before the junction (SUMO refuses to insert it otherwise: "too many lane
    changes required"); origin/destination routes take the fastest such path. None: none."""
    if not route.edges:
        path = fastest_path(hd, lane, hd.edge_row[route.destination])
        return None if path is None else tuple(hd.edge_ids[e] for e in path)
    rest = route.edges[route.edges.index(edge) :] if edge in route.edges else ()
    if len(rest) == 1 or (len(rest) > 1 and (lane, hd.edge_row[rest[1]]) in hd.conn_to):
        return rest
    return None


class RouteIndex:
    """Index of the route with exactly some edges in a growing list (appended once); a dict
    kept in step with the list, since a city places thousands of vehicles on their own paths."""

    def __init__(self, routes: list[Route]) -> None:
        self.routes = routes
        self._known: dict[tuple[str, ...], int] = {}
        self._seen = 0

    def __call__(self, edges: tuple[str, ...]) -> int:
        routes, known = self.routes, self._known
        for i in range(self._seen, len(routes)):  # routes others appended: the first one counts
            known.setdefault(routes[i].edges, i)
        if edges not in known:
            routes.append(Route(edges=edges, weight=0.0))
            known[edges] = len(routes) - 1
        self._seen = len(routes)
        return known[edges]


class Placed(NamedTuple):
    """A vehicle placed at reset, before its departure speed is capped."""

    route: int
    pos: float
    """Position on its edge [m]."""
    lane: int
    """Lane index on its edge."""
    row: int
    """Lane row in the HD map."""
    speed: float
    """Speed its lane end or red light allows [m/s]."""
    limits: list[tuple[float, float]]
    """[(distance [m], limit [m/s])] of its lane and of slower lanes ahead."""


def cap_followers(
    planned: list[Placed],
    order: list[int],
    speed: list[float],
    upstream: dict[int, tuple[int, float]],
    tail: dict[int, float],
    human: HumanConfig,
    length: float,
) -> None:
    """Lower ``speed`` (per planned vehicle, [m/s]) until every vehicle can follow its leader,
    also across junctions: SUMO refuses a vehicle that would have to brake for its leader, or
    one whose follower would (speeds fall towards a red light or a lane end). ``order``:
    downstream first; ``tail``: lane row -> distance [m] from its last vehicle to its end."""
    lanes: dict[int, list[int]] = {}  # lane row -> its vehicles, downstream first
    for i in order:
        lanes.setdefault(planned[i].row, []).append(i)
    pairs = []  # (leader, follower, gap [m])
    for row, ids in lanes.items():
        pairs += [(a, b, planned[a].pos - planned[b].pos - length) for a, b in zip(ids, ids[1:])]
        prev, junction = upstream.get(row, (-1, 0.0))
        if prev in lanes:  # the last vehicle on the lane before follows the first one here
            gap = tail[prev] + junction + planned[ids[-1]].pos - length
            pairs.append((ids[-1], lanes[prev][0], gap))
    changed = True
    while changed:  # caps only fall: a few sweeps settle chains of slow leaders
        changed = False
        for a, b, gap in pairs:
            cap = follow_cap(gap, speed[a], human)
            if cap < speed[b]:
                speed[b], changed = cap, True


def follow_cap(gap: float, v_lead: float, human: HumanConfig) -> float:
    """Highest speed [m/s] at which IDM's desired gap s0 + vT + v(v − v_lead)/2√(ab) fits in
    ``gap`` [m] behind a leader at ``v_lead`` [m/s] (1 cm/s below, see ``departure_cap``)."""
    c = 2.0 * math.sqrt(human.accel * human.decel)
    p = human.headway * c - v_lead  # v² + p·v + c·(s0 − gap) ≤ 0
    q = c * (human.min_gap - gap)
    return max(0.0, 0.5 * (-p + math.sqrt(max(0.0, p * p - 4.0 * q))) - 0.01)


def upstream_lanes(hd: HDMap) -> dict[int, tuple[int, float]]:
    """Lane row -> (the road lane that leads into it, length [m] of the junction lanes between)."""
    out: dict[int, tuple[int, float]] = {}
    for lane in np.flatnonzero(hd.lane_edge >= 0):
        nxt, junction = int(hd.lane_next[lane]), 0.0
        while nxt >= 0 and hd.lane_edge[nxt] < 0:  # internal (junction) lanes
            junction += float(hd.lane_length[nxt])
            nxt = int(hd.lane_next[nxt])
        if nxt >= 0:
            out.setdefault(nxt, (int(lane), junction))
    return out


def departure_cap(factor: float, limits: list[tuple[float, float]], human: HumanConfig) -> float:
    """Highest departure speed [m/s] SUMO accepts for a vehicle with speed ``factor`` [-] before
    lanes with lower limits ``limits`` ([(distance [m], limit [m/s])]): factor × limit, unless
    it could still stop before that lane (measured: SUMO's IDM insertion check asks for the stop
    distance v²/2b + vT, not just enough room to slow down). 1 cm/s below, as the route file
    rounds speeds to 2 decimals."""
    b, t = human.decel, human.headway

    def stop_speed(d: float) -> float:  # v with v²/2b + vT + s0 = d
        return b * (math.sqrt(t * t + 2.0 * max(0.0, d - human.min_gap) / b) - t)

    return min(max(DEPART_SHARE * factor * v, stop_speed(d)) for d, v in limits) - 0.01


def lane_ahead(
    hd: HDMap, lane: int, pos: float, last_edge: int
) -> tuple[float, list[tuple[float, float]]]:
    """From ``pos`` on ``lane``: (distance [m] to where the lane chain ends, inf: it continues
    into the route's last edge; [(distance [m], speed limit [m/s])] of the lanes ahead that are
    slower than the one before them)."""
    d = float(hd.lane_length[lane]) - pos
    slower: list[tuple[float, float]] = []
    for _ in range(6):  # a few hops (normal -> internal -> normal) are enough for placement
        if hd.lane_edge[lane] == last_edge:
            return math.inf, slower
        nxt = int(hd.lane_next[lane])
        if nxt < 0:
            return d, slower
        if hd.lane_speed[nxt] < hd.lane_speed[lane]:
            slower.append((d, float(hd.lane_speed[nxt])))
        lane = nxt
        d += float(hd.lane_length[lane])
    return math.inf, slower


def suffix_route(routes: list[Route], r: int, edge: str) -> int:
    """Index of a route that starts at ``edge`` and follows route r from there (appended once)."""
    route = routes[r]
    if not route.edges:
        suffix = Route(origin=edge, destination=route.destination, weight=0.0)
    else:
        suffix = Route(edges=route.edges[route.edges.index(edge) :], weight=0.0)
    if route.edges and suffix.edges == route.edges:
        return r
    if suffix not in routes:
        routes.append(suffix)
    return routes.index(suffix)
