"""Origin-destination pairs of a bare network without listing every pair.

A bare network's trips run between its fringe edges (every edge where it has no fringe): on
a city grid that is thousands of origins times thousands of exits. Edges of one strongly
connected component reach the same edges, so one search per component serves them all, and
the kept pairs are picked by their position in the (entry, exit) order without building it.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import islice

import numpy as np

from mixed_traffic.world.routing import predecessors


def components(succ: dict[str, set[str]]) -> dict[str, int]:
    """Strongly connected component of each edge of ``succ`` (Kosaraju, iterative)."""
    order: list[str] = []
    seen: set[str] = set()
    for start in succ:
        if start in seen:
            continue
        seen.add(start)
        stack = [(start, iter(succ.get(start, ())))]
        while stack:
            v, nxt = stack[-1]
            for w in nxt:
                if w not in seen:
                    seen.add(w)
                    stack.append((w, iter(succ.get(w, ()))))
                    break
            else:
                stack.pop()
                order.append(v)
    pred = predecessors(succ)
    comp: dict[str, int] = {}
    for start in reversed(order):
        if start in comp:
            continue
        c, todo = len(comp), [start]
        comp[start] = c
        while todo:
            for w in pred.get(todo.pop(), ()):
                if w not in comp:
                    comp[w] = c
                    todo.append(w)
    return comp


def reach_sets(
    succ: dict[str, set[str]], starts: list[str], reachable: Callable[[str], set[str]]
) -> dict[str, set[str]]:
    """``reachable(o)`` for each ``o`` of ``starts``, one search per component (shared set)."""
    comp, shared = components(succ), {}
    out: dict[str, set[str]] = {}
    for o in starts:
        if comp[o] not in shared:
            shared[comp[o]] = reachable(o)
        out[o] = shared[comp[o]]
    return out


def spread_pairs(entries: list[str], exits: list[str], reach: dict[str, set[str]],
                 k: int) -> list[tuple[str, str]]:  # fmt: skip
    """Up to ``k`` (origin, destination) pairs spread evenly over the list of every pair (o, d),
    o in ``entries`` order and d in ``exits`` order, with d reachable from o and d != o; where
    there is none, over (o, o) for the entries that are exits. [] if none."""
    exit_set = set(exits)
    inside: dict[int, int] = {}  # exits in each shared reach set
    counts = np.array([inside.setdefault(id(reach[o]), len(exit_set & reach[o])) - (o in exit_set)
                       for o in entries], dtype=np.int64)  # fmt: skip
    total = int(counts.sum())
    if total == 0:
        loops = [(o, o) for o in entries if o in exit_set]
        return [loops[i] for i in _spread(len(loops), k)]
    ends = np.cumsum(counts)
    out = []
    for i in _spread(total, k):
        row = int(np.searchsorted(ends, i, side="right"))
        o = entries[row]
        skip = i - (int(ends[row - 1]) if row else 0)
        valid = (d for d in exits if d in reach[o] and d != o)
        out.append((o, next(islice(valid, skip, None))))
    return out


def _spread(n: int, k: int) -> list[int]:
    """``min(k, n)`` indices spread evenly over ``range(n)`` (the ends included)."""
    if n == 0:
        return []
    return [int(i) for i in np.unique(np.linspace(0, n - 1, min(k, n)).round())]
