"""A user's own SUMO network (``.net.xml`` or ``.net.xml.gz``) or configuration (``.sumocfg``) as a ``Scenario``.

A bare network gets generated demand: SUMO-routed trips between fringe edges, density measured
over the whole network. A configuration keeps its own vehicles (``<vehicle>``, ``<trip>``,
``<flow>`` from its route files); ``make_demand`` turns round(p·N) of them into AVs.
"""

from __future__ import annotations

import gzip
import warnings
import xml.etree.ElementTree as ET
from collections import Counter, deque
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from mixed_traffic.world.hdmap import CAR, NetFileError, read_net
from mixed_traffic.world.network import SPLIT_ARGS
from mixed_traffic.world.od_pairs import reach_sets, spread_pairs
from mixed_traffic.world.routing import predecessors
from mixed_traffic.world.scenario import OwnVehicle, Route, Scenario

#: Fringe origin/destination pairs kept for a bare network (enough for route choice, few routes).
MAX_OD_PAIRS = 12
#: End [s] of flows without an ``end`` when the configuration has none either (SUMO's default:
#: 24 h); only the departures within an episode become vehicles (``Scenario.own_in_episode``).
DEFAULT_FLOW_END = 86400.0
#: Edge length [m] above which loading warns and names netconvert's split (``SPLIT_ARGS``).
LONG_EDGE = 3000.0


def load_user_scenario(path: Path) -> Scenario:
    """Load ``path`` (a ``.net.xml`` or ``.sumocfg``); raises ``ValueError`` naming the file."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"scenario file {path} is a folder, not a file")
    if not path.is_file():
        raise ValueError(f"scenario file {path} does not exist")
    if path.name.endswith(".sumocfg"):
        return _from_sumocfg(path)
    if path.name.endswith((".net.xml", ".net.xml.gz")):
        return _from_net(path)
    raise ValueError(f"{path}: expected a .net.xml, .net.xml.gz or .sumocfg file")


# --------------------------------------------------------------------------- network
def _parse(path: Path, what: str) -> ET.Element:
    if not path.is_file():
        raise ValueError(f"{what} {path} does not exist")
    try:
        if path.name.endswith(".gz"):
            with gzip.open(path) as f:
                return ET.parse(f).getroot()
        return ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise ValueError(f"{what} {path} is malformed XML: {e}") from e


class _Net:
    """Normal edges and their successor graph, read with sumolib from a .net.xml."""

    def __init__(self, path: Path, vclass: str = CAR) -> None:
        if not path.is_file():
            raise ValueError(f"network file {path} does not exist")
        try:
            net = read_net(path, with_internal=False)
        except NetFileError as e:
            if e.kind == "xml":
                raise ValueError(f"network file {path} is malformed XML: {e.detail}") from e
            if e.kind == "root":
                msg = f"{path} is not a SUMO network (root <{e.detail}>, expected <net>)"
                raise ValueError(msg) from e
            raise
        normal = [e for e in net.getEdges(withInternal=True)
                  if e.getFunction() not in ("internal", "walkingarea", "crossing")]  # fmt: skip
        if not normal:
            raise ValueError(f"network file {path} contains no edges")
        edges = [e for e in normal if any(ln.allows(vclass) for ln in e.getLanes())]
        if not edges:
            what = "passenger cars" if vclass == CAR else "the AVs"
            raise ValueError(
                f"network file {path} has no lane that {what} may use (vClass {vclass!r}; its "
                "lanes allow only e.g. pedestrians, bicycles or rail)"
            )
        _warn_long_edges(path, edges)
        self.path = path
        self.edges = {e.getID() for e in normal}
        # lanes cars may use, per edge (sidewalks and bike lanes do not count for density)
        self.lanes: dict[str, int] = {
            e.getID(): sum(ln.allows(vclass) for ln in e.getLanes()) for e in edges
        }
        self.nodes: dict[str, tuple[str, str]] = {
            e.getID(): (e.getFromNode().getID(), e.getToNode().getID()) for e in edges
        }
        self.succ: dict[str, set[str]] = {
            e.getID(): _car_successors(e, self.lanes, vclass) for e in edges
        }

    def reachable(self, start: str, graph: Mapping[str, Iterable[str]] | None = None) -> set[str]:
        """Edges reachable from ``start`` (itself included); over ``graph``'s links if given."""
        graph = self.succ if graph is None else graph
        seen, todo = {start}, deque([start])
        while todo:
            for nxt in graph.get(todo.popleft(), ()):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    def reaching(self, ends: set[str]) -> set[str]:
        """Edges from which every edge of ``ends`` is reachable: one backward search per end
        (not a forward one per edge, which a city's thousands of edges made minutes)."""
        pred = predecessors(self.succ)
        out = set(self.lanes)
        for end in ends:
            out &= self.reachable(end, pred)
        return out

    def fringe(self) -> tuple[list[str], list[str]]:
        """Entry and exit edges: those touching a node with a single neighbouring node."""
        neighbours: dict[str, set[str]] = {}
        for a, b in self.nodes.values():
            neighbours.setdefault(a, set()).add(b)
            neighbours.setdefault(b, set()).add(a)
        dead = {n for n, nb in neighbours.items() if len(nb) == 1}
        entries = sorted(e for e, (a, _) in self.nodes.items() if a in dead)
        exits = sorted(e for e, (_, b) in self.nodes.items() if b in dead)
        return entries or sorted(self.lanes), exits or sorted(self.lanes)

    def common_lanes(self) -> int:
        return Counter(self.lanes.values()).most_common(1)[0][0]


