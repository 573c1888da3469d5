"""``speed_std_ahead`` and ``speed_std_behind``: the speed spread of the traffic ahead of and
behind each AV in its lane (a damping AV leaves a calmer wake: behind < ahead).

Definitions (positions are front bumpers, distances along the lane graph):

* **Its lane, ahead**: the AV's lane from its position on, then the lane's primary successors
  (``HDMap.lane_next``, junction lanes included) up to ``window`` metres ahead; **behind**: the
  lane back to its start, then one predecessor per lane (``LaneGraph.pred``, the straight-on
  link of a lane with the same index preferred) up to ``window`` metres behind. Other AVs count
  as traffic like anyone else; the AV itself does not.
* **Closed loops** (a ring): when a lane's successors lead back to it within ``2·window``, the
  window of that lane is at most half the loop, so ahead and behind are the two halves of the
  ring and no vehicle counts twice.
* **Samples**: at every step at or after warm-up, every AV whose front bumper is in the
  measurement segment contributes the speeds of all vehicles in its two windows (vehicles may
  be outside the segment). Per AV (by id), all its samples over the episode are pooled and
  their standard deviation taken; the metric is the mean of these per-AV deviations weighted
  by each AV's sample count [m/s], None without samples.
* An AV whose window is empty at a step adds nothing; the all-human reference (``idm``) gets
  the values around the vehicles that carry AV ids, which SUMO drives as humans.

``AheadBehind`` keeps, per AV, the count, sum and sum of squares of the speeds in each window;
a step costs one sort of the vehicles and one batch of searches over (AVs × reachable lanes).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from itertools import repeat

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.env import metrics_kernel
from mixed_traffic.sensing.lane_graph import lane_graph
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Lanes followed at most from one lane (junction lanes are short: many can fit in a window).
MAX_REACH = 64


class LaneReach:
    """The lanes within ``window`` of each lane row along the lane graph, one direction.

    Attributes:
        lane: (L, D) int64 lane rows, column 0 the lane itself, -1 padded.
        offset: (L, D) start of each of those lanes relative to the start of the row's lane [m]
            (>= 0 ahead, <= 0 behind).
        window: (L,) the window of the row [m]: ``window``, at most half a closed loop.
    """

    def __init__(self, hd: HDMap, window: float, ahead: bool) -> None:
        step = hd.lane_next.astype(np.int64) if ahead else lane_graph(hd).pred.astype(np.int64)
        length = hd.lane_length.astype(np.float64)
        n = hd.n_lanes
        start = np.arange(n, dtype=np.int64)
        lanes, offsets = [start], [np.zeros(n)]
        loop = np.full(n, np.inf)
        cur, off = start, np.zeros(n)
        live = np.ones(n, dtype=bool)
        for _ in range(MAX_REACH):
            nxt = np.where(live, step[cur], -1)
            # start of the next lane relative to the row's start; within reach: its start
            # from the row's end (ahead), or its end (the current lane's start) from the
            # row's start (behind), as an AV may stand anywhere on the row's lane
            if ahead:
                nxt_off = off + length[cur]
                near = nxt_off - length[start]
            else:
                nxt_off, near = off - length[np.maximum(nxt, 0)], -off
            # looking 2·window far finds the loops that would make the two windows overlap
            live = (nxt >= 0) & (near <= 2 * window)
            closed = live & (nxt == start)  # back at the row's own lane: a loop
            seen = (np.stack(lanes, axis=1) == nxt[:, None]).any(axis=1)
            live &= ~seen | closed  # another cycle (a lane met twice): stop before it
            loop[closed] = np.abs(nxt_off[closed])
            if not live.any():
                break
            lanes.append(np.where(live, nxt, -1))
            offsets.append(np.where(live, nxt_off, 0.0))
            live &= ~closed  # the row's lane once more, one lap on, then stop
            cur, off = np.where(live, nxt, 0), np.where(live, nxt_off, 0.0)
        self.lane = np.stack(lanes, axis=1)
        self.offset = np.stack(offsets, axis=1)
        self.window = np.minimum(window, loop / 2)


class AheadBehind:
    """Accumulates ``speed_std_ahead`` / ``speed_std_behind`` over an episode.

    Args:
        hdmap: the network.
        window: reach ahead of and behind each AV along its lane [m] (> 0).
    """

    def __init__(self, hdmap: HDMap, window: float) -> None:
        if not window > 0:
            raise ValueError(f"AheadBehind: window={window} must be > 0 m")
        # built once per map and window (a large city network takes a few tenths of a second)
        cache = hdmap.__dict__.setdefault("_ahead_behind", {})
        if window not in cache:
            cache[window] = (LaneReach(hdmap, window, True), LaneReach(hdmap, window, False))
        ahead, behind = cache[window]
        # both sides as one (L, Da + Db) table, so a step is one batch of searches
        self._lane = np.concatenate([ahead.lane, behind.lane], axis=1)
        self._offset = np.concatenate([ahead.offset, behind.offset], axis=1)
        d_ahead = ahead.lane.shape[1]
        self._is_ahead = np.arange(self._lane.shape[1]) < d_ahead
        # lanes reached from each row, per side (a row's columns are a prefix of its side)
        self._reach = np.stack([(ahead.lane >= 0).sum(1), (behind.lane >= 0).sum(1)], axis=1)
        self._d_ahead = d_ahead
        # one window per lane for both sides, so on a loop they never overlap
        self.window = np.minimum(ahead.window, behind.window)
        """(L,) the window of each lane row [m]."""
        self._length = np.append(hdmap.lane_length.astype(np.float64), 0.0)
        # (lane, position) sort key: lanes one band apart, positions within a band
        self._band = float(np.ceil(hdmap.lane_length.max()) + 10.0)
        self._slot: dict[str, int] = {}
        self._sums = np.zeros((0, 2, 3))  # (AV slot, ahead/behind, n / Σv / Σv²)

    def update(self, snap: TrafficSnapshot, counted: np.ndarray) -> None:
        """Add one step: ``counted`` (N,) bool marks the AVs whose windows are sampled."""
        avs = np.flatnonzero(counted & snap.is_av & (snap.lane >= 0))
        if len(avs) == 0:
            return
        slots = self._slots([snap.ids[i] for i in avs.tolist()])
        if compiled.enabled():
            metrics_kernel.ahead_behind_step(
                snap.lane, snap.lane_pos, snap.speed, avs, slots, self._band, self._reach,
                self._d_ahead, self._lane, self._offset, self.window, self._length, self._sums,
            )  # fmt: skip
        else:
            self._update_reference(snap, avs, slots)

    def _update_reference(self, snap: TrafficSnapshot, avs: np.ndarray, slots: np.ndarray) -> None:
        """Adds the window sums of the AVs at rows ``avs`` (A,) into their accumulator
        ``slots`` (A,): the numpy reference of ``metrics_kernel.ahead_behind_step``."""
        on = np.flatnonzero(snap.lane >= 0)
        key = snap.lane[on] * self._band + snap.lane_pos[on]
        order = np.argsort(key, kind="stable")
        key = key[order]
        v = snap.speed[on][order]
        cum = np.stack([np.arange(len(v) + 1.0), _cumsum0(v), _cumsum0(v * v)])  # (3, M+1)
        lane = snap.lane[avs]
        # only the columns some AV's lane reaches (a few on most roads, many in a city)
        ka, kb = self._reach[lane].max(axis=0)
        cols = np.r_[0:ka, self._d_ahead : self._d_ahead + kb]
        lo, hi = self._ranges(lane, snap.lane_pos[avs], key, cols)
        side = np.stack([self._is_ahead[cols], ~self._is_ahead[cols]], axis=1).astype(np.float64)
        got = (cum[:, hi] - cum[:, lo]) @ side  # (3, A, 2): ahead, behind
        np.add.at(self._sums, slots, got.transpose(1, 2, 0))

    def _ranges(self, lane: np.ndarray, pos: np.ndarray, key: np.ndarray,
                cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """(A, C) index ranges into the sorted vehicles of each AV's windows on the lanes of
        columns ``cols`` of the reach table."""
        lanes = self._lane[lane][:, cols]  # (A, C)
        rel = pos[:, None] - self._offset[lane][:, cols]  # the AV's position in each lane's frame
        w = self.window[lane][:, None]
        ahead = self._is_ahead[cols]
        # ahead (rel, rel + w], behind [rel - w, rel): the AV itself (at rel) is left out
        a = np.where(ahead, rel, rel - w)
        b = np.where(ahead, rel + w, rel)
        # clipped to the lane's band so a range never spills onto the next lane
        top = self._length[lanes] + 1.0
        base = np.maximum(lanes, 0) * self._band
        a = base + np.clip(a, -1.0, top)
        b = base + np.clip(b, -1.0, top)
        # searches keep keys in (a, b]; behind's [a, b) is (a⁻, b⁻] with x⁻ the float below x
        a = np.where(ahead, a, np.nextafter(a, -np.inf))
        b = np.where(ahead, b, np.nextafter(b, -np.inf))
        lo = np.searchsorted(key, a, side="right")
        hi = np.searchsorted(key, b, side="right")
        return lo, np.where(lanes >= 0, np.maximum(hi, lo), lo)

    def _slots(self, ids: Sequence[str]) -> np.ndarray:
        """(A,) accumulator slot of each AV id, allocating new ones."""
        out = np.fromiter(map(self._slot.get, ids, repeat(-1)), np.int64, len(ids))
        for j in np.flatnonzero(out < 0).tolist():
            out[j] = self._slot.setdefault(ids[j], len(self._slot))
        if len(self._slot) > len(self._sums):
            grown = np.zeros((max(2 * len(self._sums), len(self._slot), 16), 2, 3))
            grown[: len(self._sums)] = self._sums
            self._sums = grown
        return out

    def summary(self, keep: Callable[[str], bool] | None = None) -> dict[str, float | None]:
        """``speed_std_ahead`` and ``speed_std_behind`` [m/s] (None without samples), over the
        AVs whose id ``keep`` accepts (default: all)."""
        s = self._sums[: len(self._slot)]
        if keep is not None:
            s = s[[k for vid, k in self._slot.items() if keep(vid)]]
        return {
            "speed_std_ahead": pooled_std_mean(s[:, 0, 0], s[:, 0, 1], s[:, 0, 2]),
            "speed_std_behind": pooled_std_mean(s[:, 1, 0], s[:, 1, 1], s[:, 1, 2]),
        }


def pooled_std_mean(n: np.ndarray, s1: np.ndarray, s2: np.ndarray) -> float | None:
    """Mean over groups of each group's standard deviation, weighted by its sample count.

    Args:
        n, s1, s2: (G,) sample count, sum and sum of squares of each group.
    Returns:
        the weighted mean [unit of the samples], None when no group has a sample.
    """
    ok = n > 0
    if not ok.any():
        return None
    n, mean = n[ok], s1[ok] / n[ok]
    std = np.sqrt(np.maximum(s2[ok] / n - mean * mean, 0.0))
    return float((n * std).sum() / n.sum())


def _cumsum0(x: np.ndarray) -> np.ndarray:
    """Cumulative sum with a leading 0 (range sums as differences)."""
    return np.concatenate([[0.0], np.cumsum(x)])
