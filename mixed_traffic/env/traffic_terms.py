"""Reward terms for the traffic around each agent (ground truth, vectorised over agents).

Terms (``traffic_terms`` returns them by these names; route distances as in
:mod:`mixed_traffic.sensing.route_traffic`, windows in ``RewardConfig``)::

    r5_local_speed       mean over the vehicles within local_upstream behind and
                         local_downstream ahead of the agent on its route, the agent
                         included (on a ring: every vehicle of the ring), of
                         v_i / speed limit of v_i's lane; in [0, ~1.2], ~1 at free flow
    r6_follower_comfort  -mean over the agent's followers of (a_i / acc_thr)^2: the
                         ``followers`` nearest vehicles behind it on its route, within
                         local_upstream, in a lane with its lane index; 0 without
                         followers; <= 0, -1 where they brake or speed up at acc_thr (3 m/s^2)
                         on average (RMS), at least -(9 / 3)^2 = -9 (SUMO's emergency decel)

r5 is the Flow benchmark's system reward (the mean speed of all vehicles) restricted to a
window, so every agent on a ring gets the same value. r8 pays for the state the benchmark's
score calls 1 (a ring's uniform flow, a road's free flow): it falls with the speeds' spread as
with their mean's shortfall, so neither waves nor a slow crawl pay. r6 is the CIRCLES idea of
judging an AV by how its followers drive, with the squared acceleration (Flow's penalty) for
their energy.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.config import RewardConfig
from mixed_traffic.env import traffic_terms_kernel
from mixed_traffic.sensing.route_traffic import map_tables, ring_pairs, route_frame, route_pairs
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

TRAFFIC_TERMS = ("r5_local_speed", "r6_follower_comfort", "r8_uniform_flow")


def traffic_terms(cfg: RewardConfig, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray,
                  routes: np.ndarray, route_len: np.ndarray, ring: bool,
                  desired: np.ndarray | None = None) -> dict[str, np.ndarray]:  # fmt: skip
    """r5, r6 and r8 (each (A,) float64) of the agents at snapshot ``rows`` (A,), whose routes
    are ``routes`` (A, W) edge rows of ``route_len`` (A,) edges; ``ring``: the network is a
    ring (r5 then counts every vehicle); ``desired``: (L,) r8's reference speed on each lane
    [m/s] (0 or None = the lane's limit: a ring's copies each have their own uniform flow). One compiled kernel (:mod:`.traffic_terms_kernel`) when kernels
    are enabled (``mixed_traffic.compiled``), else the numpy stages: equal bit for bit."""
    if len(rows) == 0:
        return {name: np.zeros(0) for name in TRAFFIC_TERMS}
    terms = _compiled if compiled.enabled() else _reference
    desired = np.zeros(len(hd.lane_ids)) if desired is None else desired
    return terms(cfg, hd, snap, rows, routes, route_len, ring, desired)


def _compiled(cfg: RewardConfig, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray,
              routes: np.ndarray, route_len: np.ndarray, ring: bool,
              desired: np.ndarray) -> dict[str, np.ndarray]:  # fmt: skip
    """:func:`_reference` as one compiled kernel (:mod:`.traffic_terms_kernel`)."""
    t = map_tables(hd)
    i64 = np.int64  # one specialisation, whatever integer arrays the caller has
    out = traffic_terms_kernel.terms(
        np.asarray(rows, i64), np.asarray(routes, i64), np.asarray(route_len, i64), snap.lane,
        snap.lane_pos, snap.speed, snap.accel, snap.lane_index, snap.route_index,
        hd.edge_length, hd.lane_speed, t.anchor_edge, t.anchor_offset, t.junction_keys,
        t.junction_len, int(t.n_edges), float(t.key_stride), float(t.key_shift), bool(ring),
        float(cfg.local_upstream), float(cfg.local_downstream), int(cfg.followers),
        float(cfg.acc_threshold), np.asarray(desired, np.float64),
    )  # fmt: skip
    return dict(zip(TRAFFIC_TERMS, out))


def _reference(cfg: RewardConfig, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray,
               routes: np.ndarray, route_len: np.ndarray, ring: bool,
               desired: np.ndarray) -> dict[str, np.ndarray]:  # fmt: skip
    """The numpy stages (the kernel's reference): :func:`traffic_terms` of A >= 1 agents."""
    A = len(rows)
    frame = route_frame(hd, snap, rows, routes, route_len)
    if ring:  # every vehicle is near; one d ahead is lap - d behind
        pairs = ring_pairs(hd, snap, frame)
        behind = np.where(pairs.distance > 0, pairs.lap[pairs.agent] - pairs.distance, 0.0)
    else:  # the vehicles within the window
        pairs = route_pairs(hd, snap, frame, cfg.local_upstream, cfg.local_downstream)
        behind = -pairs.distance
    a, v = pairs.agent, pairs.vehicle
    limit = np.maximum(hd.lane_speed[snap.lane[v]], 0.1)
    want = desired[snap.lane[v]]
    ratio = snap.speed[v] / limit
    n = np.bincount(a, minlength=A)
    own_lane = np.maximum(snap.lane[rows].astype(np.int64), 0)
    own = snap.speed[rows] / np.maximum(hd.lane_speed[own_lane], 0.1)  # if off its route
    local = np.where(n > 0, np.bincount(a, ratio, minlength=A) / np.maximum(n, 1), own)
    follower = (v != rows[a]) & (behind > 0) & (behind <= cfg.local_upstream)
    follower &= snap.lane_index[v] == snap.lane_index[rows[a]]
    return {
        "r5_local_speed": local,
        "r6_follower_comfort": _follower_comfort(
            cfg, snap, a[follower], v[follower], behind[follower], A
        ),
        "r8_uniform_flow": uniform_flow_reward(ratio, np.where(want > 0, want / limit, 1.0), a, n),
    }


def uniform_flow_reward(ratio: np.ndarray, target: np.ndarray | float, agent: np.ndarray,
                        n: np.ndarray) -> np.ndarray:  # fmt: skip
    """(A,) r8 from each pair's speed ``ratio`` and reference ``target`` (shares of its limit)
    and agent index (each (P,)); ``n`` (A,) pairs per agent (0 without any: r8 = 0)."""
    target = np.broadcast_to(target, ratio.shape)
    m = np.maximum(n, 1)
    rms = np.sqrt(np.bincount(agent, (ratio - target) ** 2, minlength=len(n)) / m)
    scale = np.bincount(agent, target, minlength=len(n)) / m
    return np.where(n > 0, np.maximum(0.0, 1.0 - rms / np.maximum(scale, 1e-9)), 0.0)


def _follower_comfort(cfg: RewardConfig, snap: TrafficSnapshot, agent: np.ndarray,
                      vehicle: np.ndarray, behind: np.ndarray, A: int) -> np.ndarray:  # fmt: skip
    """(A,) -mean (a_i / acc_thr)^2 over the ``cfg.followers`` candidates nearest behind each
    agent (candidates: ``agent``, ``vehicle``, ``behind`` [m], each (P,)); 0 without any."""
    order = np.lexsort((behind, agent))  # by agent, nearest first
    agent, vehicle = agent[order], vehicle[order]
    first = np.searchsorted(agent, agent, side="left")
    keep = np.arange(len(agent)) - first < cfg.followers
    agent, vehicle = agent[keep], vehicle[keep]
    sq = (snap.accel[vehicle] / cfg.acc_threshold) ** 2
    n = np.bincount(agent, minlength=A)
    return -np.bincount(agent, sq, minlength=A) / np.maximum(n, 1)
