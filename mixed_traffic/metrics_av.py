"""Per-AV and rear-vehicle metrics of DESIGN §9, accumulated by the env from ground truth.

C is the *conventional* vehicle directly behind an AV in its lane at that step. All inputs are
arrays over the live agents of one step; nothing loops over vehicles except the short list of
pending DEC-C events.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from mixed_traffic.schema import TERMINAL_REASONS

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


@dataclass
class AVMetrics:
    """Accumulates DT-A, AT-C, MinTTC-A, OFF-A, VEL-A, JERK-A, DEC-C, PT-RT, AvgR and events."""

    dt: float
    rear_speed_drop: float = 0.1
    _trips: dict[str, _Trip] = field(default_factory=lambda: defaultdict(_Trip))
    _ended: list[_Trip] = field(default_factory=list)
    _sums: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    _rear_seen: set[str] = field(default_factory=set)
    _dec_events: list[list] = field(default_factory=list)
    _dec_drops: list[float] = field(default_factory=list)
    events: dict[str, int] = field(default_factory=lambda: dict.fromkeys(TERMINAL_REASONS, 0))
    arrived: int = 0

    def step(self, s: AVStep, time: float, speeds: dict[str, float]) -> None:
        """Add one step. ``speeds`` maps every vehicle id in the network to its speed [m/s]."""
        n = len(s.ids)
        if n == 0:
            self._advance_dec(time, speeds)
            return
        dt = self.dt
        affected = np.nan_to_num(s.rear_prev_speed - s.rear_speed, nan=0.0) > self.rear_speed_drop
        for i, vid in enumerate(s.ids):
            trip = self._trips[vid]
            trip.time += dt
            trip.distance += float(s.speed[i]) * dt
            trip.min_ttc = min(trip.min_ttc, float(s.ttc[i]))
            trip.affected_time += dt * bool(affected[i])
        sums = self._sums
        sums["steps"] += n
        sums["speed"] += float(s.speed.sum())
        sums["jerk"] += float(np.abs(s.accel - s.prev_accel).sum()) / dt
        sums["risk_steps"] += float(((s.ttc > 0) & (s.ttc < TTC_RISK)).sum())
        sums["follow_steps"] += float(s.following.sum())
        sums["offset"] += float(np.abs(s.lateral[s.following]).sum())
        sums["reward"] += float(s.reward.sum())
        self._rear_seen.update(r for r in s.rear_ids if r)
        trigger = (s.accel < BRAKE_THRESHOLD) | s.lane_changed
        for i in np.flatnonzero(trigger):
            if s.rear_ids[i]:
                v0 = float(s.rear_speed[i])
                self._dec_events.append([s.rear_ids[i], time, v0, v0])
        self._advance_dec(time, speeds)

    def _advance_dec(self, time: float, speeds: dict[str, float]) -> None:
        keep = []
        for ev in self._dec_events:
            rid, t0, v0, vmin = ev
            if rid in speeds:
                ev[3] = min(vmin, speeds[rid])
            if time - t0 >= DEC_WINDOW - 1e-9 or rid not in speeds:
                self._dec_drops.append(max(0.0, v0 - ev[3]))
            else:
                keep.append(ev)
        self._dec_events = keep

    def end_trip(self, vid: str, reason: str) -> None:
        """An AV left: ``reason`` is 'arrived' or one of TERMINAL_REASONS."""
        if reason == "arrived":
            self.arrived += 1
        elif reason in self.events:
            self.events[reason] += 1
        trip = self._trips.pop(vid, None)
        if trip is not None:
            self._ended.append(trip)

    @property
    def rear_vehicles(self) -> set[str]:
        """Every conventional vehicle that was C at some step (for DI-C)."""
        return set(self._rear_seen)

    def summary(self) -> dict[str, float]:
        """Metric values keyed as in ``schema.METRICS`` (nan where nothing was observed)."""
        trips = [*self._ended, *self._trips.values()]
        driven = [t for t in trips if t.distance > 50.0]  # DT-A needs a meaningful distance
        s = self._sums
        steps = max(s["steps"], 1.0)
        ended = self.arrived + sum(self.events.values())
        out = {
            "avg_dt_a": _mean([t.time / (t.distance / 1000.0) for t in driven]),
            "avg_at_c": _mean([t.affected_time for t in trips]),
            "min_ttc_a": _mean([min(t.min_ttc, 1e3) for t in trips if np.isfinite(t.min_ttc)]),
            "avg_off_a": s["offset"] / s["follow_steps"] if s["follow_steps"] else float("nan"),
            "avg_vel_a": s["speed"] / steps if s["steps"] else float("nan"),
            "avg_jerk_a": s["jerk"] / steps if s["steps"] else float("nan"),
            "avg_dec_c": _mean(self._dec_drops),
            "pt_rt": 100.0 * s["risk_steps"] / steps if s["steps"] else float("nan"),
            "avg_r": s["reward"] / steps if s["steps"] else float("nan"),
            "av_trips": float(ended),
            "route_completion": 100.0 * self.arrived / ended if ended else float("nan"),
        }
        out.update({f"terminal_{k}": float(v) for k, v in self.events.items()})
        return out


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")
