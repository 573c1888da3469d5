"""What a step's ground truth leaves behind: the per-AV metric sample of the step, and the
memory the next step's events and rewards compare against."""

from __future__ import annotations

from itertools import repeat

import numpy as np

from mixed_traffic.env.agent_table import FOLLOW, AgentTable, Rows, StepMemory
from mixed_traffic.env.av_metrics import AVStep
from mixed_traffic.env.truth import StepViews, take_or_nan
from mixed_traffic.sensing.geometry import ttc
from mixed_traffic.world.snapshot import TrafficSnapshot


def av_step(snap: TrafficSnapshot, rows: Rows, views: StepViews, table: AgentTable,
            prev: StepMemory, rewards: dict[str, float], changed: np.ndarray,
            copy: np.ndarray | None = None) -> AVStep:  # fmt: skip
    """The AV metrics' sample of the live agents ``rows`` after a step (``prev``: the memory
    of the step before; ``views`` the step's ground truth of ``rows``; ``changed`` (N,)
    completed lane changes by agent number; ``copy`` (A,) the agents' copies)."""
    ids, r, n = rows.ids, rows.r, len(rows.ids)
    front, rear_ids, rear_speed = views.front, views.rear_ids, views.rear_speed
    pi = table.by_slot(prev.slots, np.arange(len(prev.ids)))[rows.slots]  # -1: new agent
    prev_accel = np.where(pi >= 0, take_or_nan(prev.accel, pi), snap.accel[r])
    # the same conventional vehicle C behind the agent as at the previous step
    rear_now = np.array(rear_ids, dtype=object)
    rear_before = np.array([*prev.rear_ids, ""], dtype=object)[pi]  # pi = -1 -> ""
    same = (pi >= 0) & (rear_now != "") & (rear_before == rear_now)
    return AVStep(
        ids=ids, speed=snap.speed[r], accel=snap.accel[r], prev_accel=prev_accel,
        lateral=snap.lateral[r], following=table.decision[rows.slots] == FOLLOW,
        lane_changed=changed[rows.slots],
        ttc=np.where(front.exists, ttc(front.gap, front.closing), np.inf),
        rear_ids=rear_ids, rear_speed=np.nan_to_num(rear_speed),
        rear_prev_speed=np.where(same, take_or_nan(prev.rear_speed, pi), np.nan),
        reward=np.fromiter(map(rewards.get, ids, repeat(0.0)), np.float64, n), copy=copy,
    )  # fmt: skip


def step_memory(snap: TrafficSnapshot, rows: Rows, views: StepViews,
                table: AgentTable) -> StepMemory:  # fmt: skip
    """Ground truth of this step that the next step's events and rewards compare against."""
    r = rows.r
    return StepMemory(
        ids=rows.ids, slots=rows.slots, accel=snap.accel[r].copy(),
        lane=snap.lane[r].astype(np.int64), edge=snap.edge[r].astype(np.int64),
        next_edge=table.next_edge(rows.slots, snap.route_index[r]),
        front_gap=views.front.gap, rear_ids=views.rear_ids, rear_speed=views.rear_speed,
    )  # fmt: skip
