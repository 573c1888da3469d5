"""Demand of one episode: the vehicles placed at reset and the queue that enters later.

Density k [veh/km summed over lanes] fixes the initial placement on every road edge and,
through the IDM equilibrium speed at that density, the inflow q = k·v_eq at the entries: on
an ``inflow`` scenario the later vehicles enter on a timetable at that rate, elsewhere each
replaces one that left (``boundary``).
Penetration p makes exactly round(p·N) of the N planned vehicles AVs (``av_0…``), chosen by
the seed; conventional vehicles are ``hv_0…``. SUMO inserts every placed vehicle at t = 0 (the
spacing continues across junctions, and departure speeds respect each vehicle's speed factor,
slower lanes ahead and its leader): one it refused would wait and appear mid-road later.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from mixed_traffic.config import EnvConfig, HumanConfig
from mixed_traffic.world.drivers import (
    AV_TYPE,
    HUMAN_TYPE,
    SPEED_FACTOR_RANGE,
    add_vehicle_types,
    cautious,
)
from mixed_traffic.world.fleet_pool import FleetTrip, pool_size
from mixed_traffic.world.hdmap import CAR, HDMap
from mixed_traffic.world.placement import (
    Placed,
    RouteIndex,
    cap_followers,
    departure_cap,
    lane_ahead,
    lane_route,
    suffix_route,
    upstream_lanes,
)
from mixed_traffic.world.ring import ring_counts, ring_lengths, ring_positions
from mixed_traffic.world.scenario import Route, Scenario


@dataclass(frozen=True)
class PlannedVehicle:
    vid: str
    depart: float
    """Departure time [s]."""
    route: int
    """Index into ``Demand.routes``."""
    is_av: bool
    depart_pos: float | None = None
    """Position on the route's first edge [m]; None = at the entry."""
    depart_lane: int | None = None
    depart_speed: float | str | None = None
    """Departure speed [m/s], or a SUMO keyword (``max``: the highest safe speed); None = the
    speed of the last vehicle on the lane (SUMO's ``last``)."""
    speed_factor: float | None = None
    """Desired speed / speed limit [-]; None = SUMO draws it from the vehicle type."""
    vtype: str | None = None
    """A user's vType (a .sumocfg's vehicle; "" = SUMO's default); None = the env's types."""


@dataclass(frozen=True)
class QueuedVehicle:
    """A vehicle that enters when one leaves (see ``boundary.PeriodicBoundary``)."""

    vid: str
    route: int
    is_av: bool
    vtype: str | None = None
    """Its vType id; None = the env's types (a human's drawn from the population)."""


@dataclass(frozen=True)
class Demand:
    """All vehicles of one episode, in departure order."""

    routes: tuple[Route, ...]
    vehicles: tuple[PlannedVehicle, ...]
    """Vehicles placed at reset, downstream first."""
    queue: tuple[QueuedVehicle, ...]
    """Vehicles that enter later, each replacing one that left (see ``boundary``)."""
    equilibrium_speed: float
    """IDM equilibrium speed at the target density [m/s]."""
    inflow: float
    """Total inflow [veh/s]."""
    fleet_trips: tuple[FleetTrip, ...] = ()
    """A .sumocfg's AV trips that a fixed fleet drives in turn (``fleet_pool``)."""

    @property
    def placed_ids(self) -> frozenset[str]:
        """Vehicles placed on the road at reset (a given position, not an entry)."""
        return frozenset(v.vid for v in self.vehicles if v.depart_pos is not None)

    @property
    def av_ids(self) -> list[str]:
        """All AV ids of the episode (placed and queued), ``av_0 … av_{N-1}``."""
        return [v.vid for v in (*self.vehicles, *self.queue) if v.is_av]


def fastest_limit(hd: HDMap, edge: str) -> float:
    """The limit [m/s] of the fastest car lane of the edge named ``edge``."""
    return float(hd.lane_speed[hd.car_lane_rows(hd.edge_of(edge))].max())


