"""The space-time field of the measurement segment: speeds, flow and congestion waves.

Every step adds each vehicle inside the segment to a fixed grid of ``dx`` metres by ``bin_s``
seconds: the distance it drove in the step (v·dt) and the time it spent (dt). Edie's
generalised definitions then give, over any region A of the grid, the flow q = Σd / |A| and
the density k = Σt / |A| (|A| in lane-metres × seconds), and the space-mean speed v = Σd / Σt.
Memory grows with the episode's length (two floats per cell), never with the vehicles.

``wave_speed`` estimates how fast stop-and-go waves travel along the road: the lag that
maximises the cross-correlation of the speed series of two places ``Δx`` apart gives
c = Δx / lag. Waves travel upstream (c < 0) at the congested branch's characteristic speed,
about −(car length + jam gap) / T (observed: −15 to −20 km/h). A pattern that moves
downstream is the vehicles carrying their own speed variations, not a wave, and a faster
upstream one is no physical wave: both give NaN (None in the records), as does a flat field.
"""

from __future__ import annotations

import math

import numpy as np

from mixed_traffic import compiled
from mixed_traffic.env import control_kernel

DX = 10.0
"""Grid cell length along the segment [m]."""
BIN_S = 1.0
"""Grid cell duration [s]."""
WAVE_WINDOW = (3, 5)
"""Smoothing window of the speed field for waves: cells along x, cells along t."""
WAVE_SEPARATIONS = (30.0, 50.0, 70.0)
"""Distances between the two places whose speed series are correlated [m]: short, so that a
wave is seen before it changes; at 70 m the lags searched (± 50 s) can reach the next wave of
a one-minute train, which ``WAVE_AGREEMENT`` rejects."""
MIN_WAVE_SPEED = 5.0
"""Slowest wave looked for [km/h]: it bounds the lags searched, both ways."""
JAM_SPACING = 7.0
"""Front-to-front spacing of a standing queue [m]: a 5 m car and a 2 m gap (143 veh/km)."""
MIN_HEADWAY = 0.6
"""A short time headway [s], half the 1.0-1.5 s of freeway drivers: a bound, not a typical one."""
MAX_WAVE_SPEED = 3.6 * JAM_SPACING / MIN_HEADWAY
"""Fastest possible wave [km/h], 42: the congested branch of the fundamental diagram,
q = (1 − k·JAM_SPACING) / T, has the characteristic speed −JAM_SPACING / T."""
MIN_SPEED_SPREAD = 1.0
"""Standard deviation of the smoothed speed field [m/s] below which there are no waves."""
MIN_CORRELATION = 0.5
"""Correlation the best lag must reach for a wave speed to be reported [-]."""
WAVE_AGREEMENT = 0.25
"""Relative distance from the separations' median [-] within which their wave speeds are one
wave's: a lag is resolved to a few tenths of a second, and is 2.6 s at the shortest."""


