"""ACC-LC's lane-change decision (:func:`agents.rules.acc_lc._decision`) as one compiled kernel.

:func:`decision` does per agent what the numpy stages of ``agents.rules.acc_lc`` do with whole
arrays: the gap checks (``acc_lc_lateral.safe``, strict and relaxed, and ``forced_ok``), a change
under way (``_change_checks``), the wanted discretionary change and the decision
(``_wanted``, ``_decide``), whether a change row shifts its target (``_go``) and the executed
accelerations (``_executed_accels`` with ``wait_accel`` and ``hidden_cap``). It does their
floating-point operations in the same order (no transcendental functions: only ``+ - * /``,
``sqrt``, min / max), so the results equal the numpy stages' bit for bit
(tests/test_acc_lc_plan_kernel.py checks it on SUMO states); those stay the reference.
"""

from __future__ import annotations

import numpy as np

from mixed_traffic.compiled import inline, maximum, minimum, njit

_L, _C, _R = 0, 1, 2
LEFT, FOLLOW, RIGHT = 0, 1, 2


@inline
def _safe(a, j, v, ln, vdist, vrel, vlen, exists, s0, rear_headway, rear_2dec, b_2, relaxed):  # fmt: skip
    """``acc_lc_lateral.safe`` of agent ``a`` into lane column ``j`` (``rear_2dec`` = 2
    ``rear_decel``, ``b_2`` = 2 ``b``)."""
    va = v[a]
    rd = -vdist[a, j, 1]
    rgap = rd - ln[a]
    v_rear = maximum(va + vrel[a, j, 1], 0.0)
    closing = maximum(vrel[a, j, 1], 0.0)
    req_r = s0 + rear_headway * v_rear + closing * closing / rear_2dec
    if relaxed:
        req_r = 0.5 * req_r
    rear_ok = (not np.isfinite(rd)) or (rgap > req_r)
    fd = vdist[a, j, 0]
    fgap = fd - vlen[a, j, 0]
    fclose = maximum(-vrel[a, j, 0], 0.0)
    req_f = s0 + 0.5 * va + fclose * fclose / b_2
    if relaxed:
        req_f = 0.5 * req_f
    front_ok = (not np.isfinite(fd)) or (fgap > req_f)
    return exists[a, j] and rear_ok and front_ok


@inline
def _forced(a, j, v, ln, vdist, vrel, vlen, exists, hv_s0, hv_T, hv_a, hv_den, frd, ffd):  # fmt: skip
    """``acc_lc_lateral.forced_ok`` of agent ``a`` into ``j`` (``hv_den`` = 2 sqrt(a b))."""
    va = v[a]
    rd = -vdist[a, j, 1]
    rgap = rd - ln[a]
    v_r = maximum(va + vrel[a, j, 1], 0.0)
    s_star = hv_s0 + v_r * hv_T + v_r * (v_r - va) / hv_den
    s_star = maximum(s_star, hv_s0)
    z = s_star / maximum(rgap, 0.1)
    acc_r = hv_a * (1.0 - z * z)
    dv = v_r - va
    kin = dv * dv / (2 * maximum(rgap - hv_s0, 0.1)) <= frd
    rear_ok = (not np.isfinite(rd)) or (((acc_r >= -frd) or kin) and (rgap > hv_s0 + 0.3 * v_r))
    fd = vdist[a, j, 0]
    fgap = fd - vlen[a, j, 0]
    fclose = maximum(-vrel[a, j, 0], 0.0)
    front_ok = (not np.isfinite(fd)) or (
        (fgap > 1.5 + 0.3 * va) and (fclose * fclose / (2 * maximum(fgap - 1.0, 0.1)) <= ffd)
    )
    return exists[a, j] and rear_ok and front_ok


@inline
def _wait(a, j, v, ln, vdist, vrel, vlen, acc_cur, hv_s0, hv_T, need_den, ffd, acc_max):  # fmt: skip
    """``acc_lc_longitudinal.wait_accel`` of agent ``a`` towards ``j`` (``need_den`` =
    sqrt(1 + force_rear_decel / hv_a))."""
    va = v[a]
    fd, rd = vdist[a, j, 0], -vdist[a, j, 1]
    has_f, has_r = np.isfinite(fd), np.isfinite(rd)
    fgap = fd - vlen[a, j, 0] if has_f else 1e3
    rgap = rd - ln[a] if has_r else 1e3
    v_f = maximum(va + vrel[a, j, 0], 0.0)
    v_r = maximum(va + vrel[a, j, 1], 0.0)
    need_r = (hv_s0 + hv_T * v_r) / need_den + 0.5
    need_f = 1.5 + 0.3 * va
    slack = fgap + rgap - need_r - need_f
    e = fgap - (need_f + 0.5 * minimum(slack, 20.0))
    v_ref = v_f if has_f else (v_r + 1.0 if has_r else va)
    acc_gap = 0.4 * e + 1.0 * (v_ref - va)
    acc_pass = 1.0 * (maximum(v_r - 2.0, 0.0) - va)
    acc = minimum(maximum(acc_gap if slack > 0 else acc_pass, -ffd), acc_max)
    return minimum(acc, acc_cur[a])


@inline
def _hidden(a, v, vdist, vrel, vlen, exists, hidden_gap, hd_2):  # fmt: skip
    """``acc_lc_longitudinal.hidden_cap`` of agent ``a`` (``hd_2`` = 2 ``hidden_decel``)."""
    va = v[a]
    cap = np.inf
    for j in (_L, _R):
        fd = vdist[a, j, 0]
        v_o = maximum(va + vrel[a, j, 0], 0.0)
        rear = fd - vlen[a, j, 0]
        room = minimum(fd + hidden_gap, rear if rear > 0 else np.inf) - 0.5
        v_max = v_o + np.sqrt(hd_2 * maximum(room, 0.0))
        if exists[a, j] and np.isfinite(fd) and vlen[a, j, 0] > 0.1:
            cap = minimum(cap, 4.0 * (v_max - va))
    return cap


