"""Batched worlds: N independent copies of a scenario in one SUMO network
(``EnvConfig.copies``), so that one simulation step, one state read and one pass of every env
stage serve N copies of a task (Flow's ``multi_ring`` does this for rings).

Copy i is the scenario's network with every edge and junction id prefixed ``c<i>_`` and moved
along y (netconvert's ``--prefix`` and ``--offset.y``), then all copies are joined into one
network by netconvert, with ``GAP`` metres between their bounding boxes: far beyond the sensors'
reach, so no vehicle, sensor or V2X feed of one copy meets another. Joined networks are cached
by content. Each copy has a view: the scenario with its own prefixed routes, measurement
segment and placement edges on the joined network (``Batch.views``).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import tempfile
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from mixed_traffic.config import EnvConfig, HumanConfig
from mixed_traffic.paths import cache_dir
from mixed_traffic.world.backend import SumoBackend, binary
from mixed_traffic.world.boundary import PeriodicBoundary, make_boundary
from mixed_traffic.world.demand import Demand, make_demand
from mixed_traffic.world.drivers import HUMAN_TYPE
from mixed_traffic.world.fleet_pool import FleetPool
from mixed_traffic.world.hdmap import HDMap, load_hdmap
from mixed_traffic.world.scenario import Route, Scenario
from mixed_traffic.world.snapshot import TrafficSnapshot

GAP = 1000.0
"""Space between the bounding boxes of two copies [m]: ten times the LiDAR's 90 m."""
BYTES_PER_VEHICLE = 80_000
"""Memory a batch needs per planned vehicle [bytes]: 64 copies of ``straight`` (12,275
vehicles) took 894 MB more than one copy (73 KB each: SUMO, the joined network, the env)."""
FAMILIES = ("ring", "straight", "highway", "wave-highway", "merge", "bottleneck")
"""Scenario families whose copies are independent: each copy's vehicles stay on its own roads
(urban grids and user networks route by SUMO over the whole network and are refused)."""


def prefix(copy: int) -> str:
    """The id prefix of copy ``copy``'s edges and junctions."""
    return f"c{copy}_"


def copy_of_id(sumo_id: str) -> int:
    """The copy of a prefixed edge, lane or junction id (``c3_meas_0`` and ``:c3_J1_0_0``
    are copy 3); ValueError for an id of no copy."""
    head = sumo_id.lstrip(":")
    if not head.startswith("c") or "_" not in head or not head[1 : head.index("_")].isdigit():
        raise ValueError(f"{sumo_id!r} is no copy's id (c<i>_...)")
    return int(head[1 : head.index("_")])


def vehicle_copy(vid: str, per_copy: int) -> int:
    """The copy of vehicle ``vid``: ``av_k`` drives in copy k // ``per_copy`` (the AVs a copy
    can have), ``c<i>.<id>`` in copy i, any other id in copy 0 (one copy's ids)."""
    if vid.startswith("av_"):
        return int(vid[3:]) // max(per_copy, 1)
    dot = vid.find(".")
    return int(vid[1:dot]) if vid.startswith("c") and vid[1:dot].isdigit() else 0


def copyable(scenario: Scenario) -> bool:
    """Whether ``scenario`` can run several copies in one network (``FAMILIES``)."""
    return scenario.source is not None and scenario.family in FAMILIES


def check_copies(scenario: Scenario, copies: int) -> None:
    """ValueError naming the scenario unless it can run ``copies`` copies in one network."""
    if copies == 1:
        return
    if not copyable(scenario):
        kind = "a user's network" if scenario.source is None else f"the {scenario.family} family"
        raise ValueError(f"copies={copies}: {scenario.name!r} is {kind}, whose vehicles SUMO "
                         f"may route anywhere; batched worlds support {', '.join(FAMILIES)}")  # fmt: skip


def check_memory(copies: int, vehicles: int) -> None:
    """ValueError unless ``copies`` copies of ``vehicles`` planned vehicles each fit in the
    memory available now (``BYTES_PER_VEHICLE``)."""
    need = copies * vehicles * BYTES_PER_VEHICLE
    free = _available_memory()
    if need > free:
        raise ValueError(f"copies={copies}: {copies * vehicles} vehicles need about "
                         f"{need / 2**30:.1f} GiB, more than the {free / 2**30:.1f} GiB available; "
                         "run fewer copies")  # fmt: skip


