"""Camera: the state of the next traffic light on each lane and the distance to its stop line."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.sensing import sensing_kernel
from mixed_traffic.sensing.lane_graph import CURRENT, LaneGraph
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Traffic-light state codes.
NO_LIGHT, RED, YELLOW, GREEN = -1, 0, 1, 2


_CODE = np.full(256, GREEN, dtype=np.int8)  # o/O (off) and unknown: no restriction
for _c in "rRs":
    _CODE[ord(_c)] = RED
for _c in "yYu":
    _CODE[ord(_c)] = YELLOW


def _link_chars(
    tls_states: Sequence[str], tl: np.ndarray, link: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(...) uint8 SUMO signal character of link ``link`` of light ``tl`` (an index into
    ``tls_states``) now, and (...) bool: that link exists (0 where not)."""
    chars = np.frombuffer("".join(tls_states).encode("ascii"), dtype=np.uint8)
    offsets = np.concatenate([[0], np.cumsum([len(s) for s in tls_states])]).astype(np.int64)
    flat = offsets[np.maximum(tl, 0)] + link
    ok = (tl >= 0) & (link >= 0) & (flat < len(chars))
    if not len(chars):
        return np.zeros(np.shape(flat), np.uint8), ok
    return chars[np.clip(flat, 0, len(chars) - 1)], ok


def traffic_lights(
    g: LaneGraph, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray, lanes: np.ndarray,
    next_edge: np.ndarray, tls_states: Sequence[str],
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(A, 3) ground-truth state code and stop-line distance of each lane's next signal."""
    A = len(rows)
    if not g.tls_ids or A == 0:
        return np.full((A, 3), NO_LIGHT, dtype=np.int8), np.full((A, 3), np.inf)
    if len(tls_states) != len(g.tls_ids):
        raise ValueError(
            f"tls_states has {len(tls_states)} strings, expected {len(g.tls_ids)} "
            f"(one per Perception.tls_ids)"
        )
    if compiled.enabled():
        chars = np.frombuffer("".join(tls_states).encode("ascii"), dtype=np.uint8)
        offsets = np.zeros(len(tls_states) + 1, np.int64)
        np.cumsum([len(s) for s in tls_states], out=offsets[1:])
        return sensing_kernel.traffic_lights(
            rows, lanes, next_edge, snap.lane_pos, hd.lane_length, g.tls_keys, g.tls_tl,
            g.tls_link, g.n_edges, g.next_edge, chars, offsets, _CODE,
        )  # fmt: skip
    lsafe = np.maximum(lanes, 0)
    tl, link = lane_signals(g, lanes, next_edge)
    chars, ok = _link_chars(tls_states, tl, link)
    state = np.where(ok, _CODE[chars], NO_LIGHT)
    ratio = hd.lane_length[lsafe] / np.maximum(hd.lane_length[lsafe[:, CURRENT]], 1e-9)[:, None]
    pos = snap.lane_pos[rows][:, None] * ratio
    dist = np.where(ok, np.maximum(hd.lane_length[lsafe] - pos, 0.0), np.inf)
    return state.astype(np.int8), dist


def lane_signals(g: LaneGraph, lanes: np.ndarray, next_edge: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(A, 3) light index (into ``g.tls_ids``) and link index of the signal at the end of each
    lane column (-1 where none): its link into the route's ``next_edge`` (A,), else the lane's
    own way on."""
    lsafe = np.maximum(lanes, 0)
    tl, link = g.signal(lanes, np.broadcast_to(next_edge[:, None], lanes.shape))
    tl2, link2 = g.signal(lanes, g.next_edge[lsafe])  # lane's own way on
    miss = tl < 0
    return np.where(miss, tl2, tl), np.where(miss, link2, link)


#: Signal characters at which a vehicle must yield to its link's foes: a permissive green
#: (g, e.g. a left turn across the oncoming stream) and a signal that is off, blinking (o).
PERMISSIVE = np.frombuffer(b"go", dtype=np.uint8)


def permissive(
    graph: LaneGraph, lane: np.ndarray, next_edge: np.ndarray, tls_states: Sequence[str]
) -> np.ndarray:
    """(A,) bool: the link from ``lane`` into ``next_edge`` is signalised and shows a
    ``PERMISSIVE`` character now (``tls_states`` in ``graph.tls_ids`` order)."""
    tl, link = graph.signal(np.asarray(lane), np.asarray(next_edge))
    chars, ok = _link_chars(tls_states, tl, link)
    return ok & np.isin(chars, PERMISSIVE)


def give_way(
    hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray, lane: np.ndarray, gate: np.ndarray,
    state: np.ndarray, dist: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """Mark in place the stop line at the end of each agent's current lane where it must give
    way (``gate`` (A,): RED while SUMO's junction model holds the link closed, GREEN while it is
    open, NO_LIGHT elsewhere) unless a nearer signal is seen, and over a permissive green at
    the line while the link is closed: right of way as SUMO rules it. Returns (A,) bool: where
    it marked a line."""
    ok = (gate != NO_LIGHT) & (lane >= 0)
    to_end = hd.lane_length[np.maximum(lane, 0)] - snap.lane_pos[rows]
    held = (gate == RED) & (to_end <= dist[:, CURRENT] + 0.5)
    mark = ok & ((state[:, CURRENT] == NO_LIGHT) | (to_end < dist[:, CURRENT]) | held)
    state[mark, CURRENT] = gate[mark]
    dist[mark, CURRENT] = np.maximum(to_end[mark], 0.0)
    return mark
