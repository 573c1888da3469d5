"""Per-AV and rear-vehicle metrics of an episode (DESIGN §9). ``AVMetrics`` (fed by the env with ground truth each step) accumulates DT-A, AT-C, MinTTC-A,
OFF-A, VEL-A, JERK-A, DEC-C, PT-RT, AvgR and the terminal events; DI-C comes from
``FlowRecorder.delay_index`` of the vehicles that were C.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import repeat

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.env import metrics_kernel
from mixed_traffic.schema import TERMINAL_REASONS

# --------------------------------------------------------------------------- per-AV metrics
# DESIGN §9 for AVs and their rear vehicle C (the *conventional* vehicle directly behind an AV
# in its lane at that step), accumulated by the env from ground truth; inputs are arrays over
# the live agents of one step.

TTC_RISK = 4.0  # PT-RT threshold [s] (paper §V, after xia2022rise)
DEC_WINDOW = 1.0  # DEC-C looks at C's speed for this long after the AV's action [s]
BRAKE_THRESHOLD = -0.5  # AV acceleration counted as braking for DEC-C [m/s^2]


@dataclass
class _Trip:
    time: float = 0.0
    distance: float = 0.0
    min_ttc: float = np.inf
    affected_time: float = 0.0


@dataclass
class AVStep:
    """Ground truth of the live agents after one step; arrays are (A,)."""

    ids: list[str]
    speed: np.ndarray
    """[m/s]"""
    accel: np.ndarray
    """[m/s^2]"""
    prev_accel: np.ndarray
    """acceleration at the previous step [m/s^2]"""
    lateral: np.ndarray
    """offset from the lane centreline [m]"""
    following: np.ndarray
    """bool: the executed decision was lane following"""
    lane_changed: np.ndarray
    """bool: the AV completed a lane change in this step"""
    ttc: np.ndarray
    """TTC to the front vehicle [s], inf when not closing"""
    rear_ids: list[str]
    """id of C, '' when the vehicle behind is absent or an AV"""
    rear_speed: np.ndarray
    """C's speed now [m/s]"""
    rear_prev_speed: np.ndarray
    """the same C's speed at the previous step [m/s], nan if C changed"""
    reward: np.ndarray
    """reward of the step"""
    copy: np.ndarray | None = None
    """int copy of the scenario each AV drives in (None: one copy)"""


SUMS = ("steps", "speed", "jerk", "risk_steps", "follow_steps", "offset", "reward")
"""The per-step sums of ``AVMetrics``, per copy."""


