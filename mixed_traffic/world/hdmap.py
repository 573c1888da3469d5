"""HD map: lane table and 1 m centreline waypoints of a SUMO network, built once and cached.

Every lane (including junction-internal lanes) is a row of the lane table; every normal edge a
row of the edge table. Waypoints of all lanes are concatenated into flat arrays, and a lane's
waypoints are ``wp_offset[lane] : wp_offset[lane] + wp_count[lane]``. Waypoints continue beyond a
lane's end along its *primary successor* (straight on, else the first connection), so
"the next m waypoints ahead" is one gather from the ``ahead`` table.
"""

from __future__ import annotations

import gzip
import hashlib
import xml.etree.ElementTree as ET
import zlib
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any
from xml.sax import SAXException, SAXParseException

import numpy as np
import sumolib.net

from mixed_traffic.paths import cache_dir

SPACING = 1.0  # waypoint spacing along the centreline [m]
#: Lateral acceleration of a junction lane's advisory speed [m/s²]: netconvert's default
#: ``--junctions.limit-turn-speed``, the turn speed SUMO itself would have built.
ADVISORY_LAT_ACCEL = 5.5
#: A junction lane leaving the road's direction by more than this is a lane shift [rad] ...
SHIFT_ANGLE = np.deg2rad(45.0)
#: ... where the road's direction changes by less than this across the junction [rad].
SHIFT_STRAIGHT = np.deg2rad(20.0)
#: Extra cost of a turnaround in ``routing.fastest_path`` [s].
UTURN_PENALTY = 120.0
_CACHE_VERSION = "hdmap-v9"  # v2: sumolib; v3: lane permissions; v4: yield links; v5: shifts,
# turnarounds; v6: internal yields; v7: unsignalised links at signals; v8: fans; v9: the shifts
# of every connection of a fanning lane
YIELD_STATES = frozenset("m=swZ")
"""SUMO link states that give way to foes (minor, equal, stop, all-way stop, zipper)."""
CAR = "passenger"
"""The vehicle class of the env's cars (a .sumocfg may give its AVs another one)."""


