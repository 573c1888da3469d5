"""Ground-truth neighbour search: the front and rear vehicle of each agent in its left,
current and right lane (``find_neighbours``), with vehicles in the way from other lanes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.sensing import blockers_kernel, neighbours_kernel, sensing_kernel
from mixed_traffic.sensing.blockers import PATH_GEOMETRY, path_blockers
from mixed_traffic.sensing.lane_graph import CURRENT, LEFT, RIGHT, SEARCH_DEPTH, lane_graph
from mixed_traffic.sensing.merges import merge_leaders
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Vehicles ahead on each neighbour lane checked for straddling into the ego's way.
STRADDLE_DEPTH = 3
#: Lateral clearance below which a straddling vehicle counts as in the ego's way [m].
STRADDLE_MARGIN = 0.2


@dataclass
class Neighbours:
    """Front and rear vehicle of each agent in its (left, current, right) lanes.

    Shapes: A agents, 3 lanes (columns LEFT, CURRENT, RIGHT), 2 slots (0 = front, 1 = rear).
    """

    lane: np.ndarray
    """(A, 3) int64 lane row, -1 if the lane does not exist."""
    vehicle: np.ndarray
    """(A, 3, 2) int64 snapshot row of the front / rear vehicle, -1 if none within range."""
    distance: np.ndarray
    """(A, 3, 2) along-lane front-bumper distance [m], + ahead; +inf / -inf when missing."""
    on_path: np.ndarray | None = None
    """(A,) bool: the current lane's front vehicle is one on another lane whose body lies on
    the ego's path ahead (across a junction, ``path_blockers``, or straddling in from a
    neighbour lane); its distance and ``path_geometry`` are then measured along the ego's
    path. None = no such test."""
    path_geometry: np.ndarray | None = None
    """(A, 4) ``PATH_GEOMETRY`` of that vehicle where ``on_path`` (0 elsewhere)."""

    @property
    def front(self) -> np.ndarray:
        """(A, 3) front vehicle rows."""
        return self.vehicle[:, :, 0]

    @property
    def rear(self) -> np.ndarray:
        """(A, 3) rear vehicle rows."""
        return self.vehicle[:, :, 1]

    @property
    def front_dist(self) -> np.ndarray:
        """(A, 3) [m] >= 0, +inf when missing."""
        return self.distance[:, :, 0]

    @property
    def rear_dist(self) -> np.ndarray:
        """(A, 3) [m] <= 0, -inf when missing."""
        return self.distance[:, :, 1]


class _Sorted(NamedTuple):
    """All vehicles on a lane, sorted once by (lane, position)."""

    order: np.ndarray
    """(M,) snapshot rows in sorted order."""
    key: np.ndarray
    """(M,) sort keys lane * offset + position."""
    pos: np.ndarray
    """(M,) lane positions [m]."""
    start: np.ndarray
    """(L+1,) first sorted index of each lane (and the end)."""
    rank: np.ndarray
    """(N,) sorted index of each snapshot row (-1 off-lane)."""


def _sort_by_lane(snap: TrafficSnapshot, n_lanes: int, offset_key: float) -> _Sorted:
    vlane = snap.lane.astype(np.int64)
    on = np.flatnonzero(vlane >= 0)
    key_all = vlane * offset_key + snap.lane_pos
    order = on[np.argsort(key_all[on], kind="stable")]
    start = np.searchsorted(key_all[order], np.arange(n_lanes + 1) * offset_key - 1e-3)
    rank = np.full(snap.n, -1, dtype=np.int64)
    rank[order] = np.arange(len(order))
    return _Sorted(order, key_all[order], snap.lane_pos[order], start, rank)


def find_neighbours(
    snap: TrafficSnapshot,
    hdmap: HDMap,
    rows: np.ndarray,
    max_range: float,
    next_edge: np.ndarray | None = None,
    via: np.ndarray | None = None,
) -> Neighbours:
    """Ground-truth front/rear vehicles in the left, current and right lane of each agent.

    Vehicles are sorted once by (lane, lane_pos); each query is a ``searchsorted``, and the
    search continues into successor / predecessor lanes for at most ``SEARCH_DEPTH`` lanes.

    Args:
        snap: the current snapshot (N vehicles).
        hdmap: the network's map.
        rows: (A,) snapshot rows of the querying agents.
        max_range: vehicles farther than this along the lane are not reported [m].
        next_edge: optional (A,) next route edge row per agent (-1 = none); used for the first
            hop ahead (route-aware successor); else the primary successor is followed.
        via: (A,) lane the current lane leads into as SUMO chose it where the lane fans out
            (-1: the map's connection to ``next_edge``).
    Returns:
        ``Neighbours`` with (A, 3) lanes and (A, 3, 2) vehicles and distances.
    """
    rows = np.asarray(rows, dtype=np.int64)
    srt, lanes, pos, succ, prev = _setup(snap, hdmap, rows, next_edge, via)
    search = _compiled if compiled.enabled() else _reference
    i, vehicle, distance, straddle = search(snap, hdmap, rows, lanes, pos, srt, succ, prev,
                                            max_range)  # fmt: skip
    on_path, geom = _in_the_way(snap, hdmap, rows, vehicle, distance, max_range, next_edge, via,
                                straddle)  # fmt: skip
    return Neighbours(lanes, vehicle.astype(np.int64), distance, on_path, geom)


def _setup(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, next_edge: np.ndarray | None,
           via: np.ndarray | None) -> tuple:  # fmt: skip
    """The search's inputs: the lane sort (``_Sorted``), the (A, 3) query ``lanes`` and
    projected positions ``pos`` [m] (``_query_lanes``), and the (A, 3) first successor
    (``_successors``) and predecessor lanes (-1 none)."""
    g = lane_graph(hdmap)
    if compiled.enabled():  # one kernel; -1 next edges and vias change nothing
        none = np.full(len(rows), -1, np.int64)
        nxt = none if next_edge is None else np.asarray(next_edge, np.int64)
        chosen = none if via is None else np.asarray(via, np.int64)
        lanes, pos, succ, prev = sensing_kernel.query_lanes(
            rows, snap.lane, snap.lane_pos, g.lane3, hdmap.lane_length, hdmap.lane_next, g.pred,
            g.conn_keys, g.conn_vals, g.n_edges, nxt, chosen,
        )  # fmt: skip
        srt = _Sorted(*sensing_kernel.lane_sort(snap.lane, snap.lane_pos, hdmap.n_lanes,
                                                g.lane_offset_key))  # fmt: skip
        return srt, lanes, pos, succ, prev
    srt = _sort_by_lane(snap, hdmap.n_lanes, g.lane_offset_key)
    lanes, pos = _query_lanes(snap, hdmap, rows)
    has, lsafe = lanes >= 0, np.maximum(lanes, 0)
    succ = _successors(hdmap, lsafe, next_edge, via)
    return srt, lanes, pos, succ, np.where(has, g.pred[lsafe], -1)


def _query_lanes(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(A, 3) the agents' left, current and right lanes (-1 none), and (A, 3) their
    positions projected onto them [m] (scaled by the lane lengths; 0 where none)."""
    lane_len = hdmap.lane_length
    ego_lane = snap.lane.astype(np.int64)[rows]
    cur = np.where(ego_lane >= 0, ego_lane, -1)
    lanes = lane_graph(hdmap).lane3[np.maximum(cur, 0)]  # (A, 3) left, current, right
    lanes[cur < 0] = -1
    has = lanes >= 0
    ratio = lane_len[np.maximum(lanes, 0)] / np.maximum(lane_len[np.maximum(cur, 0)], 1e-9)[:, None]
    return lanes, np.where(has, snap.lane_pos[rows][:, None] * ratio, 0.0)


def _successors(hdmap: HDMap, lsafe: np.ndarray, next_edge: np.ndarray | None,
                via: np.ndarray | None) -> np.ndarray:  # fmt: skip
    """(A, 3) the lane each column continues into: towards ``next_edge`` where it connects
    there, SUMO's choice ``via`` for the current lane, else the primary successor."""
    succ = hdmap.lane_next[lsafe].astype(np.int64)
    if next_edge is not None:
        nxt = np.broadcast_to(np.asarray(next_edge)[:, None], lsafe.shape)
        conn = lane_graph(hdmap).connection(lsafe, nxt)
        succ = np.where(conn >= 0, conn, succ)
    if via is not None:
        succ[:, CURRENT] = np.where(via >= 0, via, succ[:, CURRENT])
    return succ


def _reference(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, lanes: np.ndarray,
               pos: np.ndarray, srt: _Sorted, succ: np.ndarray, prev: np.ndarray,
               max_range: float) -> tuple:  # fmt: skip
    """The numpy search (the kernel's reference): the sorted start indices ``i`` (A, 3),
    ``vehicle`` and ``distance`` (A, 3, 2), and the straddler (``_straddlers``)."""
    g, lane_len = lane_graph(hdmap), hdmap.lane_length
    has, lsafe = lanes >= 0, np.maximum(lanes, 0)
    cur = lanes[:, CURRENT]
    i, front, fdist, rear, rdist = _same_lane(srt, rows, cur, lsafe, has, pos, g.lane_offset_key)
    if len(srt.order):
        front, fdist = _nearer_beside(snap, hdmap, rows, lanes, srt, pos, front, fdist, i + (np.arange(3) == CURRENT), +1)  # fmt: skip
        rear, rdist = _nearer_beside(snap, hdmap, rows, lanes, srt, pos, rear, rdist, i - 1, -1)
        offset = np.where(has, lane_len[lsafe] - pos, np.inf)  # distance to the lane end
        front, fdist = _ahead(srt, hdmap, rows, succ, offset, front, fdist, max_range)
        back = np.where(has, pos, np.inf)  # distance from the lane start
        rear, rdist = _behind(srt, hdmap, g.pred, rows, prev, back, rear, rdist, max_range)
    f_in = (front >= 0) & (fdist <= max_range)
    r_in = (rear >= 0) & (-rdist <= max_range)
    vehicle = np.stack([np.where(f_in, front, -1), np.where(r_in, rear, -1)], axis=2)
    distance = np.stack([np.where(f_in, fdist, np.inf), np.where(r_in, rdist, -np.inf)], axis=2)
    return i, vehicle, distance, _straddlers(snap, hdmap, rows, lanes, i, pos, srt, max_range)


def _compiled(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, lanes: np.ndarray,
              pos: np.ndarray, srt: _Sorted, succ: np.ndarray, prev: np.ndarray,
              max_range: float) -> tuple:  # fmt: skip
    """:func:`_reference` as one compiled kernel (:mod:`.neighbours_kernel`)."""
    g = lane_graph(hdmap)
    i, vehicle, distance, best, gap, lat = neighbours_kernel.search(
        rows, lanes, pos, srt.order, srt.key, srt.pos, srt.start, srt.rank, succ, prev,
        hdmap.lane_length, hdmap.lane_next, g.pred, hdmap.lane_width, snap.lane_pos,
        snap.lateral, snap.length, snap.width, g.lane_offset_key, max_range, SEARCH_DEPTH,
        STRADDLE_DEPTH, STRADDLE_MARGIN,
    )  # fmt: skip
    return i, vehicle, distance, (best, gap, _straddle_geometry(snap, best, lat))


def _same_lane(srt: _Sorted, rows: np.ndarray, cur: np.ndarray, lsafe: np.ndarray,
               has: np.ndarray, pos: np.ndarray, offset_key: float):  # fmt: skip
    """On each query lane: the first vehicle at >= pos (neighbour lanes) or right after the
    ego (current lane), and the one before. Returns the sorted index ``i`` (A, 3) the search
    started from, and front / rear rows and distances (A, 3)."""
    order, s_pos, start = srt.order, srt.pos, srt.start
    i = np.searchsorted(srt.key, lsafe * offset_key + pos, side="left")
    i[:, CURRENT] = np.where(cur >= 0, srt.rank[rows], 0)
    fi = i + np.where(np.arange(3) == CURRENT, 1, 0)[None, :]
    ri = i - 1
    f_ok = has & (fi < start[lsafe + 1])
    r_ok = has & (ri >= start[lsafe])
    n_sorted = max(len(order), 1)
    front = np.where(f_ok, order[np.minimum(fi, n_sorted - 1)] if len(order) else -1, -1)
    rear = np.where(r_ok, order[np.clip(ri, 0, n_sorted - 1)] if len(order) else -1, -1)
    fdist = np.where(f_ok, s_pos[np.minimum(fi, n_sorted - 1)] - pos if len(order) else 0, np.inf)
    rdist = np.where(r_ok, s_pos[np.clip(ri, 0, n_sorted - 1)] - pos if len(order) else 0, -np.inf)
    return i, front, fdist, rear, rdist


def _ahead(srt: _Sorted, hdmap: HDMap, rows: np.ndarray, succ: np.ndarray, offset: np.ndarray,
           front: np.ndarray, fdist: np.ndarray, max_range: float):  # fmt: skip
    """Lanes without a front vehicle: the first vehicle on their successor lanes, ``offset``
    (A, 3) [m] from the query position to the lane end; at most ``SEARCH_DEPTH`` lanes."""
    order, count, lane_len = srt.order, np.diff(srt.start), hdmap.lane_length
    for _ in range(SEARCH_DEPTH):
        todo = (front < 0) & (succ >= 0) & (offset <= max_range)
        if not todo.any():
            break
        ss = np.maximum(succ, 0)
        hit = todo & (count[ss] > 0)
        first = srt.start[ss]
        cand = order[np.minimum(first, len(order) - 1)]
        hit &= cand != rows[:, None]
        front = np.where(hit, cand, front)
        fdist = np.where(hit, offset + srt.pos[np.minimum(first, len(order) - 1)], fdist)
        offset = np.where(todo, offset + lane_len[ss], np.inf)
        succ = np.where(todo, hdmap.lane_next[ss], -1)
    return front, fdist


def _behind(srt: _Sorted, hdmap: HDMap, pred: np.ndarray, rows: np.ndarray, prev: np.ndarray,
            back: np.ndarray, rear: np.ndarray, rdist: np.ndarray, max_range: float):  # fmt: skip
    """Lanes without a rear vehicle: the last vehicle on their predecessor lanes, ``back``
    (A, 3) [m] from the lane start to the query position; at most ``SEARCH_DEPTH`` lanes."""
    order, count, lane_len = srt.order, np.diff(srt.start), hdmap.lane_length
    for _ in range(SEARCH_DEPTH):
        todo = (rear < 0) & (prev >= 0) & (back <= max_range)
        if not todo.any():
            break
        pp = np.maximum(prev, 0)
        hit = todo & (count[pp] > 0)
        last = np.maximum(srt.start[pp + 1] - 1, 0)
        cand = order[last]
        hit &= cand != rows[:, None]
        rear = np.where(hit, cand, rear)
        rdist = np.where(hit, -(back + lane_len[pp] - srt.pos[last]), rdist)
        back = np.where(todo, back + lane_len[pp], np.inf)
        prev = np.where(todo, pred[pp], -1)
    return rear, rdist


def _in_the_way(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, vehicle: np.ndarray,
                distance: np.ndarray, max_range: float, next_edge: np.ndarray | None,
                via: np.ndarray | None, straddle: tuple):  # fmt: skip
    """A vehicle in the way on another lane, nearer than the lane's leader: across the path
    ahead (a junction lane), or ``straddle``-ing in from a neighbour lane (``_straddlers``).
    It replaces the current lane's front vehicle in ``vehicle`` / ``distance`` (in place);
    returns ``on_path`` (A,) and its ``PATH_GEOMETRY`` (A, 4)."""
    A = len(rows)
    lead = vehicle[:, CURRENT, 0]
    lead_gap = distance[:, CURRENT, 0] - np.where(lead >= 0, snap.length[np.maximum(lead, 0)], 0.0)
    found = (
        path_blockers(snap, hdmap, rows, max_range, next_edge, lead_gap, via),
        merge_leaders(snap, hdmap, rows, max_range, next_edge, via, lead_gap),
        straddle,
    )
    if compiled.enabled():
        return blockers_kernel.take_nearer(vehicle, distance, lead_gap, *found[0], *found[1],
                                           *found[2])  # fmt: skip
    on_path, geom = np.zeros(A, bool), np.zeros((A, len(PATH_GEOMETRY)))
    for other, gap, other_geom in found:
        take = (other >= 0) & (gap < lead_gap)
        vehicle[:, CURRENT, 0] = np.where(take, other, vehicle[:, CURRENT, 0])
        distance[:, CURRENT, 0] = np.where(take, gap + other_geom[:, 1], distance[:, CURRENT, 0])
        geom = np.where(take[:, None], other_geom, geom)
        lead_gap = np.where(take, gap, lead_gap)
        on_path |= take
    return on_path, geom


def _nearer_beside(
    snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, lanes: np.ndarray, srt: _Sorted,
    pos: np.ndarray, vehicle: np.ndarray, dist: np.ndarray, idx: np.ndarray, step: int,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Neighbour lanes' front (``step`` +1) or rear (-1) vehicle on the same lane: of two cars
    side by side there (sublane model; bodies overlapping along the lane), the one laterally
    nearer the ego. The nearest by position alone could hide one straddling towards the ego,
    which is also the one a LiDAR would see.

    ``vehicle`` / ``dist`` (A, 3) as found, at sorted-order indices ``idx`` (A, 3); returns
    them with the swaps. The current lane (column ``CURRENT``) is left as it is.
    """
    order, start, s_pos = srt.order, srt.start, srt.pos
    vehicle, dist = vehicle.copy(), dist.copy()
    cur, ego = np.maximum(lanes[:, CURRENT], 0), snap.lateral[rows]
    for col, side in ((LEFT, 1.0), (RIGHT, -1.0)):
        lane = np.maximum(lanes[:, col], 0)
        j = idx[:, col] + step
        ok = (vehicle[:, col] >= 0) & (j >= start[lane]) & (j < start[lane + 1])
        j = np.clip(j, 0, len(order) - 1)
        v, w = np.maximum(vehicle[:, col], 0), order[j]
        lead = w if step > 0 else v  # the one farther along the lane
        ok &= np.abs(s_pos[j] - snap.lane_pos[v]) < snap.length[lead]
        shift = side * 0.5 * (hdmap.lane_width[cur] + hdmap.lane_width[lane])
        ok &= np.abs(snap.lateral[w] + shift - ego) < np.abs(snap.lateral[v] + shift - ego)
        vehicle[:, col] = np.where(ok, w, vehicle[:, col])
        dist[:, col] = np.where(ok, s_pos[j] - pos[:, col], dist[:, col])
    return vehicle, dist


def _straddlers(
    snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, lanes: np.ndarray, i: np.ndarray,
    pos: np.ndarray, srt: _Sorted, max_range: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The nearest vehicle ahead on the left or right lane whose body overlaps the ego's
    laterally (SUMO's sublane model lets two vehicles share a lane side by side, so one
    straddling into ours can hide behind that lane's nearest vehicle).

    Looks at the first ``STRADDLE_DEPTH`` vehicles ahead on each neighbour lane (sorted-order
    indices ``i`` (A, 3) from ``find_neighbours``) within ``max_range``. Returns like
    ``path_blockers``: (A,) snapshot row (-1 if none), (A,) bumper gap [m] (+inf if none) and
    (A, 4) ``PATH_GEOMETRY`` in the ego lane's frame (its speed, length, width, and its
    centre's offset from the ego's lane centre).
    """
    A, order, start, s_pos = len(rows), srt.order, srt.start, srt.pos
    best = np.full(A, -1, dtype=np.int64)
    best_gap, best_lat = np.full(A, np.inf), np.zeros(A)
    if len(order):
        cur = np.maximum(lanes[:, CURRENT], 0)
        w_cur = hdmap.lane_width[cur]
        for col, side in ((LEFT, 1.0), (RIGHT, -1.0)):
            lane = lanes[:, col]
            ok_lane = (lane >= 0) & (lanes[:, CURRENT] >= 0)
            lsafe = np.maximum(lane, 0)
            shift = side * 0.5 * (w_cur + hdmap.lane_width[lsafe])  # its lane centre in ours
            for k in range(STRADDLE_DEPTH):
                idx = i[:, col] + k
                j = np.minimum(idx, len(order) - 1)
                v = order[j]
                y = snap.lateral[v] + shift
                d = s_pos[j] - pos[:, col]
                half = 0.5 * (snap.width[v] + snap.width[rows]) + STRADDLE_MARGIN
                gap = d - snap.length[v]
                better = ok_lane & (idx < start[lsafe + 1]) & (d <= max_range)
                better &= (np.abs(y - snap.lateral[rows]) < half) & (gap < best_gap)
                best = np.where(better, v, best)
                best_gap = np.where(better, gap, best_gap)
                best_lat = np.where(better, y, best_lat)
    return best, best_gap, _straddle_geometry(snap, best, best_lat)


def _straddle_geometry(snap: TrafficSnapshot, best: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """(A, 4) ``PATH_GEOMETRY`` of the straddlers ``best`` (A,) at offsets ``lat`` (A,) [m]."""
    v = np.maximum(best, 0)
    geom = np.stack([snap.speed[v], snap.length[v], snap.width[v], lat], axis=1)
    return np.where((best >= 0)[:, None], geom, 0.0)
