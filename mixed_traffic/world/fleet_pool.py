"""A fixed fleet of AVs that serves a user's AV trips (``fixed_fleet`` on a .sumocfg).

PettingZoo never revives an agent within an episode ("agent cannot be revived once dead" in
``parallel_api_test``), so by default every AV trip of a .sumocfg is its own agent. With
``fixed_fleet=True`` agents never end, and a pool of K agents can drive the trips in turn:

- K, the pool size, is the peak number of AV trips under way at once when each takes
  ``SLACK`` times its free-flow time, times the penetration (``pool_size``). It depends on
  the file and the config only, never on the seed, so ``possible_agents`` is fixed.
- At its departure time a trip takes the free agent with the lowest number, which enters
  under its own id on the trip's route. A trip that finds every agent on the road waits for
  one, first come first served (``FleetPool.waits``).
- An agent whose vehicle arrives, collides or is removed is free again.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.drivers import AV_TYPE
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.routing import fastest_path
from mixed_traffic.world.scenario import Route, Scenario
from mixed_traffic.world.snapshot import TrafficSnapshot

SLACK = 4.0
"""A trip is assumed to take at most this many times its free-flow time when sizing the pool;
slower trips make later ones wait for a free agent [-]."""


@dataclass(frozen=True)
class FleetTrip:
    """One AV trip of the user's file."""

    depart: float
    """Departure time [s of SUMO time]."""
    route: int
    """Index into ``Demand.routes``."""


def free_flow_time(hd: HDMap, route: Route) -> float:
    """Free-flow travel time of ``route`` [s] (a from/to trip: along its fastest path)."""
    if route.edges:
        rows = [hd.edge_of(e) for e in route.edges]
    else:
        origin = hd.edge_of(route.origin)
        lanes = hd.car_lane_rows(origin)
        path = fastest_path(hd, lanes[0], hd.edge_of(route.destination)) if lanes else None
        rows = path or [origin]
    return float(hd.edge_free_time[rows].sum())


def pool_size(scenario: Scenario, penetration: float, episode_length: float) -> int:
    """Agents of the pool (see the module docstring): at least one if any trip is an AV,
    never more than the AV trips of the episode."""
    own = scenario.own_in_episode(episode_length)
    n_av = int(round(penetration * len(own)))
    if n_av == 0:
        return 0
    hd, routes = scenario.hdmap, scenario.routes
    duration = {r: SLACK * free_flow_time(hd, routes[r]) for r in {v.route for v in own}}
    events = sorted(
        [(v.depart, 1) for v in own] + [(v.depart + duration[v.route], -1) for v in own]
    )
    peak = int(np.cumsum([d for _, d in events]).max())
    return min(n_av, max(1, math.ceil(penetration * peak)))


@dataclass
class FleetPool:
    """Hands the user's AV trips to the agents ``names`` as they become free.

    Args:
        names: the fleet's agent ids (SUMO vehicle ids), ``av_0 … av_{K-1}``.
        trips: the AV trips, in departure order.
        route_ids: SUMO route id of each route index.
        destinations: destination edge of each from/to route ("" for explicit routes).
        begin: SUMO time of the episode's start [s] (snapshot times count from there).
    """

    names: list[str]
    trips: list[FleetTrip]
    route_ids: list[str]
    destinations: list[str]
    begin: float = 0.0
    waits: list[float] = field(default_factory=list)
    """Seconds each trip served so far waited for a free agent [s]."""
    _free: list[int] = field(default_factory=list)
    _pending: deque = field(default_factory=deque)
    _next: int = 0

    @classmethod
    def for_trips(
        cls, names: list[str], trips: tuple[FleetTrip, ...], routes: tuple[Route, ...], begin: float
    ) -> FleetPool:
        """The pool of ``names`` for ``trips`` on ``routes`` (route ``r{i}`` of the route file)."""
        return cls(list(names), list(trips), [f"r{i}" for i in range(len(routes))],
                   [r.destination for r in routes], begin)  # fmt: skip

    def __post_init__(self) -> None:
        self._free = list(range(len(self.names)))  # a sorted list is a heap
        self._index = {n: i for i, n in enumerate(self.names)}

    def step(self, snap: TrafficSnapshot, backend: SumoBackend) -> None:
        """After a SUMO step: free the agents that arrived or collided, then send the trips
        that are due to free agents."""
        self.replace(backend, snap.left)
        self._dispatch(backend, self.begin + snap.time)

    def replace(self, backend: SumoBackend, gone: list[str]) -> None:
        """Free the agents among ``gone`` (vehicles that left the road); others are ignored."""
        for vid in dict.fromkeys(gone):
            k = self._index.get(vid)
            if k is not None and k not in self._free:
                heapq.heappush(self._free, k)

    @property
    def unserved(self) -> int:
        """Trips due that still wait for an agent."""
        return len(self._pending)

    def summary(self) -> dict[str, float | int | None]:
        """Trips served, their mean wait for a free agent [s], and trips still waiting."""
        wait = float(np.mean(self.waits)) if self.waits else None
        return {
            "fleet_trips": len(self.waits),
            "fleet_wait_s": wait,
            "fleet_unserved": self.unserved,
        }

    def _dispatch(self, backend: SumoBackend, now: float) -> None:
        while self._next < len(self.trips) and self.trips[self._next].depart <= now + 1e-9:
            self._pending.append(self.trips[self._next])
            self._next += 1
        while self._pending and self._free:
            trip = self._pending.popleft()
            name = self.names[heapq.heappop(self._free)]
            self.waits.append(max(0.0, now - trip.depart))
            backend.add_vehicle(name, self.route_ids[trip.route], AV_TYPE, "base", "free", "last",
                                self.destinations[trip.route])  # fmt: skip