@dataclass
class HDMap:
    """Lane geometry of one network (shapes in SUMO's x/y/z metres, headings ENU radians)."""

    net_file: str
    lane_ids: list[str]
    """(L,) SUMO lane ids."""
    lane_edge: np.ndarray
    """(L,) int32 edge row, -1 for internal (junction) lanes."""
    lane_index: np.ndarray
    """(L,) int16 index within the edge, 0 = rightmost."""
    lane_length: np.ndarray
    """(L,) [m]."""
    lane_width: np.ndarray
    """(L,) [m]."""
    lane_speed: np.ndarray
    """(L,) speed limit [m/s]."""
    lane_car: np.ndarray
    """(L,) bool: SUMO's permissions let the AVs' vClass use the lane (``passenger``, or a
    .sumocfg's own class): not a sidewalk, bike, bus or rail lane."""
    lane_yields: np.ndarray
    """(L,) bool: a connection at the lane's end must give way (SUMO link state m, =, s, w or
    Z: a minor road, an all-way stop, a stop sign, right before left, a zipper merge); for a
    junction lane, at the internal junction where a turn waits for the oncoming stream."""
    lane_fans: np.ndarray
    """(L,) bool: the lane reaches a next edge by more than one connection (it fans out onto
    several of that edge's lanes). SUMO picks one by its best lanes and their occupancy as the
    vehicle arrives, so the env asks SUMO which (``SumoBackend.next_vias``); ``conn_to`` holds
    only the first."""
    lane_uturn: np.ndarray
    """(L,) bool: the junction lane of a turnaround (SUMO direction t)."""
    lane_next: np.ndarray
    """(L,) int32 primary successor lane row (via the junction lane if any; a car lane's is a
    car lane), -1 at a dead end."""
    edge_ids: list[str]
    """(E,) ids of normal edges."""
    edge_lanes: np.ndarray
    """(E, Kmax) int32 lane rows of each edge by index (0 = rightmost), -1 padded."""
    edge_length: np.ndarray
    """(E,) [m]."""
    conn_to: dict[tuple[int, int], int]
    """(car lane row, next edge row) -> first lane row to take (junction lane, or the next
    lane), for connections cars may use."""
    tls_links: dict[tuple[int, int], tuple[str, int]]
    """(lane row, next edge row) -> (traffic light id, link index) for signalised connections."""
    wp_offset: np.ndarray
    """(L,) int64 first waypoint row of each lane."""
    wp_count: np.ndarray
    """(L,) int64 waypoints of each lane."""
    wp_xyz: np.ndarray
    """(W, 3) waypoint positions [m]."""
    wp_heading: np.ndarray
    """(W,) heading of the centreline at the waypoint [rad]."""
    wp_lane: np.ndarray
    """(W,) int32 lane row of the waypoint."""

    # ----------------------------------------------------------------- derived tables
    @property
    def n_lanes(self) -> int:
        return len(self.lane_ids)

    @cached_property
    def any_yield(self) -> bool:
        """Some lane must give way at its end (``lane_yields``)."""
        return bool(self.lane_yields.any())

    @cached_property
    def edge_num_lanes(self) -> np.ndarray:
        """(E,) lanes per edge."""
        return (self.edge_lanes >= 0).sum(axis=1)

    @cached_property
    def edge_car_lanes(self) -> np.ndarray:
        """(E,) lanes per edge that cars may use."""
        rows = self.edge_lanes
        return ((rows >= 0) & self.lane_car[np.maximum(rows, 0)]).sum(axis=1)

    def car_lane_rows(self, edge: int) -> list[int]:
        """Lane rows of ``edge`` that cars may use, rightmost first."""
        return [int(r) for r in self.edge_lanes[edge] if r >= 0 and self.lane_car[r]]

    @cached_property
    def lane_row(self) -> dict[str, int]:
        return {lid: i for i, lid in enumerate(self.lane_ids)}

    @cached_property
    def edge_row(self) -> dict[str, int]:
        return {eid: i for i, eid in enumerate(self.edge_ids)}

    @cached_property
    def lane_exits(self) -> dict[int, set[int]]:
        """Lane row -> edge rows it connects to through the junction at its end."""
        out: dict[int, set[int]] = {}
        for lane, nxt in self.conn_to:
            out.setdefault(lane, set()).add(nxt)
        return out

    @cached_property
    def edge_successors(self) -> dict[int, set[int]]:
        """Edge row -> edge rows reachable through one junction."""
        out: dict[int, set[int]] = {}
        for lane, nxt in self.lane_exits.items():
            out.setdefault(int(self.lane_edge[lane]), set()).update(nxt)
        return out

    @cached_property
    def lane_advisory(self) -> np.ndarray:
        """(L,) the lane's speed limit [m/s]; for a junction lane whose turn (heading change
        over its length) allows less than 80 % of it at ``ADVISORY_LAT_ACCEL``, that speed.
        netconvert limits turns so (its own turns keep their limits: the estimates differ by
        a few %), but a hand-drawn junction may keep the road's limit. A bend of a road lane
        lies somewhere along the lane: the waypoints see it."""
        first = self.wp_offset
        last = first + np.maximum(self.wp_count - 1, 0)
        turn = np.abs(_wrap(self.wp_heading[last] - self.wp_heading[first]))
        kappa = turn / np.maximum(self.lane_length, 0.1)  # mean curvature [1/m]
        curve = np.sqrt(ADVISORY_LAT_ACCEL / np.maximum(kappa, 1e-6))
        ignored = (self.lane_edge < 0) & (curve < 0.8 * self.lane_speed)
        return np.where(ignored, curve, self.lane_speed)

    @cached_property
    def edge_free_time(self) -> np.ndarray:
        """(E,) free-flow travel time of each edge at its fastest car lane's limit [s]."""
        rows = np.maximum(self.edge_lanes, 0)
        car = (self.edge_lanes >= 0) & self.lane_car[rows]
        speed = np.where(car, self.lane_speed[rows], 0.0).max(axis=1)
        return self.edge_length / np.maximum(speed, 0.1)

    @cached_property
    def edge_uturns(self) -> set[tuple[int, int]]:
        """(edge row, next edge row) pairs joined by a turnaround's junction lane."""
        return {(int(self.lane_edge[a]), b) for (a, b), v in self.conn_to.items()
                if self.lane_uturn[v]}  # fmt: skip

    @cached_property
    def wp_speed(self) -> np.ndarray:
        """(W,) speed limit at each waypoint [m/s]."""
        return self.lane_speed[self.wp_lane]

    @cached_property
    def wp_lane_index(self) -> np.ndarray:
        """(W,) lane index within the edge of each waypoint."""
        return self.lane_index[self.wp_lane]

    def ahead_table(self, m: int) -> np.ndarray:
        """(W, m) rows of the m waypoints from each waypoint on (itself first), following
        primary successors; a dead end repeats the last waypoint."""
        cached = self.__dict__.setdefault("_ahead", {})
        if m not in cached:
            last = self.wp_offset + self.wp_count - 1
            nxt = np.arange(len(self.wp_lane), dtype=np.int64) + 1
            nxt[last] = last  # dead end: stay
            succ = self.lane_next
            has = succ >= 0
            nxt[last[has]] = self.wp_offset[succ[has]]
            table = np.empty((len(nxt), m), dtype=np.int64)
            table[:, 0] = np.arange(len(nxt))
            for j in range(1, m):
                table[:, j] = nxt[table[:, j - 1]]
            cached[m] = table
        return cached[m]

    def waypoint_at(self, lane: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """(N,) waypoint row nearest below lane position ``pos`` [m] on ``lane``."""
        lane = np.asarray(lane, dtype=np.int64)
        k = np.clip(
            np.floor(np.asarray(pos) / SPACING).astype(np.int64), 0, self.wp_count[lane] - 1
        )
        return self.wp_offset[lane] + k

    def waypoints_ahead(self, lane: np.ndarray, pos: np.ndarray, m: int) -> np.ndarray:
        """(N, m) waypoint rows of the next m waypoints from each lane position."""
        return self.ahead_table(m)[self.waypoint_at(lane, pos)]

    def neighbour_lane(self, lane: np.ndarray, offset: int) -> np.ndarray:
        """(N,) lane row ``offset`` lanes to the left (+) or right (-) on the same edge, -1 if
        none; beside a car lane, a lane cars may not use (a sidewalk, a bike lane) is none."""
        lane = np.asarray(lane, dtype=np.int64)
        edge = self.lane_edge[lane]
        idx = self.lane_index[lane].astype(np.int64) + offset
        ok = (edge >= 0) & (idx >= 0) & (idx < self.edge_lanes.shape[1])
        out = np.full(lane.shape, -1, dtype=np.int64)
        out[ok] = self.edge_lanes[edge[ok], idx[ok]]
        barred = (out >= 0) & self.lane_car[lane] & ~self.lane_car[np.maximum(out, 0)]
        out[barred] = -1
        return out

    def edge_of(self, edge_id: str) -> int:
        if edge_id not in self.edge_row:
            raise KeyError(f"edge {edge_id!r} is not in network {self.net_file}")
        return self.edge_row[edge_id]


# --------------------------------------------------------------------------- building
def load_hdmap(net_file: str | Path, vclass: str = CAR) -> HDMap:
    """HD map of ``net_file`` for AVs of ``vclass``, from the cache when the file is unchanged."""
    net_file = Path(net_file)
    if not net_file.is_file():
        raise FileNotFoundError(f"network file {net_file} does not exist")
    key = net_file.read_bytes() + _CACHE_VERSION.encode() + vclass.encode()
    digest = hashlib.sha256(key).hexdigest()[:20]
    cache = cache_dir("hdmap") / f"{digest}.npz"
    if cache.exists():
        try:
            return _from_npz(cache, str(net_file))
        except (OSError, KeyError, ValueError):
            cache.unlink(missing_ok=True)  # corrupt cache: rebuild
    hdmap = build_hdmap(net_file, vclass)
    _to_npz(hdmap, cache)
    return hdmap


class NetFileError(ValueError):
    """Not a readable SUMO network; ``kind``: "xml", "root", "edges" or "content"."""

    def __init__(self, message: str, kind: str, detail: str) -> None:
        super().__init__(message)
        self.kind, self.detail = kind, detail


def read_net(net_file: str | Path, with_internal: bool = True) -> sumolib.net.Net:
    """sumolib network of a .net.xml or .net.xml.gz (with macro connectors, and with internal,
    crossing and walking-area edges if ``with_internal``); ``NetFileError`` naming the file if
    it is malformed or its root is not ``<net>``, ``FileNotFoundError`` if it is missing."""
    try:
        tag, empty = _root_of(net_file)
        net = None
        if tag == "net" and not empty:
            net = sumolib.net.readNet(
                str(net_file), withInternal=with_internal, withMacroConnectors=True, withFoes=True
            )
    except (SyntaxError, SAXException, EOFError, zlib.error, gzip.BadGzipFile) as e:
        detail = str(e)
        if isinstance(e, SAXParseException):  # as ElementTree words it, without the file name
            detail = f"{e.getMessage()}: line {e.getLineNumber()}, column {e.getColumnNumber()}"
        raise NetFileError(
            f"network file {net_file} is not valid XML: {detail}", "xml", detail
        ) from e
    except (KeyError, IndexError, TypeError, AttributeError, ValueError) as e:
        msg = f"network file {net_file} is not a valid SUMO network ({type(e).__name__}: {e})"
        raise NetFileError(msg, "content", str(e)) from e
    if tag != "net":
        msg = f"{net_file} is not a SUMO network (root element <{tag}>, expected <net>)"
        raise NetFileError(msg, "root", tag)
    if net is None:
        raise NetFileError(f"network file {net_file} contains no edges", "edges", "")
    return net


def _root_of(net_file: str | Path) -> tuple[str, bool]:
    """Tag of the root element, and whether it has no child element (reads only the start)."""
    with open(net_file, "rb") as f:
        gz = f.read(2) == b"\x1f\x8b"
    with (gzip.open if gz else open)(net_file, "rb") as f:
        events = ET.iterparse(f, events=("start", "end"))
        _, root = next(events)
        event, elem = next(events)
        return root.tag, event == "end" and elem is root


def build_hdmap(net_file: str | Path, vclass: str = CAR) -> HDMap:
    """Read a .net.xml (or .net.xml.gz) with sumolib and sample every lane centreline at 1 m;
    ``lane_car`` holds SUMO's permissions for ``vclass``."""
    lanes, lane_edge, edge_ids, edge_lane_rows, edge_row = _lane_table(read_net(net_file))
    if not edge_ids:
        raise NetFileError(f"network file {net_file} contains no edges", "edges", "")
    lane_ids = [lane.getID() for lane in lanes]
    lane_length = [lane.getLength() for lane in lanes]
    kmax = max(len(r) for r in edge_lane_rows)
    edge_lanes = np.full((len(edge_ids), kmax), -1, dtype=np.int32)
    for e, rows in enumerate(edge_lane_rows):
        edge_lanes[e, : len(rows)] = rows
    lane_car = np.array([lane.allows(vclass) for lane in lanes], dtype=bool)
    lane_next, conn_to, tls_links, fans = _connections(
        lanes, lane_ids, lane_edge, edge_row, lane_car
    )
    uturn = {c.getViaLaneID() for ln in lanes for c in ln.getOutgoing() if c.getDirection() == "t"}
    yields = np.array([any(map(_gives_way, ln.getOutgoing())) for ln in lanes])
    samples = [_sample(np.reshape(ln.getShape3D(), (-1, 3)), ln.getLength()) for ln in lanes]
    counts = np.array([len(pts) for pts, _ in samples], dtype=np.int64)
    hdmap = HDMap(
        net_file=str(net_file),
        lane_ids=lane_ids,
        lane_edge=np.array(lane_edge, dtype=np.int32),
        lane_index=np.array([lane.getIndex() for lane in lanes], dtype=np.int16),
        lane_length=np.array(lane_length),
        lane_width=np.array([lane.getWidth() for lane in lanes]),
        lane_speed=np.array([lane.getSpeed() for lane in lanes]),
        lane_car=lane_car,
        lane_yields=yields,
        lane_fans=fans,
        lane_uturn=np.array([lid in uturn for lid in lane_ids], dtype=bool),
        lane_next=lane_next,
        edge_ids=edge_ids,
        edge_lanes=edge_lanes,
        edge_length=np.array([lane_length[rows[0]] if rows else 0.0 for rows in edge_lane_rows]),
        conn_to=conn_to,
        tls_links=tls_links,
        wp_offset=np.cumsum(counts) - counts,
        wp_count=counts,
        wp_xyz=np.concatenate([pts for pts, _ in samples]),
        wp_heading=np.concatenate([hdg for _, hdg in samples]),
        wp_lane=np.repeat(np.arange(len(lanes), dtype=np.int32), counts),
    )
    row = {lid: i for i, lid in enumerate(lane_ids)}
    vias = [(row[ln.getID()], row[c.getViaLaneID()]) for ln in lanes for c in ln.getOutgoing()
            if c.getViaLaneID() in row]  # fmt: skip
    _straighten_shifts(hdmap, vias)
    return hdmap


def _gives_way(c: Any) -> bool:
    """A sumolib connection must give way: its state is one of ``YIELD_STATES``, or it is a
    link without a signal at a signalised junction whose right-of-way table (``<request>``
    response) lets other links go first: its state reads M, SUMO still makes it yield."""
    if c.getState() in YIELD_STATES:
        return True
    node = c.getFrom().getToNode()
    if c.getState() != "M" or c.getTLSID() or not node.getType().startswith("traffic_light"):
        return False
    return "1" in node._prohibits.get(node.getLinkIndex(c), "")  # sumolib keeps it private


def _straighten_shifts(hd: HDMap, vias: list[tuple[int, int]]) -> None:
    """Give the waypoints of every lane shift the road's heading (in place); ``vias``: (lane,
    junction lane) rows of every connection through a junction lane (``conn_to`` holds one
    per next edge: SUMO's A10KW widens a road into two lanes through a jog of 52 deg that was
    left a curve, and the AVs that took it left the road or drifted into the next lane).

    A lane shift is a junction lane that leaves the road's direction by more than
    ``SHIFT_ANGLE`` although the road keeps it (within ``SHIFT_STRAIGHT``) across the
    junction: imported networks join edges whose centrelines are offset sideways this way
    (a 4.8 m jump on a 4.8 m junction lane of SUMO's highway example), and zero-length
    junction lanes have no heading at all. SUMO moves a vehicle across along the lane; read as
    a curve, the kink asked for yaw no car has and sent the AVs off the road."""
    if not vias:
        return
    src, via = np.array(vias, dtype=np.int64).reshape(-1, 2).T
    dst = hd.lane_next[via].astype(np.int64)
    ok = (hd.lane_edge[via] < 0) & (dst >= 0)
    ok[ok] &= hd.lane_edge[dst[ok]] >= 0
    src, via, dst = src[ok], via[ok], dst[ok]
    h_in = hd.wp_heading[hd.wp_offset[src] + hd.wp_count[src] - 1]
    turn = _wrap(hd.wp_heading[hd.wp_offset[dst]] - h_in)
    dev = np.zeros(len(via))
    for k in range(int(hd.wp_count[via].max(initial=0))):
        w = hd.wp_offset[via] + np.minimum(k, hd.wp_count[via] - 1)
        dev = np.maximum(dev, np.abs(_wrap(hd.wp_heading[w] - h_in)))
    shift = (np.abs(turn) < SHIFT_STRAIGHT) & (dev > SHIFT_ANGLE)
    for lane, h0, dh in zip(via[shift].tolist(), h_in[shift], turn[shift]):
        n = int(hd.wp_count[lane])
        w = slice(int(hd.wp_offset[lane]), int(hd.wp_offset[lane]) + n)
        hd.wp_heading[w] = _wrap(h0 + dh * (np.arange(n) + 0.5) / n)


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles [rad] wrapped into [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def _lane_table(net: Any) -> tuple[list, list[int], list[str], list[list[int]], dict]:
    """Lane rows (sumolib lanes, edges in file order, walking areas and crossings left out),
    the edge row of each (-1 internal), the normal edges' ids and lane rows, and sumolib edge
    -> edge row."""
    lanes: list = []
    lane_edge: list[int] = []
    edge_ids: list[str] = []
    edge_lane_rows: list[list[int]] = []
    edge_row: dict = {}
    for edge in net.getEdges(withInternal=True):
        function = edge.getFunction()
        if function in ("walkingarea", "crossing"):
            continue
        internal = function == "internal"
        erow = -1 if internal else len(edge_ids)
        rows = list(range(len(lanes), len(lanes) + len(edge.getLanes())))
        lanes += edge.getLanes()
        lane_edge += [erow] * len(rows)
        if not internal:
            edge_row[edge] = erow
            edge_ids.append(edge.getID())
            edge_lane_rows.append(rows)  # sumolib keeps lanes by index, 0 = rightmost
    return lanes, lane_edge, edge_ids, edge_lane_rows, edge_row


def _connections(
    lanes: list, lane_ids: list[str], lane_edge: list[int], edge_row: dict, car: np.ndarray
):
    """``lane_next`` (primary successor: straight on, else the first connection in file
    order), ``conn_to``, ``tls_links`` and ``lane_fans`` of ``HDMap``; from a car lane only
    connections that cars may use (SUMO's own permissions of the connection's lanes)."""
    lane_row = {lid: i for i, lid in enumerate(lane_ids)}
    lane_next = np.full(len(lanes), -1, dtype=np.int32)
    conn_to: dict[tuple[int, int], int] = {}
    tls_links: dict[tuple[int, int], tuple[str, int]] = {}
    fans = np.zeros(len(lanes), dtype=bool)
    for src, lane in enumerate(lanes):
        straight = False
        for c in lane.getOutgoing():  # in file order
            dst = lane_row.get(c.getToLane().getID())
            if dst is None:  # onto a crossing or walking area
                continue
            via = c.getViaLaneID()
            first = lane_row.get(via, dst) if via else dst
            if car[src] and not (car[dst] and car[first]):
                continue
            to = edge_row.get(c.getTo())
            if lane_edge[src] >= 0 and to is not None and car[src]:
                fans[src] |= conn_to.setdefault((src, to), first) != first
                if c.getTLSID():
                    tls_links[(src, to)] = (c.getTLSID(), c.getTLLinkIndex())
            if c.getDirection() == "s" and not straight:  # straight on: the primary successor
                lane_next[src] = first
                straight = True
            elif lane_next[src] < 0:
                lane_next[src] = first
    return lane_next, conn_to, tls_links, fans


def _sample(shape: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every SPACING metres of lane position (SUMO scales positions to the drawn shape)."""
    if len(shape) < 2:
        shape = np.vstack([shape, shape + [0.1, 0, 0]]) if len(shape) else np.zeros((2, 3))
    seg = np.diff(shape[:, :2], axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    geo = max(cum[-1], 1e-9)
    s = np.arange(0.0, max(length, SPACING * 0.5), SPACING)
    g = np.clip(s * geo / max(length, 1e-9), 0, geo)
    k = np.clip(np.searchsorted(cum, g, side="right") - 1, 0, len(seg) - 1)
    t = ((g - cum[k]) / np.maximum(seg_len[k], 1e-9))[:, None]
    pts = shape[k] + t * (shape[k + 1] - shape[k])
    hdg = np.arctan2(seg[k, 1], seg[k, 0])
    return pts, hdg


_ARRAYS = [
    "lane_edge",
    "lane_uturn",
    "lane_index",
    "lane_length",
    "lane_width",
    "lane_speed",
    "lane_car",
    "lane_yields",
    "lane_fans",
    "lane_next",
    "edge_lanes",
    "edge_length",
    "wp_offset",
    "wp_count",
    "wp_xyz",
    "wp_heading",
    "wp_lane",
]


def _to_npz(hdmap: HDMap, path: Path) -> None:
    conn = np.array([(a, b, c) for (a, b), c in hdmap.conn_to.items()], dtype=np.int64).reshape(
        -1, 3
    )
    tls = [(a, b, t, i) for (a, b), (t, i) in hdmap.tls_links.items()]
    tmp = path.with_suffix(f".tmp{np.random.randint(1 << 30)}.npz")
    np.savez(
        tmp,
        lane_ids=np.array(hdmap.lane_ids),
        edge_ids=np.array(hdmap.edge_ids),
        conn=conn,
        tls_src=np.array([t[:2] for t in tls], dtype=np.int64).reshape(-1, 2),
        tls_id=np.array([t[2] for t in tls], dtype=str),
        tls_idx=np.array([t[3] for t in tls], dtype=np.int64),
        **{k: getattr(hdmap, k) for k in _ARRAYS},
    )
    tmp.replace(path)


def _from_npz(path: Path, net_file: str) -> HDMap:
    with np.load(path, allow_pickle=False) as z:
        conn = {(int(a), int(b)): int(c) for a, b, c in z["conn"]}
        tls = {
            (int(a), int(b)): (str(t), int(i))
            for (a, b), t, i in zip(z["tls_src"], z["tls_id"], z["tls_idx"])
        }
        return HDMap(
            net_file=net_file,
            lane_ids=[str(s) for s in z["lane_ids"]],
            edge_ids=[str(s) for s in z["edge_ids"]],
            conn_to=conn,
            tls_links=tls,
            **{k: z[k] for k in _ARRAYS},
        )