@dataclass
class AVMetrics:
    """Accumulates DT-A, AT-C, MinTTC-A, OFF-A, VEL-A, JERK-A, DEC-C, PT-RT, AvgR and events,
    per copy of the scenario (``copies``; ``copy_of``: the copy of a vehicle id)."""

    dt: float
    rear_speed_drop: float = 0.1
    copies: int = 1
    copy_of: Callable[[str], int] = lambda vid: 0
    _trips: _LiveTrips = field(default_factory=lambda: _LiveTrips())
    _ended: list[tuple[str, _Trip]] = field(default_factory=list)
    _sums: dict[str, np.ndarray] = field(default_factory=dict)
    _rear_seen: set[str] = field(default_factory=set)
    _dec_events: list[list] = field(default_factory=list)
    _dec_drops: list[tuple[int, float]] = field(default_factory=list)
    events: dict[str, np.ndarray] = field(default_factory=dict)
    arrived: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __post_init__(self) -> None:
        self._sums = {k: np.zeros(self.copies) for k in SUMS}
        self.events = {k: np.zeros(self.copies, np.int64) for k in TERMINAL_REASONS}
        self.arrived = np.zeros(self.copies, np.int64)

    def step(self, s: AVStep, time: float, speeds: dict[str, float]) -> None:
        """Add one step. ``speeds`` maps every vehicle id in the network to its speed [m/s]."""
        n = len(s.ids)
        if n == 0:
            self._advance_dec(time, speeds)
            return
        dt = self.dt
        affected = np.nan_to_num(s.rear_prev_speed - s.rear_speed, nan=0.0) > self.rear_speed_drop
        self._trips.add(s.ids, dt, np.asarray(s.speed, np.float64), np.asarray(s.ttc, np.float64),
                        affected)  # fmt: skip
        sums, c = self._sums, s.copy
        sums["steps"] += self._by_copy(np.ones(n), c)
        sums["speed"] += self._by_copy(s.speed, c)
        sums["jerk"] += self._by_copy(np.abs(s.accel - s.prev_accel), c) / dt
        sums["risk_steps"] += self._by_copy((s.ttc > 0) & (s.ttc < TTC_RISK), c)
        sums["follow_steps"] += self._by_copy(s.following, c)
        sums["offset"] += self._by_copy(np.where(s.following, np.abs(s.lateral), 0.0), c,
                                        s.following)  # fmt: skip
        sums["reward"] += self._by_copy(s.reward, c)
        self._rear_seen.update(r for r in s.rear_ids if r)
        trigger = (s.accel < BRAKE_THRESHOLD) | s.lane_changed
        for i in np.flatnonzero(trigger):
            if s.rear_ids[i]:
                v0 = float(s.rear_speed[i])
                self._dec_events.append([s.rear_ids[i], time, v0, v0])
        self._advance_dec(time, speeds)

    def _by_copy(self, x: np.ndarray, copy: np.ndarray | None,
                 among: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        """(C,) Σ ``x`` (over the rows ``among`` marks) by copy; one copy: numpy's sum of
        those rows, as without copies."""
        x = np.asarray(x, np.float64)
        if self.copies == 1:
            return np.array([(x if among is None else x[among]).sum()])
        return np.bincount(copy, x, minlength=self.copies)

    def _advance_dec(self, time: float, speeds: dict[str, float]) -> None:
        keep = []
        for ev in self._dec_events:
            rid, t0, v0, vmin = ev
            if rid in speeds:
                ev[3] = min(vmin, speeds[rid])
            if time - t0 >= DEC_WINDOW - 1e-9 or rid not in speeds:
                self._dec_drops.append((self.copy_of(rid), max(0.0, v0 - ev[3])))
            else:
                keep.append(ev)
        self._dec_events = keep

    def end_trip(self, vid: str, reason: str) -> None:
        """An AV left: ``reason`` is 'arrived' or one of TERMINAL_REASONS."""
        c = self.copy_of(vid)
        if reason == "arrived":
            self.arrived[c] += 1
        elif reason in self.events:
            self.events[reason][c] += 1
        trip = self._trips.pop(vid)
        if trip is not None:
            self._ended.append((vid, trip))

    def rear_vehicles(self, copy: int = 0) -> set[str]:
        """Every conventional vehicle of copy ``copy`` that was C at some step (for DI-C)."""
        return {r for r in self._rear_seen if self.copy_of(r) == copy}

    def summary(self, copy: int = 0) -> dict[str, float]:
        """Copy ``copy``'s metric values keyed as in ``schema.METRICS`` (nan where nothing
        was observed)."""
        trips = [t for vid, t in (*self._ended, *self._trips.items()) if self.copy_of(vid) == copy]
        driven = [t for t in trips if t.distance > 50.0]  # DT-A needs a meaningful distance
        s = {k: float(v[copy]) for k, v in self._sums.items()}
        steps = max(s["steps"], 1.0)
        arrived = int(self.arrived[copy])
        ended = arrived + sum(int(v[copy]) for v in self.events.values())
        drops = [d for c, d in self._dec_drops if c == copy]
        out = {
            "avg_dt_a": _mean([t.time / (t.distance / 1000.0) for t in driven]),
            "avg_at_c": _mean([t.affected_time for t in trips]),
            "min_ttc_a": _mean([min(t.min_ttc, 1e3) for t in trips if np.isfinite(t.min_ttc)]),
            "avg_off_a": s["offset"] / s["follow_steps"] if s["follow_steps"] else float("nan"),
            "avg_vel_a": s["speed"] / steps if s["steps"] else float("nan"),
            "avg_jerk_a": s["jerk"] / steps if s["steps"] else float("nan"),
            "avg_dec_c": _mean(drops),
            "pt_rt": 100.0 * s["risk_steps"] / steps if s["steps"] else float("nan"),
            "avg_r": s["reward"] / steps if s["steps"] else float("nan"),
            "av_trips": float(ended),
            "route_completion": 100.0 * arrived / ended if ended else float("nan"),
        }
        out.update({f"terminal_{k}": float(v[copy]) for k, v in self.events.items()})
        return out


class _LiveTrips:
    """Running trips of the AVs in the network, as arrays indexed by a slot per AV.

    Same sums as one ``_Trip`` per AV updated in a loop (each slot adds the same float64 terms
    in the same order), without per-agent Python work each step. Slots are listed in the order
    the trips started, as the ``_Trip`` dict was.
    """

    def __init__(self) -> None:
        self._slot: dict[str, int] = {}  # vid -> slot, in trip start order
        self._free: list[int] = []
        self._time = np.zeros(0)
        self._distance = np.zeros(0)
        self._min_ttc = np.zeros(0)
        self._affected = np.zeros(0)

    def add(self, ids: list[str], dt: float, speed: np.ndarray, ttc: np.ndarray,
            affected: np.ndarray) -> None:  # fmt: skip
        """One step of the AVs ``ids`` (a trip starts at an AV's first step)."""
        idx = np.fromiter(map(self._slot.get, ids, repeat(-1)), np.int64, len(ids))
        for j in np.flatnonzero(idx < 0).tolist():
            idx[j] = self._open(ids[j])
        if compiled.enabled():
            metrics_kernel.trips_add(idx, dt, speed, ttc, affected, self._time, self._distance,
                                     self._min_ttc, self._affected)  # fmt: skip
            return
        self._time[idx] += dt
        self._distance[idx] += speed * dt
        self._min_ttc[idx] = np.fmin(self._min_ttc[idx], ttc)  # the ttc unless it is nan
        self._affected[idx] += np.where(affected, dt, 0.0)

    def _open(self, vid: str) -> int:
        if not self._free:
            n = len(self._time)
            grow = max(n, 16)
            self._time = np.concatenate([self._time, np.zeros(grow)])
            self._distance = np.concatenate([self._distance, np.zeros(grow)])
            self._min_ttc = np.concatenate([self._min_ttc, np.full(grow, np.inf)])
            self._affected = np.concatenate([self._affected, np.zeros(grow)])
            self._free = list(range(n + grow - 1, n - 1, -1))
        k = self._free.pop()
        self._slot[vid] = k
        return k

    def _trip(self, k: int) -> _Trip:
        return _Trip(float(self._time[k]), float(self._distance[k]), float(self._min_ttc[k]),
                     float(self._affected[k]))  # fmt: skip

    def pop(self, vid: str) -> _Trip | None:
        """The trip of ``vid``, closed (None if it has none)."""
        k = self._slot.pop(vid, None)
        if k is None:
            return None
        trip = self._trip(k)
        self._time[k] = self._distance[k] = self._affected[k] = 0.0
        self._min_ttc[k] = np.inf
        self._free.append(k)
        return trip

    def items(self) -> list[tuple[str, _Trip]]:
        """(AV id, its running trip), in the order the trips started."""
        return [(vid, self._trip(k)) for vid, k in self._slot.items()]


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")