def _warn_long_edges(path: Path, edges: list) -> None:
    """Warn, naming the longest edge and SUMO's fix, when an edge exceeds ``LONG_EDGE``."""
    longest = max(edges, key=lambda e: e.getLength())
    if longest.getLength() > LONG_EDGE:
        warnings.warn(
            f"network file {path}: edge {longest.getID()!r} is {longest.getLength() / 1000:.1f} "
            "km long, and SUMO's sublane model slows with the square of the vehicles on one "
            f"edge; split it: netconvert -s {path.name} {' '.join(SPLIT_ARGS)} -o split.net.xml",
            stacklevel=4,
        )


def _car_successors(edge, car_edges: dict[str, int], vclass: str) -> set[str]:
    """Edges a car of ``vclass`` can reach from ``edge`` through one junction: a connection
    between lanes it may use (SUMO's permissions)."""
    return {
        to.getID()
        for to, conns in edge.getOutgoing().items()
        if to.getID() in car_edges
        and any(c.getFromLane().allows(vclass) and c.getToLane().allows(vclass) for c in conns)
    }


def _from_net(path: Path) -> Scenario:
    net = _Net(path)
    entries, exits = net.fringe()
    reach = reach_sets(net.succ, entries, net.reachable)
    # spread over the pairs so every entry appears (deterministic, no seed needed); a road of
    # single edges: each is its own trip (SUMO accepts from == to)
    chosen = spread_pairs(entries, exits, reach, MAX_OD_PAIRS)
    if not chosen:
        raise ValueError(f"network file {path}: no exit edge is reachable from any entry edge")
    routes = tuple(Route(origin=o, destination=d) for o, d in chosen)
    dests = {d for _, d in chosen}
    # vehicles are placed only where every destination can still be reached
    placement = tuple(sorted(net.reaching(dests)))
    return Scenario(
        name=str(path),
        family="user",
        split="eval",
        description=f"user network {path.name}",
        net_file=path.resolve(),
        routes=routes,
        measurement=tuple(sorted(net.lanes)),
        lanes=net.common_lanes(),
        placement_edges=placement or tuple(o for o, _ in chosen),
    )


# --------------------------------------------------------------------------- sumocfg
def _cfg_value(root: ET.Element, key: str) -> str:
    """``<input><net-file value=.../>`` (also accepts the attribute form ``<input net-file=...>``)."""
    for el in root.iter(key):
        if el.get("value"):
            return el.get("value", "")
    for el in root.iter("input"):
        if el.get(key):
            return el.get(key, "")
    return ""


