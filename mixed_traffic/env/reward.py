"""Hybrid reward (paper §IV-E, DESIGN §8) as named, vectorised terms.

All functions take plain (A,) arrays, one entry per agent, in ground-truth SI units, so the env
can feed them from the snapshot and the perception module's neighbours. "No vehicle" is NaN or
+inf in a distance/gap input.

Terms (``reward_terms`` returns them by these names)::

    r1_ttc         max(-3, ln(TTC/G)) if 0 < TTC < G else 0,
                   TTC = (along-lane distance to C1 - (len_A + len_C1)/2) / (v_A - v_C1)
    r1_lane        -|lateral offset from the lane centre| / lane width (``lane_term="waypoint"``:
                   the paper's distance to the nearest centreline waypoint)
    r1_terminal    terminal_penalty (-20) on a terminal event, else 0
    r2_speed       v / speed limit
    r2_lane_change (gap_new(t+1) / gap_old(t) - 1) * lane_change_gain (20) on a completed lane
                   change, else 0; bumper gaps to the front vehicle, capped at the LiDAR range
                   (no vehicle = the range), floored at MIN_GAP; |gap_new/gap_old - 1| is
                   bounded by lane_change_cap (0 = unbounded, the paper)
    r3_comfort     -|a_t - a_{t-1}| / (2 acc_thr)
    r4_impact      (v_C2(t+1) - v_C2(t)) / (2 acc_thr dt) if the same rear vehicle C2 slowed by
                   more than v_thr, else 0
    r7_accel       -|a_t| / acc_thr: the agent's own acceleration (Flow's ring penalty)
    r8_uniform_flow  how near the traffic around the agent is to the reference flow (Flow's
                   desired-velocity reward; ``traffic_terms``)

``total_reward = w1 (r1_ttc + r1_lane + r1_terminal) + w2 (r2_speed + r2_lane_change)
+ w3 r3_comfort + w4 r4_impact (+ w5 r5_local_speed + w6 r6_follower_comfort + w7 r7_accel
+ w8 r8_uniform_flow)``; r5, r6 and r8, the traffic around the agent, come from
:mod:`mixed_traffic.env.traffic_terms` (w5-w8 are 0 by default: the paper's reward).
"""

from __future__ import annotations

from collections.abc import Mapping
from itertools import repeat

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.config import EnvConfig, RewardConfig
from mixed_traffic.env import step_kernel
from mixed_traffic.env.agent_table import AgentTable, Rows, StepMemory
from mixed_traffic.env.traffic_terms import traffic_terms
from mixed_traffic.env.truth import FrontView, StepViews, speeds_of
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

TERM_NAMES = (
    "r1_ttc",
    "r1_lane",
    "r1_terminal",
    "r2_speed",
    "r2_lane_change",
    "r3_comfort",
    "r4_impact",
    "r5_local_speed",
    "r6_follower_comfort",
    "r7_accel",
    "r8_uniform_flow",
)
#: The terms of ``step_kernel.reward_terms``, in its order.
_KERNEL_TERMS = ("r1_ttc", "r1_lane", "r1_terminal", "r2_speed", "r2_lane_change", "r3_comfort",
                 "r4_impact", "r7_accel")  # fmt: skip
#: Smallest bumper gap used in the lane-change ratio [m] (avoids dividing by ~0).
MIN_GAP = 0.5


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
    cap: float = 0.0,
) -> np.ndarray:
    """(A,) (gap_new/gap_old - 1)·gain where ``completed``, else 0; the ratio's change is
    clipped to ±``cap`` unless ``cap`` is 0.

    Args:
        gap_new: bumper gap to the front vehicle in the new lane at t+1 [m] (NaN/inf = none).
        gap_old: bumper gap to the front vehicle in the old lane at t [m] (NaN/inf = none).
    """

    def clip(g: np.ndarray) -> np.ndarray:
        g = np.asarray(g, float)
        g = np.where(np.isfinite(g), g, lidar_range)
        return np.clip(g, MIN_GAP, lidar_range)

    change = clip(gap_new) / clip(gap_old) - 1.0
    if cap > 0:
        change = np.clip(change, -cap, cap)
    return np.where(np.asarray(completed, bool), change * gain, 0.0)


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
    if compiled.enabled():
        *terms, ratio, hits = step_kernel.reward_terms(
            front_distance, closing_speed, length, front_length, centre_distance, lane_width,
            terminal, speed, speed_limit, lane_changed, gap_new, gap_old, lidar_range, accel,
            prev_accel, rear_speed_prev, rear_speed_now, rear_same, cfg.ttc_threshold,
            cfg.terminal_penalty, cfg.lane_change_gain, cfg.lane_change_cap, cfg.acc_threshold,
            cfg.rear_speed_drop, dt, MIN_GAP,
        )  # fmt: skip
        if hits:  # numpy's log (SIMD), as r1_ttc's
            k = np.flatnonzero(ratio >= 0)
            terms[0][k] = np.maximum(-3.0, np.log(ratio[k]))
        return dict(zip(_KERNEL_TERMS, terms))
    ttc = time_to_collision(front_distance, closing_speed, length, front_length)
    lane_dist = np.nan_to_num(np.asarray(centre_distance, float), nan=0.0)
    return {
        "r1_ttc": r1_ttc(ttc, cfg.ttc_threshold),
        "r1_lane": -lane_dist / np.asarray(lane_width, float),
        "r1_terminal": np.where(np.asarray(terminal, bool), cfg.terminal_penalty, 0.0),
        "r2_speed": np.asarray(speed, float) / np.asarray(speed_limit, float),
        "r2_lane_change": r2_lane_change(
            lane_changed, gap_new, gap_old, lidar_range, cfg.lane_change_gain, cfg.lane_change_cap
        ),
        "r3_comfort": -np.abs(np.asarray(accel, float) - np.asarray(prev_accel, float))
        / (2.0 * cfg.acc_threshold),
        "r4_impact": r4_impact(
            rear_speed_prev, rear_speed_now, rear_same, cfg.acc_threshold, cfg.rear_speed_drop, dt
        ),
        "r7_accel": -np.abs(np.asarray(accel, float)) / cfg.acc_threshold,
    }


