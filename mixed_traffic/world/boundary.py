"""Boundary conditions that keep the target density during an episode.

An open road cannot hold a congested state: its downstream end discharges at capacity and the
jam dissolves. The periodic boundary used here makes the road behave like a ring without
bending it: each vehicle that leaves at the end is replaced by the next planned vehicle at the
entry (same lane), and the conventional vehicle at the head of each exit lane follows, by IDM,
a *virtual leader*: the rearmost vehicle of the same lane at the entry, one road length ahead.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mixed_traffic.config import HumanConfig
from mixed_traffic.world.backend import SumoBackend
from mixed_traffic.world.demand import Demand, QueuedVehicle
from mixed_traffic.world.fleet_pool import FleetPool
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.scenario import Scenario
from mixed_traffic.world.snapshot import TrafficSnapshot


@dataclass
class PeriodicBoundary:
    """Re-inserts leaving vehicles upstream and (if ``virtual_leader``) closes the road into a ring.

    Args:
        hdmap: the network.
        entry_edges: entry edge of each route (``route_ids[i]`` starts on ``entry_edges[i]``).
        exit_edge: last edge of the main road (vehicles leave at its end), or "" for none.
        queue: vehicles to insert, in order.
        road_length: entry start to exit end along the main road [m].
    """

    hdmap: HDMap
    route_ids: list[str]
    destinations: list[str]
    """Destination of trip routes (routed by SUMO), "" for explicit routes."""
    entry_edges: list[str]
    exit_edge: str
    queue: list[QueuedVehicle]
    road_length: float
    human: HumanConfig
    """The drivers whose mean parameters the virtual leader's follower uses."""
    virtual_leader: bool = True
    fixed_fleet: bool = False
    dt: float = 0.1
    _next: int = 0
    _held: set[str] = field(default_factory=set)

    def step(
        self, snap: TrafficSnapshot, backend: SumoBackend, left: list[str] | None = None
    ) -> None:
        """After a step: replace vehicles that arrived or collided (``left``: those of this
        road, default all that left), and hold the exit heads."""
        self.replace(backend, snap.left if left is None else left)
        if self.virtual_leader and self.exit_edge:
            self._hold_heads(snap, backend)

    def replace(self, backend: SumoBackend, gone: list[str]) -> None:
        """Insert one vehicle at the entry for each vehicle in ``gone`` (which left the road).

        With ``fixed_fleet`` an AV re-enters under its own id; otherwise the next queued
        vehicle enters (nothing once the queue is used up).
        """
        for vid in gone:
            if self.fixed_fleet and vid.startswith("av_"):
                backend.add_vehicle(vid, self.route_ids[0], "av", "base", "free", "last",
                                    self.destinations[0])  # fmt: skip
                continue
            if self._next >= len(self.queue):
                continue
            q = self.queue[self._next]
            self._next += 1
            vtype = q.vtype or ("av" if q.is_av else "hv")
            backend.add_vehicle(q.vid, self.route_ids[q.route], vtype, "base", "free", "last",
                                self.destinations[q.route])  # fmt: skip

    def _hold_heads(self, snap: TrafficSnapshot, backend: SumoBackend) -> None:
        hd = self.hdmap
        ex, en = hd.edge_of(self.exit_edge), hd.edge_of(self.entry_edges[0])
        exit_len = float(hd.edge_length[ex])
        held_now: set[str] = set()
        for k in range(int(hd.edge_num_lanes[ex])):
            on_exit = np.flatnonzero((snap.edge == ex) & (snap.lane_index == k))
            if len(on_exit) == 0:
                continue
            head = on_exit[np.argmax(snap.lane_pos[on_exit])]
            if snap.is_av[head]:
                continue
            k_en = min(k, int(hd.edge_num_lanes[en]) - 1)
            on_entry = np.flatnonzero((snap.edge == en) & (snap.lane_index == k_en))
            if len(on_entry) == 0:
                continue
            tail = on_entry[np.argmin(snap.lane_pos[on_entry])]
            # a vehicle leaving at the exit end re-enters with its front at one length (base)
            gap = exit_len - snap.lane_pos[head] + snap.lane_pos[tail] - snap.length[tail]
            gap -= snap.length[head]
            v = self._idm_speed(float(snap.speed[head]), float(snap.speed[tail]), float(gap),
                                float(hd.lane_speed[hd.edge_lanes[ex, k]]))  # fmt: skip
            vid = snap.ids[head]
            backend.set_speeds([vid], np.array([v]))
            held_now.add(vid)
        for vid in self._held - held_now:
            backend.release_speed(vid)
        self._held = held_now

    def _idm_speed(self, v: float, v_lead: float, gap: float, v0: float) -> float:
        acc = self.human.idm_accel(v, v_lead, gap, v0)
        return float(max(0.0, v + max(acc, -9.0) * self.dt))

    @classmethod
    def for_demand(
        cls,
        scenario: Scenario,
        demand: Demand,
        human: HumanConfig,
        dt: float,
        fixed_fleet: bool,
        first_route: int = 0,
    ) -> PeriodicBoundary:
        """The boundary of ``scenario``'s road, whose routes are ``r<first_route>`` on in the
        route file."""
        hd = scenario.hdmap
        main = scenario.routes[0]
        return cls(
            hdmap=hd,
            route_ids=[f"r{first_route + i}" for i in range(len(scenario.routes))],
            destinations=[r.destination for r in scenario.routes],
            entry_edges=[r.entry for r in scenario.routes],
            exit_edge=main.edges[-1] if main.edges else "",
            queue=list(demand.queue),
            road_length=float(sum(hd.edge_length[hd.edge_of(e)] for e in main.edges)),
            human=human,
            virtual_leader=scenario.periodic,
            fixed_fleet=fixed_fleet,
            dt=dt,
        )

    @property
    def inserted(self) -> int:
        """Queued vehicles inserted so far."""
        return self._next


def make_boundary(
    scenario: Scenario,
    demand: Demand,
    human: HumanConfig,
    dt: float,
    fleet: list[str] | None,
    first_route: int = 0,
) -> PeriodicBoundary | FleetPool:
    """What brings vehicles in during an episode: the fixed ``fleet`` (agent ids) driving a
    user's AV trips in turn, else the periodic boundary (``fleet`` None: no fixed fleet;
    ``first_route``: the route file's index of the scenario's first route)."""
    if fleet is not None and scenario.own_vehicles:
        return FleetPool.for_trips(fleet, demand.fleet_trips, demand.routes, scenario.begin)
    return PeriodicBoundary.for_demand(scenario, demand, human, dt, fleet is not None,
                                       first_route)  # fmt: skip
