"""The backward-search fastest paths against a full forward Dijkstra on real networks (issue
45: a city's placement asks for a path from every lane to every destination)."""

from __future__ import annotations

import heapq
import subprocess

import pytest

from mixed_traffic.world.backend import binary
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.registry import load_scenario
from mixed_traffic.world.routing import TIE, fastest_path, step_cost, time_to


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