def total_reward(terms: Mapping[str, np.ndarray], cfg: RewardConfig) -> np.ndarray:
    """(A,) w1·r1 + w2·r2 + w3·r3 + w4·r4 (+ w5·r5 + ... + w8·r8 where their weights are not
    0) from the named terms."""
    r1 = terms["r1_ttc"] + terms["r1_lane"] + terms["r1_terminal"]
    r2 = terms["r2_speed"] + terms["r2_lane_change"]
    total = (
        cfg.w_safety * r1
        + cfg.w_efficiency * r2
        + cfg.w_comfort * terms["r3_comfort"]
        + cfg.w_impact * terms["r4_impact"]
    )
    extra = {"r5_local_speed": cfg.w_local_speed, "r6_follower_comfort": cfg.w_follower_comfort,
             "r7_accel": cfg.w_accel, "r8_uniform_flow": cfg.w_uniform}  # fmt: skip
    for name, w in extra.items():
        if w:  # weight 0: the paper's sum, bit for bit
            total = total + w * terms[name]
    return total


# ---------------------------------------------------------------------- per step
def agent_rewards(
    cfg: EnvConfig, hd: HDMap, memory: StepMemory, table: AgentTable, snap: TrafficSnapshot,
    rows: Rows, views: StepViews, events: dict[str, str], ring: bool = False,
    desired: np.ndarray | None = None, dicts: bool = True,
):  # fmt: skip
    """Reward, named terms and completed lane changes (bool per agent number) of every
    agent that acted (``views``: the step's ground truth of ``rows``); ``ring``: the network is
    a ring (for r5, r6 and r8); ``desired``: (L,) r8's reference speed on each lane [m/s] (0 or
    None = the lane limits); ``dicts`` False: the named terms only of agents that left the
    network (the others' stay arrays, unbuilt)."""
    prev = memory
    rewards: dict[str, float] = {}
    terms_out: dict[str, dict[str, float]] = {}
    failed = {a for a, e in events.items() if e not in ("", "arrived")}
    now = table.by_slot(rows.slots, rows.r)[prev.slots]  # row now, -1 if gone
    for i in np.flatnonzero(now < 0).tolist():
        # left the network this step: only the terminal penalty applies
        a = prev.ids[i]
        t = dict.fromkeys(TERM_NAMES, 0.0)
        t["r1_terminal"] = cfg.reward.terminal_penalty if a in failed else 0.0
        terms_out[a], rewards[a] = t, cfg.reward.w_safety * t["r1_terminal"]
    p = np.flatnonzero(now >= 0)
    if not len(p):
        return rewards, terms_out, table.by_slot(p, np.zeros(0, bool), False)
    ids = [prev.ids[i] for i in p.tolist()]
    # views are in the order of rows
    k = table.by_slot(rows.slots, np.arange(len(rows.r)))[prev.slots[p]]
    terms, changed = _terms(cfg, hd, memory, snap, views.front.take(k), now[p], p, ids, failed)
    slots = prev.slots[p]
    terms.update(traffic_terms(cfg.reward, hd, snap, now[p], table.route_table[slots],
                               table.route_len[slots], ring, desired))  # fmt: skip
    total = total_reward(terms, cfg.reward)
    if dicts:
        names = list(terms)
        columns = [np.asarray(v, np.float64).tolist() for v in terms.values()]
        # one {term: value} dict per agent, built by C-level maps (hundreds of agents per step)
        terms_out.update(zip(ids, map(dict, map(zip, repeat(names), zip(*columns)))))
    rewards.update(zip(ids, np.asarray(total, np.float64).tolist()))
    return rewards, terms_out, table.by_slot(prev.slots[p], np.asarray(changed, bool), False)


def _terms(cfg: EnvConfig, hd: HDMap, memory: StepMemory, snap: TrafficSnapshot,
           front: FrontView, r: np.ndarray, p: np.ndarray, ids: list[str],
           failed: set[str]):  # fmt: skip
    """Named reward terms (and completed lane changes) of the agents still present: their
    front view ``front``, snapshot rows ``r``, memory rows ``p``."""
    prev = memory
    rear_now = speeds_of(snap, [prev.rear_ids[i] for i in p.tolist()])
    lane = snap.lane[r]
    changed = lane_change_completed(prev.lane[p], lane, prev.edge[p], snap.edge[r])
    if cfg.reward.lane_term == "offset":
        centre = np.abs(snap.lateral[r])
    else:
        centre = centreline_distance(hd, lane, snap.lane_pos[r], snap.x[r], snap.y[r])
    terms = reward_terms(
        cfg.reward, cfg.step_length,
        front_distance=front.distance, closing_speed=front.closing, length=snap.length[r],
        front_length=front.length,
        centre_distance=centre,
        lane_width=hd.lane_width[lane], terminal=np.fromiter(map(failed.__contains__, ids), bool, len(ids)),
        speed=snap.speed[r], speed_limit=hd.lane_speed[lane],
        lane_changed=changed, gap_new=front.gap, gap_old=prev.front_gap[p],
        lidar_range=cfg.sensors.lidar_range, accel=snap.accel[r], prev_accel=prev.accel[p],
        rear_speed_prev=prev.rear_speed[p], rear_speed_now=rear_now, rear_same=~np.isnan(rear_now),
    )  # fmt: skip
    return terms, changed
