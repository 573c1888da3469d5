"""Routing of a bare network at city scale (issue 45) against the plain algorithms on real
networks: fastest paths against a full forward Dijkstra (a city's placement asks for a path
from every lane to every destination), OD pairs against listing every pair, placement edges
against one forward search per edge."""

from __future__ import annotations

import heapq
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mixed_traffic.world.backend import binary
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.od_pairs import components, reach_sets, spread_pairs
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.routing import TIE, fastest_path, step_cost, time_to
from mixed_traffic.world.user_scenario import MAX_OD_PAIRS, _Net


def full_search(hd: HDMap, lane: int, destination: int) -> list[int] | None:
    """The reference: Dijkstra forwards over the whole edge graph, no pruning."""
    start = int(hd.lane_edge[lane])
    if start == destination:
        return [start]
    heap = [(step_cost(hd, start, e), e, [start, e]) for e in hd.lane_exits.get(lane, ())]
    heapq.heapify(heap)
    done: set[int] = set()
    while heap:
        t, e, path = heapq.heappop(heap)
        if e == destination:
            return path
        if e in done:
            continue
        done.add(e)
        for n in hd.edge_successors.get(e, ()):
            if n not in done:
                heapq.heappush(heap, (t + step_cost(hd, e, n), n, [*path, n]))
    return None


def _grid(tmp_path) -> str:
    out = tmp_path / "grid.net.xml"
    subprocess.run([binary("netgenerate"), "--grid", "--grid.number=5", "--grid.length=150",
                    "--default.lanenumber=2", "--tls.guess", "--no-warnings", "--output-file",
                    str(out)], check=True, capture_output=True)  # fmt: skip
    return str(out)


def _time(hd: HDMap, path: list[int]) -> float:
    return sum(step_cost(hd, a, b) for a, b in zip(path, path[1:]))


@pytest.mark.parametrize("name", ["urban-eval", "grid"])
def test_paths_are_the_full_searchs_with_ties_by_edge_order(name: str, tmp_path) -> None:
    hd = load_scenario(_grid(tmp_path) if name == "grid" else name).hdmap
    lanes = [lane for lane in range(len(hd.lane_ids)) if hd.lane_edge[lane] >= 0]
    pairs = [(lane, d) for d in range(len(hd.edge_ids)) for lane in lanes]
    found = [fastest_path(hd, lane, d) for lane, d in pairs]
    full = [full_search(hd, lane, d) for lane, d in pairs]
    assert [p is None for p in found] == [p is None for p in full]
    both = [(a, b) for a, b in zip(found, full) if a is not None]
    assert all(abs(_time(hd, a) - _time(hd, b)) <= TIE * _time(hd, b) for a, b in both)
    differ = [(a, b) for a, b in both if a != b]
    assert all(a < b for a, b in differ)  # a tie up to the last bit: the lower edge rows
    assert sum(len(a) > 3 for a, _ in both) > len(both) // 4  # real detours
    d = len(hd.edge_ids) // 2  # the backward search reaches most edges, itself at 0 s
    assert time_to(hd, d)[d] == 0.0 and (time_to(hd, d) > 0).sum() >= len(hd.edge_ids) // 2


def listed_pairs(entries: list[str], exits: list[str], reach: dict, k: int) -> list:
    """The reference: every (entry, exit) pair listed, then ``k`` spread over the list."""
    pairs = [(o, d) for o in entries for d in exits if d in reach[o] and d != o]
    pairs = pairs or [(o, o) for o in entries if o in exits]
    idx = np.unique(np.linspace(0, len(pairs) - 1, min(k, len(pairs))).round()) if pairs else []
    return [pairs[int(i)] for i in idx]


@pytest.mark.parametrize("name", ["grid", "DRT/osm.net.xml", "bs3d/bs.net.xml"])
def test_od_pairs_and_placement_edges_equal_the_listed_ones(name: str, tmp_path) -> None:
    import sumo

    path = Path(_grid(tmp_path) if name == "grid" else Path(sumo.SUMO_HOME) / "tools/game" / name)
    net = _Net(path)
    entries, exits = net.fringe()
    reach = {o: net.reachable(o) for o in entries}
    for k in (1, 5, MAX_OD_PAIRS):
        assert spread_pairs(entries, exits, reach_sets(net.succ, entries, net.reachable), k) == \
            listed_pairs(entries, exits, reach, k)  # fmt: skip
    ends = set(exits[:: max(1, len(exits) // 4)])
    assert net.reaching(ends) == {e for e in net.lanes if ends <= net.reachable(e)}
    assert len(set(components(net.succ).values())) < len(net.succ)  # components were merged
