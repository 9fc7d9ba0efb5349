"""The filter's loop over a block of samples: predict across the real time between samples, per-output sensor
checks, the update, noise learning, the consistency guard, divergence recovery and checkpoints (see
:mod:`twin.online.ukf`).

:func:`filter_loop` takes four records (:data:`twin.online.ukf.Setup`, :data:`~twin.online.ukf.Carry`,
:data:`~twin.online.ukf.Block`, :data:`~twin.online.ukf.Out`).  The model comes through the prediction, imported in
the one line marked ``# kernel: the model's prediction``: each model's kernel (:func:`twin.online.ukf.kernel_for`)
is a copy of this module whose marked line names that model's copy of :mod:`twin.online.ukf_predict`.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from twin.online.ukf_linalg import _all_finite, dlog_dz
from twin.online.ukf_predict import _predict, lanes_apply  # kernel: the model's prediction
from twin.online.ukf_status import (
    C_ADAPT, C_A_MAX, C_CENTRAL, C_NSHARE, C_CK_S, C_CLEAR_N, C_DIV_NIS, C_GAP_MAX, C_INFLATE, C_NIS_CLIP, C_NIS_HI, C_NOISY, C_OFF_N,
    C_OUT_NU, C_RHO_HI, C_SETTLE_S, C_SIG_HI, C_SIG_LO, C_STUCK_N, C_TAU_DIV, C_TAU_GUARD, C_TAU_NOISE, C_WARM_S,
    C_ZPIN, F_CK_OK, F_CK_T, F_CTRL, F_EXC0, F_EXC1, F_EXC2, F_GATED_RUN, F_HAVE_PREV, F_NIS_EMA, F_NIS_FAST,
    F_R1, F_RECOVERIES, F_REINITS, F_SETTLE, F_T, F_U1, F_U2, F_UPREV_OK, F_XM1, G_COLOUR, G_DIVERGED, G_NIS, G_OK,
    G_SENSOR, G_SETTLE, H_A, H_C, H_CLEAR_RUN, H_EXT, H_HAVE_NU, H_LAST_RAW, H_NU_PREV, H_OUT_RUN, H_R1,
    H_R_FLOOR, H_RUN_SAME, H_SIG, H_SIG_NOM, H_STATUS, H_UNIT_RUN, PARAM_STD_CAP, S_CLIPPED, S_MISSING, S_NOISY,
    S_OFFSET, S_OK, S_STUCK, S_UNIT, ST_FROZEN, ST_GAP, ST_GATED, ST_OK, ST_RECOVERED, ST_REINIT, ST_REPAIRED,
    ST_SENSOR, ST_STALE)
from twin.online.ukf_update import _update_into


@nb.njit(cache=True)
def _reinit_states(x, P, z, meas_idx, u, setup, ch, nmod, inflate, p_count):
    """Model states from the measurement (the model's rest otherwise, the state that follows the drive at it),
    prior covariance; parameters kept, inflated."""
    n = x.shape[0]
    q = meas_idx.shape[0]
    scale = setup.scale
    ns = scale.shape[0]
    for i in range(ns):
        x[i] = setup.rest[i] / scale[i]
    if math.isfinite(u) and setup.input_state >= 0:
        x[setup.input_state] = setup.input_gain * u / scale[setup.input_state]
    for j in range(q):
        if math.isfinite(z[j]) and ch[j, H_STATUS] in (S_OK, S_NOISY):
            x[meas_idx[j]] = z[j]
    for j in range(nmod, n):
        x[j] = 0.0
    for i in range(n):
        for j in range(n):
            if i < ns or j < ns or i >= nmod or j >= nmod:
                P[i, j] = 0.0
    for i in range(ns):
        P[i, i] = setup.prior_mod[i] * setup.prior_mod[i]
    for j in range(q):
        P[nmod + j, nmod + j] = ch[j, H_SIG] * ch[j, H_SIG]
    for i in range(ns, nmod):
        for j in range(ns, nmod):
            P[i, j] *= inflate


@nb.njit(cache=True)
def _carry_controller(ctrl, fs, closed, ps, nc):
    """After a prediction driven by the demand: the rig controller's memory moves on to the interval's end."""
    if closed and ps >= 0:
        for j in range(nc):
            ctrl[nc + j] = ctrl[2 * nc + j]
            fs[F_CTRL + j] = ctrl[2 * nc + j]


@nb.njit
def filter_loop(setup, carry, block, closed, ticks, mode, out):
    """Filter the ``T`` samples of ``block`` in place; ``carry`` carries over between calls; returns the index of
    an unrecoverable sample, or -1.

    ``block.U[k]`` the logged drive (NaN if missing), ``block.XREF[k]`` the demand (the drive when ``closed``),
    ``block.Z[k]`` scaled measurements (NaN = missing) of the model states ``setup.mia``, ``block.DT[k]`` seconds
    since the previous sample (NaN for the first sample ever).
    """
    x, P, fs, ch, x_ck, P_ck = carry.x, carry.P, carry.fs, carry.ch, carry.x_ck, carry.P_ck
    U, XREF, Z, DT = block.U, block.XREF, block.Z, block.DT
    mia, dt0, pvec, idx, lo_log, width = setup.mia, setup.dt0, setup.pvec, setup.idx, setup.lo_log, setup.width
    scale, nsub, q_state, q_param = setup.scale, setup.nsub, setup.q_state, setup.q_param
    Wm, Wc, lam, floor, gate, max_gated = setup.Wm, setup.Wc, setup.lam, setup.floor, setup.gate, setup.max_gated
    chan, thresh, tau_excite, fb_col, cfg = setup.chan, setup.thresh, setup.tau_excite, setup.fb_col, setup.cfg
    X_out, Pd_out, nis_out, ll_out, st_out = out.X, out.Pd, out.nis, out.ll, out.status
    innov_out, S_out, frozen_out, guard_out, sens_out = out.innov, out.S, out.frozen, out.guard, out.sensors
    sig_out, used_out = out.noise, out.used
    ns = scale.shape[0]
    nc = fs.shape[0] - F_CTRL
    fb = setup.fb_state
    n = x.shape[0]
    T = U.shape[0]
    q = Z.shape[1]
    p_count = idx.shape[0]
    nmod = ns + p_count
    L = np.zeros((n, n))
    A = np.empty((n, n))
    Q = np.zeros((n, n))
    pw = pvec.copy()
    si = np.empty(ns)
    so = np.empty(ns)
    ctrl = np.zeros(3 * nc)  # controller memory: working, carried from sample to sample, at the interval's end
    fast = lanes_apply(pvec)
    for j in range(nc):
        ctrl[nc + j] = fs[F_CTRL + j]
    sig = np.empty((2 * n + 1, n))
    sf = np.empty((2 * n + 1, n))
    W = np.empty(setup.lane_work)
    S_l = np.empty((setup.lanes, ns))
    TH = np.empty((setup.lanes, p_count))
    rows = np.empty(2 * n + 1, dtype=np.int64)
    sel = np.empty(q, dtype=np.int64)
    WQ = np.empty((4 * q + 1, q))
    WN = np.empty((2 * n, q))
    B = np.empty((n, n))
    freeze = np.zeros(n, dtype=np.bool_)
    innov = np.empty(q)
    Sd = np.empty(q)
    nu = np.empty(q)
    share = np.ones(q)  # the sensor noise's share of each output's innovation variance (noise learning's weight)
    by_share = cfg[C_NSHARE] > 0.0
    central = cfg[C_CENTRAL] > 0.0
    use = np.zeros(q, dtype=np.bool_)
    R = np.empty(q)
    a_pow = np.empty(q)
    wnd = np.empty(4)
    unit_like = np.zeros(q, dtype=np.bool_)
    inn2 = np.empty(q)
    sd2 = np.empty(q)
    EXO, exo_idx = block.EXO, setup.exo_idx
    for k in range(T):
        dtk = DT[k]
        status = ST_OK
        for j in range(exo_idx.shape[0]):  # an exogenous input (the oil's temperature) sets its parameter
            if math.isfinite(EXO[k, j]):
                pw[exo_idx[j]] = EXO[k, j]
        # ---- the drive at this sample
        if closed:
            a_now = XREF[k]
        else:
            a_now = U[k]
        drive_ok = math.isfinite(a_now)
        if not drive_ok:
            a_now = fs[F_U1]
        # ---- excitation and freeze
        for j in range(n):
            freeze[j] = False
        for j in range(p_count):
            c = chan[j]
            if fs[F_EXC0 + c] < thresh[c]:
                freeze[ns + j] = True
            frozen_out[k, j] = freeze[ns + j]
        # ---- predict from the previous sample
        reinit = False
        if fs[F_HAVE_PREV] > 0.0 and math.isfinite(fs[F_U1]):
            if not (dtk > 0.0) or not math.isfinite(dtk):
                dtk = 0.0
            nint = int(dtk / dt0 + 0.5)
            if dtk > cfg[C_GAP_MAX]:
                reinit = True
            elif nint >= 1:
                if nint > 1:
                    status = ST_GAP
                dtk = nint * dt0  # time stamps on the nominal grid: the rest of the step is jitter (twin.record)
                h = dt0
                # process noise over the whole interval: diagonal (its every diagonal entry is set here, and the
                # entries off it stay the zeros Q starts with)
                for i in range(ns):
                    Q[i, i] = q_state[i] * dtk / dt0
                for j in range(p_count):
                    g = 1.0 / max(dlog_dz(x[ns + j], width[j]), 1e-12)
                    add = q_param[j] * dtk * g * g
                    cap = PARAM_STD_CAP * PARAM_STD_CAP * g * g
                    if P[ns + j, ns + j] + add > cap:  # the random walk stops at the cap
                        add = max(0.0, cap - P[ns + j, ns + j])
                    Q[ns + j, ns + j] = add
                for j in range(q):
                    aj = ch[j, H_A] ** nint
                    a_pow[j] = aj
                    Q[nmod + j, nmod + j] = ch[j, H_SIG] * ch[j, H_SIG] * (1.0 - aj * aj)
                ps = ST_OK
                if nint == 1:
                    wnd[0] = fs[F_U2]
                    wnd[1] = fs[F_U1]
                    wnd[2] = a_now
                    wnd[3] = a_now
                    ps = _predict(x, P, wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub,
                                  fs[F_XM1], Q, Wm, Wc, lam, floor, nmod, a_pow, L, A, sig, sf, si, so, ctrl, nc,
                                  fast, W, S_l, TH, rows, central)
                    _carry_controller(ctrl, fs, closed, ps, nc)
                else:  # across a gap: the drive linear from the last sample to this one
                    for j in range(q):
                        a_pow[j] = ch[j, H_A]
                    for i in range(n):
                        Q[i, i] /= nint
                    for s_i in range(nint):
                        f0 = s_i / nint
                        f1 = (s_i + 1) / nint
                        wnd[0] = fs[F_U1] + f0 * (a_now - fs[F_U1])
                        wnd[1] = wnd[0]
                        wnd[2] = fs[F_U1] + f1 * (a_now - fs[F_U1])
                        wnd[3] = wnd[2]
                        xm = fs[F_XM1] if s_i == 0 or fb < 0 else x[fb] * scale[fb]
                        ps = _predict(x, P, wnd, closed, ticks, min(mode, 1), pw, idx, lo_log, width, scale,
                                      h, nsub, xm, Q, Wm, Wc, lam, floor, nmod, a_pow, L, A, sig, sf, si, so, ctrl,
                                      nc, fast, W, S_l, TH, rows, central)
                        _carry_controller(ctrl, fs, closed, ps, nc)
                        if ps < 0:
                            break
                if ps < 0:  # not finite, not repairable: back to the last consistent checkpoint
                    if fs[F_CK_OK] <= 0.0 or not _all_finite(x_ck, P_ck):
                        return k
                    reinit = True
                    fs[F_RECOVERIES] += 1.0
                    for i in range(n):
                        x[i] = x_ck[i]
                        for j in range(n):
                            P[i, j] = P_ck[i, j]
                    status = ST_RECOVERED
                elif ps == ST_REPAIRED:
                    status = ST_REPAIRED
        fs[F_T] += dtk if fs[F_HAVE_PREV] > 0.0 else 0.0
        # ---- measurement noise (white floor) and per-output checks on the raw signal
        for j in range(q):
            R[j] = ch[j, H_R_FLOOR]
            innov[j] = np.nan
            Sd[j] = np.nan
            nu[j] = np.nan
        zk = Z[k]
        any_fault = False
        for j in range(q):
            zj = zk[j]
            st = int(ch[j, H_STATUS])
            unit_like[j] = False
            if not math.isfinite(zj):
                use[j] = False
                continue
            use[j] = st in (S_OK, S_NOISY)
            # physical range (a unit error shows first here)
            zsi = zj * scale[mia[j]]
            if zsi < setup.out_lo[j] or zsi > setup.out_hi[j]:
                use[j] = False
                unit_like[j] = True
            else:
                unit_like[j] = False
            # the largest excursion of the signal from its centre lately (a clip sits at it)
            cen = setup.out_centre[j]
            ch[j, H_EXT] = max(abs(zj - cen), ch[j, H_EXT] * (1.0 - max(dtk, dt0) / 30.0))
            # the same value again: a held value (a signal at its own, slower rate, twin.record.fresh_mask),
            # not a measurement; suspect until it moves
            if zj == ch[j, H_LAST_RAW]:
                ch[j, H_RUN_SAME] += 1.0
            else:
                ch[j, H_RUN_SAME] = 0.0
            ch[j, H_LAST_RAW] = zj
            if ch[j, H_RUN_SAME] >= 1.0:
                use[j] = False
        # ---- re-initialise after a long gap (or after an unrepairable prediction)
        if reinit:
            _reinit_states(x, P, zk, mia, a_now if not closed else np.nan, setup, ch, nmod, cfg[C_INFLATE], p_count)
            if status != ST_RECOVERED:
                status = ST_REINIT
                fs[F_REINITS] += 1.0
            fs[F_SETTLE] = cfg[C_SETTLE_S]
            fs[F_GATED_RUN] = 0.0
        # ---- innovations of every finite output (for the detectors), then the update
        for j in range(q):
            zj = zk[j]
            if not math.isfinite(zj):
                continue
            e = zj - (x[mia[j]] + x[nmod + j])
            s2 = P[mia[j], mia[j]] + 2.0 * P[mia[j], nmod + j] + P[nmod + j, nmod + j] + R[j]
            innov[j] = e
            Sd[j] = s2
            nu[j] = e / math.sqrt(s2) if s2 > 0.0 else np.nan
            if by_share:
                share[j] = min(1.0, max(0.0, (P[nmod + j, nmod + j] + R[j]) / s2)) if s2 > 0.0 else 0.0
        # per-output outliers: this output far off while another agrees with the model, in a filter that
        # was consistent (while it converges, a large innovation on one output is the model's, not the sensor's)
        was_consistent = fs[F_NIS_EMA] < cfg[C_NIS_HI] and fs[F_SETTLE] <= 0.0 and fs[F_T] >= cfg[C_WARM_S]
        for j in range(q):
            if not use[j] or not math.isfinite(nu[j]):
                continue
            if abs(nu[j]) > cfg[C_OUT_NU] and (was_consistent or ch[j, H_OUT_RUN] > 0.0) and \
                    (ch[j, H_C] < 4.0 or ch[j, H_OUT_RUN] > 0.0):
                other_ok = False
                for i in range(q):
                    if i != j and math.isfinite(nu[i]) and abs(nu[i]) < 0.5 * cfg[C_OUT_NU] and \
                            int(ch[i, H_STATUS]) in (S_OK, S_NOISY):
                        other_ok = True
                if other_ok:
                    use[j] = False
                    ch[j, H_OUT_RUN] += 1.0
                    # a power of ten off the prediction: a unit error
                    pred = zk[j] - innov[j]
                    if abs(pred) > 1e-9 and abs(zk[j]) > 0.0:
                        l10 = math.log10(abs(zk[j] / pred))
                        if abs(l10) >= 1.9 and abs(l10 - round(l10)) < 0.1:
                            unit_like[j] = True
                    continue
            ch[j, H_OUT_RUN] = 0.0
        # sensor status transitions
        for j in range(q):
            st = int(ch[j, H_STATUS])
            zj = zk[j]
            if not math.isfinite(zj):
                continue
            ch[j, H_UNIT_RUN] = ch[j, H_UNIT_RUN] + 1.0 if unit_like[j] else 0.0
            run = ch[j, H_RUN_SAME]
            nuj = nu[j]
            if st in (S_OK, S_NOISY):
                centre = setup.out_centre[j]
                at_extreme = abs(zj - centre) >= 0.98 * ch[j, H_EXT]
                if ch[j, H_UNIT_RUN] >= 3.0:
                    st = S_UNIT
                elif ch[j, H_OUT_RUN] >= cfg[C_OFF_N]:
                    st = S_OFFSET
                elif run >= 2.0 and at_extreme and math.isfinite(nuj) and abs(nuj) > 4.0 and \
                        (zj - centre) * (-innov[j]) > 0.0:
                    st = S_CLIPPED  # held at its extreme while the model goes beyond it
                elif run >= cfg[C_STUCK_N] and math.isfinite(nuj) and abs(nuj) > 2.0:
                    st = S_STUCK
                if st != S_NOISY and st != S_OK:
                    ch[j, H_CLEAR_RUN] = 0.0
                    use[j] = False
            else:
                use[j] = False
                fine = run < 1.0 and math.isfinite(nuj) and abs(nuj) < 3.0 and not unit_like[j]
                ch[j, H_CLEAR_RUN] = ch[j, H_CLEAR_RUN] + 1.0 if fine else 0.0
                if ch[j, H_CLEAR_RUN] >= cfg[C_CLEAR_N]:
                    st = S_OK
                    ch[j, H_OUT_RUN] = 0.0
            if st in (S_OK, S_NOISY):
                st = S_NOISY if ch[j, H_SIG] > cfg[C_NOISY] * ch[j, H_SIG_NOM] else (
                    S_OK if ch[j, H_SIG] < 0.7 * cfg[C_NOISY] * ch[j, H_SIG_NOM] else st)
            ch[j, H_STATUS] = st
            if st != S_OK:  # a faulty or noisy sensor: the drift test holds
                any_fault = True
        # the update
        us = ST_STALE
        nis = np.nan
        ll = np.nan
        if not reinit:
            g = gate if fs[F_GATED_RUN] < max_gated else np.inf
            us, nis, ll, m = _update_into(x, P, zk, mia, nmod, R, use, freeze, g, inn2, sd2, sel, WQ, WN, B)
            fs[F_GATED_RUN] = fs[F_GATED_RUN] + 1.0 if us == ST_GATED else 0.0
            # ---- noise learning and the consistency guard on the normalised innovations
            w_n = min(1.0, max(dtk, dt0) / cfg[C_TAU_NOISE])
            for j in range(q):
                if not use[j] or not math.isfinite(nu[j]):
                    continue
                # noise_share: an innovation tells of the sensor's noise in proportion to that noise's share of its
                # variance (while the model's own uncertainty dominates, a small innovation says the prior was
                # wide, not that the sensor is quiet); off: every innovation counts fully
                wj = w_n * share[j]
                v2 = min(nu[j] * nu[j], 100.0)
                ch[j, H_C] += wj * (v2 - ch[j, H_C])
                if ch[j, H_HAVE_NU] > 0.0:
                    r1 = max(-10.0, min(10.0, nu[j] * ch[j, H_NU_PREV]))
                    ch[j, H_R1] += wj * (r1 - ch[j, H_R1])
                ch[j, H_NU_PREV] = nu[j]
                ch[j, H_HAVE_NU] = 1.0
                if cfg[C_ADAPT] > 0.0 and fs[F_SETTLE] <= 0.0:
                    cj = max(ch[j, H_C], 1e-3)
                    sg = ch[j, H_SIG] * math.exp(0.5 * wj * math.log(min(max(cj, 0.25), 4.0)))
                    ch[j, H_SIG] = min(max(sg, cfg[C_SIG_LO] * ch[j, H_SIG_NOM]), cfg[C_SIG_HI] * ch[j, H_SIG_NOM])
                    rho = ch[j, H_R1] / cj
                    ch[j, H_A] = min(max(ch[j, H_A] + 2.0 * wj * rho, 0.0), cfg[C_A_MAX])
            if m > 0 and math.isfinite(nis):
                w_g = min(1.0, max(dtk, dt0) / cfg[C_TAU_GUARD])
                w_d = min(1.0, max(dtk, dt0) / cfg[C_TAU_DIV])
                fs[F_NIS_EMA] += w_g * (min(nis / m, cfg[C_NIS_CLIP]) - fs[F_NIS_EMA])
                fs[F_NIS_FAST] += w_d * (min(nis / m, 1e4) - fs[F_NIS_FAST])
        # ---- divergence: enormous innovations for a while, a parameter pinned at a bound, or not finite
        bad = False
        for i in range(n):
            if not math.isfinite(x[i]):
                bad = True
        for j in range(p_count):
            if abs(x[ns + j]) > cfg[C_ZPIN]:
                bad = True
        if fs[F_NIS_FAST] > cfg[C_DIV_NIS]:
            bad = True
        gcode = G_OK
        if bad:
            if fs[F_CK_OK] <= 0.0 or not _all_finite(x_ck, P_ck):
                return k
            for i in range(n):
                x[i] = x_ck[i]
                for j in range(n):
                    P[i, j] = P_ck[i, j]
            _reinit_states(x, P, zk, mia, a_now if not closed else np.nan, setup, ch, nmod, cfg[C_INFLATE], p_count)
            fs[F_RECOVERIES] += 1.0
            fs[F_SETTLE] = cfg[C_SETTLE_S]
            fs[F_NIS_EMA] = 1.0
            fs[F_NIS_FAST] = 1.0
            fs[F_GATED_RUN] = 0.0
            status = ST_RECOVERED
            gcode = G_DIVERGED
        # ---- guard code for the drift test
        if gcode == G_OK:
            if any_fault:
                gcode = G_SENSOR
            elif fs[F_SETTLE] > 0.0 or fs[F_T] < cfg[C_WARM_S]:
                gcode = G_SETTLE
            elif fs[F_NIS_EMA] > cfg[C_NIS_HI]:
                gcode = G_NIS
            else:
                for j in range(q):
                    cj = ch[j, H_C]
                    if cj > 0.0 and abs(ch[j, H_R1] / cj) > cfg[C_RHO_HI]:
                        gcode = G_COLOUR
        if fs[F_SETTLE] > 0.0:
            fs[F_SETTLE] -= max(dtk, dt0)
        # ---- checkpoint once the filter has been consistent for ck_s without a break
        if gcode != G_OK:
            fs[F_CK_T] = fs[F_T]
        elif fs[F_T] - fs[F_CK_T] >= cfg[C_CK_S]:
            for i in range(n):
                x_ck[i] = x[i]
                for j in range(n):
                    P_ck[i, j] = P[i, j]
            fs[F_CK_T] = fs[F_T]
            fs[F_CK_OK] = 1.0
        # ---- status and outputs
        if status == ST_OK:
            if us in (ST_GATED, ST_STALE):
                status = us
            elif us == ST_FROZEN:
                status = ST_FROZEN
        if any_fault and status in (ST_OK, ST_FROZEN, ST_GATED):
            for j in range(q):
                if int(ch[j, H_STATUS]) not in (S_OK, S_NOISY):
                    status = ST_SENSOR
        if not drive_ok and status in (ST_OK, ST_GATED, ST_FROZEN, ST_GAP):
            status = ST_STALE
        for i in range(n):
            X_out[k, i] = x[i]
            Pd_out[k, i] = P[i, i]
        for j in range(q):
            innov_out[k, j] = innov[j]
            S_out[k, j] = Sd[j]
            sens_out[k, j] = int(ch[j, H_STATUS]) if math.isfinite(zk[j]) else S_MISSING
            sig_out[k, j] = ch[j, H_SIG]
            used_out[k, j] = use[j] and not reinit
        nis_out[k] = nis
        ll_out[k] = ll
        st_out[k] = status
        guard_out[k] = gcode
        # ---- this sample's drive and measurement feed the next prediction
        if fb_col >= 0 and math.isfinite(zk[fb_col]) and use[fb_col]:
            fs[F_XM1] = zk[fb_col] * scale[fb]
        elif fb >= 0:
            fs[F_XM1] = x[fb] * scale[fb]
        u_exc = U[k] if math.isfinite(U[k]) else (setup.demand_gain * (XREF[k] - fs[F_XM1]) if closed else fs[F_U1])
        du = abs(u_exc - fs[F_R1]) / max(dtk, dt0) if fs[F_UPREV_OK] > 0.0 and math.isfinite(u_exc) else 0.0
        alpha = min(1.0, max(dtk, dt0) / tau_excite)
        e0 = 0.0
        e2 = 0.0
        for i in range(ns):  # the model's excitation channels: rod motion, (the drive's rate,) a load
            e0 += setup.excitation[0, i] * (x[i] * scale[i])
            e2 += setup.excitation[2, i] * (x[i] * scale[i])
        fs[F_EXC0] += alpha * (abs(e0) - fs[F_EXC0])
        fs[F_EXC1] += alpha * (du - fs[F_EXC1])
        fs[F_EXC2] += alpha * (abs(e2) - fs[F_EXC2])
        if math.isfinite(u_exc):
            fs[F_R1] = u_exc
            fs[F_UPREV_OK] = 1.0
        fs[F_U2] = fs[F_U1] if math.isfinite(fs[F_U1]) else a_now
        fs[F_U1] = a_now
        fs[F_HAVE_PREV] = 1.0
    return -1
