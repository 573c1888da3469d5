"""Scenario registry, network building and demand generation (DESIGN §4).

A scenario is a folder ``scenarios/<family>/<variant>/`` with plain SUMO XML sources
(``*.nod.xml``, ``*.edg.xml``, optionally ``*.con.xml``/``*.tll.xml``) and a ``spec.toml``. The
network is built with netconvert from the eclipse-sumo wheel into the user cache, keyed by a
hash of the sources, so editing a source rebuilds it. A user's own ``.net.xml`` (routes are
generated) or ``.sumocfg`` (its vehicles are used, a fraction of them become AVs) loads too.

Demand: density k [veh/km summed over lanes] fixes the initial placement on every road edge
and, through the IDM equilibrium speed at that density, the inflow q = k·v_eq at the entries.
Penetration p makes exactly round(p·N) of the N planned vehicles AVs (``av_0…``), chosen by
the seed; conventional vehicles are ``hv_0…``. SUMO inserts every placed vehicle at t = 0 (the
spacing continues across junctions, and departure speeds respect each vehicle's speed factor,
slower lanes ahead and its leader): one it refused would wait and appear mid-road later.
"""

from __future__ import annotations

import hashlib
import math
import subprocess
import tomllib
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from mixed_traffic.config import JAM_DENSITY_PER_LANE, EnvConfig, VehicleConfig
from mixed_traffic.paths import SCENARIOS_DIR, cache_dir
from mixed_traffic.world.backend import binary
from mixed_traffic.world.hdmap import HDMap, load_hdmap

SPLITS = ("train", "eval")
SPEED_FACTOR_RANGE = (0.8, 1.2)
"""Truncation of conventional vehicles' speed factor (desired speed / speed limit) [-]."""
DEPART_SHARE = 0.95
"""Placed vehicles depart at most at this share of their desired speed [-] (measured: SUMO
refuses some that depart at their desired speed on a lane they must leave soon, "too many lane
changes required", but not at 0.95 of it)."""


@dataclass(frozen=True)
class Route:
    """A path through the network: explicit ``edges``, or ``from``/``to`` routed by SUMO."""

    edges: tuple[str, ...] = ()
    origin: str = ""
    destination: str = ""
    weight: float = 1.0
    """Share of the inflow entering on this route (relative)."""

    @property
    def entry(self) -> str:
        return self.edges[0] if self.edges else self.origin


@dataclass(frozen=True)
class OwnVehicle:
    """A vehicle given by the user's own route files (``Scenario.own_vehicles``)."""

    vid: str
    depart: float
    """Departure time [s]."""
    route: int
    """Index into ``Scenario.routes``."""


@dataclass(frozen=True)
class Scenario:
    """A loadable scenario: network, routes, measurement segment."""

    name: str
    family: str
    split: str
    description: str
    net_file: Path
    routes: tuple[Route, ...]
    measurement: tuple[str, ...]
    """Consecutive edges of the measurement segment (DT-TF, measured density)."""
    lanes: int
    """Lanes of the main road: the reference for density (veh/km summed over lanes)."""
    sumocfg: Path | None = None
    extra_args: tuple[str, ...] = ()
    placement_edges: tuple[str, ...] = field(default=())
    """Edges on which vehicles are placed at reset (default: all edges of the routes)."""
    periodic: bool = False
    """Close the main road into a ring with a virtual leader (see ``boundary``)."""
    own_vehicles: tuple[OwnVehicle, ...] = ()
    """A user's .sumocfg vehicles: used instead of generated demand (see ``user_scenario``)."""

    @property
    def hdmap(self) -> HDMap:
        return load_hdmap(self.net_file)

    @property
    def measurement_length(self) -> float:
        """Length of the measurement segment [m]."""
        hd = self.hdmap
        return float(sum(hd.edge_length[hd.edge_of(e)] for e in self.measurement))

    @property
    def max_density(self) -> float:
        """Jam density of the main road [veh/km summed over lanes]."""
        return self.lanes * JAM_DENSITY_PER_LANE


# --------------------------------------------------------------------------- registry
def _spec_files() -> list[Path]:
    return sorted(SCENARIOS_DIR.glob("*/*/spec.toml"))