def uniform_flow_speed(scenario: Scenario, config: EnvConfig, ring_length: float,
                       vehicles: int | None = None) -> float:  # fmt: skip
    """Speed [m/s] of the ring's uniform flow: ``vehicles`` (default ``config.ring_vehicles``)
    evenly spaced on ``scenario`` (a ring) of ``ring_length`` [m] per lane, each at the IDM
    equilibrium speed of that spacing (the human model's T and s0, the limit as desired
    speed)."""
    limit = fastest_limit(scenario.hdmap, scenario.routes[0].entry)
    spacing = ring_length * scenario.lanes / (vehicles or config.ring_vehicles)
    return idm_equilibrium_speed(spacing, limit, config.human, config.vehicle.length)


def reference_speed(scenario: Scenario, config: EnvConfig, ring_length: float | None,
                    demand: Demand) -> float:  # fmt: skip
    """The speed [m/s] r8_uniform_flow pays for: on a ring the uniform flow of the vehicles
    ``demand`` places on it, elsewhere 0 (each lane's limit)."""
    if not scenario.ring or not demand.placed_ids or ring_length is None:
        return 0.0
    return uniform_flow_speed(scenario, config, ring_length, len(demand.placed_ids))


def idm_equilibrium_speed(spacing: float, v0: float, human: HumanConfig, length: float) -> float:
    """Speed [m/s] at which IDM keeps a constant ``spacing`` [m] (front to front) between
    vehicles of ``length`` [m]."""
    gap = spacing - length
    if gap <= human.min_gap:
        return 0.0
    lo, hi = 0.0, v0
    for _ in range(60):
        v = 0.5 * (lo + hi)
        s_star = human.min_gap + v * human.headway
        needed = s_star / math.sqrt(max(1e-12, 1.0 - (v / v0) ** human.delta))
        lo, hi = (v, hi) if needed < gap else (lo, v)
    return lo


@dataclass(frozen=True)
class _Plan:
    """What the density fixes before any random draw: inflow and the equilibrium speed."""

    per_lane: float
    """Target density per lane [veh/m]."""
    v_eq: float
    """IDM equilibrium speed at the target density [m/s]."""
    inflow: float
    """Total inflow at the entries [veh/s]."""
    n_queue: int
    """Vehicles that enter later: queued to replace those that leave (1.5 x the inflow over the
    episode, plus slack), or on an inflow scenario's timetable (the inflow over the episode)."""


def _plan(scenario: Scenario, config: EnvConfig) -> _Plan:
    hd = scenario.hdmap
    per_lane = config.density / scenario.lanes / 1000.0  # veh/m per lane
    if scenario.ring and config.ring_vehicles is not None:  # the count, whatever the length
        per_lane = config.ring_vehicles / sum(ring_lengths(scenario))
    entry = hd.car_lane_rows(hd.edge_of(scenario.routes[0].entry))
    speed_limit = float(hd.lane_speed[entry[0]])
    v_eq = idm_equilibrium_speed(1.0 / per_lane, speed_limit, cautious(config.human),
                                 config.vehicle.length)  # fmt: skip
    if scenario.ring:  # closed: nobody enters
        return _Plan(per_lane, v_eq, 0.0, 0)
    inflow = per_lane * scenario.lanes * v_eq if v_eq > 0 else 0.0
    if scenario.inflow:  # a timetable: the count must not depend on the seed
        return _Plan(per_lane, v_eq, inflow, int(math.floor(inflow * config.episode_length)))
    n_queue = int(math.ceil(1.5 * inflow * config.episode_length)) + 4 * scenario.lanes
    return _Plan(per_lane, v_eq, inflow, n_queue)


def _laps(scenario: Scenario, config: EnvConfig) -> Scenario:
    """A ring scenario whose route repeats the loop for longer than anyone can drive in the
    episode (at the fastest lane's limit x the highest speed factor, plus two laps)."""
    hd, loop = scenario.hdmap, scenario.routes[0].edges
    rows = [hd.edge_of(e) for e in loop]
    length = float(hd.edge_length[rows].sum())
    lanes = hd.edge_lanes[rows]
    v_max = float(hd.lane_speed[lanes[lanes >= 0]].max()) * SPEED_FACTOR_RANGE[1]
    laps = math.ceil(v_max * config.episode_length / length) + 2
    return replace(scenario, routes=(Route(edges=loop * laps),))


