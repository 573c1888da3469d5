"""Ground-truth views the reward and metric stages read: the front vehicle of each agent, the
conventional vehicle C behind it (both found once per step, :class:`StepViews`), speeds by
vehicle id (all from one snapshot and one ``PerceptionFrame`` of ground truth)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from itertools import repeat

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.env import control_kernel
from mixed_traffic.sensing.frame import PerceptionFrame
from mixed_traffic.sensing.geometry import bumper_gap
from mixed_traffic.sensing.lane_graph import CURRENT
from mixed_traffic.world.snapshot import TrafficSnapshot


class FrontView:
    """Ground-truth front vehicle in the current lane for agents at truth rows ``k``, snapshot rows ``r``."""

    def __init__(
        self, snap: TrafficSnapshot, truth: PerceptionFrame, k: np.ndarray, r: np.ndarray
    ) -> None:
        nb = truth.neighbours
        if compiled.enabled() and _kernel_dtypes(snap, truth, k, r):
            self.exists, self.distance, self.length, self.closing, self.gap = (
                control_kernel.front_view(nb.vehicle, nb.distance, truth.vehicles, snap.speed,
                                          snap.length, k, r, CURRENT)
            )  # fmt: skip
            return
        row = nb.front[k, CURRENT]
        self.exists = row >= 0
        self.distance = nb.front_dist[k, CURRENT]
        # from the ground-truth features: a vehicle across the path is measured in its frame
        feats = truth.vehicles[k, CURRENT, 0]
        self.length = np.where(self.exists, feats[:, 3], 0.0)
        self.closing = np.where(self.exists, -feats[:, 1], snap.speed[r])
        self.gap = bumper_gap(self.distance, snap.length[r], self.length)

    def take(self, k: np.ndarray, then: FrontView | None = None) -> FrontView:
        """The view of the agents at rows ``k`` of this one (with ``then``: of this one's rows
        and then's, stacked)."""
        out = object.__new__(FrontView)
        for name in ("exists", "distance", "length", "closing", "gap"):
            mine = getattr(self, name)
            rows = mine if then is None else np.concatenate([mine, getattr(then, name)])
            setattr(out, name, rows[k])
        return out


@dataclass(frozen=True)
class StepViews:
    """The ground truth a step's reward, metric and memory stages read, found once for the
    agents of a ``PerceptionFrame`` (its rows, in order)."""

    front: FrontView
    """The front vehicle in each agent's lane."""
    rear_ids: list[str]
    """C, the conventional vehicle behind each agent ('' if none or an AV)."""
    rear_speed: np.ndarray
    """(A,) C's speed [m/s], nan without C."""

    @classmethod
    def of(cls, snap: TrafficSnapshot, truth: PerceptionFrame, r: np.ndarray) -> StepViews:
        """The views of the agents at truth rows 0..A-1 and snapshot rows ``r`` (A,)."""
        return cls(FrontView(snap, truth, np.arange(len(r)), r), *rear_conventional(snap, truth))

    def joined(self, then: StepViews, idx: np.ndarray) -> StepViews:
        """Rows ``idx`` of this step's views and ``then``'s stacked (this one's agents first):
        each agent's views are its own, so those of agents that entered later in the step
        join without a new search."""
        if (idx < 0).any():
            raise RuntimeError("an agent's ground truth is missing")  # would be a bug in _finish
        rear = [*self.rear_ids, *then.rear_ids]
        return StepViews(self.front.take(idx, then.front), [rear[i] for i in idx.tolist()],
                         np.concatenate([self.rear_speed, then.rear_speed])[idx])  # fmt: skip


def _kernel_dtypes(snap: TrafficSnapshot, truth: PerceptionFrame, k: np.ndarray,
                   r: np.ndarray) -> bool:  # fmt: skip
    """The arrays have the dtypes and layouts ``control_kernel.front_view`` is warmed for
    (the env's: C-contiguous int64 rows and float64 values), so it keeps one specialisation."""
    f, i, nb = np.float64, np.int64, truth.neighbours
    pairs = ((nb.vehicle, i), (nb.distance, f), (truth.vehicles, f), (snap.speed, f),
             (snap.length, f), (k, i), (r, i))  # fmt: skip
    return all(x.dtype == t and x.flags.c_contiguous for x, t in pairs)


def rear_conventional(
    snap: TrafficSnapshot, truth: PerceptionFrame
) -> tuple[list[str], np.ndarray]:
    """C, the conventional vehicle behind each agent in its lane ('' if none or an AV), and its speed."""
    rear = truth.neighbours.rear[:, CURRENT]
    ok = (rear >= 0) & ~snap.is_av[np.maximum(rear, 0)]
    ids = [""] * len(rear)
    for k in np.flatnonzero(ok).tolist():
        ids[k] = snap.ids[rear[k]]
    return ids, np.where(ok, snap.speed[np.maximum(rear, 0)], np.nan)


def speeds_of(snap: TrafficSnapshot, ids: list[str]) -> np.ndarray:
    """Speed of each vehicle id now, nan if it is not in the network (or '')."""
    k = np.fromiter(map(snap.index_of().get, ids, repeat(-1)), np.int64, len(ids))
    return np.where(k >= 0, snap.speed[np.maximum(k, 0)], np.nan) if len(k) else np.zeros(0)


class SpeedView(Mapping):
    """Vehicle id -> speed now [m/s], read from the snapshot on demand (no per-step dict)."""

    def __init__(self, snap: TrafficSnapshot) -> None:
        self._index, self._speed = snap.index_of(), snap.speed

    def __getitem__(self, vid: str) -> float:
        return float(self._speed[self._index[vid]])

    def __contains__(self, vid: object) -> bool:
        return vid in self._index

    def __iter__(self):
        return iter(self._index)

    def __len__(self) -> int:
        return len(self._index)


def take_or_nan(values: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """values[idx] with idx = -1 giving nan (also for an empty ``values``)."""
    out = np.full(len(idx), np.nan)
    ok = idx >= 0
    out[ok] = values[idx[ok]]
    return out
