"""Closed-loop (ring) scenarios: the loop's lanes, how many vehicles a density puts on each,
and where they stand at reset (evenly spaced all around the loop, with a random phase).

The loop is the first route's edges, in order; lane k of every edge and the junction lanes
between them form lane k of the loop. Positions are measured along a lane of the loop from
the start of its first edge, junction lanes included.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.scenario import Scenario


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
