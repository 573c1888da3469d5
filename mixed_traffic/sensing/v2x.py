"""The downstream (V2X) feed: the traffic's mean speed in segments ahead on each AV's route.

``EnvConfig.v2x`` adds the observation key ``downstream`` (S, 2) float32, S segments between
the distances ``V2XConfig.segments`` ahead of the AV's front bumper along its route
(0-100, 100-300, 300-1000 m by default), per segment:

==== ===========================================================================================
col  feature / normalisation (clipped to [0, 1])
==== ===========================================================================================
0    mean speed of the vehicles in the segment, over all lanes of the route's edges (the AV
     itself left out) + the feed's noise, / 40 m/s; where no vehicle reported, the free-flow
     speed: the speed limit averaged over the segment's length (beyond the route's end, the
     AV's lane's limit)
1    density: vehicles reported / ``probe_share`` / lane-metres of the segment, / the jam
     density (1000/7 veh/km per lane); 0 = no vehicle reported (col 0 is then free flow)
==== ===========================================================================================

All zeros: no report has arrived yet (an AV that entered less than ``update_period +
latency`` ago). Timing: the feed measures once in every period [k·P, (k+1)·P) of P =
``update_period`` seconds, at the period's first step with an AV on the road, for the AVs on
the road then (and those entering in that step), from the ground-truth snapshot; a measurement
reaches its AV ``latency`` seconds later (the first step at or after that time) and is held
until the next one arrives. The AV's own position moves on meanwhile:
the segments are those of the moment of measurement. Noise: a Gaussian error of
``speed_noise`` m/s on each segment's mean speed; below ``probe_share`` 1 each vehicle's
report reaches a measurement with that chance. Both are drawn from the feed's generator,
seeded from the episode seed apart from the sensors' (switching the feed on changes no other
observation). On a ring the segments wrap around: a vehicle ``d`` ahead counts in every
segment holding ``d + k·lap`` (k = 0, 1, ...), so a segment longer than the ring averages it
weighted by how often each position recurs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mixed_traffic.config import JAM_DENSITY_PER_LANE, EnvConfig
from mixed_traffic.sensing.observation import SPEED_SCALE
from mixed_traffic.sensing.route_traffic import (
    Pairs,
    RouteFrame,
    lane_metres,
    ring_pairs,
    route_frame,
    route_pairs,
)
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot

#: Features per segment: mean speed, density.
FEATURES = 2
#: Tolerance of the feed's clock against SUMO's step times [s].
TIME_EPS = 1e-6


@dataclass
class _Report:
    """A measurement on its way: arrives at ``time`` [s] for the agents ``slots``."""

    time: float
    slots: np.ndarray
    epochs: np.ndarray
    values: np.ndarray = field(repr=False)


class DownstreamFeed:
    """The ``downstream`` observation of every agent, with the feed's timing and noise.

    Args:
        config: the env config: ``v2x`` (the feed is on) and ``v2x_feed`` (segments, update
            period, latency, noise).
        n_agents: number of possible agents (slots).
        ring: the scenario is a ring (segments wrap around).
    """

    def __init__(self, config: EnvConfig, n_agents: int, ring: bool) -> None:
        self.on, self.cfg, self.ring = config.v2x, config.v2x_feed, ring
        seg = np.asarray(self.cfg.segments, np.float64)
        self.lo, self.hi = seg[:-1], seg[1:]
        self.shape = (len(seg) - 1, FEATURES)
        self._value = np.zeros((n_agents, *self.shape), np.float32)
        self._epoch = np.zeros(n_agents, np.int64)
        self.reset(np.random.default_rng(0))

    def reset(self, rng: np.random.Generator) -> None:
        """A new episode: nothing measured, nothing on its way; ``rng`` draws the noise."""
        self.rng = rng
        self._value[:] = 0.0
        self._epoch += 1
        self._queue: list[_Report] = []
        self._tick = -1  # index of the last measurement (time // update_period)
        self._measured_at = -np.inf

    def drop(self, slots: np.ndarray) -> None:
        """Forget what ``slots`` received, and reports still on their way to them."""
        slots = np.asarray(slots, np.int64)
        self._value[slots] = 0.0
        self._epoch[slots] += 1

    def keys(self, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray, slots: np.ndarray,
             route_table: np.ndarray, route_len: np.ndarray) -> dict[str, np.ndarray]:  # fmt: skip
        """``{"downstream": (A, S, 2)}`` of the agents at snapshot ``rows`` (A,) and slots
        ``slots`` (A,) (routes by slot: ``route_table`` (n, W), ``route_len`` (n,)); ``{}``
        when the feed is off."""
        if not self.on:
            return {}
        down = self.observe(hd, snap, rows, slots, route_table[slots], route_len[slots])
        return {"downstream": down}

    def observe(self, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray, slots: np.ndarray,
                routes: np.ndarray, route_len: np.ndarray) -> np.ndarray:  # fmt: skip
        """(A, S, 2) float32 ``downstream`` of the agents at snapshot ``rows`` (A,), agent
        slots ``slots`` (A,), routes ``routes`` (A, W) edge rows of ``route_len`` (A,) edges;
        measures them first when a measurement is due at ``snap.time`` (a second call at the
        same time measures its agents too: those that entered in that step)."""
        t = snap.time
        tick = int(np.floor((t + TIME_EPS) / self.cfg.update_period))
        if len(rows) and (tick > self._tick or abs(t - self._measured_at) < TIME_EPS):
            values = self.measure(hd, snap, np.asarray(rows, np.int64), routes, route_len)
            slots = np.asarray(slots, np.int64)
            self._queue.append(_Report(t + self.cfg.latency, slots, self._epoch[slots], values))
            self._tick, self._measured_at = tick, t
        self._deliver(t)
        return self._value[slots].copy()

    def _deliver(self, t: float) -> None:
        """Reports due by ``t`` reach their agents (in measurement order)."""
        due = [r for r in self._queue if r.time <= t + TIME_EPS]
        self._queue = [r for r in self._queue if r.time > t + TIME_EPS]
        for r in due:
            live = self._epoch[r.slots] == r.epochs  # not dropped since
            self._value[r.slots[live]] = r.values[live]

    def measure(self, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray, routes: np.ndarray,
                route_len: np.ndarray) -> np.ndarray:  # fmt: skip
        """(A, S, 2) float32 the feed's values for the agents at ``rows`` now (noise drawn)."""
        A, S = len(rows), self.shape[0]
        cfg = self.cfg
        frame = route_frame(hd, snap, rows, routes, route_len)
        pairs = (
            ring_pairs(hd, snap, frame)
            if self.ring
            else route_pairs(hd, snap, frame, 0.0, self.hi[-1])
        )
        keep = pairs.vehicle != rows[pairs.agent]  # the AV itself is no traffic ahead
        if cfg.probe_share < 1.0:
            keep &= (self.rng.random(snap.n) < cfg.probe_share)[pairs.vehicle]
        a, v, d = pairs.agent[keep], pairs.vehicle[keep], pairs.distance[keep]
        weight = self._weights(d, pairs.lap[a])  # (P, S) occurrences in each segment
        count = np.zeros((A, S))
        speed = np.zeros((A, S))
        for s in range(S):
            count[:, s] = np.bincount(a, weight[:, s], minlength=A)
            speed[:, s] = np.bincount(a, weight[:, s] * snap.speed[v], minlength=A)
        metres, limit = self._road(hd, snap, rows, frame, pairs)
        noise = self.rng.normal(0.0, cfg.speed_noise, (A, S)) if cfg.speed_noise > 0 else 0.0
        seen = count > 0
        mean = np.where(seen, speed / np.maximum(count, 1e-9) + noise, limit)
        density = np.where(metres > 0, count / cfg.probe_share / np.maximum(metres, 1e-9), 0.0)
        out = np.empty((A, S, FEATURES), np.float32)
        out[..., 0] = np.clip(np.maximum(mean, 0.0) / SPEED_SCALE, 0.0, 1.0)
        out[..., 1] = np.clip(density * 1000.0 / JAM_DENSITY_PER_LANE, 0.0, 1.0)
        return out

    def _weights(self, d: np.ndarray, lap: np.ndarray) -> np.ndarray:
        """(P, S) how often each vehicle ``d`` (P,) [m] ahead counts in each segment: once
        where it lies in it; on a ring (``lap`` (P,) [m]) once per k >= 0 with d + k·lap in it."""
        lo, hi = self.lo[None, :], self.hi[None, :]
        dd = d[:, None]
        if not self.ring:
            return ((dd >= lo) & (dd < hi)).astype(np.float64)
        L = lap[:, None]
        n = np.ceil((hi - dd) / L) - np.ceil(np.maximum(lo - dd, 0.0) / L)
        return np.maximum(n, 0.0)

    def _road(self, hd: HDMap, snap: TrafficSnapshot, rows: np.ndarray, frame: RouteFrame,
              pairs: Pairs) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """(A, S) lane-metres of each segment and (A, S) its free-flow speed [m/s]."""
        if self.ring:  # one lap of the route, scaled: the route may hold fewer laps than a segment
            lap = np.where(np.isfinite(pairs.lap), pairs.lap, 0.0)[:, None]
            per_lap, limit = lane_metres(hd, frame, np.zeros_like(lap), lap)
            metres = per_lap * (self.hi - self.lo)[None, :] / np.maximum(lap, 1e-9)
            limit = np.broadcast_to(limit, metres.shape)
        else:
            metres, limit = lane_metres(hd, frame, self.lo, self.hi)
        lane = snap.lane[rows].astype(np.int64)
        own = np.where(lane >= 0, hd.lane_speed[np.maximum(lane, 0)], 0.0)[:, None]
        return metres, np.where(np.isfinite(limit), limit, own)
