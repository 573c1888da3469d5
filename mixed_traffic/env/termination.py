"""Terminal events of the agents (DESIGN §8), as vectorised masks over (A,) arrays of ground
truth: collision, off_road, route_deviation, red_light, speed_limit.

``terminal_events`` combines them, first match wins, in ``TERMINAL_REASONS`` order; '' = none.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from itertools import repeat

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.env import step_kernel
from mixed_traffic.env.agent_table import AgentTable, Rows, StepMemory
from mixed_traffic.env.control import ControlCommand
from mixed_traffic.schema import TERMINAL_REASONS
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Default distance of the vehicle centre beyond the outer lane edge that counts as off-road [m].
OFF_ROAD_MARGIN = 0.3
#: Distance to a lane's end within which a missing connection to the next route edge counts as
#: a route deviation [m].
DEAD_END_DISTANCE = 1.0


def collided_mask(ids: Sequence[str], collisions: Iterable) -> np.ndarray:
    """(A,) bool: agent ``ids[a]`` was collider or victim of one of the snapshot's collisions."""
    involved = set()
    for c in collisions:
        involved.add(c.collider)
        involved.add(c.victim)
    return np.fromiter((i in involved for i in ids), bool, len(ids))


def overlap_mask(
    bumper_gap: np.ndarray,
    lateral_separation: np.ndarray,
    width: np.ndarray,
    front_width: np.ndarray,
) -> np.ndarray:
    """(A,) bool: the front vehicle overlaps the agent (bumper gap < 0 and lateral overlap).

    Args:
        bumper_gap: along-lane bumper-to-bumper gap to the front vehicle [m] (NaN = none).
        lateral_separation: |lateral_A - lateral_C1| [m] in a common lane frame.
    """
    gap = np.asarray(bumper_gap, float)
    sep = np.abs(np.asarray(lateral_separation, float))
    half = 0.5 * (np.asarray(width, float) + np.asarray(front_width, float))
    return np.isfinite(gap) & (gap < 0) & (sep < half)