@inline
def _choose(a, mand, mask, sl, sr, cl, cr, gl, gr, wl, wr):  # fmt: skip
    """``_decide``'s decision of agent ``a`` from the checks and the wanted changes."""
    m = mand[a]
    dec = FOLLOW
    if wr:
        dec = RIGHT
    if wl:
        dec = LEFT
    if gl and cl:
        dec = LEFT
    if gr and cr:
        dec = RIGHT
    m_l = m and mask[a, LEFT] and ((not mask[a, RIGHT]) or sl or not sr)
    if m and not m_l and mask[a, RIGHT]:
        dec = RIGHT
    if m_l:
        dec = LEFT
    if not mask[a, dec]:  # never a masked decision (else the first allowed, as np.argmax)
        first = 0
        for k in range(3):
            if mask[a, k]:
                first = k
                break
        dec = FOLLOW if mask[a, FOLLOW] else first
    return dec


@njit
def decision(
    v, d, ln, vlat, vdist, vrel, vlen, exists, mask, mand, now_c, now_l, now_r, acc_f, acc_l,
    acc_r, acc_fc, s0, rear_headway, rear_2dec, b_2, signal_offset, lc_start_offset,
    lc_threshold, keep_right_bias, hv_s0, hv_T, hv_a, hv_den, need_den, frd, ffd, acc_max,
    hidden_gap, hd_2,
):  # fmt: skip
    """Per agent (A): the decision (int64), go_l / go_r (bool) and the accelerations [m/s²]
    of the follow, left and right rows (float64) of ``AccLcPolicy.plan``.

    ``v``, ``d``, ``ln`` (len), ``vlat`` (vlat_hist) (A,); ``vdist``, ``vrel``, ``vlen`` (A, 3,
    2); ``exists``, ``mask`` (A, 3) bool; ``mand`` (A,) bool; ``now_*``, ``acc_*`` the (A,)
    candidate-lane accelerations (``_LaneAccels``); the rest ``AccLcConfig`` scalars."""
    A = v.shape[0]
    dec = np.empty(A, np.int64)
    go_l, go_r = np.empty(A, np.bool_), np.empty(A, np.bool_)
    out_f, out_l, out_r = np.empty(A), np.empty(A), np.empty(A)
    for a in range(A):
        ml, mr, m = mask[a, LEFT], mask[a, RIGHT], mand[a]
        # _change_checks
        sl = _safe(a, _L, v, ln, vdist, vrel, vlen, exists, s0, rear_headway, rear_2dec, b_2,
                   False) and ml  # fmt: skip
        sr = _safe(a, _R, v, ln, vdist, vrel, vlen, exists, s0, rear_headway, rear_2dec, b_2,
                   False) and mr  # fmt: skip
        cl = _safe(a, _L, v, ln, vdist, vrel, vlen, exists, s0, rear_headway, rear_2dec, b_2,
                   True) and ml  # fmt: skip
        cr = _safe(a, _R, v, ln, vdist, vrel, vlen, exists, s0, rear_headway, rear_2dec, b_2,
                   True) and mr  # fmt: skip
        start = signal_offset + 0.15 if m else lc_start_offset
        gl = d[a] > start and vlat[a] > 0.1
        gr = d[a] < -start and vlat[a] < -0.1
        # _wanted
        centred = abs(d[a]) < lc_start_offset
        inc_l = now_l[a] - now_c[a] - lc_threshold
        inc_r = now_r[a] - now_c[a] - lc_threshold + keep_right_bias
        wl = sl and centred and inc_l > 0 and v[a] > 3.0
        wr = sr and centred and inc_r > 0 and v[a] > 3.0
        both = wl and wr
        wl = wl and (not both or inc_l > inc_r)
        wr = wr and not (both and inc_l > inc_r)
        dec[a] = _choose(a, mand, mask, sl, sr, cl, cr, gl, gr, wl, wr)
        # _go
        fl = m and ml and _forced(a, _L, v, ln, vdist, vrel, vlen, exists, hv_s0, hv_T, hv_a,
                                  hv_den, frd, ffd)  # fmt: skip
        fr = m and mr and _forced(a, _R, v, ln, vdist, vrel, vlen, exists, hv_s0, hv_T, hv_a,
                                  hv_den, frd, ffd)  # fmt: skip
        g_l = (cl if gl else sl) or fl
        g_r = (cr if gr else sr) or fr
        go_l[a], go_r[a] = g_l, g_r
        # _executed_accels
        af = acc_f[a]
        al = minimum(acc_l[a], acc_fc[a]) if g_l else af
        ar = minimum(acc_r[a], acc_fc[a]) if g_r else af
        if m and not (g_l and (sl or (gl and cl))):
            al = _wait(a, _L, v, ln, vdist, vrel, vlen, acc_f, hv_s0, hv_T, need_den, ffd,
                       acc_max)  # fmt: skip
        if m and not (g_r and (sr or (gr and cr))):
            ar = _wait(a, _R, v, ln, vdist, vrel, vlen, acc_f, hv_s0, hv_T, need_den, ffd,
                       acc_max)  # fmt: skip
        cap = _hidden(a, v, vdist, vrel, vlen, exists, hidden_gap, hd_2)
        out_f[a], out_l[a], out_r[a] = minimum(af, cap), minimum(al, cap), minimum(ar, cap)
    return dec, go_l, go_r, out_f, out_l, out_r