def _placement_edges(scenario: Scenario) -> tuple[str, ...]:
    edges = (e for r in scenario.routes for e in r.edges)
    return scenario.placement_edges or tuple(dict.fromkeys(edges))


def _lane_count(length: float, per_lane: float) -> int:
    """Vehicles placed on a lane of ``length`` [m]: independent of the seed, so that
    ``possible_agents`` is fixed for a config."""
    return round(length * per_lane)


def av_count(scenario: Scenario, config: EnvConfig) -> int:
    """Number of AVs ``make_demand`` plans for ``config`` under any seed (without drawing it)."""
    if scenario.own_vehicles and config.fixed_fleet:
        return pool_size(scenario, config.penetration, config.episode_length)
    if scenario.own_vehicles:
        return int(round(config.penetration * len(scenario.own_in_episode(config.episode_length))))
    plan, hd = _plan(scenario, config), scenario.hdmap
    n_init = sum(ring_counts(scenario, plan.per_lane)) if scenario.ring else 0
    for edge in () if scenario.ring else _placement_edges(scenario):
        e = hd.edge_of(edge)
        n_init += int(hd.edge_car_lanes[e]) * _lane_count(float(hd.edge_length[e]), plan.per_lane)
    if config.fixed_fleet:
        return int(round(config.penetration * n_init))
    return int(round(config.penetration * (n_init + plan.n_queue)))


def make_demand(scenario: Scenario, config: EnvConfig, rng: np.random.Generator) -> Demand:
    """Initial placement plus entry inflow for one episode of ``config`` (density checked by
    the caller: ``Scenario.check_density``)."""
    if scenario.own_vehicles:
        return _own_demand(scenario, config, rng)
    if scenario.ring:
        scenario = _laps(scenario, config)
    plan = _plan(scenario, config)
    routes = list(scenario.routes)
    weights = np.array([r.weight for r in routes], dtype=float)
    weights /= weights.sum()
    placed = _Placement(scenario, config, plan, rng, routes, weights)
    queue_routes = rng.choice(len(weights), size=plan.n_queue, p=weights)
    is_av = _draw_avs(len(placed.planned), plan.n_queue, config, rng)
    vehicles, queue = _vehicles(placed, queue_routes, is_av, config, rng)
    if scenario.inflow:
        vehicles, queue = vehicles + _timetable(queue, plan.inflow, rng), ()
    return Demand(tuple(routes), vehicles, queue, plan.v_eq, plan.inflow)


def _timetable(queue: tuple[QueuedVehicle, ...], inflow: float,
               rng: np.random.Generator) -> tuple[PlannedVehicle, ...]:  # fmt: skip
    """The queued vehicles entering one every 1/``inflow`` [s] (random phase) at the highest
    safe speed, whether or not anyone left: the demand of an open road, which a bottleneck
    downstream cannot discharge (SUMO keeps a vehicle that finds no room until it fits)."""
    first = 1.0 - float(rng.random())  # in (0, 1]: after the placed vehicles' t = 0
    return tuple(
        PlannedVehicle(q.vid, (j + first) / inflow, q.route, q.is_av, depart_speed="max")
        for j, q in enumerate(queue)
    )


END_ROOM = 40.0
"""Nobody is placed within this distance of a lane's dead end [m]: a vehicle placed there
would start at a standstill at the end of its lane, with no room to merge out of it."""