def _available_memory() -> int:
    """Memory available to new work [bytes] (MemAvailable, else all physical memory)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


@dataclass(frozen=True)
class Batch:
    """``len(views)`` copies of one scenario in one network."""

    net_file: Path
    """The joined network."""
    views: tuple[Scenario, ...]
    """Copy i's scenario on the joined network: its routes, measurement segment and placement
    edges carry its prefix."""

    @property
    def copies(self) -> int:
        return len(self.views)

    @cached_property
    def lane_copy(self) -> np.ndarray:
        """(L,) int32 copy of each lane row of the joined HD map (junction lanes included)."""
        return self._copies_of(self.views[0].hdmap.lane_ids)

    @cached_property
    def edge_copy(self) -> np.ndarray:
        """(E,) int32 copy of each edge row."""
        return self._copies_of(self.views[0].hdmap.edge_ids)

    def _copies_of(self, ids: list[str]) -> np.ndarray:
        if self.copies == 1:
            return np.zeros(len(ids), np.int32)
        return np.array([copy_of_id(x) for x in ids], dtype=np.int32)


def make_batch(scenarios: tuple[Scenario, ...]) -> Batch:
    """The batch of ``scenarios`` (one per copy: the same scenario, or rings of different
    lengths), their networks joined in copy order; one scenario is its own batch, unchanged."""
    if len(scenarios) == 1:
        return Batch(scenarios[0].net_file, scenarios)
    net = joined_network(tuple(s.net_file for s in scenarios))
    return Batch(net, tuple(copy_view(s, net, i) for i, s in enumerate(scenarios)))


def copy_view(scenario: Scenario, net: Path, copy: int) -> Scenario:
    """``scenario`` as copy ``copy`` of the joined network ``net``."""
    p = prefix(copy)

    def edges(ids: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(p + e for e in ids)

    def route(r: Route) -> Route:
        return replace(r, edges=edges(r.edges), origin=p + r.origin if r.origin else "",
                       destination=p + r.destination if r.destination else "")  # fmt: skip

    return replace(scenario, name=f"{scenario.name}[{copy}]", net_file=net,
                   routes=tuple(map(route, scenario.routes)),
                   measurement=edges(scenario.measurement),
                   placement_edges=edges(scenario.placement_edges))  # fmt: skip


def joined_network(nets: tuple[Path, ...]) -> Path:
    """One network of ``nets`` side by side, copy i the i-th with its ids prefixed; built by
    netconvert once and cached by the files' content."""
    h = hashlib.sha256(f"copies-v1 gap={GAP}".encode())
    for net in nets:
        h.update(hashlib.sha256(net.read_bytes()).digest())
    out = cache_dir("nets") / f"copies{len(nets)}-{h.hexdigest()[:16]}.net.xml"
    if out.exists():
        return out
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        parts, y = [], 0.0
        for i, net in enumerate(nets):
            lo, hi = _y_extent(load_hdmap(net))
            part = Path(tmp) / f"c{i}.net.xml"
            _netconvert(["-s", str(net), "--prefix", prefix(i), "--offset.y", f"{y - lo:.3f}"],
                        part)  # fmt: skip
            parts.append(str(part))
            y += hi - lo + GAP
        joined = Path(tmp) / "joined.net.xml"
        _netconvert(["-s", ",".join(parts)], joined)
        joined.replace(out)
    return out


def _y_extent(hd: HDMap) -> tuple[float, float]:
    """(lowest, highest) y of the network's lane centrelines [m]."""
    return float(hd.wp_xyz[:, 1].min()), float(hd.wp_xyz[:, 1].max())


def _netconvert(args: list[str], out: Path) -> None:
    proc = subprocess.run([binary("netconvert"), *args, "--output-file", str(out),
                           "--no-warnings"], capture_output=True, text=True)  # fmt: skip
    if proc.returncode != 0 or not out.exists():
        raise ValueError(f"netconvert failed joining copies: {proc.stderr.strip()[-500:]}")


