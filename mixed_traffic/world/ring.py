"""Closed-loop (ring) scenarios: the loop's lanes, how many vehicles a density puts on each,
and where they stand at reset (evenly spaced all around the loop, with a random phase).

The loop is the first route's edges, in order; lane k of every edge and the junction lanes
between them form lane k of the loop. Positions are measured along a lane of the loop from
the start of its first edge, junction lanes included.

A bundled ring can be scaled to another circumference (``EnvConfig.ring_length``): its plain
XML sources with every coordinate scaled, rebuilt by netconvert and cached by length.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from mixed_traffic.paths import cache_dir
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.network import build_network
from mixed_traffic.world.scenario import Scenario

LENGTH_STEP = 0.1
"""Resolution of drawn ring lengths [m]: one network per step is built and cached."""


def loop_edges(scenario: Scenario) -> tuple[str, ...]:
    """One lap: the first route's edges up to where they repeat."""
    edges = scenario.routes[0].edges
    return edges[: edges.index(edges[0], 1)] if edges.count(edges[0]) > 1 else edges


def loop_lane(hd: HDMap, loop: tuple[str, ...], lane: int) -> list[tuple[str, int, float, float]]:
    """Lane ``lane`` of the loop: per edge (edge id, lane row, lane length [m], length of the
    junction lanes to the next edge [m])."""
    out = []
    for edge in loop:
        row = int(hd.edge_lanes[hd.edge_of(edge), lane])
        junction, nxt = 0.0, int(hd.lane_next[row])
        while nxt >= 0 and hd.lane_edge[nxt] < 0:
            junction += float(hd.lane_length[nxt])
            nxt = int(hd.lane_next[nxt])
        out.append((edge, row, float(hd.lane_length[row]), junction))
    return out


def loop_lanes(scenario: Scenario) -> int:
    """Lanes every edge of the loop has."""
    hd = scenario.hdmap
    return int(min(hd.edge_num_lanes[hd.edge_of(e)] for e in loop_edges(scenario)))


def ring_lengths(scenario: Scenario) -> list[float]:
    """Length of each lane of the loop, junction lanes included [m]."""
    hd, loop = scenario.hdmap, loop_edges(scenario)
    return [
        sum(n + j for _, _, n, j in loop_lane(hd, loop, k)) for k in range(loop_lanes(scenario))
    ]


def ring_counts(scenario: Scenario, per_lane: float) -> list[int]:
    """Vehicles on each lane of the loop at ``per_lane`` [veh/m]: independent of the seed."""
    return [round(length * per_lane) for length in ring_lengths(scenario)]


def ring_positions(
    scenario: Scenario, lane: int, n: int, phase: float
) -> list[tuple[str, int, float]]:
    """``n`` vehicles evenly spaced on lane ``lane`` of the loop, the first ``phase`` [0-1) of a
    spacing after its start: (edge id, lane row, position on the edge [m]) each. A vehicle that
    would stand on a junction lane moves to the start of the next edge."""
    parts = loop_lane(scenario.hdmap, loop_edges(scenario), lane)
    length = sum(n_ + j for _, _, n_, j in parts)
    spacing = length / n
    starts = np.cumsum([0.0] + [n_ + j for _, _, n_, j in parts])
    out = []
    for s in (phase + np.arange(n)) * spacing:
        k = int(np.searchsorted(starts, s, side="right") - 1)
        edge, row, edge_len, _ = parts[k]
        out.append((edge, row, min(s - starts[k], edge_len)))
    return out


def draw_ring_length(spec: tuple[float, ...], rng: np.random.Generator) -> float:
    """The circumference of one episode [m]: the one value of ``spec``, or one drawn uniformly
    from its (low, high) pair, on the ``LENGTH_STEP`` grid."""
    lo, hi = spec[0], spec[-1]
    return round(round(float(rng.uniform(lo, hi)) / LENGTH_STEP) * LENGTH_STEP, 1)