class _Placement:
    """Vehicles placed evenly spaced per lane with a random phase on every road edge."""

    def __init__(self, scenario: Scenario, config: EnvConfig, plan: _Plan,
                 rng: np.random.Generator, routes: list[Route], weights: np.ndarray) -> None:  # fmt: skip
        self.hd, self.config, self.plan, self.rng = scenario.hdmap, config, plan, rng
        self.routes, self.weights, self.base = routes, weights, scenario.routes
        self.route_of = RouteIndex(routes)
        self.planned: list[Placed] = []
        self.signalised = {src for src, _ in self.hd.tls_links}
        self.upstream = upstream_lanes(self.hd)
        self.tail: dict[int, float] = {}
        """Lane row -> distance [m] from its last placed vehicle to its end."""
        if scenario.ring:
            self._ring(scenario)
            return
        for edge in _placement_edges(scenario):
            self._edge(edge)

    def _ring(self, scenario: Scenario) -> None:
        """Evenly spaced all around each lane of the loop, at the equilibrium speed."""
        hd, human, car = self.hd, cautious(self.config.human), self.config.vehicle.length
        for lane, n in enumerate(ring_counts(scenario, self.plan.per_lane)):
            if n == 0:
                continue
            spots = ring_positions(scenario, lane, n, float(self.rng.random()))
            limit = float(min(hd.lane_speed[row] for _, row, _ in spots))
            spacing = ring_lengths(scenario)[lane] / n
            v = idm_equilibrium_speed(spacing, limit, human, car)
            for edge, row, pos in spots:
                route = suffix_route(self.routes, 0, edge)
                self.planned.append(Placed(route, pos, lane, row, v, [(0.0, limit)]))
                self.tail[row] = float(hd.lane_length[row]) - pos  # the last one's stays

    def _edge(self, edge: str) -> None:
        hd, base = self.hd, self.base
        e = hd.edge_of(edge)
        candidates = [i for i, r in enumerate(base) if edge in r.edges or r.origin == edge]
        if not candidates:
            candidates = list(range(len(base)))
        for row in hd.car_lane_rows(e):  # never on a sidewalk, bike or bus lane
            self._lane(edge, float(hd.edge_length[e]), int(hd.lane_index[row]), row, candidates)

    def _lane(
        self, edge: str, length: float, lane: int, lane_row: int, candidates: list[int]
    ) -> None:
        hd, human, car = self.hd, cautious(self.config.human), self.config.vehicle.length
        # routes this lane continues (SUMO refuses a vehicle that must change lanes to
        # reach its next edge before the edge ends: "too many lane changes required")
        paths = {i: lane_route(hd, lane_row, self.base[i], edge) for i in candidates}
        fit = [i for i in candidates if paths[i] is not None] or candidates
        fw = self.weights[fit] / self.weights[fit].sum()
        n = _lane_count(length, self.plan.per_lane)
        if n == 0:
            return
        usable = min(length - 1.0, self._dead_end(lane_row, fit) - END_ROOM)
        spacing = min(length, max(usable, 1.0)) / n
        # rounding n up makes the spacing tighter than the target: SUMO refuses to insert
        # at a speed above the IDM equilibrium of the actual spacing
        lane_limit = float(hd.lane_speed[lane_row])  # e.g. a slower on-ramp
        v_lane = min(self.plan.v_eq, idm_equilibrium_speed(spacing, lane_limit, human, car))
        start = self._phase(lane_row, spacing)
        self.tail[lane_row] = length - min(start + (n - 1) * spacing, length - 1.0)
        for k in range(n):
            pos = min(start + k * spacing, length - 1.0)  # clip, never drop: fixed count
            r = int(self.rng.choice(fit, p=fw))
            route = self.route_of(paths[r]) if paths[r] else suffix_route(self.routes, r, edge)
            v, limits = self._speed(lane_row, length, pos, route, v_lane, lane_limit)
            self.planned.append(Placed(route, pos, lane, lane_row, v, limits))

    def _dead_end(self, lane_row: int, fit: list[int]) -> float:
        """Distance [m] from the lane's start to where it ends on the way of the routes ``fit``
        (inf: it continues to their last edge)."""
        hd = self.hd
        last = [self.base[i].edges[-1] if self.base[i].edges else "" for i in fit]
        return min(lane_ahead(hd, lane_row, 0.0, hd.edge_row.get(e, -1))[0] for e in last)

    def _phase(self, lane_row: int, spacing: float) -> float:
        """Position of the first vehicle [m]: continue the spacing of the lane before this one
        (SUMO refuses, and keeps retrying for the rest of the episode, a vehicle too close to
        the one behind it), else a random phase."""
        prev, junction = self.upstream.get(lane_row, (-1, 0.0))
        if prev in self.tail:
            return (spacing - self.tail[prev] - junction) % spacing
        return self.rng.random() * spacing

    def _speed(self, lane_row: int, length: float, pos: float, route: int, v_lane: float,
               lane_limit: float) -> tuple[float, list[tuple[float, float]]]:  # fmt: skip
        """Speed its lane end or red light allows [m/s], and the limits ahead."""
        hd = self.hd
        # a lane that ends ahead (lane drop, acceleration lane): SUMO only inserts a
        # vehicle that can still stop before the end (IDM brakes gently: b, not 2b)
        last = self.routes[route].edges[-1] if self.routes[route].edges else ""
        d, slower = lane_ahead(hd, lane_row, pos, hd.edge_row.get(last, -1))
        if lane_row in self.signalised:  # the light ahead may be red
            d = min(d, length - pos)
        v = min(v_lane, math.sqrt(max(0.0, self.config.human.decel * (d - 15.0))))
        return v, [(0.0, lane_limit), *slower]


