"""Flow metrics of an episode (DESIGN §9) from snapshots: ``FlowRecorder`` (DT-TF, delay
index, density, mean speed, safety counts); the per-AV metrics are in ``av_metrics``.

``FlowRecorder`` is fed one ``TrafficSnapshot`` per step and keeps per-vehicle state in flat
numpy arrays (one slot per vehicle id ever seen), so a step costs a few vectorised operations
over the N vehicles in the network, not a Python loop.

Definitions (all positions are the front bumper, as in the snapshot):

* **Travel time** of a vehicle: the time from crossing the start of the measurement segment to
  crossing its end. It is recorded only for vehicles that *entered at the segment's start*
  (they were seen outside it before, then on its first edge) and *left at its end* (last seen
  on its last edge, then seen elsewhere or arrived). Vehicles that were already inside at
  their first observation, or that left it sideways (ramps), get no travel time. Entry and
  exit instants are interpolated within the step from position and speed (exact at constant
  speed), never earlier/later than the neighbouring observation.
* **DT-TF**: mean travel time over all vehicles that crossed the whole segment during the
  episode (AVs and conventional alike) [s]. Warm-up does not filter crossings.
* **Free-flow travel time**: the time the same distance takes at the *lane speed limit* of the
  lanes the vehicle actually used (``∫ ds / v_limit(lane)``, accumulated as
  ``Σ v·dt / v_limit``). The speed limit, not the vehicle's desired speed (limit × its
  speed factor), is the reference: the snapshot does not carry speed factors, and the legal
  speed is the usual reference of a delay index. A vehicle with a speed factor > 1 driving
  freely therefore has a delay index slightly below 1 (≈ 0.95 at factor 1.05).
* **Delay index**: actual / free-flow time. For a vehicle that crossed the segment it is the
  travel time over the segment's free-flow time; for one that was only partly in it, the time
  it spent inside over the free-flow time of the distance it drove inside. ``trip_delay_index``
  gives the same ratio over the vehicle's whole time in the network.
* **Measured density**: vehicles inside the segment / segment length, summed over lanes
  [veh/km], averaged over the steps at or after ``warmup``.
* **Mean speed**: mean over all (vehicle, step) samples inside the segment after warm-up,
  i.e. total distance / total time, the space-mean speed [m/s].
* **Speed spread, flow, waves** (``space_time``): the standard deviation of all (vehicle,
  step) speed samples inside the segment after warm-up [m/s]; Edie's flow per lane
  [veh/h/lane]; the propagation speed of speed disturbances [km/h], NaN without waves.
* **Fuel**: the fuel SUMO's emission model gives every vehicle (its vType's emission class;
  SUMO's default, HBEFA4/PC_petrol_Euro-4, for the bundled types) summed over the (vehicle,
  step) samples inside the segment after warm-up, over the distance they drove there
  [l/100 km]; SUMO converts mass to volume at the fuel's density (742 g/l petrol, 836 g/l
  diesel); electric vehicles count 0.
* **Speed spread ahead of / behind the AVs** (``ahead_behind``): for the AVs inside the
  segment after warm-up, the standard deviation of the speeds within ``av_window`` metres
  ahead of and behind each AV in its lane [m/s].
* **Collisions / teleports**: events reported by SUMO over the whole episode (counts).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.env import metrics_kernel
from mixed_traffic.env.ahead_behind import AheadBehind

# per-vehicle crossing states (int8) and the speed below which entry/exit interpolation uses
# the observation time itself [m/s]: the kernels' (one definition for both paths)
from mixed_traffic.env.metrics_kernel import CROSSED, INSIDE, INSIDE_UNKNOWN, LEFT, UNSEEN, UPSTREAM
from mixed_traffic.env.metrics_kernel import V_MIN as _V_MIN
from mixed_traffic.env.space_time import SpaceTimeField
from mixed_traffic.world.hdmap import HDMap
from mixed_traffic.world.snapshot import TrafficSnapshot


# --------------------------------------------------------------------------- pure functions
def entry_time(t: np.ndarray, s: np.ndarray, v: np.ndarray, t_prev: np.ndarray) -> np.ndarray:
    """(N,) instant [s] the front bumper crossed the segment start.

    Args:
        t: (N,) time of the first observation inside [s].
        s: (N,) distance past the segment start at ``t`` [m].
        v: (N,) speed at ``t`` [m/s].
        t_prev: (N,) time of the previous observation (outside) [s]; the result is not earlier.
    """
    back = np.where(v > _V_MIN, s / np.maximum(v, _V_MIN), 0.0)
    return np.maximum(t - back, t_prev)


def exit_time(
    t_last: np.ndarray, s_last: np.ndarray, v_last: np.ndarray, length: float, t_next: np.ndarray
) -> np.ndarray:
    """(N,) instant [s] the front bumper crossed the segment end.

    Args:
        t_last: (N,) time of the last observation inside [s].
        s_last: (N,) distance past the segment start at ``t_last`` [m].
        v_last: (N,) speed at ``t_last`` [m/s].
        length: segment length [m].
        t_next: (N,) time of the first observation outside [s]; the result is not later.
    """
    ahead = np.maximum(length - s_last, 0.0)
    fwd = np.where(v_last > _V_MIN, ahead / np.maximum(v_last, _V_MIN), t_next - t_last)
    return np.minimum(t_last + fwd, t_next)


def density_per_km(count: int | np.ndarray, length_m: float) -> float | np.ndarray:
    """Vehicles per km (summed over lanes) of ``count`` vehicles on ``length_m`` metres of road."""
    return count / (length_m / 1000.0)


def delay_index(actual: np.ndarray, free_flow: np.ndarray) -> np.ndarray:
    """(N,) actual / free-flow time; NaN where the free-flow time is not positive."""
    actual = np.asarray(actual, dtype=np.float64)
    free_flow = np.asarray(free_flow, dtype=np.float64)
    out = np.full(actual.shape, np.nan)
    ok = free_flow > 0
    out[ok] = actual[ok] / free_flow[ok]
    return out


def _mean_or_none(values: np.ndarray) -> float | None:
    values = values[np.isfinite(values)]
    return float(values.mean()) if len(values) else None


# --------------------------------------------------------------------------- recorder
class FlowRecorder:
    """Accumulates flow metrics over one episode from snapshots.

    Args:
        hdmap: the network (edge lengths, lane speed limits).
        measurement: consecutive edge ids of the measurement segment, upstream first; or one
            such segment per copy of the scenario (``EnvConfig.copies``), each measured apart.
        dt: step length [s].
        warmup: simulated time before which density and speed are not averaged [s].
        copy_of: the copy of a vehicle id (default: one copy).
    """

    def __init__(
        self, hdmap: HDMap, measurement: Sequence[str] | Sequence[Sequence[str]], dt: float,
        warmup: float = 0.0, trace_every: int = 0, av_window: float | None = None,
        copy_of: Callable[[str], int] | None = None,
    ) -> None:  # fmt: skip
        segments = [measurement] if isinstance(measurement[0], str) else list(measurement)
        if not all(segments):
            raise ValueError("FlowRecorder needs at least one measurement edge")
        if dt <= 0 or warmup < 0:
            raise ValueError(f"FlowRecorder: dt={dt} must be > 0 and warmup={warmup} >= 0")
        self.dt = float(dt)
        self.warmup = float(warmup)
        self.copies = len(segments)
        self.copy_of = copy_of or (lambda vid: 0)
        n_edges = len(hdmap.edge_ids)
        # lookup tables indexed by snapshot edge row; row -1 (junction) hits the extra last slot
        self._offset = np.full(n_edges + 1, np.nan)
        self._first = np.zeros(n_edges + 1, np.bool_)
        self._last = np.zeros(n_edges + 1, np.bool_)
        self._edge_copy = np.zeros(n_edges + 1, np.int64)
        lengths, lane_metres = [], []
        for c, segment in enumerate(segments):
            rows = [hdmap.edge_of(e) for e in segment]
            self._offset[rows] = np.concatenate([[0.0], np.cumsum(hdmap.edge_length[rows])[:-1]])
            self._first[rows[0]], self._last[rows[-1]], self._edge_copy[rows] = True, True, c
            lengths.append(float(hdmap.edge_length[rows].sum()))
            lane_metres.append(float((hdmap.edge_length[rows] * hdmap.edge_car_lanes[rows]).sum()))
        self.lengths = np.array(lengths)
        """(C,) each copy's segment length [m]."""
        self.length = lengths[0]
        """Segment length [m] (copy 0's)."""
        self.field = SpaceTimeField(self.lengths, np.array(lane_metres), self.dt, self.warmup,
                                    trace_every)  # fmt: skip
        """Edie's sums on a space-time grid over the segment (flow, speed spread, waves)."""
        # lane speed limit by snapshot lane row; row -1 (unknown) -> NaN
        self._lane_speed = np.append(hdmap.lane_speed.astype(np.float64), np.nan)
        self._slot: dict[str, int] = {}
        self._ids: list[str] = []
        self._cap = 0
        self._alloc(256)
        self._density_sum = np.zeros(self.copies)
        self._density_steps = 0
        self._speed_sum = np.zeros(self.copies)
        self._speed_samples = np.zeros(self.copies, np.int64)
        self._fuel_sum = np.zeros(self.copies)  # Σ fuel rate [ml/s] over the samples with fuel
        self._fuel_speed_sum = np.zeros(self.copies)  # Σ speed [m/s] over the same samples
        self.around = AheadBehind(hdmap, av_window) if av_window is not None else None
        """speed_std_ahead / speed_std_behind (None: not measured)."""
        self.collisions = np.zeros(self.copies, np.int64)
        self.teleports = np.zeros(self.copies, np.int64)
        self.steps = 0

    # ------------------------------------------------------------------ storage
    def _alloc(self, cap: int) -> None:
        def grow(name: str, dtype: type, fill: float) -> None:
            new = np.full(cap, fill, dtype=dtype)
            old = getattr(self, name, None)
            if old is not None:
                new[: len(old)] = old
            setattr(self, name, new)

        grow("_state", np.int8, UNSEEN)
        grow("_copy", np.int64, 0)
        grow("_t_entry", np.float64, np.nan)
        grow("_t_exit", np.float64, np.nan)
        grow("_t_last", np.float64, np.nan)
        grow("_s_last", np.float64, np.nan)
        grow("_v_last", np.float64, np.nan)
        grow("_on_last_edge", np.bool_, False)
        grow("_seg_time", np.float64, 0.0)
        grow("_seg_free", np.float64, 0.0)
        grow("_seg_dist", np.float64, 0.0)
        grow("_t_in", np.float64, np.nan)
        grow("_trip_time", np.float64, 0.0)
        grow("_trip_free", np.float64, 0.0)
        self._cap = cap

    def _slots(self, ids: Sequence[str]) -> np.ndarray:
        """(N,) slot of each id, allocating new ones."""
        get = self._slot.get
        out = np.fromiter((get(v, -1) for v in ids), np.int64, len(ids))
        new = np.flatnonzero(out < 0)
        if len(new):
            start = len(self._ids)
            if start + len(new) > self._cap:
                self._alloc(max(2 * self._cap, start + len(new)))
            for k, i in enumerate(new.tolist()):
                self._slot[ids[i]] = start + k
                self._ids.append(ids[i])
            out[new] = np.arange(start, start + len(new))
        return out

    # ------------------------------------------------------------------ update
    def update(self, snap: TrafficSnapshot) -> None:
        """Account for one step's snapshot (call once per step, after ``backend.step()``)."""
        t = snap.time
        self.steps += 1
        for c in (self.copy_of(col.collider) for col in snap.collisions):
            self.collisions[c] += 1
        for c in map(self.copy_of, snap.teleports):
            self.teleports[c] += 1
        self._finish_gone(snap)
        if snap.n == 0:
            if t >= self.warmup:
                self._density_steps += 1
            return
        slot = self._slots(snap.ids)
        step = self._step_compiled if compiled.enabled() else self._step_reference
        s, inside = step(snap, slot)
        v = snap.speed
        copy = self._edge_copy[snap.edge]  # a vehicle inside is on an edge of its copy
        self.field.add(t, s, v, copy)
        if t >= self.warmup:
            n_in = self._by_copy(inside, copy, np.ones_like(v)).astype(np.int64)
            self._density_sum += density_per_km(n_in, self.lengths)
            self._density_steps += 1
            v_sum = self._by_copy(inside, copy, v)
            self._speed_sum += v_sum
            self._speed_samples += n_in
            if snap.fuel is not None:
                self._fuel_sum += self._by_copy(inside, copy, snap.fuel)
                self._fuel_speed_sum += v_sum
            if self.around is not None:
                self.around.update(snap, inside)

    def _by_copy(self, inside: np.ndarray, copy: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(C,) Σ ``x`` over the vehicles ``inside`` their segment, by copy (one copy: numpy's
        pairwise sum, as ever)."""
        if self.copies == 1:
            return np.array([x[inside].sum()], np.float64)
        return np.bincount(copy[inside], x[inside], minlength=self.copies)

    def _step_reference(
        self, snap: TrafficSnapshot, slot: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The per-vehicle state of one step (crossings, time and free-flow sums) for the
        vehicles at ``slot`` (N,); returns (N,) the position along the segment [m] (NaN
        outside) and (N,) bool inside it. The numpy reference of ``_step_compiled``."""
        t, dt = snap.time, self.dt
        s = self._offset[snap.edge] + snap.lane_pos  # NaN outside the segment
        inside = ~np.isnan(s)
        self._copy[slot[inside]] = self._edge_copy[snap.edge[inside]]
        outside = ~inside & (snap.edge >= 0)
        v = snap.speed
        # free-flow time of the distance driven this step: v·dt / v_limit(lane)
        vlim = self._lane_speed[snap.lane]
        free = np.where(vlim > 0, v * dt / np.where(vlim > 0, vlim, 1.0), 0.0)
        self._trip_time[slot] += dt
        self._trip_free[slot] += free

        st = self._state[slot]
        # first sightings
        st = np.where((st == UNSEEN) & outside, UPSTREAM, st)
        st = np.where((st == UNSEEN) & inside, INSIDE_UNKNOWN, st)
        # entries from upstream
        on_first = self._first[snap.edge]
        enter = (st == UPSTREAM) & inside
        good = enter & on_first
        if good.any():
            g = slot[good]
            self._t_entry[g] = entry_time(
                np.full(len(g), t), s[good], v[good], np.nan_to_num(self._t_last[g], nan=-np.inf)
            )
        st = np.where(good, INSIDE, np.where(enter, INSIDE_UNKNOWN, st))
        # exits
        was_in = (st == INSIDE) | (st == INSIDE_UNKNOWN)
        leave = was_in & outside
        if leave.any():
            crossed = leave & (st == INSIDE) & self._on_last_edge[slot]
            c = slot[crossed]
            self._t_exit[c] = exit_time(self._t_in[c], self._s_last[c], self._v_last[c],
                                        self.lengths[self._copy[c]], np.full(len(c), t))  # fmt: skip
            st = np.where(crossed, CROSSED, np.where(leave, LEFT, st))
        # inside: accumulate and remember the last observation
        now_in = inside & ((st == INSIDE) | (st == INSIDE_UNKNOWN))
        i = slot[now_in]
        self._seg_time[i] += dt
        self._seg_free[i] += free[now_in]
        self._seg_dist[i] += v[now_in] * dt
        self._t_in[i] = t
        self._s_last[i] = s[now_in]
        self._v_last[i] = v[now_in]
        self._on_last_edge[i] = self._last[snap.edge[now_in]]
        self._t_last[slot] = t
        self._state[slot] = st

        return s, inside

    def _step_compiled(
        self, snap: TrafficSnapshot, slot: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``_step_reference`` as one compiled kernel (:func:`.metrics_kernel.flow_step`)."""
        return metrics_kernel.flow_step(
            slot, snap.edge, snap.lane, snap.lane_pos, snap.speed, snap.time, self.dt,
            self._offset, self._lane_speed, self._first, self._last, self._edge_copy,
            self.lengths, self._copy, self._state, self._t_entry, self._t_exit, self._t_last, self._s_last, self._v_last,
            self._on_last_edge, self._seg_time, self._seg_free, self._seg_dist, self._t_in,
            self._trip_time, self._trip_free,
        )  # fmt: skip

    def _finish_gone(self, snap: TrafficSnapshot) -> None:
        """Vehicles that left the network in the last step (arrived, or removed by a collision)."""
        if snap.arrived:
            slot = np.array([self._slot[v] for v in snap.arrived if v in self._slot], np.int64)
            if compiled.enabled():
                metrics_kernel.flow_gone(slot, snap.time, self.lengths, self._copy, self._state,
                                         self._t_exit, self._t_in, self._s_last, self._v_last,
                                         self._on_last_edge)  # fmt: skip
            else:
                self._gone_reference(slot, snap.time)
        for col in snap.collisions:
            for vid in (col.collider, col.victim):
                k = self._slot.get(vid)
                if k is not None and self._state[k] != CROSSED:
                    self._state[k] = LEFT

    def _gone_reference(self, slot: np.ndarray, t: float) -> None:
        """The vehicles at ``slot`` (G,) arrived at ``t`` [s]: the ones inside on the last edge
        crossed, the others inside left (numpy reference of ``metrics_kernel.flow_gone``)."""
        st = self._state[slot]
        crossed = (st == INSIDE) & self._on_last_edge[slot]
        c = slot[crossed]
        self._t_exit[c] = exit_time(self._t_in[c], self._s_last[c], self._v_last[c],
                                    self.lengths[self._copy[c]], np.full(len(c), t))  # fmt: skip
        self._state[c] = CROSSED
        rest = slot[~crossed & ((st == INSIDE) | (st == INSIDE_UNKNOWN))]
        self._state[rest] = LEFT

    # ------------------------------------------------------------------ per-vehicle results
    def _crossed_slots(self, copy: int | None = None) -> np.ndarray:
        n = len(self._ids)
        crossed = self._state[:n] == CROSSED
        return np.flatnonzero(crossed if copy is None else crossed & (self._copy[:n] == copy))

    def vehicle_travel_times(self, copy: int | None = None) -> dict[str, float]:
        """Vehicle id -> travel time across the whole segment [s], for vehicles that crossed it
        (``copy``: those of one copy)."""
        c = self._crossed_slots(copy)
        tt = self._t_exit[c] - self._t_entry[c]
        return {self._ids[k]: float(x) for k, x in zip(c.tolist(), tt.tolist())}

    def free_flow_times(self, ids: Iterable[str]) -> np.ndarray:
        """(len(ids),) free-flow time [s] of each vehicle's stretch in the segment.

        For a vehicle that crossed: segment length at the (distance-weighted) speed limit of the
        lanes it used; for one partly inside: the distance it drove inside at those limits;
        NaN for vehicles never seen inside.
        """
        return self._per_vehicle(ids)[1]

    def delay_index(self, ids: Iterable[str]) -> np.ndarray:
        """(len(ids),) delay index in the measurement segment (actual / free-flow), NaN if none."""
        actual, free = self._per_vehicle(ids)
        return delay_index(actual, free)

    def mean_delay_index(self, ids: Iterable[str]) -> float | None:
        """Mean delay index of the vehicles ``ids`` seen in the measurement segment (None: none
        was)."""
        di = self.delay_index(ids)
        di = di[np.isfinite(di)] if len(di) else di
        return float(np.mean(di)) if len(di) else None

    def trip_delay_index(self, ids: Iterable[str]) -> np.ndarray:
        """(len(ids),) delay index over each vehicle's whole observed time in the network."""
        k = self._known(ids)
        ok = k >= 0
        actual = np.full(len(k), np.nan)
        free = np.full(len(k), np.nan)
        actual[ok] = self._trip_time[k[ok]]
        free[ok] = self._trip_free[k[ok]]
        return delay_index(actual, free)

    def _known(self, ids: Iterable[str]) -> np.ndarray:
        return np.array([self._slot.get(v, -1) for v in ids], dtype=np.int64)

    def _per_vehicle(self, ids: Iterable[str]) -> tuple[np.ndarray, np.ndarray]:
        """(actual, free-flow) time in the segment [s] per id (see ``free_flow_times``)."""
        k = self._known(ids)
        actual = np.full(len(k), np.nan)
        free = np.full(len(k), np.nan)
        ok = k >= 0
        kk = k[ok]
        seen = self._seg_time[kk] > 0
        crossed = self._state[kk] == CROSSED
        a = np.where(crossed, self._t_exit[kk] - self._t_entry[kk], self._seg_time[kk])
        # distance driven inside ≈ Σ v·dt; scale the free-flow time of a crossing to the full length
        f = self._seg_free[kk]
        a = np.where(seen, a, np.nan)
        f = np.where(seen, f, np.nan)
        if crossed.any():
            # Σ v·dt over the samples misses part of a step at each end: scale the sampled
            # free-flow pace [s/m] to the full segment length
            dist = self._seg_dist[kk]
            pace = np.divide(f, dist, out=np.full(len(kk), np.nan), where=dist > 0)
            f = np.where(crossed, self.lengths[self._copy[kk]] * pace, f)
        actual[ok], free[ok] = a, f
        return actual, free

    # ------------------------------------------------------------------ summary
    def summary(self, copy: int = 0) -> dict[str, float | int | None]:
        """Flow metrics of copy ``copy`` keyed by ``schema.METRICS`` keys (None where nothing
        was measured)."""
        tt = np.array(list(self.vehicle_travel_times(copy).values()), dtype=np.float64)
        samples = int(self._speed_samples[copy])
        keep = None if self.copies == 1 else (lambda vid: self.copy_of(vid) == copy)
        return {
            "dt_tf": _mean_or_none(tt),
            "measured_density": (
                float(self._density_sum[copy]) / self._density_steps
                if self._density_steps
                else None
            ),
            "mean_speed": float(self._speed_sum[copy]) / samples if samples else None,
            "vehicles_crossed": len(tt),
            "speed_std": self.field.speed_std(copy),
            "fuel": self._fuel_per_100km(copy),
            **(self.around.summary(keep) if self.around is not None else {}),
            "flow": self.field.flow(copy),
            "wave_speed": self.field.wave_speed(copy),
            "collisions": int(self.collisions[copy]),
            "teleports": int(self.teleports[copy]),
        }

    def _fuel_per_100km(self, copy: int) -> float | None:
        """Σ fuel rate / Σ speed over the samples [ml/m], x 100 = l/100 km; None without any."""
        fuel, speed = float(self._fuel_sum[copy]), float(self._fuel_speed_sum[copy])
        return 100.0 * fuel / speed if speed > 0 else None

    def diagnostics(self, copy: int | None = None) -> dict[str, float | int | None]:
        """Extra flow figures not in the metric catalogue (delay indices, free-flow time), of
        one ``copy`` or, None, of every vehicle."""
        n = len(self._ids)
        ids = (
            self._ids
            if copy is None
            else [self._ids[k] for k in range(n) if self.copy_of(self._ids[k]) == copy]
        )
        di = self.delay_index(ids)
        crossed = [self._ids[k] for k in self._crossed_slots(copy).tolist()]
        return {
            "delay_index_mean": _mean_or_none(di),
            "delay_index_crossed_mean": _mean_or_none(self.delay_index(crossed)),
            "free_flow_time_mean": _mean_or_none(self.free_flow_times(crossed)),
            "vehicles_seen": len(ids),
            "steps": self.steps,
        }