# --------------------------------------------------------------------------- demand
def batch_demand(
    batch: Batch, config: EnvConfig, seed: int, per_copy: int
) -> tuple[Demand, tuple[Demand, ...]]:
    """The episode's demand as SUMO's route file holds it, and each copy's part.

    One copy: ``make_demand`` of its scenario under ``seed``, unchanged. Several: copy i draws
    its demand from its own stream (``SeedSequence(seed).spawn``), its AVs are ``av_{i·per_copy
    + k}`` (``per_copy``: the AVs a copy can have) and its humans ``c<i>.hv_j``, each with its
    driver type drawn from the copy's stream, so that no copy's draws depend on another's."""
    if batch.copies == 1:
        d = make_demand(batch.views[0], config, np.random.default_rng(seed))
        return d, (d,)
    streams = np.random.SeedSequence(seed).spawn(batch.copies)
    parts = []
    for i, (view, stream) in enumerate(zip(batch.views, streams)):
        demand_rng, type_rng = (np.random.default_rng(s) for s in stream.spawn(2))
        d = make_demand(view, config, demand_rng)
        parts.append(_renamed(d, i, i * per_copy, type_rng, config.human))
    return _joined(parts), tuple(parts)


def _renamed(demand: Demand, copy: int, first_av: int, rng: np.random.Generator,
             human: HumanConfig) -> Demand:  # fmt: skip
    """``demand`` of copy ``copy``: AVs numbered from ``first_av``, humans prefixed and given a
    driver type of the population each."""

    def rename(vid: str) -> str:
        if vid.startswith("av_"):
            return f"av_{first_av + int(vid[3:])}"
        return f"c{copy}.{vid}"

    def human_type() -> str:
        return f"{HUMAN_TYPE}{int(rng.integers(human.driver_types))}"

    vehicles = tuple(replace(v, vid=rename(v.vid), vtype=None if v.is_av else human_type())
                     for v in demand.vehicles)  # fmt: skip
    queue = tuple(replace(q, vid=rename(q.vid), vtype=None if q.is_av else human_type())
                  for q in demand.queue)  # fmt: skip
    return replace(demand, vehicles=vehicles, queue=queue)


def _joined(parts: list[Demand]) -> Demand:
    """One demand of the copies' parts: their routes in copy order, their vehicles by
    departure (a copy's placed vehicles keep their order)."""
    first = np.cumsum([0, *(len(d.routes) for d in parts)])
    vehicles = [replace(v, route=v.route + int(r0)) for d, r0 in zip(parts, first)
                for v in d.vehicles]  # fmt: skip
    queue = [replace(q, route=q.route + int(r0)) for d, r0 in zip(parts, first) for q in d.queue]
    return Demand(
        routes=tuple(r for d in parts for r in d.routes),
        vehicles=tuple(sorted(vehicles, key=lambda v: v.depart)),
        queue=tuple(queue),
        equilibrium_speed=parts[0].equilibrium_speed,
        inflow=sum(d.inflow for d in parts),
    )


# --------------------------------------------------------------------------- boundaries
def batch_boundary(batch: Batch, parts: tuple[Demand, ...], human: HumanConfig, dt: float,
                   fleet: list[str] | None, per_copy: int) -> PeriodicBoundary | FleetPool | Boundaries:  # fmt: skip
    """What brings vehicles in during an episode: ``make_boundary`` of the one copy, or one
    per copy behind ``Boundaries``."""
    if batch.copies == 1:
        return make_boundary(batch.views[0], parts[0], human, dt, fleet)
    first = np.cumsum([0, *(len(d.routes) for d in parts)])
    each = []
    for i, (view, demand) in enumerate(zip(batch.views, parts)):
        own = fleet[i * per_copy : (i + 1) * per_copy] if fleet is not None else None
        each.append(make_boundary(view, demand, human, dt, own, int(first[i])))
    return Boundaries(each, per_copy)


@dataclass
class Boundaries:
    """One boundary per copy, each handed the vehicles of its copy that left."""

    parts: list[PeriodicBoundary]
    per_copy: int
    """AVs a copy can have: ``av_k`` belongs to copy k // per_copy."""

    def step(self, snap: TrafficSnapshot, backend: SumoBackend) -> None:
        for part, left in zip(self.parts, self._split(snap.left)):
            part.step(snap, backend, left)

    def replace(self, backend: SumoBackend, gone: list[str]) -> None:
        for part, left in zip(self.parts, self._split(gone)):
            part.replace(backend, left)

    def _split(self, vids: list[str]) -> list[list[str]]:
        out: list[list[str]] = [[] for _ in self.parts]
        for vid in vids:
            out[vehicle_copy(vid, self.per_copy)].append(vid)
        return out

    @property
    def inserted(self) -> int:
        return sum(p.inserted for p in self.parts)