@cache
def _registry() -> dict[str, Path]:
    reg: dict[str, Path] = {}
    for spec in _spec_files():
        family, variant = spec.parent.parent.name, spec.parent.name
        reg[f"{family}-{variant}"] = spec.parent
        data = tomllib.loads(spec.read_text())
        if data.get("default"):
            reg[family] = spec.parent
    return reg


def list_scenarios() -> list[str]:
    """Names of all bundled scenarios (``family-variant``; a bare family name is its default)."""
    return sorted(_registry())


def train_scenarios() -> list[str]:
    """Every bundled train-split scenario, one name per variant folder (aliases dropped)."""
    seen, out = set(), []
    for name, folder in sorted(_registry().items(), key=lambda kv: ("-" not in kv[0], kv[0])):
        if folder in seen or load_scenario(name).split != "train":
            continue
        seen.add(folder)
        out.append(name)
    return sorted(out)


def train_split_scenario(name: str) -> Scenario:
    """``load_scenario(name)``, refused (ValueError) unless it is on the train split: training
    and checkpoint selection must leave the held-out variants unseen."""
    scenario = load_scenario(name)
    if scenario.split != "train":
        raise ValueError(f"{name!r} is a held-out {scenario.split!r} scenario; use train-split "
                         f"ones: {', '.join(train_scenarios())}")  # fmt: skip
    return scenario


def load_scenario(name: str) -> Scenario:
    """A bundled scenario by name, or a user's ``.net.xml`` / ``.sumocfg`` by path."""
    if name.endswith(".net.xml") or name.endswith(".sumocfg"):
        from mixed_traffic.world.user_scenario import load_user_scenario

        return load_user_scenario(Path(name))
    reg = _registry()
    if name not in reg:
        raise ValueError(
            f"unknown scenario {name!r}; known: {', '.join(sorted(reg))} "
            "(or a path to a .net.xml or .sumocfg file)"
        )
    return _load_folder(name, reg[name])


def _load_folder(name: str, folder: Path) -> Scenario:
    spec_path = folder / "spec.toml"
    try:
        spec = tomllib.loads(spec_path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"scenario spec {spec_path} is malformed: {e}") from e
    for key in ("family", "split", "lanes", "routes", "measurement"):
        if key not in spec:
            raise ValueError(f"scenario spec {spec_path} lacks the required key {key!r}")
    if spec["split"] not in SPLITS:
        raise ValueError(f"{spec_path}: split={spec['split']!r} is not one of {SPLITS}")
    routes = tuple(
        Route(
            edges=tuple(r.get("edges", ())),
            origin=r.get("from", ""),
            destination=r.get("to", ""),
            weight=float(r.get("weight", 1.0)),
        )
        for r in spec["routes"]
    )
    scenario = Scenario(
        name=name,
        family=spec["family"],
        split=spec["split"],
        description=spec.get("description", ""),
        net_file=build_network(folder),
        routes=routes,
        measurement=tuple(spec["measurement"]),
        lanes=int(spec["lanes"]),
        extra_args=tuple(spec.get("sumo_args", ())),
        placement_edges=tuple(spec.get("placement_edges", ())),
        periodic=bool(spec.get("periodic", False)),
    )
    _validate(scenario, spec_path)
    return scenario


def _validate(scenario: Scenario, source: Path) -> None:
    hd = scenario.hdmap
    for e in scenario.measurement:
        if e not in hd.edge_row:
            raise ValueError(f"{source}: measurement edge {e!r} is not in the network")
    for r in scenario.routes:
        for e in (*r.edges, r.origin, r.destination):
            if e and e not in hd.edge_row:
                raise ValueError(f"{source}: route edge {e!r} is not in the network")