def _draw_avs(n_init: int, n_queue: int, config: EnvConfig, rng: np.random.Generator) -> np.ndarray:
    """(n_init + n_queue,) bool: which planned vehicles are AVs, exactly round(p·N)."""
    n_total = n_init + n_queue
    is_av = np.zeros(n_total, dtype=bool)
    if config.fixed_fleet:  # all AVs exist from reset
        # the fleet is the initial vehicles: p of them (not p of initial + queued ones)
        n_av = int(round(config.penetration * n_init))
        is_av[rng.choice(n_init, size=n_av, replace=False)] = True
    else:
        n_av = int(round(config.penetration * n_total))
        is_av[rng.choice(n_total, size=n_av, replace=False)] = True
    return is_av


def _vehicles(placed: _Placement, queue_routes: np.ndarray, is_av: np.ndarray, config: EnvConfig,
              rng: np.random.Generator) -> tuple[tuple[PlannedVehicle, ...], tuple[QueuedVehicle, ...]]:  # fmt: skip
    """Ids, speed factors and departure speeds of the placed vehicles, and the queue."""
    planned = placed.planned
    n_init, n_total = len(planned), len(is_av)
    # A vehicle desires speed_factor × limit, and SUMO refuses one that departs faster or could
    # not slow down to it on a slower lane ahead ("slow lane ahead"): placed conventional
    # vehicles get their factor here, and every placed vehicle departs within what it allows.
    dev, human = config.human.speed_factor_dev, cautious(config.human)
    factor = np.round(np.clip(rng.normal(1.0, dev, n_init), *SPEED_FACTOR_RANGE), 4)
    factor[is_av[:n_init]] = 1.0
    speed = [
        min(p.speed, departure_cap(float(f), p.limits, human)) for p, f in zip(planned, factor)
    ]
    order = sorted(range(n_init), key=lambda i: -planned[i].pos)  # downstream first
    cap_followers(planned, order, speed, placed.upstream, placed.tail, human, config.vehicle.length)
    ids = _vehicle_ids(is_av[[*order, *range(n_init, n_total)]])
    vehicles = []
    for j, i in enumerate(order):
        p, sf = planned[i], None if is_av[i] else float(factor[i])
        vehicles.append(
            PlannedVehicle(ids[j], 0.0, p.route, bool(is_av[i]), p.pos, p.lane, speed[i], sf)
        )
    queue = tuple(
        QueuedVehicle(ids[n_init + j], int(r), bool(is_av[n_init + j]))
        for j, r in enumerate(queue_routes)
    )
    return tuple(vehicles), queue


