"""The per-step array work of the flow metrics as compiled kernels: ``FlowRecorder.update``'s
crossing state machine (:func:`flow_step`), its arrivals (:func:`flow_gone`),
``AheadBehind.update``'s window sums (:func:`ahead_behind_step`) and ``AVMetrics``' trip sums
(:func:`trips_add`).

The Python callers keep the bookkeeping with string ids (vehicle id -> slot); the kernels do
the arithmetic after it, one vehicle (or AV and window column) at a time, with the
floating-point operations of the numpy stages in their order (``np.maximum`` / ``np.minimum``
propagate NaN, ``np.cumsum`` adds in order, the 0/1 matmul of ``AheadBehind`` adds its
columns in order), so the results are equal bit for bit (tests/test_metrics_kernel.py checks
it on SUMO episodes). Sums numpy computes pairwise stay numpy's. The numpy stages stay the
reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import inline, maximum, minimum, njit

#: Crossing states, as ``flow_metrics`` (int8).
UNSEEN, UPSTREAM, INSIDE, INSIDE_UNKNOWN, CROSSED, LEFT = 0, 1, 2, 3, 4, 5
#: Speed below which entry/exit interpolation uses the observation time itself [m/s].
V_MIN = 0.1


@inline
def _in(st):
    """State ``st`` is INSIDE or INSIDE_UNKNOWN (2 and 3)."""
    return INSIDE <= st <= INSIDE_UNKNOWN


@inline
def _entry_time(t, s, v, t_prev):
    """``flow_metrics.entry_time`` of one vehicle [s]."""
    back = s / maximum(v, V_MIN) if v > V_MIN else 0.0
    return maximum(t - back, t_prev)


@inline
def _exit_time(t_last, s_last, v_last, length, t_next):
    """``flow_metrics.exit_time`` of one vehicle [s]."""
    ahead = maximum(length - s_last, 0.0)
    fwd = ahead / maximum(v_last, V_MIN) if v_last > V_MIN else t_next - t_last
    return minimum(t_last + fwd, t_next)


@njit
def flow_step(
    slot, edge, lane, lane_pos, speed, t, dt, offset, lane_speed, is_first, is_last, edge_copy,
    lengths, slot_copy, state, t_entry, t_exit, t_last, s_last, v_last, on_last_edge, seg_time,
    seg_free, seg_dist, t_in, trip_time, trip_free,
):  # fmt: skip
    """One step of ``FlowRecorder.update`` after the slots: updates the per-slot arrays in
    place and returns (N,) the position along its copy's segment [m] (NaN outside) and (N,)
    bool inside it.

    Args (N vehicles, E edges, L lanes, S slots, C copies): ``slot`` (N,) int64 distinct
    slots; the snapshot's ``edge`` and ``lane`` (N,) rows (-1 none), ``lane_pos`` [m] and
    ``speed`` [m/s]; ``t`` the time [s], ``dt`` the step [s]; ``offset`` (E + 1,) start of
    each edge along its copy's segment [m] (NaN off it, the last entry for row -1);
    ``lane_speed`` (L + 1,) [m/s] (NaN last); ``is_first`` / ``is_last`` (E + 1,) bool the
    segments' first and last edges; ``edge_copy`` (E + 1,) int64 each edge's copy;
    ``lengths`` (C,) the segments' [m]; the recorder's (S,) arrays ``slot_copy`` (int64, set
    when a vehicle is first inside), ``state`` (int8), ``t_entry`` .. ``trip_free`` (float64,
    bool).
    """
    n = len(slot)
    s_out = np.empty(n)
    inside_out = np.empty(n, np.bool_)
    for i in range(n):
        k, e, v = slot[i], edge[i], speed[i]
        s = offset[e if e >= 0 else len(offset) - 1] + lane_pos[i]
        inside = not np.isnan(s)
        outside = not inside and e >= 0
        ln = lane[i]
        vlim = lane_speed[ln if ln >= 0 else len(lane_speed) - 1]
        free = v * dt / vlim if vlim > 0 else 0.0
        trip_time[k] += dt
        trip_free[k] += free
        if inside:
            slot_copy[k] = edge_copy[e]
        st = _crossing(state[k], inside, outside, is_first[e if e >= 0 else len(is_first) - 1],
                       k, t, s, v, t_entry, t_exit, t_last, t_in, s_last, v_last, on_last_edge,
                       lengths[slot_copy[k]])  # fmt: skip
        if inside and _in(st):
            seg_time[k] += dt
            seg_free[k] += free
            seg_dist[k] += v * dt
            t_in[k] = t
            s_last[k] = s
            v_last[k] = v
            on_last_edge[k] = is_last[e]
        t_last[k] = t
        state[k] = st
        s_out[i], inside_out[i] = s, inside
    return s_out, inside_out


@inline
def _crossing(st, inside, outside, on_first, k, t, s, v, t_entry, t_exit, t_last, t_in, s_last,
              v_last, on_last_edge, length):  # fmt: skip
    """The new crossing state of slot ``k`` (was ``st``); records its entry or exit time."""
    if st == UNSEEN:  # first sighting
        st = UPSTREAM if outside else (INSIDE_UNKNOWN if inside else st)
    if st == UPSTREAM and inside:  # entry from upstream: at the start, or sideways
        if on_first:
            t_prev = t_last[k] if not np.isnan(t_last[k]) else -np.inf
            t_entry[k] = _entry_time(t, s, v, t_prev)
            st = INSIDE
        else:
            st = INSIDE_UNKNOWN
    if _in(st) and outside:  # left: at the end, or sideways
        if st == INSIDE and on_last_edge[k]:
            t_exit[k] = _exit_time(t_in[k], s_last[k], v_last[k], length, t)
            st = CROSSED
        else:
            st = LEFT
    return st


@njit
def flow_gone(slot, t, lengths, slot_copy, state, t_exit, t_in, s_last, v_last, on_last_edge):
    """``FlowRecorder._finish_gone`` for the (G,) int64 slots of the vehicles that arrived at
    time ``t`` [s]: the ones inside on the last edge crossed (exit time; ``lengths`` (C,) the
    segments' [m], ``slot_copy`` (S,) each slot's copy), the others inside left; the (S,)
    arrays are updated in place."""
    for i in range(len(slot)):
        k = slot[i]
        st = state[k]
        if st == INSIDE and on_last_edge[k]:
            t_exit[k] = _exit_time(t_in[k], s_last[k], v_last[k], lengths[slot_copy[k]], t)
            state[k] = CROSSED
        elif _in(st):
            state[k] = LEFT


@njit
def ahead_behind_step(
    lane, lane_pos, speed, avs, slots, band, reach, d_ahead, lane_tab, offset_tab, window,
    lane_length, sums,
):  # fmt: skip
    """One step of ``AheadBehind.update``: adds each AV's window sums into ``sums``.

    Args (N vehicles, A AVs, L lanes, D reach columns, S slots): the snapshot's ``lane`` (N,)
    rows (-1 none), ``lane_pos`` [m] and ``speed`` [m/s]; ``avs`` (A,) int64 the AVs' rows,
    all on a lane; ``slots`` (A,) int64 their distinct accumulator slots; ``band`` the sort
    key's lane stride [m]; ``reach`` (L, 2) lanes reached per side; ``d_ahead`` the ahead
    columns; ``lane_tab`` (L, D) int64 and ``offset_tab`` (L, D) [m] the reach table;
    ``window`` (L,) [m]; ``lane_length`` (L + 1,) [m] (0 last); ``sums`` (S, 2, 3) float64
    per slot and side (ahead, behind) the count, Σv [m/s] and Σv² [m²/s²].
    """
    key, cum = _sorted_sums(lane, lane_pos, speed, band)
    ka, kb = 0, 0
    for a in range(len(avs)):
        ka = max(ka, reach[lane[avs[a]], 0])
        kb = max(kb, reach[lane[avs[a]], 1])
    for a in range(len(avs)):
        ln, pos = lane[avs[a]], lane_pos[avs[a]]
        for side in range(2):
            c0, c1 = (0, ka) if side == 0 else (d_ahead, d_ahead + kb)
            got = np.zeros(3)  # the matmul's sums start at 0 and add the columns in order
            for c in range(c0, c1):
                lo, hi = _range(ln, pos, c, side == 0, lane_tab, offset_tab, window,
                                lane_length, band, key)  # fmt: skip
                for q in range(3):
                    got[q] += cum[q, hi] - cum[q, lo]
            for q in range(3):
                sums[slots[a], side, q] += got[q]


@inline
def _sorted_sums(lane, lane_pos, speed, band):
    """(M,) the (lane, position) keys of the vehicles on a lane, sorted (stable), and (3, M + 1)
    the cumulative count, Σv and Σv² in that order, with a leading 0."""
    m = 0
    for i in range(len(lane)):
        m += lane[i] >= 0
    key, v = np.empty(m), np.empty(m)
    m = 0
    for i in range(len(lane)):
        if lane[i] >= 0:
            key[m], v[m] = lane[i] * band + lane_pos[i], speed[i]
            m += 1
    order = np.argsort(key, kind="mergesort")  # stable, as numpy's kind="stable"
    cum = np.zeros((3, m + 1))
    for j in range(m):
        x = v[order[j]]
        cum[0, j + 1] = j + 1.0
        cum[1, j + 1] = cum[1, j] + x
        cum[2, j + 1] = cum[2, j] + x * x
    return key[order], cum


@inline
def _range(ln, pos, c, ahead, lane_tab, offset_tab, window, lane_length, band, key):
    """(lo, hi) the index range into the sorted ``key`` of the window of the AV on lane row
    ``ln`` at ``pos`` [m] on the lane of reach column ``c`` (``AheadBehind._ranges``)."""
    other = lane_tab[ln, c]
    rel = pos - offset_tab[ln, c]  # the AV's position in that lane's frame
    w = window[ln]
    # ahead (rel, rel + w], behind [rel - w, rel): the AV itself (at rel) is left out
    a = rel if ahead else rel - w
    b = rel + w if ahead else rel
    top = lane_length[other if other >= 0 else len(lane_length) - 1] + 1.0
    base = max(other, 0) * band
    a = base + minimum(maximum(a, -1.0), top)
    b = base + minimum(maximum(b, -1.0), top)
    if not ahead:  # searches keep keys in (a, b]; behind's [a, b) is (a⁻, b⁻]
        a = np.nextafter(a, -np.inf)
        b = np.nextafter(b, -np.inf)
    lo = np.searchsorted(key, a, side="right")
    if other < 0:
        return lo, lo
    return lo, max(np.searchsorted(key, b, side="right"), lo)


@njit
def trips_add(idx, dt, speed, ttc, affected, time, distance, min_ttc, affected_time):
    """``av_metrics._LiveTrips.add`` after the slots: the (A,) int64 distinct slots ``idx`` of
    the AVs drove ``dt`` [s] at ``speed`` (A,) [m/s] with ``ttc`` (A,) [s] (NaN: none) and
    ``affected`` (A,) bool their rear vehicle; the (S,) sums are updated in place."""
    for i in range(len(idx)):
        k = idx[i]
        time[k] += dt
        distance[k] += speed[i] * dt
        min_ttc[k] = _fmin(min_ttc[k], ttc[i])
        affected_time[k] += dt if affected[i] else 0.0


@inline
def _fmin(a, b):
    """``np.fmin`` of two floats: the other one where one is NaN."""
    return a if (a <= b or b != b) else b


def warm() -> None:
    """Load the kernels (from the disk cache, else compile them) for the dtypes and layouts
    the env passes, on one vehicle: a process that forks workers calls this once, and they
    inherit them."""
    i64, i32, f64 = np.int64, np.int32, np.float64
    one, slot, no = np.zeros(1), np.zeros(1, i64), np.zeros(1, np.bool_)
    lane, edge = np.zeros(1, i32), np.zeros(1, i32)
    two_no, two_i64 = np.zeros(2, np.bool_), np.zeros(2, i64)
    flow_step(slot, edge, lane, one, one, 1.0, 0.1, np.zeros(2), np.ones(2), two_no, two_no,
              two_i64, np.ones(1), slot.copy(), np.zeros(1, np.int8), one.copy(), one.copy(),
              one.copy(), one.copy(), one.copy(), no, one.copy(), one.copy(), one.copy(),
              one.copy(), one.copy(), one.copy())  # fmt: skip
    flow_gone(slot, 1.0, np.ones(1), slot.copy(), np.zeros(1, np.int8), one.copy(), one.copy(),
              one.copy(), one.copy(), no)  # fmt: skip
    trips_add(slot, 0.1, one, one, no, one.copy(), one.copy(), one.copy(), one.copy())
    ahead_behind_step(lane, one, one, slot, slot, 10.0, np.ones((1, 2), i64), 1,
                      np.zeros((1, 2), i64), np.zeros((1, 2), f64), one, np.ones(2),
                      np.zeros((1, 2, 3)))  # fmt: skip