def build_network(folder: Path) -> Path:
    """Build (or reuse the cached) .net.xml from the plain XML sources in ``folder``."""
    sources = {
        kind: sorted(folder.glob(f"*.{kind}.xml")) for kind in ("nod", "edg", "con", "tll", "typ")
    }
    if not sources["nod"] or not sources["edg"]:
        raise ValueError(f"scenario folder {folder} needs at least one .nod.xml and one .edg.xml")
    h = hashlib.sha256()
    for path in (p for paths in sources.values() for p in paths):
        h.update(path.name.encode() + path.read_bytes())
    h.update(
        (folder / "netconvert.args").read_bytes() if (folder / "netconvert.args").exists() else b""
    )
    out = cache_dir("nets") / f"{folder.parent.name}-{folder.name}-{h.hexdigest()[:16]}.net.xml"
    if out.exists():
        return out
    flags = {"nod": "--node-files", "edg": "--edge-files", "con": "--connection-files",
             "tll": "--tllogic-files", "typ": "--type-files"}  # fmt: skip
    cmd = [binary("netconvert")]
    for kind, paths in sources.items():
        if paths:
            cmd += [flags[kind], ",".join(str(p) for p in paths)]
    extra = (
        (folder / "netconvert.args").read_text().split()
        if (folder / "netconvert.args").exists()
        else []
    )
    tmp = out.with_suffix(f".tmp{np.random.randint(1 << 30)}.xml")
    cmd += ["--output-file", str(tmp), "--no-warnings", *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0 or not tmp.exists():
        tmp.unlink(missing_ok=True)
        raise ValueError(
            f"netconvert failed on {folder}: {proc.stderr.strip() or proc.stdout.strip()}"
        )
    tmp.replace(out)
    return out


# --------------------------------------------------------------------------- demand
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
    depart_speed: float | None = None
    speed_factor: float | None = None
    """Desired speed / speed limit [-]; None = SUMO draws it from the vehicle type."""


@dataclass(frozen=True)
class QueuedVehicle:
    """A vehicle that enters when one leaves (see ``boundary.PeriodicBoundary``)."""

    vid: str
    route: int
    is_av: bool


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

    @property
    def placed_ids(self) -> frozenset[str]:
        """Vehicles placed on the road at reset (a given position, not an entry)."""
        return frozenset(v.vid for v in self.vehicles if v.depart_pos is not None)

    @property
    def av_ids(self) -> list[str]:
        """All AV ids of the episode (placed and queued), ``av_0 … av_{N-1}``."""
        return [v.vid for v in (*self.vehicles, *self.queue) if v.is_av]


def idm_equilibrium_speed(spacing: float, v0: float, vehicle: VehicleConfig) -> float:
    """Speed [m/s] at which IDM keeps a constant ``spacing`` [m] (front to front)."""
    gap = spacing - vehicle.length
    if gap <= vehicle.idm_min_gap:
        return 0.0
    lo, hi = 0.0, v0
    for _ in range(60):
        v = 0.5 * (lo + hi)
        s_star = vehicle.idm_min_gap + v * vehicle.idm_headway
        needed = s_star / math.sqrt(max(1e-12, 1.0 - (v / v0) ** vehicle.idm_delta))
        lo, hi = (v, hi) if needed < gap else (lo, v)
    return lo


def check_density(scenario: Scenario, density: float) -> None:
    if not 0 < density <= scenario.max_density:
        raise ValueError(
            f"density={density} veh/km is outside (0, {scenario.max_density:.0f}] for scenario "
            f"{scenario.name!r} ({scenario.lanes} lanes; jam density {JAM_DENSITY_PER_LANE:.0f} "
            "veh/km per lane)"
        )


def make_demand(scenario: Scenario, config: EnvConfig, rng: np.random.Generator) -> Demand:
    """Initial placement plus entry inflow for one episode of ``config``."""
    if scenario.own_vehicles:
        return _own_demand(scenario, config, rng)
    check_density(scenario, config.density)
    hd = scenario.hdmap
    per_lane = config.density / scenario.lanes / 1000.0  # veh/m per lane
    speed_limit = float(hd.lane_speed[hd.edge_lanes[hd.edge_of(scenario.routes[0].entry), 0]])
    v_eq = idm_equilibrium_speed(1.0 / per_lane, speed_limit, config.vehicle)
    routes = list(scenario.routes)
    weights = np.array([r.weight for r in routes], dtype=float)
    weights /= weights.sum()
    planned: list[_Placed] = []

    # initial placement: evenly spaced per lane with a random phase, on every road edge
    placement = scenario.placement_edges or tuple(dict.fromkeys(e for r in routes for e in r.edges))
    signalised = {src for src, _ in hd.tls_links}
    upstream = _upstream_lanes(hd)
    tail: dict[int, float] = {}  # lane row -> distance [m] from its last placed vehicle to its end
    for edge in placement:
        e = hd.edge_of(edge)
        base = scenario.routes
        candidates = [i for i, r in enumerate(base) if edge in r.edges or r.origin == edge]
        if not candidates:
            candidates = list(range(len(base)))
        length = float(hd.edge_length[e])
        for lane in range(int(hd.edge_num_lanes[e])):
            # routes this lane continues (SUMO refuses a vehicle that must change lanes to
            # reach its next edge before the edge ends: "too many lane changes required")
            lane_row = int(hd.edge_lanes[e, lane])
            paths = {i: _lane_route(hd, lane_row, base[i], edge) for i in candidates}
            fit = [i for i in candidates if paths[i] is not None] or candidates
            fw = weights[fit] / weights[fit].sum()
            # a count independent of the seed keeps possible_agents fixed for a config
            n = round(length * per_lane)
            if n == 0:
                continue
            spacing = length / n
            # rounding n up makes the spacing tighter than the target: SUMO refuses to insert
            # at a speed above the IDM equilibrium of the actual spacing
            lane_limit = float(hd.lane_speed[lane_row])  # e.g. a slower on-ramp
            v_lane = min(v_eq, idm_equilibrium_speed(spacing, lane_limit, config.vehicle))
            # continue the spacing of the lane before this one (SUMO refuses, and keeps
            # retrying for the rest of the episode, a vehicle too close to the one behind it)
            prev, junction = upstream.get(lane_row, (-1, 0.0))
            if prev in tail:
                start = (spacing - tail[prev] - junction) % spacing
            else:
                start = rng.random() * spacing
            tail[lane_row] = length - min(start + (n - 1) * spacing, length - 1.0)
            for k in range(n):
                pos = min(start + k * spacing, length - 1.0)  # clip, never drop: fixed count
                r = int(rng.choice(fit, p=fw))
                route_idx = (
                    _route_index(routes, paths[r]) if paths[r] else _suffix_route(routes, r, edge)
                )
                # a lane that ends ahead (lane drop, acceleration lane): SUMO only inserts a
                # vehicle that can still stop before the end (IDM brakes gently: b, not 2b)
                last = routes[route_idx].edges[-1] if routes[route_idx].edges else ""
                d, slower = _lane_ahead(hd, lane_row, pos, hd.edge_row.get(last, -1))
                if lane_row in signalised:  # the light ahead may be red
                    d = min(d, length - pos)
                v = min(v_lane, math.sqrt(max(0.0, config.vehicle.idm_decel * (d - 15.0))))
                limits = [(0.0, lane_limit), *slower]
                planned.append(_Placed(route_idx, pos, lane, lane_row, v, limits))

    # the inflow queue: vehicles that replace leaving ones at the entries (PeriodicBoundary)
    inflow = per_lane * scenario.lanes * v_eq if v_eq > 0 else 0.0
    n_queue = int(math.ceil(1.5 * inflow * config.episode_length)) + 4 * scenario.lanes
    queue_routes = rng.choice(len(weights), size=n_queue, p=weights)

    n_init = len(planned)
    n_total = n_init + n_queue
    n_av = int(round(config.penetration * n_total))
    is_av = np.zeros(n_total, dtype=bool)
    if config.fixed_fleet:  # all AVs exist from reset
        # the fleet is the initial vehicles: p of them (not p of initial + queued ones)
        is_av[rng.choice(n_init, size=int(round(config.penetration * n_init)), replace=False)] = (
            True
        )
    else:
        is_av[rng.choice(n_total, size=n_av, replace=False)] = True
    # A vehicle desires speed_factor × limit, and SUMO refuses one that departs faster or could
    # not slow down to it on a slower lane ahead ("slow lane ahead"): placed conventional
    # vehicles get their factor here, and every placed vehicle departs within what it allows.
    dev = config.vehicle.speed_factor_dev
    factor = np.round(np.clip(rng.normal(1.0, dev, n_init), *SPEED_FACTOR_RANGE), 4)
    factor[is_av[:n_init]] = 1.0
    speed = [
        min(p.speed, _departure_cap(float(f), p.limits, config.vehicle))
        for p, f in zip(planned, factor)
    ]
    order = sorted(range(n_init), key=lambda i: -planned[i].pos)  # downstream first
    _cap_followers(planned, order, speed, upstream, tail, config.vehicle)
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
    return Demand(tuple(routes), tuple(vehicles), queue, v_eq, inflow)


def _own_demand(scenario: Scenario, config: EnvConfig, rng: np.random.Generator) -> Demand:
    """The user's vehicles as given; exactly round(p*N) of them, drawn by the seed, become AVs."""
    own = sorted(scenario.own_vehicles, key=lambda v: v.depart)  # SUMO wants sorted departures
    n_av = int(round(config.penetration * len(own)))
    is_av = np.zeros(len(own), dtype=bool)
    is_av[rng.choice(len(own), size=n_av, replace=False)] = True
    vehicles, k = [], 0
    for v, av in zip(own, is_av):
        if av:
            vid, k = f"av_{k}", k + 1
        else:  # keep the user's id unless it could clash with an AV id
            vid = f"hv_{v.vid}" if v.vid.startswith("av_") else v.vid
        vehicles.append(PlannedVehicle(vid, v.depart, v.route, bool(av)))
    span = max(1.0, own[-1].depart - own[0].depart)
    return Demand(scenario.routes, tuple(vehicles), (), 0.0, len(own) / span)


def _lane_route(hd: HDMap, lane: int, route: Route, edge: str) -> tuple[str, ...] | None:
    """The edges of ``route`` from ``edge`` on, if a vehicle on ``lane`` can follow them without
    changing lanes before the junction (SUMO refuses to insert it otherwise: "too many lane
    changes required"); origin/destination routes take the fastest such path. None: none."""
    if not route.edges:
        path = hd.fastest_path(lane, hd.edge_row[route.destination])
        return None if path is None else tuple(hd.edge_ids[e] for e in path)
    rest = route.edges[route.edges.index(edge) :] if edge in route.edges else ()
    if len(rest) == 1 or (len(rest) > 1 and (lane, hd.edge_row[rest[1]]) in hd.conn_to):
        return rest
    return None


def _route_index(routes: list[Route], edges: tuple[str, ...]) -> int:
    """Index of the route with exactly these ``edges`` (appended once)."""
    for i, r in enumerate(routes):
        if r.edges == edges:
            return i
    routes.append(Route(edges=edges, weight=0.0))
    return len(routes) - 1


class _Placed(NamedTuple):
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


def _cap_followers(
    planned: list[_Placed],
    order: list[int],
    speed: list[float],
    upstream: dict[int, tuple[int, float]],
    tail: dict[int, float],
    veh: VehicleConfig,
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
        pairs += [
            (a, b, planned[a].pos - planned[b].pos - veh.length) for a, b in zip(ids, ids[1:])
        ]
        prev, junction = upstream.get(row, (-1, 0.0))
        if prev in lanes:  # the last vehicle on the lane before follows the first one here
            gap = tail[prev] + junction + planned[ids[-1]].pos - veh.length
            pairs.append((ids[-1], lanes[prev][0], gap))
    changed = True
    while changed:  # caps only fall: a few sweeps settle chains of slow leaders
        changed = False
        for a, b, gap in pairs:
            cap = _follow_cap(gap, speed[a], veh)
            if cap < speed[b]:
                speed[b], changed = cap, True


def _follow_cap(gap: float, v_lead: float, veh: VehicleConfig) -> float:
    """Highest speed [m/s] at which IDM's desired gap s0 + vT + v(v − v_lead)/2√(ab) fits in
    ``gap`` [m] behind a leader at ``v_lead`` [m/s] (1 cm/s below, see ``_departure_cap``)."""
    c = 2.0 * math.sqrt(veh.idm_accel * veh.idm_decel)
    p = veh.idm_headway * c - v_lead  # v² + p·v + c·(s0 − gap) ≤ 0
    q = c * (veh.idm_min_gap - gap)
    return max(0.0, 0.5 * (-p + math.sqrt(max(0.0, p * p - 4.0 * q))) - 0.01)


def _upstream_lanes(hd: HDMap) -> dict[int, tuple[int, float]]:
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


def _departure_cap(factor: float, limits: list[tuple[float, float]], veh: VehicleConfig) -> float:
    """Highest departure speed [m/s] SUMO accepts for a vehicle with speed ``factor`` [-] before
    lanes with lower limits ``limits`` ([(distance [m], limit [m/s])]): factor × limit, unless
    it could still stop before that lane (measured: SUMO's IDM insertion check asks for the stop
    distance v²/2b + vT, not just enough room to slow down). 1 cm/s below, as the route file
    rounds speeds to 2 decimals."""
    b, t = veh.idm_decel, veh.idm_headway

    def stop_speed(d: float) -> float:  # v with v²/2b + vT + s0 = d
        return b * (math.sqrt(t * t + 2.0 * max(0.0, d - veh.idm_min_gap) / b) - t)

    return min(max(DEPART_SHARE * factor * v, stop_speed(d)) for d, v in limits) - 0.01


def _lane_ahead(
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


def _vehicle_ids(is_av: np.ndarray) -> list[str]:
    """``av_i`` / ``hv_j`` ids numbered in order."""
    n_av = np.cumsum(is_av) - 1
    n_hv = np.cumsum(~is_av) - 1
    return [f"av_{a}" if av else f"hv_{h}" for av, a, h in zip(is_av, n_av, n_hv)]


def _suffix_route(routes: list[Route], r: int, edge: str) -> int:
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


def write_demand(demand: Demand, config: EnvConfig, path: Path) -> None:
    """Write vehicle types and the planned vehicles as a SUMO route file."""
    veh = config.vehicle
    lo, hi = SPEED_FACTOR_RANGE
    root = ET.Element("routes")
    ET.SubElement(
        root, "vType", id="hv", vClass="passenger", carFollowModel="IDM", accel=f"{veh.idm_accel}",
        decel=f"{veh.idm_decel}", emergencyDecel="9.0", tau=f"{veh.idm_headway}",
        minGap=f"{veh.idm_min_gap}", delta=f"{veh.idm_delta}", length=f"{veh.length}",
        width=f"{veh.width}", speedFactor=f"normc(1,{veh.speed_factor_dev},{lo},{hi})",
        laneChangeModel="SL2015", latAlignment="center", color="0.6,0.6,0.6",
    )  # fmt: skip
    ET.SubElement(
        root, "vType", id="av", vClass="passenger", carFollowModel="IDM", accel=f"{veh.max_accel}",
        decel=f"{veh.max_decel}", emergencyDecel="9.0", tau=f"{veh.idm_headway}",
        minGap=f"{veh.idm_min_gap}", length=f"{veh.length}", width=f"{veh.width}",
        speedFactor="1", laneChangeModel="SL2015", latAlignment="arbitrary", maxSpeedLat="30",
        lcSublane="0", color="0.85,0.1,0.1",
    )  # fmt: skip
    for i, r in enumerate(demand.routes):
        ET.SubElement(root, "route", id=f"r{i}", edges=" ".join(r.edges or (r.origin,)))
    for v in demand.vehicles:
        r = demand.routes[v.route]
        attrs = {"id": v.vid, "type": "av" if v.is_av else "hv", "depart": f"{v.depart:.2f}"}
        attrs["departPos"] = f"{v.depart_pos:.2f}" if v.depart_pos is not None else "base"
        attrs["departLane"] = str(v.depart_lane) if v.depart_lane is not None else "free"
        attrs["departSpeed"] = f"{v.depart_speed:.2f}" if v.depart_speed is not None else "last"
        if v.speed_factor is not None:
            attrs["speedFactor"] = f"{v.speed_factor:.4f}"
        if r.edges:
            ET.SubElement(root, "vehicle", route=f"r{v.route}", **attrs)
        else:
            ET.SubElement(root, "trip", attrs, **{"from": r.origin, "to": r.destination})
    ET.indent(root)
    tmp = path.with_suffix(".tmp")
    ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=True)
    tmp.replace(path)


def sumo_args(scenario: Scenario, config: EnvConfig, route_file: Path, seed: int) -> list[str]:
    """SUMO command line (without the binary) for one episode."""
    return [
        "--net-file", str(scenario.net_file),
        "--route-files", str(route_file),
        "--step-length", f"{config.step_length}",
        "--lateral-resolution", f"{config.lateral_resolution}",
        "--time-to-teleport", "-1",
        "--collision.action", "remove",
        "--collision.check-junctions", "true",
        "--collision.mingap-factor", "0",
        "--seed", str(seed),
        "--no-step-log", "true",
        "--no-warnings", "true",
        "--duration-log.disable", "true",
        "--eager-insert", "true",
        "--default.speeddev", "0",
        *scenario.extra_args,
    ]  # fmt: skip