def episode_ring(
    bundled: Scenario, spec: tuple[float, ...], rng: np.random.Generator | None
) -> tuple[Scenario, float | None]:
    """The scenario of an episode and its ring's centre-line length [m] (None: no ring): the
    bundled ring, or scaled to ``spec``'s one length, or to a length ``rng`` draws from its
    (low, high) pair (``rng`` None: the longest, which sizes ``possible_agents``)."""
    if not bundled.ring:
        return bundled, None
    if not spec:
        return bundled, round(centre_length(bundled), 1)
    length = draw_ring_length(spec, rng) if rng is not None and len(spec) == 2 else spec[-1]
    return scaled_ring(bundled, length), length


def centre_length(scenario: Scenario) -> float:
    """Length of a bundled ring's centre line [m]: its edges' shapes (or their nodes) summed."""
    nodes, edges = _sources(scenario.source)
    return sum(_polyline_length(_shape(e, nodes)) for e in edges.iter("edge"))


def scaled_ring(scenario: Scenario, length: float) -> Scenario:
    """``scenario`` with its centre line scaled to ``length`` [m] (lanes, widths and speed
    limits unchanged); the network is built once per length and cached."""
    net = _scaled_net(scenario.source, round(length, 1))
    return replace(scenario, net_file=net, description=f"{scenario.description}; scaled to "
                   f"{length:g} m")  # fmt: skip


@lru_cache(maxsize=64)
def _scaled_net(source: Path, length: float) -> Path:
    nodes, edges = _sources(source)
    factor = length / sum(_polyline_length(_shape(e, nodes)) for e in edges.iter("edge"))
    for node in nodes.iter("node"):
        for axis in ("x", "y"):
            node.set(axis, f"{float(node.get(axis)) * factor:.4f}")
    for edge in edges.iter("edge"):
        if edge.get("shape"):
            points = np.array(_points(edge.get("shape"))) * factor
            edge.set("shape", " ".join(f"{x:.4f},{y:.4f}" for x, y in points))
    folder = cache_dir("rings") / f"{source.parent.name}-{source.name}-{length:.1f}m"
    folder.mkdir(parents=True, exist_ok=True)
    _write_atomic(folder / "ring.nod.xml", ET.tostring(nodes, encoding="unicode"))
    _write_atomic(folder / "ring.edg.xml", ET.tostring(edges, encoding="unicode"))
    args = source / "netconvert.args"
    if args.exists():
        _write_atomic(folder / "netconvert.args", args.read_text())
    return build_network(folder)


def _sources(folder: Path | None) -> tuple[ET.Element, ET.Element]:
    """The (nodes, edges) roots of a bundled ring's one .nod.xml and one .edg.xml."""
    nod = sorted(folder.glob("*.nod.xml")) if folder else []
    edg = sorted(folder.glob("*.edg.xml")) if folder else []
    others = [
        p for k in ("con", "tll", "typ") for p in (folder.glob(f"*.{k}.xml") if folder else ())
    ]
    if len(nod) != 1 or len(edg) != 1 or others:
        raise ValueError(f"a ring to scale needs exactly one .nod.xml and one .edg.xml in its "
                         f"folder (and nothing else netconvert reads): {folder}")  # fmt: skip
    return ET.parse(nod[0]).getroot(), ET.parse(edg[0]).getroot()


def _points(shape: str) -> list[tuple[float, float]]:
    return [tuple(map(float, p.split(",")[:2])) for p in shape.split()]


def _shape(edge: ET.Element, nodes: ET.Element) -> list[tuple[float, float]]:
    """The edge's shape points, or its two nodes when it has none."""
    if edge.get("shape"):
        return _points(edge.get("shape"))
    at = {n.get("id"): (float(n.get("x")), float(n.get("y"))) for n in nodes.iter("node")}
    return [at[edge.get("from")], at[edge.get("to")]]


def _polyline_length(points: list[tuple[float, float]]) -> float:
    return float(np.hypot(*np.diff(np.array(points), axis=0).T).sum())


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` unless ``path`` already holds it (parallel workers build the same ring)."""
    if path.exists() and path.read_text() == text:
        return
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(text)
    tmp.replace(path)