def _from_sumocfg(path: Path) -> Scenario:
    root = _parse(path, "SUMO configuration")
    net_value = _cfg_value(root, "net-file")
    if not net_value:
        raise ValueError(f"SUMO configuration {path} has no net-file")
    net_path = (path.parent / net_value).resolve()
    route_files = [
        (path.parent / f.strip()).resolve()
        for f in _cfg_value(root, "route-files").split(",")
        if f.strip()
    ]
    roots = [(rf, _parse(rf, "route file")) for rf in route_files]
    # additional files may define vehicles too (SUMO loads them at the start): read them as
    # route files and keep them out of the additional files SUMO gets
    additional = [(path.parent / f.strip()).resolve()
                  for f in _cfg_value(root, "additional-files").split(",") if f.strip()]  # fmt: skip
    carrying = [(af, r) for af in additional for r in [_parse(af, "additional file")]
                if any(el.tag in VEHICLES for el in r)]  # fmt: skip
    roots += carrying
    carried = {af for af, _ in carrying}
    kept = [str(af) for af in additional if af not in carried]
    types = [el for _, r in roots for el in r if el.tag in ("vType", "vTypeDistribution")]
    vclass, size = _av_template(types, [el for _, r in roots for el in r])
    if vclass in OFF_ROAD:
        raise ValueError(f"SUMO configuration {path}: its route files define no vehicle on "
                         f"roads the AVs may use (only vClass {vclass!r})")  # fmt: skip
    net = _Net(net_path, vclass)
    seed = int(_cfg_value(root, "seed") or 0)
    routes: list[Route] = []
    own: list[OwnVehicle] = []
    verbatim: list[tuple[float, str]] = []
    begin, end = (_seconds(root, path, key) for key in ("begin", "end"))
    rng = np.random.default_rng(seed)
    for rf, rroot in roots:
        _read_routes(rroot, rf, net, routes, own, rng, end or DEFAULT_FLOW_END, verbatim)
    if not own:
        raise ValueError(f"SUMO configuration {path}: its route files define no vehicle on "
                         f"roads the AVs may use")  # fmt: skip
    return Scenario(
        name=str(path),
        family="user",
        split="eval",
        description=f"user configuration {path.name}",
        net_file=net_path,
        routes=tuple(routes),
        measurement=tuple(sorted(net.lanes)),
        lanes=net.common_lanes(),
        sumocfg=path.resolve(),
        own_vehicles=tuple(own),
        vclass=vclass,
        av_size=size,
        vtypes=tuple(ET.tostring(el, encoding="unicode") for el in types),
        verbatim=tuple(sorted(verbatim, key=lambda tv: tv[0])),
        begin=begin or 0.0,
        step_length=_seconds(root, path, "step-length"),
        end=None if end is None else end - (begin or 0.0),
        extra_args=("--additional-files", ",".join(kept)) if carrying else (),
    )


#: SUMO's default vType (a vehicle without ``type``): class, length and width [m].
_DEFAULT_TYPE = (CAR, 5.0, 1.8)


def _av_template(types: list[ET.Element], vehicles: list[ET.Element]) -> tuple[str, tuple]:
    """(vClass, (length, width) [m]) of the type the AVs derive from: the file's most used
    passenger type, else its most used type of any class (e.g. only racing cars)."""
    defs: dict[str, ET.Element] = {}
    for el in types:  # a distribution stands for its first member
        first = el if el.tag == "vType" else next(iter(el.findall("vType")), None)
        if first is not None:
            defs[el.get("id", "")] = first
    used = Counter(v.get("type", "") for v in vehicles if v.tag in ("vehicle", "trip", "flow"))

    def spec(type_id: str) -> tuple[str, float, float]:
        el = defs.get(type_id)
        if el is None:
            return _DEFAULT_TYPE
        return (el.get("vClass", CAR), float(el.get("length", _DEFAULT_TYPE[1])),
                float(el.get("width", _DEFAULT_TYPE[2])))  # fmt: skip

    ranked = [spec(t) for t, _ in used.most_common()] or [_DEFAULT_TYPE]
    vclass, length, width = next((s for s in ranked if s[0] == CAR), ranked[0])
    return vclass, (length, width)