class SpaceTimeField:
    """Edie's sums on a (time × space) grid, plus speed moments, after a warm-up; one grid per
    copy of the scenario (``EnvConfig.copies``), side by side in one array.

    Args:
        length: segment length [m], or (C,) each copy's.
        lane_metres: Σ over the segment's edges of length × lanes [m], or (C,) each copy's.
        dt: simulation step [s].
        warmup: samples before this time [s] are not counted.
    """

    def __init__(self, length: float | np.ndarray, lane_metres: float | np.ndarray, dt: float,
                 warmup: float, trace_every: int = 0) -> None:  # fmt: skip
        self.lengths = np.atleast_1d(np.asarray(length, np.float64))
        self.lane_metres = np.atleast_1d(np.asarray(lane_metres, np.float64))
        self.length, self.dt, self.warmup = float(self.lengths[0]), dt, warmup
        self.copies = len(self.lengths)
        self.trace_every = trace_every
        """Keep every vehicle's (t, s, v) every this many steps (0: no traces; copy 0's)."""
        self._traces: list[np.ndarray] = []
        self.widths = np.maximum(1, np.ceil(self.lengths / DX)).astype(np.int64)
        """(C,) cells along each copy's segment."""
        self.n_x = int(self.widths.max())
        self._last = self.widths - 1  # (C,) a copy's last column
        self._dist = np.zeros((64, self.copies * self.n_x))
        self._time = np.zeros((64, self.copies * self.n_x))
        self._t0: float | None = None  # start of the first bin (the first step after warm-up)
        self._n_bins = 0
        self._moments = np.zeros((self.copies, 3))  # Σ 1, Σ v, Σ v² over (vehicle, step) samples
        self._steps = 0

    def add(self, t: float, s: np.ndarray, v: np.ndarray, copy: np.ndarray | None = None) -> None:
        """One step ending at ``t`` [s]: vehicles at positions ``s`` [m] along their copy's
        segment (NaN outside it) driving at ``v`` [m/s], in copies ``copy`` (all (N,); None:
        copy 0)."""
        if t < self.warmup - 1e-9:
            return
        if self._t0 is None:
            self._t0 = t - self.dt
        self._steps += 1
        row = int((t - self._t0 - 1e-9) // BIN_S)
        self._grow(row + 1)
        copy = np.zeros(len(s), np.int64) if copy is None else copy
        if compiled.enabled() and _kernel_layout(s, v, copy):
            control_kernel.edie_add(self._dist, self._time, row, s, v, float(self.dt), DX, copy,
                                    self.n_x, self._last)  # fmt: skip
            inside = ~np.isnan(s)
            s, v, copy = s[inside], v[inside], copy[inside]
        else:
            inside = ~np.isnan(s)
            s, v, copy = s[inside], v[inside], copy[inside]
            col = np.clip((s // DX).astype(np.int64), 0, self._last[copy]) + copy * self.n_x
            np.add.at(self._dist[row], col, v * self.dt)
            np.add.at(self._time[row], col, self.dt)
        if self.copies == 1:  # numpy's pairwise sums, as without copies
            self._moments[0] += (len(v), v.sum(), (v * v).sum())
        else:
            for q, w in enumerate((np.ones_like(v), v, v * v)):
                self._moments[:, q] += np.bincount(copy, w, minlength=self.copies)
        if self.trace_every and self._steps % self.trace_every == 1 % self.trace_every:
            s, v = s[copy == 0], v[copy == 0]
            self._traces.append(np.stack([np.full(len(s), t), s, v], axis=1).astype(np.float32))

    def _grow(self, rows: int) -> None:
        if rows > len(self._dist):
            extra = max(rows, 2 * len(self._dist)) - len(self._dist)
            self._dist = np.vstack([self._dist, np.zeros((extra, self._dist.shape[1]))])
            self._time = np.vstack([self._time, np.zeros((extra, self._time.shape[1]))])
        self._n_bins = max(self._n_bins, rows)

    def _cells(self, copy: int) -> slice:
        return slice(copy * self.n_x, copy * self.n_x + int(self.widths[copy]))

    def distance(self, copy: int = 0) -> np.ndarray:
        """(T, X) distance driven in each cell of copy ``copy`` [m] (summed over vehicles and
        lanes)."""
        return self._dist[: self._n_bins, self._cells(copy)]

    def time(self, copy: int = 0) -> np.ndarray:
        """(T, X) time spent in each cell of copy ``copy`` [s] (summed over vehicles and
        lanes)."""
        return self._time[: self._n_bins, self._cells(copy)]

    def traces(self) -> dict[str, np.ndarray]:
        """Arrays ``t`` [s], ``s`` [m along the segment] and ``v`` [m/s] of the traced samples."""
        rows = np.concatenate(self._traces) if self._traces else np.zeros((0, 3), np.float32)
        return {"t": rows[:, 0], "s": rows[:, 1], "v": rows[:, 2]}

    def speed_std(self, copy: int = 0) -> float:
        """Population standard deviation of copy ``copy``'s (vehicle, step) speed samples [m/s]."""
        n, s1, s2 = self._moments[copy]
        return math.sqrt(max(s2 / n - (s1 / n) ** 2, 0.0)) if n else math.nan

    def flow(self, copy: int = 0) -> float:
        """Edie's flow over copy ``copy``'s field [veh/h/lane]."""
        area = self.lane_metres[copy] * self._steps * self.dt
        # every allocated row (zeros beyond the last bin): numpy's pairwise sum as ever
        driven = float(self._dist[:, self._cells(copy)].sum())
        return 3600.0 * driven / area if area > 0 else math.nan

    def wave_speed(self, copy: int = 0) -> float:
        """Speed of the stop-and-go waves along copy ``copy``'s segment [km/h], < 0 upstream;
        NaN without waves (see ``wave_speed``)."""
        return wave_speed(self.distance(copy), self.time(copy), DX, BIN_S)


def _kernel_layout(s: np.ndarray, v: np.ndarray, copy: np.ndarray) -> bool:
    """``s`` and ``v`` are C-contiguous float64 arrays and ``copy`` int64, the one
    specialisation of ``control_kernel.edie_add`` (the env's)."""
    f = np.float64
    arrays = ((s, f), (v, f), (copy, np.int64))
    return all(
        isinstance(x, np.ndarray) and x.dtype == d and x.flags.c_contiguous for x, d in arrays
    )


def smoothed_speed(dist: np.ndarray, time: np.ndarray, window: tuple[int, int]) -> np.ndarray:
    """(T, X) space-mean speed [m/s] over a box of ``window`` = (cells along x, cells along
    t) around each cell (Edie's definition on the box), NaN where the box is empty."""
    wx, wt = window

    def box(a: np.ndarray) -> np.ndarray:
        c = np.cumsum(np.cumsum(np.pad(a, ((1, 0), (1, 0))), axis=0), axis=1)
        t0 = np.clip(np.arange(a.shape[0]) - wt // 2, 0, a.shape[0])
        t1 = np.clip(np.arange(a.shape[0]) + wt - wt // 2, 0, a.shape[0])
        x0 = np.clip(np.arange(a.shape[1]) - wx // 2, 0, a.shape[1])
        x1 = np.clip(np.arange(a.shape[1]) + wx - wx // 2, 0, a.shape[1])
        return c[t1][:, x1] - c[t0][:, x1] - c[t1][:, x0] + c[t0][:, x0]

    d, t = box(dist), box(time)
    return np.divide(d, t, out=np.full(d.shape, np.nan), where=t > 0)


def wave_speed(dist: np.ndarray, time: np.ndarray, dx: float, bin_s: float) -> float:
    """Speed [km/h] of the stop-and-go waves in a (T, X) grid of Edie sums (< 0: upstream).

    The speed field is smoothed over ``WAVE_WINDOW`` cells. For each separation Δx in
    ``WAVE_SEPARATIONS`` that fits in the grid, the lag τ [s] maximising the correlation of
    v(x, t) and v(x + Δx, t + τ), averaged over all pairs of places Δx apart, gives Δx / τ
    (see ``_separation_speed`` for when it counts as a wave). The median of the estimates
    within ``WAVE_AGREEMENT`` of their median is returned if they come from at least half of
    the separations; NaN otherwise, or when the field is flat (std < ``MIN_SPEED_SPREAD``) or
    too short.
    """
    v = smoothed_speed(dist, time, WAVE_WINDOW)
    if v.shape[0] < 20 or np.isnan(v).mean() > 0.2:
        return math.nan
    v = np.where(np.isnan(v), np.nanmean(v), v)
    if v.std() < MIN_SPEED_SPREAD:
        return math.nan
    shifts = [k for k in (round(sep / dx) for sep in WAVE_SEPARATIONS) if 1 <= k < v.shape[1]]
    speeds = np.array([_separation_speed(v, k, dx, bin_s) for k in shifts])
    if np.isnan(speeds).all():
        return math.nan
    # one wave gives one speed at every separation; spurious peaks of the correlation do not
    centre = np.nanmedian(speeds)
    agree = speeds[np.abs(speeds - centre) <= WAVE_AGREEMENT * abs(centre)]
    return float(np.median(agree)) if 2 * len(agree) >= len(shifts) else math.nan


def _separation_speed(v: np.ndarray, k: int, dx: float, bin_s: float) -> float:
    """Wave speed [km/h] between the places ``k`` cells apart in the (T, X) speed field ``v``,
    or NaN unless the global best lag over ± the slowest wave's lag is a wave: an interior
    peak (not cut by the search range), correlated by at least ``MIN_CORRELATION``, upstream
    at ``MIN_WAVE_SPEED`` to ``MAX_WAVE_SPEED``."""
    max_lag = math.ceil(3.6 * k * dx / MIN_WAVE_SPEED / bin_s)
    lag, corr = _best_lag(v[:, :-k], v[:, k:], max_lag)
    if math.isnan(lag) or corr < MIN_CORRELATION or lag == 0:
        return math.nan
    c = 3.6 * k * dx / (lag * bin_s)
    return c if -MAX_WAVE_SPEED <= c <= -MIN_WAVE_SPEED else math.nan


def _best_lag(a: np.ndarray, b: np.ndarray, max_lag: int) -> tuple[float, float]:
    """The lag τ [cells], |τ| <= ``max_lag`` and at most a third of the series, maximising the
    mean over columns of corr(a[t], b[t + τ]) (refined between cells by a parabola through the
    peak and its neighbours), and that correlation; τ is NaN when the maximum lies on the edge
    of the lags searched (the true peak may lie beyond)."""
    a = a - a.mean(axis=0)
    b = b - b.mean(axis=0)
    reach = min(max_lag, len(a) // 3)
    lags = np.arange(-reach, reach + 1)
    corr = np.array([_mean_corr(a, b, int(lag)) for lag in lags])
    i = int(np.argmax(corr))
    if not 0 < i < len(lags) - 1:
        return math.nan, float(corr[i])
    left, mid, right = corr[i - 1 : i + 2]
    curve = left - 2 * mid + right
    shift = 0.5 * (left - right) / curve if curve < 0 else 0.0
    return float(lags[i] + shift), float(mid)


def _mean_corr(a: np.ndarray, b: np.ndarray, lag: int) -> float:
    """Mean over columns of the correlation of a[t] and b[t + lag] (centred series)."""
    n = len(a)
    x, y = (a[: n - lag], b[lag:]) if lag >= 0 else (a[-lag:], b[: n + lag])
    den = np.sqrt((x * x).sum(axis=0) * (y * y).sum(axis=0))
    ok = den > 0
    return float(np.mean((x * y).sum(axis=0)[ok] / den[ok])) if ok.any() else -1.0
