"""Hybrid reward (paper §IV-E, DESIGN §8) as named, vectorised terms, and terminal events.

All functions take plain (A,) arrays, one entry per agent, in ground-truth SI units, so the env
can feed them from the snapshot and the perception module's neighbours. "No vehicle" is NaN or
+inf in a distance/gap input.

Terms (``reward_terms`` returns them by these names)::

    r1_ttc         max(-3, ln(TTC/G)) if 0 < TTC < G else 0,
                   TTC = (along-lane distance to C1 - (len_A + len_C1)/2) / (v_A - v_C1)
    r1_lane        -(distance to the nearest centreline waypoint) / lane width
    r1_terminal    terminal_penalty (-20) on a terminal event, else 0
    r2_speed       v / speed limit
    r2_lane_change (gap_new(t+1) / gap_old(t) - 1) * lane_change_gain (20) on a completed lane
                   change, else 0; bumper gaps to the front vehicle, capped at the LiDAR range
                   (no vehicle = the range), floored at MIN_GAP
    r3_comfort     -|a_t - a_{t-1}| / (2 acc_thr)
    r4_impact      (v_C2(t+1) - v_C2(t)) / (2 acc_thr dt) if the same rear vehicle C2 slowed by
                   more than v_thr, else 0

``total_reward = w1 (r1_ttc + r1_lane + r1_terminal) + w2 (r2_speed + r2_lane_change)
+ w3 r3_comfort + w4 r4_impact``.

Terminal events (``terminal_events``), first match wins, in ``TERMINAL_REASONS`` order:
collision, off_road, route_deviation, red_light, speed_limit; '' = none.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from mixed_traffic.config import RewardConfig
from mixed_traffic.world.hdmap import HDMap

TERM_NAMES = (
    "r1_ttc",
    "r1_lane",
    "r1_terminal",
    "r2_speed",
    "r2_lane_change",
    "r3_comfort",
    "r4_impact",
)
TERMINAL_REASONS = ("collision", "off_road", "route_deviation", "red_light", "speed_limit")
#: Smallest bumper gap used in the lane-change ratio [m] (avoids dividing by ~0).
MIN_GAP = 0.5
#: Default distance of the vehicle centre beyond the outer lane edge that counts as off-road [m].
OFF_ROAD_MARGIN = 0.3
#: Distance to a lane's end within which a missing connection to the next route edge counts as
#: a route deviation [m].
DEAD_END_DISTANCE = 1.0


# ---------------------------------------------------------------------- single terms
def time_to_collision(
    distance: np.ndarray, closing_speed: np.ndarray, length: np.ndarray, front_length: np.ndarray
) -> np.ndarray:
    """(A,) TTC [s] to the front vehicle; +inf if none (NaN/inf distance) or not closing.

    Args:
        distance: along-lane centre-to-centre distance to the front vehicle C1 [m].
        closing_speed: v_A - v_C1 [m/s] (> 0 when approaching).
        length, front_length: lengths of A and C1 [m].
    """
    gap = np.asarray(distance, float) - 0.5 * (np.asarray(length) + np.asarray(front_length))
    closing = np.asarray(closing_speed, float)
    ok = np.isfinite(gap) & (closing > 0)
    out = np.full(gap.shape, np.inf)
    np.divide(gap, closing, out=out, where=ok)
    return out


def r1_ttc(ttc: np.ndarray, threshold: float) -> np.ndarray:
    """(A,) max(-3, ln(TTC/G)) for 0 < TTC < G, else 0."""
    ttc = np.asarray(ttc, float)
    hit = (ttc > 0) & (ttc < threshold)
    out = np.zeros(ttc.shape)
    out[hit] = np.maximum(-3.0, np.log(ttc[hit] / threshold))
    return out


def centreline_distance(
    hdmap: HDMap, lane: np.ndarray, lane_pos: np.ndarray, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """(A,) Euclidean distance [m] from (x, y) to the nearest 1 m centreline waypoint of ``lane``.

    Searches the waypoints at ``lane_pos`` and one either side; (x, y) and ``lane_pos`` must
    refer to the same point of the vehicle (the snapshot's front bumper). NaN if lane < 0.
    """
    lane = np.asarray(lane, np.int64)
    ok = lane >= 0
    safe = np.where(ok, lane, 0)
    k = hdmap.waypoint_at(safe, np.maximum(np.asarray(lane_pos, float), 0.0))
    first = hdmap.wp_offset[safe]
    last = first + hdmap.wp_count[safe] - 1
    cand = np.clip(k[:, None] + np.array([-1, 0, 1]), first[:, None], last[:, None])
    dx = hdmap.wp_xyz[cand, 0] - np.asarray(x, float)[:, None]
    dy = hdmap.wp_xyz[cand, 1] - np.asarray(y, float)[:, None]
    dist = np.sqrt(dx * dx + dy * dy).min(axis=1)
    return np.where(ok, dist, np.nan)


def lane_change_completed(
    lane_prev: np.ndarray, lane_now: np.ndarray, edge_prev: np.ndarray, edge_now: np.ndarray
) -> np.ndarray:
    """(A,) bool: the lane row changed between t and t+1 while staying on the same normal edge."""
    lane_prev, lane_now = np.asarray(lane_prev), np.asarray(lane_now)
    edge_prev, edge_now = np.asarray(edge_prev), np.asarray(edge_now)
    return (
        (lane_prev >= 0)
        & (lane_now >= 0)
        & (lane_prev != lane_now)
        & (edge_prev == edge_now)
        & (edge_now >= 0)
    )


def r2_lane_change(
    completed: np.ndarray,
    gap_new: np.ndarray,
    gap_old: np.ndarray,
    lidar_range: float,
    gain: float,
) -> np.ndarray:
    """(A,) (gap_new/gap_old - 1)·gain where ``completed``, else 0.

    Args:
        gap_new: bumper gap to the front vehicle in the new lane at t+1 [m] (NaN/inf = none).
        gap_old: bumper gap to the front vehicle in the old lane at t [m] (NaN/inf = none).
    """

    def cap(g: np.ndarray) -> np.ndarray:
        g = np.asarray(g, float)
        g = np.where(np.isfinite(g), g, lidar_range)
        return np.clip(g, MIN_GAP, lidar_range)

    ratio = cap(gap_new) / cap(gap_old)
    return np.where(np.asarray(completed, bool), (ratio - 1.0) * gain, 0.0)


def r4_impact(
    rear_speed_prev: np.ndarray,
    rear_speed_now: np.ndarray,
    rear_same: np.ndarray,
    acc_threshold: float,
    speed_drop: float,
    dt: float,
) -> np.ndarray:
    """(A,) (v_C2(t+1) - v_C2(t)) / (2·acc_thr·dt) if the same C2 slowed by more than v_thr."""
    prev, now = np.asarray(rear_speed_prev, float), np.asarray(rear_speed_now, float)
    dv = now - prev
    hit = np.asarray(rear_same, bool) & np.isfinite(dv) & (-dv > speed_drop)
    return np.where(hit, dv / (2.0 * acc_threshold * dt), 0.0)


# ---------------------------------------------------------------------- all terms
def reward_terms(
    cfg: RewardConfig,
    dt: float,
    *,
    front_distance: np.ndarray,
    closing_speed: np.ndarray,
    length: np.ndarray,
    front_length: np.ndarray,
    centre_distance: np.ndarray,
    lane_width: np.ndarray,
    terminal: np.ndarray,
    speed: np.ndarray,
    speed_limit: np.ndarray,
    lane_changed: np.ndarray,
    gap_new: np.ndarray,
    gap_old: np.ndarray,
    lidar_range: float,
    accel: np.ndarray,
    prev_accel: np.ndarray,
    rear_speed_prev: np.ndarray,
    rear_speed_now: np.ndarray,
    rear_same: np.ndarray,
) -> dict[str, np.ndarray]:
    """Every reward term by name, each (A,) float64 (see the module docstring).

    Inputs at t+1 unless named ``prev``/``old`` (at t): ``front_distance`` along-lane
    centre distance to C1 [m] and ``closing_speed`` v_A - v_C1 [m/s]; ``centre_distance`` to
    the nearest centreline waypoint [m] (``centreline_distance``); ``terminal`` bool;
    ``speed`` [m/s]; ``speed_limit`` [m/s]; ``lane_changed`` (``lane_change_completed``);
    ``gap_new``/``gap_old`` bumper gaps [m]; ``accel``/``prev_accel`` [m/s²]; rear vehicle C2
    speeds [m/s] and whether it is the same vehicle at t and t+1.
    """
    ttc = time_to_collision(front_distance, closing_speed, length, front_length)
    lane_dist = np.nan_to_num(np.asarray(centre_distance, float), nan=0.0)
    return {
        "r1_ttc": r1_ttc(ttc, cfg.ttc_threshold),
        "r1_lane": -lane_dist / np.asarray(lane_width, float),
        "r1_terminal": np.where(np.asarray(terminal, bool), cfg.terminal_penalty, 0.0),
        "r2_speed": np.asarray(speed, float) / np.asarray(speed_limit, float),
        "r2_lane_change": r2_lane_change(
            lane_changed, gap_new, gap_old, lidar_range, cfg.lane_change_gain
        ),
        "r3_comfort": -np.abs(np.asarray(accel, float) - np.asarray(prev_accel, float))
        / (2.0 * cfg.acc_threshold),
        "r4_impact": r4_impact(
            rear_speed_prev, rear_speed_now, rear_same, cfg.acc_threshold, cfg.rear_speed_drop, dt
        ),
    }


def total_reward(terms: Mapping[str, np.ndarray], cfg: RewardConfig) -> np.ndarray:
    """(A,) w1·r1 + w2·r2 + w3·r3 + w4·r4 from the named terms."""
    r1 = terms["r1_ttc"] + terms["r1_lane"] + terms["r1_terminal"]
    r2 = terms["r2_speed"] + terms["r2_lane_change"]
    return (
        cfg.w_safety * r1
        + cfg.w_efficiency * r2
        + cfg.w_comfort * terms["r3_comfort"]
        + cfg.w_impact * terms["r4_impact"]
    )


# ---------------------------------------------------------------------- terminal events
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