def _seconds(root: ET.Element, path: Path, key: str) -> float | None:
    """A time option of the configuration [s] (SUMO's plain seconds), None if absent."""
    value = _cfg_value(root, key)
    if not value:
        return None
    try:
        return sumo_time(value)
    except ValueError:
        raise ValueError(f"SUMO configuration {path}: {key}={value!r} is not a time") from None


def sumo_time(value: str) -> float:
    """SUMO's time value [s]: seconds, or ``[[d:]h:]m:s`` (``ValueError`` if neither)."""
    parts = [float(p) for p in value.split(":")]
    if len(parts) > 4:
        raise ValueError(value)
    return sum(p * u for p, u in zip(reversed(parts), (1.0, 60.0, 3600.0, 86400.0)))


def _route_index(routes: list[Route], route: Route) -> int:
    if route not in routes:
        routes.append(route)
    return routes.index(route)


def _route_of(el: ET.Element, named: dict[str, list[tuple[tuple[str, ...], float]]], net: _Net,
              source: Path, rng: np.random.Generator) -> Route:  # fmt: skip
    """The route of a vehicle/trip/flow: a named route (a distribution's member drawn by its
    probability), an inline ``<route>``, or from/to."""
    if el.get("route"):
        if el.get("route") not in named:
            raise ValueError(f"{source}: {el.tag} {el.get('id')!r} uses unknown route")
        choices = named[el.get("route", "")]
        p = np.array([w for _, w in choices])
        edges = choices[int(rng.choice(len(choices), p=p / p.sum())) if len(choices) > 1 else 0][0]
    elif el.find("route") is not None:
        edges = tuple(el.find("route").get("edges", "").split())  # type: ignore[union-attr]
    elif el.get("from") and el.get("to"):
        route = Route(origin=el.get("from", ""), destination=el.get("to", ""))
        for e in (route.origin, route.destination):
            if e not in net.lanes:
                raise ValueError(f"{source}: {el.tag} {el.get('id')!r} uses unknown edge {e!r}")
        return route
    else:
        raise ValueError(f"{source}: {el.tag} {el.get('id')!r} has no route and no from/to")
    for e in edges:
        if e not in net.lanes:
            raise ValueError(f"{source}: {el.tag} {el.get('id')!r} uses unknown edge {e!r}")
    return Route(edges=edges)


#: Route-file elements the env passes to SUMO as written (never AVs).
PASSENGERS = ("person", "personFlow", "container", "containerFlow")
#: Route-file elements that define vehicles.
VEHICLES = ("vehicle", "trip", "flow")
#: Vehicle classes that do not drive on roads: a file of only these has no vehicle to be an AV.
OFF_ROAD = frozenset({"rail", "rail_urban", "rail_electric", "rail_fast", "tram", "cable_car",
                      "subway", "ship", "aircraft", "drone", "pedestrian", "wheelchair"})  # fmt: skip


def _read_routes(
    root: ET.Element,
    source: Path,
    net: _Net,
    routes: list[Route],
    own: list[OwnVehicle],
    rng: np.random.Generator,
    flow_end: float,
    verbatim: list[tuple[float, str]],
) -> None:
    """Append ``root``'s vehicles to ``own`` (their routes to ``routes``) and, as (departure
    [s], XML text), what SUMO runs as written to ``verbatim``: persons and containers, and
    vehicles routed by their stops or on roads the AVs may not use (trains, bikes), with the
    named routes these use (departure -1: before everything)."""
    named = _named_routes(root)
    used: set[str] = set()
    for el in root:
        vtype = el.get("type", "")
        if el.tag in PASSENGERS or (el.tag in VEHICLES and _as_written(el, named, net)):
            used.add(el.get("route", ""))
            verbatim.append((_depart(el, source), ET.tostring(el, encoding="unicode")))
        elif el.tag in ("vehicle", "trip"):
            r = _route_index(routes, _route_of(el, named, net, source, rng))
            own.append(OwnVehicle(el.get("id", ""), _depart(el, source), r, vtype))
        elif el.tag == "flow":
            drawn = len(named.get(el.get("route", ""), ())) > 1  # a route per vehicle
            r = _route_index(routes, _route_of(el, named, net, source, rng))
            for k, t in enumerate(_flow_departures(el, source, rng, flow_end)):
                if drawn and k:
                    r = _route_index(routes, _route_of(el, named, net, source, rng))
                own.append(OwnVehicle(f"{el.get('id')}.{k}", t, r, vtype))
    verbatim.extend((-1.0, ET.tostring(r, encoding="unicode")) for r in root
                    if r.tag in ("route", "routeDistribution") and r.get("id") in used)  # fmt: skip