def lane_edge_offsets(hdmap: HDMap, lane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A,) distances [m] from the lane centreline to the road's right and left edges.

    For a lane of a normal edge the road is all lanes of that edge; for a junction-internal
    lane it is the lane itself.
    """
    lane = np.asarray(lane, np.int64)
    width = hdmap.lane_width[lane]
    edge = hdmap.lane_edge[lane]
    safe_edge = np.where(edge >= 0, edge, 0)
    rows = hdmap.edge_lanes[safe_edge]  # (A, K)
    widths = np.where(rows >= 0, hdmap.lane_width[np.maximum(rows, 0)], 0.0)
    idx = hdmap.lane_index[lane].astype(np.int64)
    k = np.arange(rows.shape[1])[None, :]
    below = (widths * (k < idx[:, None])).sum(axis=1)
    above = (widths * (k > idx[:, None])).sum(axis=1)
    right = np.where(edge >= 0, below + 0.5 * width, 0.5 * width)
    left = np.where(edge >= 0, above + 0.5 * width, 0.5 * width)
    return right, left


def off_road_mask(
    hdmap: HDMap, lane: np.ndarray, lateral: np.ndarray, margin: float = OFF_ROAD_MARGIN
) -> np.ndarray:
    """(A,) bool: the vehicle centre is more than ``margin`` beyond the road's outer edge.

    ``lateral`` is the offset from ``lane``'s centreline [m, + = left]. SUMO clamps lateral
    moves to the road, so pass the controller's ``intended_lateral`` (relative to the lane at
    t) with the lane at t, not SUMO's clamped offset. Unknown lanes (-1) are not off-road.
    """
    lane = np.asarray(lane, np.int64)
    ok = lane >= 0
    right, left = lane_edge_offsets(hdmap, np.where(ok, lane, 0))
    lat = np.asarray(lateral, float)
    return ok & ((lat > left + margin) | (-lat > right + margin))


def route_deviation_mask(
    hdmap: HDMap,
    edge: np.ndarray,
    lane: np.ndarray,
    lane_pos: np.ndarray,
    routes: np.ndarray,
    route_index: np.ndarray,
    dead_end_distance: float = DEAD_END_DISTANCE,
) -> np.ndarray:
    """(A,) bool: off the route, or stuck at the end of a lane that cannot reach the route.

    Args:
        edge, lane, lane_pos: edge row (-1 on junctions), lane row, lane position [m] now.
        routes: (A, R) int edge rows of each agent's route, -1 padded.
        route_index: (A,) index of the current (or last normal) edge within the route.
    """
    edge = np.asarray(edge, np.int64)
    lane = np.asarray(lane, np.int64)
    routes = np.asarray(routes, np.int64)
    ri = np.asarray(route_index, np.int64)
    on_normal = edge >= 0
    in_route = (routes == edge[:, None]).any(axis=1)
    off_route = on_normal & ~in_route
    a = np.arange(len(edge))
    nxt_i = ri + 1
    has_next = nxt_i < routes.shape[1]
    nxt = np.where(has_next, routes[a, np.minimum(nxt_i, routes.shape[1] - 1)], -1)
    has_next &= nxt >= 0
    safe_lane = np.where(lane >= 0, lane, 0)
    near_end = (hdmap.lane_length[safe_lane] - np.asarray(lane_pos, float)) < dead_end_distance
    check = on_normal & in_route & has_next & near_end & (lane >= 0)
    no_conn = np.zeros(len(edge), bool)
    for k in np.flatnonzero(check):
        no_conn[k] = (int(lane[k]), int(nxt[k])) not in hdmap.conn_to
    return off_route | no_conn


def red_light_mask(
    hdmap: HDMap,
    lane_prev: np.ndarray,
    lane_now: np.ndarray,
    next_edge: np.ndarray,
    tls_state_prev: Mapping[str, str],
) -> np.ndarray:
    """(A,) bool: the agent crossed a stop line whose signal was red ('r') at the previous step.

    Args:
        lane_prev, lane_now: lane rows at t and t+1.
        next_edge: (A,) edge row of the route edge after the one driven at t (-1 = none).
        tls_state_prev: traffic light id -> state string at t (``SumoBackend.tls_states``).
    """
    lane_prev = np.asarray(lane_prev, np.int64)
    lane_now = np.asarray(lane_now, np.int64)
    ok = (lane_prev >= 0) & (lane_now >= 0) & (lane_prev != lane_now)
    prev_edge = hdmap.lane_edge[np.where(ok, lane_prev, 0)]
    now_edge = hdmap.lane_edge[np.where(ok, lane_now, 0)]
    crossed = ok & (prev_edge >= 0) & (now_edge != prev_edge)
    out = np.zeros(len(lane_prev), bool)
    for k in np.flatnonzero(crossed):
        link = hdmap.tls_links.get((int(lane_prev[k]), int(next_edge[k])))
        if link is None:
            continue
        state = tls_state_prev.get(link[0], "")
        out[k] = 0 <= link[1] < len(state) and state[link[1]] == "r"
    return out


def speed_limit_mask(speed: np.ndarray, limit: np.ndarray, tolerance: float) -> np.ndarray:
    """(A,) bool: speed > limit·(1 + tolerance)."""
    return np.asarray(speed, float) > np.asarray(limit, float) * (1.0 + tolerance)


def terminal_events(
    collision: np.ndarray,
    off_road: np.ndarray,
    route_deviation: np.ndarray,
    red_light: np.ndarray,
    speed_limit: np.ndarray,
) -> np.ndarray:
    """(A,) reason strings ('' = none), first true mask in ``TERMINAL_REASONS`` order."""
    masks = np.stack(
        [
            np.asarray(m, bool)
            for m in (collision, off_road, route_deviation, red_light, speed_limit)
        ]
    )
    reasons = np.array(("", *TERMINAL_REASONS), dtype=object)
    first = np.where(masks.any(axis=0), masks.argmax(axis=0) + 1, 0)
    return reasons[first]


def agent_events(
    hd: HDMap, memory: StepMemory, table: AgentTable, snap: TrafficSnapshot, rows: Rows,
    cmd: ControlCommand, tls_prev: Mapping[str, str], speed_tolerance: float,
) -> dict[str, str]:  # fmt: skip
    """'arrived', a terminal reason, or '' for every agent that acted (``memory.ids``), judged
    on ``snap`` after the step."""
    prev = memory
    crashed = (
        collided_mask(prev.ids, snap.collisions)
        if snap.collisions
        else repeat(False, len(prev.ids))
    )
    arrived = set(snap.arrived)
    events = {
        a: "collision" if c else "arrived" if a in arrived else ""
        for a, c in zip(prev.ids, crashed)
    }
    if not events:
        return events
    now = table.by_slot(rows.slots, rows.r)[prev.slots]  # row now, -1 if gone
    fine = np.fromiter(map(events.__getitem__, prev.ids), object, len(prev.ids)) == ""
    p = np.flatnonzero((now >= 0) & fine)
    if not len(p):
        return events
    ids = [prev.ids[i] for i in p.tolist()]
    r = now[p]
    # SUMO clamps lateral moves to the road: judge off-road by the commanded position
    lateral = table.aligned(cmd.ids, cmd.intended_lateral, prev.slots[p], snap.lateral[r])
    reasons = event_reasons(hd, prev.lane[p], lateral, snap.edge[r], snap.lane[r], snap.lane_pos[r],
                            table.route_table[prev.slots[p]], snap.route_index[r],
                            prev.next_edge[p], snap.speed[r], tls_prev, speed_tolerance)  # fmt: skip
    events.update(zip(ids, reasons.tolist()))
    return events


def event_reasons(
    hd: HDMap, lane_prev: np.ndarray, lateral: np.ndarray, edge: np.ndarray, lane: np.ndarray,
    lane_pos: np.ndarray, routes: np.ndarray, route_index: np.ndarray, next_edge: np.ndarray,
    speed: np.ndarray, tls_prev: Mapping[str, str], speed_tolerance: float,
) -> np.ndarray:  # fmt: skip
    """(A,) object reason strings ('' = none, never 'collision') of agents still in the
    network: ``terminal_events`` of the masks above (lane, lateral [m] and next edge at t;
    edge, lane, lane position [m], route index and speed [m/s] now; ``routes`` (A, W))."""
    if not compiled.enabled() or hd.edge_lanes.shape[1] >= 8:  # np.sum is pairwise from 8
        return terminal_events(
            collision=np.zeros(len(lane), bool),
            off_road=off_road_mask(hd, lane_prev, lateral),
            route_deviation=route_deviation_mask(hd, edge, lane, lane_pos, routes, route_index),
            red_light=red_light_mask(hd, lane_prev, lane, next_edge, tls_prev),
            speed_limit=speed_limit_mask(speed, hd.lane_speed[lane], speed_tolerance),
        )
    codes, crossed = step_kernel.event_codes(
        hd.lane_width, hd.lane_edge, hd.lane_index, hd.lane_length, hd.lane_speed,
        hd.edge_lanes, _conn_keys(hd), lane_prev, lateral, OFF_ROAD_MARGIN, edge, lane,
        lane_pos, routes, route_index, speed_tolerance, DEAD_END_DISTANCE, speed,
    )  # fmt: skip
    for k in np.flatnonzero(crossed).tolist():  # rare: the string states stay Python
        link = hd.tls_links.get((int(lane_prev[k]), int(next_edge[k])))
        state = tls_prev.get(link[0], "") if link is not None else ""
        red = link is not None and 0 <= link[1] < len(state) and state[link[1]] == "r"
        if red and codes[k] in (0, step_kernel.SPEED_LIMIT):  # red light precedes speed
            codes[k] = step_kernel.RED_LIGHT
    return _REASONS[codes]


_REASONS = np.array(("", *TERMINAL_REASONS), dtype=object)
#: ``step_kernel.conn_keys`` of each map, by ``id`` (with the map, so an id is not reused).
_CONN_KEYS: dict[int, tuple[HDMap, np.ndarray]] = {}


def _conn_keys(hd: HDMap) -> np.ndarray:
    """The map's sorted ``conn_to`` keys for ``step_kernel.event_codes``, built once."""
    entry = _CONN_KEYS.get(id(hd))
    if entry is None or entry[0] is not hd:
        if len(_CONN_KEYS) > 16:  # maps of finished envs: let them go
            _CONN_KEYS.clear()
        entry = _CONN_KEYS[id(hd)] = (hd, step_kernel.conn_keys(hd.conn_to, len(hd.edge_lanes)))
    return entry[1]
