"""Perception: ground-truth neighbour search and the AV's sensors with weather noise (paper §III-B).

Public API (all arrays numpy; A = number of queried agents, N = vehicles in the snapshot):

``find_neighbours(snap, hdmap, rows, max_range, next_edge=None) -> Neighbours``
    Ground truth. For each agent row and each of its lanes (left, current, right) = columns
    0, 1, 2: the lane row and the front / rear vehicle within ``max_range`` metres along the lane.
``path_blockers(snap, hdmap, rows, max_range, next_edge=None, limit=None) -> (row, gap, geom)``
    The nearest vehicle across each agent's path ahead on another (junction) lane;
    ``find_neighbours`` reports it as the current lane's front vehicle when it is nearer.
``bumper_gap(distance, len_ego, len_other) -> gap``   and   ``ttc(gap, closing_speed) -> s``
``WEATHER_PRESETS[name] -> WeatherPreset``              noise, misdetection, range factors
``tls_ids(hdmap) -> list[str]``                         order of the traffic-light state strings
``next_route_edge(routes, route_index) -> (A,) int``    next edge row of each agent's route
``Perception(sensors, hdmap, weather)``
    ``.sense(snap, rows, next_edge, tls_states, rng) -> (truth, sensed)``, two ``PerceptionFrame``.

The env calls, once per step::

    nxt = next_route_edge(routes, snap.route_index[rows])
    truth, sensed = perception.sense(snap, rows, nxt, backend.tls_states(perception.tls_ids), rng)

and uses ``truth`` for rewards/metrics and ``sensed`` for observations. With
``SensorConfig.noise=False``, ``sensed is truth``.

Conventions
-----------
* Along-lane distance is front bumper to front bumper (SUMO ``lanePosition``), + = ahead.
  A missing vehicle has row -1 and distance +inf (front) / -inf (rear), so gaps and TTCs of
  missing vehicles are +inf without special cases.
* The search follows each lane across its end into its successor (through junction lanes),
  up to ``SEARCH_DEPTH`` lanes deep, and behind into one predecessor per lane (the lane whose
  primary successor it is). For the first hop ahead the route is used when ``next_edge`` is
  given (``hdmap.conn_to[(lane, next_edge)]``), else the primary successor ``hdmap.lane_next``.
* Vehicles across the path: a vehicle on another lane of a junction the ego's path crosses
  (the current lane and its successors within range) whose body comes within half the ego's
  width of the path is the current lane's front vehicle when its bumper gap is smaller
  (``path_blockers``). Its distance is the bumper gap along the path + its body's extent along
  the path, and its features are measured in the path's frame (``PATH_GEOMETRY``): length and
  width are its extents along / across the path, the relative velocity is its speed along the
  path minus the ego's, the lateral offset is its centre's offset from the path.
* Sublane model: a vehicle straddling two lanes is in the lane SUMO reports for it, which is
  the lane holding its centre; its ``lateral`` offset (feature) shows the overlap. A vehicle
  among the first ``STRADDLE_DEPTH`` ahead on a neighbour lane whose body overlaps the ego's
  laterally is also the current lane's front vehicle when nearer (two cars can share a lane
  side by side, and the nearer one would hide it); like a vehicle across the path, its
  features are then in the ego lane's frame (``path_geometry``). Of two cars side by side on
  a neighbour lane (bodies overlapping along it), that lane's front / rear vehicle is the one
  laterally nearer the ego (``_nearer_beside``): the other may be a few cm nearer along the
  lane while this one straddles towards the ego.
* On a neighbour lane the agent's position is projected by the lane-length ratio
  (lanes of one edge have near-equal lengths; curves make them differ slightly).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from mixed_traffic.config import SensorConfig
from mixed_traffic.world.hdmap import SPACING, HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Lanes followed ahead (and behind) of a lane when looking for a leader (follower).
SEARCH_DEPTH = 4
#: Vehicles ahead on each neighbour lane checked for straddling into the ego's way.
STRADDLE_DEPTH = 3
#: Lateral clearance below which a straddling vehicle counts as in the ego's way [m].
STRADDLE_MARGIN = 0.2
#: Column of each lane in the (A, 3) lane arrays.
LEFT, CURRENT, RIGHT = 0, 1, 2
#: Traffic-light state codes.
NO_LIGHT, RED, YELLOW, GREEN = -1, 0, 1, 2
#: Vehicle feature columns (physical units): distance [m], relative velocity v_other - v_ego
#: [m/s], relative heading [rad], length [m], width [m], lateral offset of the other vehicle from
#: its lane centre, + = left [m].
VEHICLE_FEATURES = ("distance", "rel_velocity", "rel_heading", "length", "width", "lateral")
#: Geometry of a vehicle on the ego's path (``path_blockers``), in the path's frame at the point
#: where the path meets it: speed along the path [m/s], extent of its body along the path [m]
#: and across it [m], offset of its centre from the path, + = left [m].
PATH_GEOMETRY = ("speed", "along", "across", "lateral")
#: Ego feature columns: speed [m/s], heading relative to the lane [rad], length [m], width [m],
#: lateral offset from the centreline, + = left [m].
EGO_FEATURES = ("velocity", "heading_rel_lane", "length", "width", "lateral")
#: Additive noise floors per vehicle / ego feature (same units): noise std is
#: ``rel_noise * (|x| + floor)`` so features that are zero (relative speed, offset) still jitter.
VEHICLE_NOISE_FLOOR = np.array([1.0, 0.5, 0.02, 0.2, 0.1, 0.1])
EGO_NOISE_FLOOR = np.array([0.5, 0.02, 0.0, 0.0, 0.1])
#: Ego length and width are known exactly (own vehicle): noise multiplier per ego feature.
EGO_NOISY = np.array([1.0, 1.0, 0.0, 0.0, 1.0])


# --------------------------------------------------------------------------- weather
@dataclass(frozen=True)
class WeatherPreset:
    """Sensor degradation of one weather condition (paper §V-I: 3-18 % perturbation).

    A sensed continuous feature is ``x + rel_noise * (|x| + floor) * eps`` with eps ~ N(0, 1),
    i.e. its relative RMS error is ``rel_noise`` (floors: ``VEHICLE_NOISE_FLOOR``,
    ``EGO_NOISE_FLOOR``). A detected light shows one of the two wrong states (uniformly) with
    probability ``light_misdetect``. Detection ranges are multiplied by the range factors.
    """

    name: str
    rel_noise: float
    """Relative standard deviation of every perturbed feature [-]."""
    light_misdetect: float
    """Probability that a detected traffic light reports a wrong state [-]."""
    lidar_range_factor: float
    """Multiplier of ``SensorConfig.lidar_range`` [-]."""
    camera_range_factor: float
    """Multiplier of ``SensorConfig.camera_range`` [-]."""


WEATHER_PRESETS: dict[str, WeatherPreset] = {
    # clear day: residual sensor error only
    "normal": WeatherPreset("normal", 0.03, 0.02, 1.0, 1.0),
    # rain: wet-road LiDAR returns and lens droplets; paper's 13 % light error rate
    "rain": WeatherPreset("rain", 0.08, 0.13, 0.9, 0.85),
    # fog: strongest perturbation and shortest ranges
    "fog": WeatherPreset("fog", 0.15, 0.18, 0.6, 0.5),
    # night: LiDAR is active (small loss), the camera loses contrast
    "night": WeatherPreset("night", 0.06, 0.08, 0.95, 0.7),
}


# --------------------------------------------------------------------------- lane graph
@dataclass
class LaneGraph:
    """Vectorised lookups over an HDMap, built once per map (``lane_graph(hdmap)``)."""

    n_edges: int
    conn_keys: np.ndarray
    """(C,) sorted keys lane * E + next_edge of ``hdmap.conn_to``."""
    conn_vals: np.ndarray
    """(C,) first lane row to take."""
    tls_keys: np.ndarray
    """(T,) sorted keys lane * E + next_edge of ``hdmap.tls_links``."""
    tls_tl: np.ndarray
    """(T,) index into ``tls_ids``."""
    tls_link: np.ndarray
    """(T,) link index within that light's state string."""
    tls_ids: list[str]
    pred: np.ndarray
    """(L,) one predecessor lane row (-1 if none)."""
    next_edge: np.ndarray
    """(L,) first normal edge reached by following primary successors (-1 if none)."""
    lane_offset_key: float
    """Multiplier of the lane row in the (lane, position) sort key [m]."""
    lane3: np.ndarray
    """(L, 3) (left neighbour, lane, right neighbour) of each lane row, -1 where none (a
    per-step ``neighbour_lane`` becomes one lookup)."""
    junction: np.ndarray
    """(L,) junction number of each internal lane, -1 for normal lanes."""
    entry_junction: np.ndarray
    """(L,) junction number at the start of each normal lane (the junction its incoming
    internal lanes belong to), -1 for internal lanes and lanes no junction feeds."""
    chain: np.ndarray
    """(L, SEARCH_DEPTH) the lane and its primary successors (``lane_next``), -1 padded."""
    chain_start: np.ndarray
    """(L, SEARCH_DEPTH) distance from the lane's start to the start of each of them [m]."""

    def connection(self, lane: np.ndarray, edge: np.ndarray) -> np.ndarray:
        """(...) first lane row of the connection lane -> edge, -1 if there is none."""
        found, i = self._find(self.conn_keys, lane, edge)
        return np.where(found, self.conn_vals[np.minimum(i, len(self.conn_vals) - 1)], -1)

    def signal(self, lane: np.ndarray, edge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(...) light index into ``tls_ids`` and link index of lane -> edge (-1, -1 if none)."""
        found, i = self._find(self.tls_keys, lane, edge)
        i = np.minimum(i, max(len(self.tls_keys) - 1, 0))
        if len(self.tls_keys) == 0:
            return np.full(found.shape, -1), np.full(found.shape, -1)
        return np.where(found, self.tls_tl[i], -1), np.where(found, self.tls_link[i], -1)

    def _find(self, keys: np.ndarray, lane: np.ndarray, edge: np.ndarray):
        lane = np.asarray(lane, dtype=np.int64)
        edge = np.asarray(edge, dtype=np.int64)
        key = lane * self.n_edges + edge
        i = np.searchsorted(keys, key)
        ok = (lane >= 0) & (edge >= 0) & (i < len(keys))
        found = (
            ok & (keys[np.minimum(i, max(len(keys) - 1, 0))] == key) if len(keys) else ok & False
        )
        return found, i


def lane_graph(hdmap: HDMap) -> LaneGraph:
    """The (cached) ``LaneGraph`` of ``hdmap``."""
    cached = hdmap.__dict__.get("_lane_graph")
    if cached is None:
        cached = _build_lane_graph(hdmap)
        hdmap.__dict__["_lane_graph"] = cached
    return cached


def _build_lane_graph(hd: HDMap) -> LaneGraph:
    E, L = len(hd.edge_ids), hd.n_lanes
    conn = sorted((a * E + b, c) for (a, b), c in hd.conn_to.items())
    names = sorted({t for t, _ in hd.tls_links.values()})
    tl_row = {t: i for i, t in enumerate(names)}
    tls = sorted((a * E + b, tl_row[t], k) for (a, b), (t, k) in hd.tls_links.items())
    # predecessor: prefer a straight-on (primary) link from a lane with the same index
    pred = np.full(L, -1, dtype=np.int64)
    for src in np.argsort(
        hd.lane_index != hd.lane_index[np.maximum(hd.lane_next, 0)], kind="stable"
    ):
        dst = hd.lane_next[src]
        if dst >= 0 and pred[dst] < 0:
            pred[dst] = src
    nxt_edge = np.full(L, -1, dtype=np.int64)
    lane = hd.lane_next.astype(np.int64)
    for _ in range(SEARCH_DEPTH):
        edge = np.where(lane >= 0, hd.lane_edge[np.maximum(lane, 0)], -1)
        nxt_edge = np.where((nxt_edge < 0) & (edge >= 0), edge, nxt_edge)
        lane = np.where(lane >= 0, hd.lane_next[np.maximum(lane, 0)], -1)
    return LaneGraph(
        n_edges=E,
        conn_keys=np.array([k for k, _ in conn], dtype=np.int64),
        conn_vals=np.array([v for _, v in conn], dtype=np.int64),
        tls_keys=np.array([k for k, _, _ in tls], dtype=np.int64),
        tls_tl=np.array([t for _, t, _ in tls], dtype=np.int64),
        tls_link=np.array([i for _, _, i in tls], dtype=np.int64),
        tls_ids=names,
        pred=pred,
        next_edge=nxt_edge,
        lane_offset_key=float(np.ceil(hd.lane_length.max()) + 10.0),
        lane3=np.stack([hd.neighbour_lane(np.arange(L), +1), np.arange(L),
                        hd.neighbour_lane(np.arange(L), -1)], axis=1).astype(np.int64),
        junction=(junction := _lane_junctions(hd)),
        entry_junction=_entry_junctions(hd, junction),
        **_successor_chains(hd),
    )  # fmt: skip


def _lane_junctions(hd: HDMap) -> np.ndarray:
    """(L,) junction number of each internal lane (-1 for normal lanes), from SUMO's internal
    lane ids ``:<junction>_<edge index>_<lane index>``."""
    names: dict[str, int] = {}
    out = np.full(hd.n_lanes, -1, dtype=np.int64)
    for row in np.flatnonzero(hd.lane_edge < 0).tolist():
        name = hd.lane_ids[row].lstrip(":").rsplit("_", 2)[0]
        out[row] = names.setdefault(name, len(names))
    return out


def _successor_chains(hd: HDMap) -> dict[str, np.ndarray]:
    """``chain`` and ``chain_start`` of ``LaneGraph``."""
    L = hd.n_lanes
    chain = np.full((L, SEARCH_DEPTH), -1, dtype=np.int64)
    start = np.full((L, SEARCH_DEPTH), np.inf)
    chain[:, 0], start[:, 0] = np.arange(L), 0.0
    for k in range(1, SEARCH_DEPTH):
        prev = chain[:, k - 1]
        nxt = np.where(prev >= 0, hd.lane_next[np.maximum(prev, 0)], -1)
        chain[:, k] = nxt
        start[:, k] = np.where(
            nxt >= 0, start[:, k - 1] + hd.lane_length[np.maximum(prev, 0)], np.inf
        )
    return {"chain": chain, "chain_start": start}


def _entry_junctions(hd: HDMap, junction: np.ndarray) -> np.ndarray:
    """(L,) junction of the internal lanes leading into each normal lane, -1 if none."""
    out = np.full(hd.n_lanes, -1, dtype=np.int64)
    src = np.flatnonzero((junction >= 0) & (hd.lane_next >= 0))
    dst = hd.lane_next[src].astype(np.int64)
    normal = hd.lane_edge[dst] >= 0
    out[dst[normal]] = junction[src[normal]]
    return out


def tls_ids(hdmap: HDMap) -> list[str]:
    """Traffic-light ids whose state strings ``Perception.sense`` expects, in this order."""
    return lane_graph(hdmap).tls_ids


def next_route_edge(routes: Sequence[Sequence[int]], route_index: np.ndarray) -> np.ndarray:
    """(A,) int64 edge row after the current one on each agent's route, -1 on the last edge.

    Args:
        routes: per agent, the edge rows of its route (``HDMap.edge_row`` of each edge id).
        route_index: (A,) index of the current (or last normal) edge within the route.
    """
    nxt = (
        r[k] if 0 <= k < len(r) else -1
        for r, k in zip(routes, (np.asarray(route_index) + 1).tolist())
    )
    return np.fromiter(nxt, np.int64, len(routes))


# --------------------------------------------------------------------------- neighbours
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


def find_neighbours(
    snap: TrafficSnapshot,
    hdmap: HDMap,
    rows: np.ndarray,
    max_range: float,
    next_edge: np.ndarray | None = None,
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
    Returns:
        ``Neighbours`` with (A, 3) lanes and (A, 3, 2) vehicles and distances.
    """
    g = lane_graph(hdmap)
    rows = np.asarray(rows, dtype=np.int64)
    A = len(rows)
    L = hdmap.n_lanes
    lane_len = hdmap.lane_length
    # ---- sort all vehicles on a lane by (lane, position) once
    vlane = snap.lane.astype(np.int64)
    on = np.flatnonzero(vlane >= 0)
    key_all = vlane * g.lane_offset_key + snap.lane_pos
    order = on[np.argsort(key_all[on], kind="stable")]
    s_key = key_all[order]
    s_pos = snap.lane_pos[order]
    start = np.searchsorted(s_key, np.arange(L + 1) * g.lane_offset_key - 1e-3)  # (L+1,)
    rank = np.full(snap.n, -1, dtype=np.int64)
    rank[order] = np.arange(len(order))

    # ---- query lanes (A, 3) and the agent's position projected onto them
    ego_lane = vlane[rows]
    ego_pos = snap.lane_pos[rows]
    cur = np.where(ego_lane >= 0, ego_lane, -1)
    lanes = g.lane3[np.maximum(cur, 0)]  # (A, 3) left, current, right
    lanes[cur < 0] = -1
    has = lanes >= 0
    lsafe = np.maximum(lanes, 0)
    ratio = lane_len[lsafe] / np.maximum(lane_len[np.maximum(cur, 0)], 1e-9)[:, None]
    pos = np.where(has, ego_pos[:, None] * ratio, 0.0)

    # ---- same lane: first vehicle at >= pos (neighbour lanes) or right after self (current)
    q_key = lsafe * g.lane_offset_key + pos
    i = np.searchsorted(s_key, q_key, side="left")
    i[:, CURRENT] = np.where(cur >= 0, rank[rows], 0)
    fi = i + np.where(np.arange(3) == CURRENT, 1, 0)[None, :]
    ri = i - 1
    f_ok = has & (fi < start[lsafe + 1])
    r_ok = has & (ri >= start[lsafe])
    n_sorted = max(len(order), 1)
    front = np.where(f_ok, order[np.minimum(fi, n_sorted - 1)] if len(order) else -1, -1)
    rear = np.where(r_ok, order[np.clip(ri, 0, n_sorted - 1)] if len(order) else -1, -1)
    fdist = np.where(f_ok, s_pos[np.minimum(fi, n_sorted - 1)] - pos if len(order) else 0, np.inf)
    rdist = np.where(r_ok, s_pos[np.clip(ri, 0, n_sorted - 1)] - pos if len(order) else 0, -np.inf)

    if len(order):
        front, fdist = _nearer_beside(
            snap, hdmap, rows, lanes, order, start, s_pos, pos, front, fdist, fi, +1
        )
        rear, rdist = _nearer_beside(
            snap, hdmap, rows, lanes, order, start, s_pos, pos, rear, rdist, ri, -1
        )
        count = np.diff(start)  # (L,) vehicles per lane
        # ---- ahead: successor lanes (first hop on the route if known)
        lane_k = lsafe
        offset = np.where(has, lane_len[lsafe] - pos, np.inf)  # distance to the lane end
        succ = hdmap.lane_next[lane_k].astype(np.int64)
        if next_edge is not None:
            via = g.connection(lane_k, np.broadcast_to(np.asarray(next_edge)[:, None], (A, 3)))
            succ = np.where(via >= 0, via, succ)
        for _ in range(SEARCH_DEPTH):
            todo = (front < 0) & (succ >= 0) & (offset <= max_range)
            if not todo.any():
                break
            ss = np.maximum(succ, 0)
            hit = todo & (count[ss] > 0)
            first = start[ss]
            cand = order[np.minimum(first, len(order) - 1)]
            hit &= cand != rows[:, None]
            front = np.where(hit, cand, front)
            fdist = np.where(hit, offset + s_pos[np.minimum(first, len(order) - 1)], fdist)
            offset = np.where(todo, offset + lane_len[ss], np.inf)
            succ = np.where(todo, hdmap.lane_next[ss], -1)
        # ---- behind: predecessor lanes
        back = np.where(has, pos, np.inf)  # distance from the lane start
        prev = np.where(has, g.pred[lsafe], -1)
        for _ in range(SEARCH_DEPTH):
            todo = (rear < 0) & (prev >= 0) & (back <= max_range)
            if not todo.any():
                break
            pp = np.maximum(prev, 0)
            hit = todo & (count[pp] > 0)
            last = np.maximum(start[pp + 1] - 1, 0)
            cand = order[last]
            hit &= cand != rows[:, None]
            rear = np.where(hit, cand, rear)
            rdist = np.where(hit, -(back + lane_len[pp] - s_pos[last]), rdist)
            back = np.where(todo, back + lane_len[pp], np.inf)
            prev = np.where(todo, g.pred[pp], -1)

    # ---- range
    f_in = (front >= 0) & (fdist <= max_range)
    r_in = (rear >= 0) & (-rdist <= max_range)
    vehicle = np.stack([np.where(f_in, front, -1), np.where(r_in, rear, -1)], axis=2)
    distance = np.stack([np.where(f_in, fdist, np.inf), np.where(r_in, rdist, -np.inf)], axis=2)
    # ---- a vehicle in the way on another lane, nearer than the lane's leader: across the
    # path ahead (a junction lane), or straddling in from a neighbour lane
    lead = vehicle[:, CURRENT, 0]
    lead_gap = distance[:, CURRENT, 0] - np.where(lead >= 0, snap.length[np.maximum(lead, 0)], 0.0)
    on_path, geom = np.zeros(A, bool), np.zeros((A, len(PATH_GEOMETRY)))
    for other, gap, other_geom in (
        path_blockers(snap, hdmap, rows, max_range, next_edge, lead_gap),
        _straddlers(snap, hdmap, rows, lanes, i, pos, order, start, s_pos, max_range),
    ):
        take = (other >= 0) & (gap < lead_gap)
        vehicle[:, CURRENT, 0] = np.where(take, other, vehicle[:, CURRENT, 0])
        distance[:, CURRENT, 0] = np.where(take, gap + other_geom[:, 1], distance[:, CURRENT, 0])
        geom = np.where(take[:, None], other_geom, geom)
        lead_gap = np.where(take, gap, lead_gap)
        on_path |= take
    return Neighbours(lanes, vehicle.astype(np.int64), distance, on_path, geom)


def _nearer_beside(
    snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray, lanes: np.ndarray, order: np.ndarray,
    start: np.ndarray, s_pos: np.ndarray, pos: np.ndarray, vehicle: np.ndarray, dist: np.ndarray,
    idx: np.ndarray, step: int,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Neighbour lanes' front (``step`` +1) or rear (-1) vehicle on the same lane: of two cars
    side by side there (sublane model; bodies overlapping along the lane), the one laterally
    nearer the ego. The nearest by position alone could hide one straddling towards the ego,
    which is also the one a LiDAR would see.

    ``vehicle`` / ``dist`` (A, 3) as found, at sorted-order indices ``idx`` (A, 3); returns
    them with the swaps. The current lane (column ``CURRENT``) is left as it is.
    """
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
    pos: np.ndarray, order: np.ndarray, start: np.ndarray, s_pos: np.ndarray, max_range: float,
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
    A = len(rows)
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
    v = np.maximum(best, 0)
    geom = np.stack([snap.speed[v], snap.length[v], snap.width[v], best_lat], axis=1)
    return best, best_gap, np.where((best >= 0)[:, None], geom, 0.0)


def _path_lanes(
    hdmap: HDMap, lane: np.ndarray, pos: np.ndarray, max_range: float,
    next_edge: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(A, H) lanes of each ego's path ahead from ``lane`` at ``pos`` (then the successors
    ``find_neighbours`` follows, while they start within ``max_range``), -1 padded; and (A, H)
    the distance from the ego's front bumper to each lane's start [m] (+inf where padded)."""
    g = lane_graph(hdmap)
    cur = np.asarray(lane, dtype=np.int64)
    csafe = np.maximum(cur, 0)
    succ = hdmap.lane_next[csafe].astype(np.int64)
    if next_edge is not None:
        via = g.connection(csafe, np.asarray(next_edge))
        succ = np.where(via >= 0, via, succ)
    succ = np.where(cur >= 0, succ, -1)
    ssafe = np.maximum(succ, 0)
    hops = np.concatenate([cur[:, None], g.chain[ssafe]], axis=1)
    start = np.concatenate(
        [-pos[:, None], (hdmap.lane_length[csafe] - pos)[:, None] + g.chain_start[ssafe]], axis=1
    )
    start[:, 1:][succ < 0] = np.inf
    keep = (hops >= 0) & (start <= max_range)
    keep[:, 1:] &= (succ >= 0)[:, None]
    keep &= (cur >= 0)[:, None]
    return np.where(keep, hops, -1), np.where(keep, start, np.inf)


def path_blockers(
    snap: TrafficSnapshot,
    hdmap: HDMap,
    rows: np.ndarray,
    max_range: float,
    next_edge: np.ndarray | None = None,
    limit: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest vehicle across each agent's path ahead, on a lane the path does not follow.

    The path is the agent's lane from its front bumper on, then the successors
    ``find_neighbours`` follows (route-aware first hop), up to ``max_range``. Candidates are the
    vehicles on internal lanes of the junctions the path crosses, and those that left such a
    junction by less than their length (a vehicle on a lane of the path is found by the lane
    search). The path is sampled at the HD map's 1 m waypoints (only around the candidate's
    junction); a candidate blocks it where its body (a rectangle behind its front bumper) comes
    within half the agent's width of a sample. Vectorised over (agent, candidate) pairs that
    share a junction, times samples.

    Args:
        limit: optional (A,) bumper gap [m] beyond which blockers are not wanted (the lane
            leader's: ``find_neighbours`` passes it, which spares the test for most agents).
    Returns:
        (A,) snapshot row of the nearest blocker (-1 if none); (A,) bumper gap [m] >= 0 along
        the path from the agent's front bumper to where the path meets its body (+inf if none);
        (A, 4) its ``PATH_GEOMETRY`` (0 where none).
    """
    g = lane_graph(hdmap)
    rows = np.asarray(rows, dtype=np.int64)
    A = len(rows)
    none = (np.full(A, -1, dtype=np.int64), np.full(A, np.inf), np.zeros((A, 4)))
    vlane = snap.lane.astype(np.int64)
    cand = np.flatnonzero(vlane >= 0)
    # vehicles on internal lanes, or leaving a junction with the rear still inside it
    cl = vlane[cand]
    cj = np.where(snap.lane_pos[cand] < snap.length[cand], g.entry_junction[cl], g.junction[cl])
    cj = np.where(g.junction[cl] >= 0, g.junction[cl], cj)
    cand, cl, cj = cand[cj >= 0], cl[cj >= 0], cj[cj >= 0]
    if A == 0 or len(cand) == 0:
        return none
    # agents whose path reaches a junction before their limit: from a normal lane, the next
    # junction begins at the lane's end; on an internal lane, here
    reach_max = 0.5 * (np.hypot(snap.length[cand], snap.width[cand]).max() + snap.width.max())
    cut = max_range if limit is None else np.minimum(np.asarray(limit, np.float64), max_range)
    cur = vlane[rows]
    csafe = np.maximum(cur, 0)
    to_junction = np.where(
        g.junction[csafe] >= 0, 0.0, hdmap.lane_length[csafe] - snap.lane_pos[rows]
    )
    sub = np.flatnonzero((cur >= 0) & (to_junction - reach_max <= cut + SPACING))
    if len(sub) == 0:
        return none
    nxt = None if next_edge is None else np.asarray(next_edge)[sub]
    hops, start = _path_lanes(hdmap, cur[sub], snap.lane_pos[rows[sub]], max_range, nxt)
    hj = np.where(hops >= 0, g.junction[np.maximum(hops, 0)], -1)  # (a, H)
    match = (hj[:, :, None] == cj[None, None, :]) & (hj >= 0)[:, :, None]  # (a, H, C)
    pair = match.any(axis=1)
    pair &= ~(hops[:, :, None] == cl[None, None, :]).any(axis=1)  # not on a lane of the path
    pair &= cand[None, :] != rows[sub, None]
    ai, ci = np.nonzero(pair)  # ai: index into sub
    if len(ai) == 0:
        return none
    # ---- window of the path around the junction: its lanes, +- the body's reach
    m = match[ai, :, ci]  # (P, H)
    H = m.shape[1]
    h1 = np.argmax(m, axis=1)
    h2 = H - 1 - np.argmax(m[:, ::-1], axis=1)
    v = cand[ci]
    half_l, half_w = 0.5 * snap.length[v], 0.5 * snap.width[v]
    r = 0.5 * snap.width[rows[sub[ai]]]  # the agent's half width
    reach = np.hypot(half_l, half_w) + r
    st = start[ai]  # (P, H)
    lo = np.maximum(st[np.arange(len(ai)), h1] - reach, 0.0)
    hi = st[np.arange(len(ai)), h2] + hdmap.lane_length[hops[ai, h2]] + reach
    hi = np.minimum(hi, max_range)
    if limit is not None:  # the first hit is at most SPACING beyond the gap
        hi = np.minimum(hi, np.asarray(limit, dtype=np.float64)[sub[ai]] + SPACING)
    near = lo <= hi
    if not near.all():
        ai, v, lo, hi, r = ai[near], v[near], lo[near], hi[near], r[near]
        half_l, half_w, st = half_l[near], half_w[near], st[near]
        if len(ai) == 0:
            return none
    n = int(np.ceil(np.max(hi - lo, initial=0.0) / SPACING)) + 1
    d = lo[:, None] + SPACING * np.arange(n)[None, :]  # (P, S)
    h = np.zeros(d.shape, dtype=np.int64)  # hop of each sample
    for hh in range(1, st.shape[1]):
        h += d >= st[:, hh, None]
    lane = np.take_along_axis(hops[ai], h, axis=1)
    lsafe = np.maximum(lane, 0)
    q = d - np.take_along_axis(st, h, axis=1)  # position on that lane
    k = np.clip(np.rint(q / SPACING).astype(np.int64), 0, hdmap.wp_count[lsafe] - 1)
    wp = hdmap.wp_offset[lsafe] + k
    ok = (lane >= 0) & (d <= hi[:, None]) & (q <= hdmap.lane_length[lsafe] + 0.5 * SPACING)
    # ---- the body: rectangle behind the front bumper, in its own frame
    c, s = np.cos(snap.heading[v]), np.sin(snap.heading[v])
    cx = snap.x[v] - half_l * c
    cy = snap.y[v] - half_l * s
    dx = hdmap.wp_xyz[wp, 0] - cx[:, None]
    dy = hdmap.wp_xyz[wp, 1] - cy[:, None]
    out_l = np.maximum(np.abs(dx * c[:, None] + dy * s[:, None]) - half_l[:, None], 0.0)
    out_w = np.maximum(np.abs(dy * c[:, None] - dx * s[:, None]) - half_w[:, None], 0.0)
    hit = ok & (out_l**2 + out_w**2 < (r * r)[:, None])
    found = hit.any(axis=1)
    if not found.any():
        return none
    # ---- where the path meets each blocker: first hit sample, in the path's frame there
    p = np.flatnonzero(found)
    j = np.argmax(hit[p], axis=1)
    ai, v, wj = ai[p], v[p], wp[p, j]
    dj = np.take_along_axis(st[p], h[p, j][:, None], axis=1)[:, 0] + k[p, j] * SPACING
    t = hdmap.wp_heading[wj]
    rel = snap.heading[v] - t
    ca, sa = np.abs(np.cos(rel)), np.abs(np.sin(rel))
    along = snap.length[v] * ca + snap.width[v] * sa
    across = snap.length[v] * sa + snap.width[v] * ca
    ex, ey = cx[p] - hdmap.wp_xyz[wj, 0], cy[p] - hdmap.wp_xyz[wj, 1]
    centre = ex * np.cos(t) + ey * np.sin(t)
    lateral = ey * np.cos(t) - ex * np.sin(t)
    # the body's near end, between the last sample that missed it and the hit's reach
    gap = np.maximum(np.clip(dj + centre - 0.5 * along, dj - SPACING, dj + r[p]), 0.0)
    # ---- nearest blocker per agent
    order = np.lexsort((gap, ai))
    first = order[np.r_[True, ai[order][1:] != ai[order][:-1]]]
    vehicle, best, geom = none
    a = sub[ai[first]]
    vehicle[a] = v[first]
    best[a] = gap[first]
    geom[a] = np.stack([snap.speed[v] * np.cos(rel), along, across, lateral], axis=1)[first]
    return vehicle, best, geom


def bumper_gap(distance: np.ndarray, len_ego: np.ndarray, len_other: np.ndarray) -> np.ndarray:
    """Bumper gap as in the paper's TTC: |front-bumper distance| - (len_ego + len_other) / 2 [m].

    Shapes broadcast; an infinite distance gives an infinite gap.
    """
    return np.abs(distance) - 0.5 * (np.asarray(len_ego) + np.asarray(len_other))


def ttc(gap: np.ndarray, closing_speed: np.ndarray) -> np.ndarray:
    """Time to collision [s] = gap / closing speed where closing (> 0), else +inf.

    Args:
        gap: bumper gap [m] (``bumper_gap``); a gap <= 0 with closing speed > 0 gives 0.
        closing_speed: v_follower - v_leader [m/s].
    """
    gap = np.asarray(gap, dtype=np.float64)
    v = np.asarray(closing_speed, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(v > 0, np.maximum(gap, 0.0) / np.where(v > 0, v, 1.0), np.inf)
    return np.where(np.isnan(t), np.inf, t)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angle wrapped to (-pi, pi] [rad]."""
    return np.pi - np.mod(np.pi - np.asarray(a), 2 * np.pi)


# --------------------------------------------------------------------------- sensors
@dataclass
class PerceptionFrame:
    """What the agents perceive at one step (physical units). A agents, 3 lanes, 2 slots."""

    neighbours: Neighbours
    """Detected neighbours (rows -1 where not detected); distances possibly noisy."""
    vehicles: np.ndarray
    """(A, 3, 2, 6) features ``VEHICLE_FEATURES`` of front/rear vehicles; 0 where missing."""
    ego: np.ndarray
    """(A, 5) features ``EGO_FEATURES`` (GNSS/IMU)."""
    light_state: np.ndarray
    """(A, 3) int8 RED / YELLOW / GREEN of the next signal on each lane, NO_LIGHT if none."""
    light_dist: np.ndarray
    """(A, 3) distance from the front bumper to the stop line [m], +inf where no light."""


class Perception:
    """LiDAR (vehicles), camera (traffic lights) and GNSS/IMU (ego) over ground truth.

    Args:
        sensors: ranges and the noise switch.
        hdmap: the network.
        weather: preset name or ``WeatherPreset``.
    """

    def __init__(self, sensors: SensorConfig, hdmap: HDMap, weather: str | WeatherPreset) -> None:
        if isinstance(weather, str):
            if weather not in WEATHER_PRESETS:
                raise ValueError(f"weather={weather!r} is not one of {tuple(WEATHER_PRESETS)}")
            weather = WEATHER_PRESETS[weather]
        self.sensors = sensors
        self.hdmap = hdmap
        self.weather = weather
        self.graph = lane_graph(hdmap)

    @property
    def tls_ids(self) -> list[str]:
        """Light ids whose ``backend.tls_states`` strings ``sense`` expects, in this order."""
        return self.graph.tls_ids

    def sense(
        self,
        snap: TrafficSnapshot,
        rows: np.ndarray,
        next_edge: np.ndarray,
        tls_states: Sequence[str],
        rng: np.random.Generator,
    ) -> tuple[PerceptionFrame, PerceptionFrame]:
        """Ground truth and sensed frames for the agents at snapshot ``rows`` (A,).

        Args:
            next_edge: (A,) next route edge row of each agent, -1 on its last edge.
            tls_states: state strings of ``self.tls_ids`` (``backend.tls_states``).
            rng: the env's generator; the only source of randomness.
        Returns:
            ``(truth, sensed)``; truth uses the nominal ranges and no noise. ``sensed is truth``
            when ``sensors.noise`` is False.
        """
        rows = np.asarray(rows, dtype=np.int64)
        next_edge = np.asarray(next_edge, dtype=np.int64)
        nb = find_neighbours(snap, self.hdmap, rows, self.sensors.lidar_range, next_edge)
        state, dist = self._lights(snap, rows, nb.lane, next_edge, tls_states)
        cam = self.sensors.camera_range
        state = np.where(dist <= cam, state, NO_LIGHT).astype(np.int8)
        dist = np.where(state != NO_LIGHT, dist, np.inf)
        truth = PerceptionFrame(nb, vehicle_features(snap, rows, nb), ego_features(snap, self.hdmap, rows),
                                state, dist)  # fmt: skip
        if not self.sensors.noise:
            return truth, truth
        return truth, self._degrade(truth, rng)

    def _lights(self, snap, rows, lanes, next_edge, tls_states) -> tuple[np.ndarray, np.ndarray]:
        """(A, 3) ground-truth state code and stop-line distance of each lane's next signal."""
        g, hd = self.graph, self.hdmap
        A = len(rows)
        if not g.tls_ids or A == 0:
            return np.full((A, 3), NO_LIGHT, dtype=np.int8), np.full((A, 3), np.inf)
        if len(tls_states) != len(g.tls_ids):
            raise ValueError(
                f"tls_states has {len(tls_states)} strings, expected {len(g.tls_ids)} "
                f"(one per Perception.tls_ids)"
            )
        lsafe = np.maximum(lanes, 0)
        tl, link = g.signal(lanes, np.broadcast_to(next_edge[:, None], lanes.shape))
        tl2, link2 = g.signal(lanes, g.next_edge[lsafe])  # lane's own way on
        miss = tl < 0
        tl, link = np.where(miss, tl2, tl), np.where(miss, link2, link)
        codes = _state_codes("".join(tls_states))
        offsets = np.concatenate([[0], np.cumsum([len(s) for s in tls_states])])
        flat = offsets[np.maximum(tl, 0)] + link
        ok = (tl >= 0) & (link >= 0) & (flat < len(codes))
        state = np.where(ok, codes[np.minimum(flat, max(len(codes) - 1, 0))], NO_LIGHT)
        ratio = hd.lane_length[lsafe] / np.maximum(hd.lane_length[lsafe[:, CURRENT]], 1e-9)[:, None]
        pos = snap.lane_pos[rows][:, None] * ratio
        dist = np.where(ok, np.maximum(hd.lane_length[lsafe] - pos, 0.0), np.inf)
        return state.astype(np.int8), dist

    def skip_noise(self, n_agents: int, rng: np.random.Generator) -> None:
        """Consume exactly the random numbers ``sense`` would draw for ``n_agents`` agents,
        for a caller that only needs ground truth but must keep the noise stream unchanged."""
        if self.sensors.noise:
            _noise_draws(rng, n_agents)

    def _degrade(self, truth: PerceptionFrame, rng: np.random.Generator) -> PerceptionFrame:
        w, s = self.weather, self.sensors
        nb = truth.neighbours
        z_veh, z_ego, u_light, shift, z_ldist = _noise_draws(rng, len(nb.lane))
        # ranges
        lidar = s.lidar_range * w.lidar_range_factor
        seen = (nb.vehicle >= 0) & (np.abs(nb.distance) <= lidar)
        # continuous noise
        # veh + rel_noise * (|veh| + floor) * N(0, 1), evaluated in place (the same roundings)
        noise = np.abs(truth.vehicles)
        noise += VEHICLE_NOISE_FLOOR
        noise *= w.rel_noise
        noise *= z_veh
        noise += truth.vehicles
        veh = np.where(seen[..., None], noise, 0.0)
        dist = np.where(seen, veh[..., 0], np.where(np.arange(2) == 0, np.inf, -np.inf))
        ego = truth.ego
        ego = ego + EGO_NOISY * w.rel_noise * (np.abs(ego) + EGO_NOISE_FLOOR) * z_ego
        # traffic lights: shorter range, wrong states
        cam = s.camera_range * w.camera_range_factor
        state = np.where(truth.light_dist <= cam, truth.light_state, NO_LIGHT)
        wrong = (state != NO_LIGHT) & (u_light < w.light_misdetect)
        state = np.where(wrong, (state + shift) % 3, state).astype(np.int8)
        ldist = truth.light_dist * (1.0 + w.rel_noise * z_ldist)
        ldist = np.where(state != NO_LIGHT, np.maximum(ldist, 0.0), np.inf)
        sensed_nb = replace(nb, vehicle=np.where(seen, nb.vehicle, -1), distance=dist)
        return PerceptionFrame(sensed_nb, veh, ego, state, ldist)


def _noise_draws(rng: np.random.Generator, a: int) -> tuple[np.ndarray, ...]:
    """Every random number ``_degrade`` uses for ``a`` agents, in the order it draws them:
    vehicle and ego feature noise, light misdetection (uniform, state shift), light distance."""
    return (
        rng.standard_normal((a, 3, 2, len(VEHICLE_FEATURES))),
        rng.standard_normal((a, len(EGO_FEATURES))),
        rng.random((a, 3)),
        rng.integers(1, 3, size=(a, 3)),
        rng.standard_normal((a, 3)),
    )


_CODE = np.full(256, GREEN, dtype=np.int8)  # o/O (off) and unknown: no restriction
for _c in "rRs":
    _CODE[ord(_c)] = RED
for _c in "yYu":
    _CODE[ord(_c)] = YELLOW


def _state_codes(state: str) -> np.ndarray:
    """SUMO signal characters -> codes: r/R/s red, y/Y/u yellow, g/G/o/O green."""
    return _CODE[np.frombuffer(state.encode("ascii"), dtype=np.uint8)]


def vehicle_features(snap: TrafficSnapshot, rows: np.ndarray, nb: Neighbours) -> np.ndarray:
    """(A, 3, 2, 6) ground-truth ``VEHICLE_FEATURES`` of the neighbours, 0 where missing."""
    v = nb.vehicle
    ok = v >= 0
    o = np.maximum(v, 0)
    ego = rows[:, None, None]
    feats = np.stack(
        [
            np.where(ok, nb.distance, 0.0),
            snap.speed[o] - snap.speed[ego],
            wrap_angle(snap.heading[o] - snap.heading[ego]),
            snap.length[o],
            snap.width[o],
            snap.lateral[o],
        ],
        axis=-1,
    )
    if nb.on_path is not None and nb.on_path.any():
        # a vehicle across the path: speed along the path, extents along / across it, offset
        # from it (``PATH_GEOMETRY``)
        g = nb.path_geometry
        path = np.stack([g[:, 0] - snap.speed[rows], g[:, 1], g[:, 2], g[:, 3]], axis=1)
        cols = [1, 3, 4, 5]
        feats[:, CURRENT, 0, cols] = np.where(nb.on_path[:, None], path, feats[:, CURRENT, 0, cols])
    return np.where(ok[..., None], feats, 0.0)


def ego_features(snap: TrafficSnapshot, hdmap: HDMap, rows: np.ndarray) -> np.ndarray:
    """(A, 5) ground-truth ``EGO_FEATURES``; heading is relative to the lane at the front bumper."""
    lane = snap.lane[rows]
    wp = hdmap.waypoint_at(np.maximum(lane, 0), snap.lane_pos[rows])
    rel = np.where(lane >= 0, wrap_angle(snap.heading[rows] - hdmap.wp_heading[wp]), 0.0)
    return np.stack(
        [snap.speed[rows], rel, snap.length[rows], snap.width[rows], snap.lateral[rows]], axis=1
    )