def _named_routes(root: ET.Element) -> dict[str, list[tuple[tuple[str, ...], float]]]:
    """Route id -> its (edges, probability) choices: one for a ``<route>``, the members of a
    ``<routeDistribution>`` (given inline or by ``refId``)."""
    named = {r.get("id", ""): [(tuple(r.get("edges", "").split()), 1.0)]
             for r in root.findall("route")}  # fmt: skip
    for dist in root.findall("routeDistribution"):
        members = []
        for r in dist.findall("route"):
            edges = (named[r.get("refId", "")][0][0] if r.get("refId") in named
                     else tuple(r.get("edges", "").split()))  # fmt: skip
            members.append((edges, float(r.get("probability", 1.0))))
        named[dist.get("id", "")] = members
    return named


def _as_written(el: ET.Element, named: dict[str, list[tuple[tuple[str, ...], float]]],
                net: _Net) -> bool:  # fmt: skip
    """A vehicle the env leaves to SUMO as written: routed only by its stops (no route and no
    from/to), or on an existing road that the AVs may not use."""
    if el.get("route"):
        edges = tuple(e for r, _ in named.get(el.get("route", ""), ()) for e in r)
    elif el.find("route") is not None:
        edges = tuple(el.find("route").get("edges", "").split())  # type: ignore[union-attr]
    elif el.get("from") and el.get("to"):
        edges = (el.get("from", ""), el.get("to", ""))
    else:
        return el.find("stop") is not None
    return all(e in net.edges for e in edges) and not all(e in net.lanes for e in edges)


def _depart(el: ET.Element, source: Path) -> float:
    value = el.get("depart", el.get("begin", "0"))  # a flow's first departure
    try:
        return sumo_time(value)
    except ValueError:
        if value in ("triggered", "containerTriggered", "now", "begin"):
            return 0.0
        raise ValueError(f"{source}: {el.get('id')!r} has depart={value!r}") from None


def _flow_departures(
    el: ET.Element, source: Path, rng: np.random.Generator, default_end: float
) -> list[float]:
    """Departure times of a ``<flow>``, as SUMO defines number / period / vehsPerHour / probability."""
    begin = sumo_time(el.get("begin", "0"))
    end = sumo_time(el.get("end", str(default_end)))
    if el.get("number"):
        n = int(el.get("number", 0))
        period = float(el.get("period") or ((end - begin) / n if n else 1.0))
        return [begin + k * period for k in range(n)]
    if el.get("period", "").startswith("exp("):  # Poisson arrivals with the given rate
        rate = float(el.get("period", "")[4:-1])
        times, t = [], begin + rng.exponential(1.0 / rate)
        while t < end:
            times.append(t)
            t += rng.exponential(1.0 / rate)
        return times
    if el.get("period") or el.get("vehsPerHour"):
        period = float(el.get("period") or 3600.0 / float(el.get("vehsPerHour", 1)))
        return list(np.arange(begin, end, period))
    if el.get("probability"):
        p = float(el.get("probability", 0))
        steps = np.arange(begin, end, 1.0)  # one Bernoulli draw per second
        return [float(t) for t in steps[rng.random(len(steps)) < p]]
    raise ValueError(
        f"{source}: flow {el.get('id')!r} needs number, period, vehsPerHour or probability"
    )