def _own_demand(scenario: Scenario, config: EnvConfig, rng: np.random.Generator) -> Demand:
    """The user's vehicles as given; exactly round(p*N) of them, drawn by the seed, become AVs
    (with a fixed fleet: trips that the fleet drives in turn, see ``fleet_pool``)."""
    own = scenario.own_in_episode(config.episode_length)  # sorted: SUMO wants it so
    n_av = int(round(config.penetration * len(own)))
    is_av = np.zeros(len(own), dtype=bool)
    is_av[rng.choice(len(own), size=n_av, replace=False)] = True
    vehicles, trips, k = [], [], 0
    for v, av in zip(own, is_av):
        if av and config.fixed_fleet:
            trips.append(FleetTrip(v.depart, v.route))
            continue
        if av:
            vid, k = f"av_{k}", k + 1
        else:  # keep the user's id unless it could clash with an AV id
            vid = f"hv_{v.vid}" if v.vid.startswith("av_") else v.vid
        vehicles.append(PlannedVehicle(vid, v.depart, v.route, bool(av), vtype=v.vtype))
    span = max(1.0, own[-1].depart - own[0].depart) if own else 1.0
    return Demand(scenario.routes, tuple(vehicles), (), 0.0, len(own) / span, tuple(trips))


def _type_of(v: PlannedVehicle, avs_as_humans: bool) -> str:
    """A vehicle's vType id: the AV type for AVs (the human drivers' copy when SUMO drives
    them), else the user's type of its own vehicles, else the env's human drivers."""
    if v.vtype is not None and not (v.is_av and not avs_as_humans):
        return v.vtype
    return AV_TYPE if v.is_av else HUMAN_TYPE


def _vehicle_ids(is_av: np.ndarray) -> list[str]:
    """``av_i`` / ``hv_j`` ids numbered in order."""
    n_av = np.cumsum(is_av) - 1
    n_hv = np.cumsum(~is_av) - 1
    return [f"av_{a}" if av else f"hv_{h}" for av, a, h in zip(is_av, n_av, n_hv)]


def write_demand(
    demand: Demand,
    config: EnvConfig,
    path: Path,
    avs_as_humans: bool = False,
    vtypes: tuple[str, ...] = (),
    av_class: str = CAR,
    verbatim: tuple[tuple[float, str], ...] = (),
) -> None:
    """Write vehicle types and the planned vehicles as a SUMO route file (``avs_as_humans``: the
    AV-labelled vehicles get the human drivers' types, for the all-human reference; ``vtypes``:
    a user's vType elements as XML text, for its own vehicles; ``av_class``: the AVs' SUMO
    vehicle class; ``verbatim``: (departure [s], XML text) of elements written as given, in
    departure order among the vehicles)."""
    root = ET.Element("routes")
    add_vehicle_types(root, config.human, config.vehicle, avs_as_humans, av_class)
    root.extend(ET.fromstring(t) for t in vtypes)
    for i, r in enumerate(demand.routes):
        ET.SubElement(root, "route", id=f"r{i}", edges=" ".join(r.edges or (r.origin,)))
    written = iter(verbatim)
    pending = next(written, None)
    for v in demand.vehicles:
        while pending is not None and pending[0] <= v.depart:  # SUMO reads departures in order
            root.append(ET.fromstring(pending[1]))
            pending = next(written, None)
        r = demand.routes[v.route]
        attrs = {"id": v.vid, "type": _type_of(v, avs_as_humans), "depart": f"{v.depart:.2f}"}
        if not attrs["type"]:
            del attrs["type"]  # SUMO's default type, as in the user's file
        attrs["departPos"] = f"{v.depart_pos:.2f}" if v.depart_pos is not None else "base"
        attrs["departLane"] = str(v.depart_lane) if v.depart_lane is not None else "free"
        speed = v.depart_speed if v.depart_speed is not None else "last"
        attrs["departSpeed"] = speed if isinstance(speed, str) else f"{speed:.2f}"
        if v.speed_factor is not None:
            attrs["speedFactor"] = f"{v.speed_factor:.4f}"
        if r.edges:
            ET.SubElement(root, "vehicle", route=f"r{v.route}", **attrs)
        else:
            ET.SubElement(root, "trip", attrs, **{"from": r.origin, "to": r.destination})
    rest = [pending, *written] if pending is not None else []  # departing after every vehicle
    root.extend(ET.fromstring(text) for _, text in rest)
    ET.indent(root)
    tmp = path.with_suffix(".tmp")
    ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=True)
    tmp.replace(path)
