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

from twin.online.ukf_linalg import NO_REFCOUNT, _all_finite, dlog_dz
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

# The stages below take arrays and numbers, never the kernel's records: a record handed to a compiled function is
# reference-counted member by member at each call, inlined or not (measured: passing Setup and the scratch arrays
# as records to the stages cost 0.6-1 us a sample).  filter_loop reads the records once per block.  The loop itself
# (_filter_loop) and the prediction and update it calls are compiled without numba's reference counting
# (``NO_REFCOUNT``): they allocate nothing (filter_loop allocates the block's work arrays before), and every array
# an inlined stage or a call names was otherwise counted in and out with an atomic operation, sample by sample
# (measured: a quarter of a two-state model's kernel time in numba's NRT_incref/NRT_decref).


@nb.njit
def _work(n, ns, q, p_count, nc, lanes, lane_work):
    """Fresh scratch arrays for one block: ``L, A, Q, B`` [n, n] (the sigma points' factor, its argument, the
    process noise, the update's work); ``si, so`` [ns] (one state in and out of the model, SI); ``ctrl`` [3 nc]
    (controller memory: working, carried from sample to sample, at the interval's end); ``sig, sf`` [2n + 1, n]
    (the sigma points and their predictions); ``W, S_l, TH`` (the model's side-by-side lanes); ``rows`` (the sigma
    points that move the model); ``sel, WQ, WN, inn2, sd2`` (the update's work); ``freeze`` [n] (a parameter
    without excitation is not updated); ``innov, Sd, nu, share, use, R, a_pow, unit_like`` [q] (each output's
    innovation, its variance, normalised, the sensor noise's share of it, read by the update, the white floor of
    its noise, its noise state's AR power over the interval, a reading off by a power of ten or out of range);
    ``wnd`` [4] (the drive at samples k-2, k-1, k, k)."""
    return (np.zeros((n, n)), np.empty((n, n)), np.zeros((n, n)), np.empty((n, n)), np.empty(ns), np.empty(ns),
            np.zeros(3 * nc), np.empty((2 * n + 1, n)), np.empty((2 * n + 1, n)), np.empty(lane_work),
            np.empty((lanes, ns)), np.empty((lanes, p_count)), np.empty(2 * n + 1, dtype=np.int64),
            np.empty(q, dtype=np.int64), np.empty((4 * q + 1, q)), np.empty((2 * n, q)), np.empty(q), np.empty(q),
            np.zeros(n, dtype=np.bool_), np.empty(q), np.empty(q), np.empty(q), np.ones(q),
            np.zeros(q, dtype=np.bool_), np.empty(q), np.empty(q), np.zeros(q, dtype=np.bool_), np.empty(4))


@nb.njit(inline="always")
def _freeze_flags(fs, chan, thresh, freeze, frozen_out, k, ns):
    """A parameter whose excitation channel is below its threshold is frozen (not updated) at this sample."""
    for j in range(freeze.shape[0]):
        freeze[j] = False
    for j in range(chan.shape[0]):
        c = chan[j]
        if fs[F_EXC0 + c] < thresh[c]:
            freeze[ns + j] = True
        frozen_out[k, j] = freeze[ns + j]


@nb.njit(inline="always")
def _interval(fs, dtk, dt0, gap_max):
    """The interval to this sample on the nominal grid (time stamps off it by jitter, twin.record): its log periods
    (0: no prediction, the first sample or a long gap) and seconds, and whether the states are re-initialised (a
    gap longer than ``gap_max``)."""
    if not (fs[F_HAVE_PREV] > 0.0 and math.isfinite(fs[F_U1])):
        return 0, dtk, False
    if not (dtk > 0.0) or not math.isfinite(dtk):
        dtk = 0.0
    nint = int(dtk / dt0 + 0.5)
    if dtk > gap_max:
        return 0, dtk, True
    if nint >= 1:
        dtk = nint * dt0
    return nint, dtk, False


@nb.njit(inline="always")
def _process_noise(x, P, ch, Q, a_pow, q_state, q_param, width, dt0, dtk, nint, ns, nmod):
    """The process noise over an interval of ``dtk`` s (``nint`` log periods): diagonal (its every diagonal entry
    is set here, the entries off it stay the zeros ``Q`` starts with); each noise state's AR power over it."""
    for i in range(ns):
        Q[i, i] = q_state[i] * dtk / dt0
    for j in range(q_param.shape[0]):
        g = 1.0 / max(dlog_dz(x[ns + j], width[j]), 1e-12)
        add = q_param[j] * dtk * g * g
        cap = PARAM_STD_CAP * PARAM_STD_CAP * g * g
        if P[ns + j, ns + j] + add > cap:  # the random walk stops at the cap
            add = max(0.0, cap - P[ns + j, ns + j])
        Q[ns + j, ns + j] = add
    for j in range(ch.shape[0]):
        aj = ch[j, H_A] ** nint
        a_pow[j] = aj
        Q[nmod + j, nmod + j] = ch[j, H_SIG] * ch[j, H_SIG] * (1.0 - aj * aj)


@nb.njit(inline="always")
def _gap_window(wnd, fs, a_now, s_i, nint):
    """The drive across one period of a gap: linear from the last sample to this one."""
    f0 = s_i / nint
    f1 = (s_i + 1) / nint
    wnd[0] = fs[F_U1] + f0 * (a_now - fs[F_U1])
    wnd[1] = wnd[0]
    wnd[2] = fs[F_U1] + f1 * (a_now - fs[F_U1])
    wnd[3] = wnd[2]


@nb.njit(inline="always")
def _restore(x, P, x_ck, P_ck):
    """Back to the last consistent checkpoint; False when there is none."""
    if not _all_finite(x_ck, P_ck):
        return False
    n = x.shape[0]
    for i in range(n):
        x[i] = x_ck[i]
        for j in range(n):
            P[i, j] = P_ck[i, j]
    return True


@nb.njit(inline="always")
def _raw_checks(zk, ch, mia, scale, out_lo, out_hi, out_centre, R, innov, Sd, nu, use, unit_like, dtk, dt0):
    """Each output's white noise floor, and the checks on its raw value: missing, out of its physical range (a
    unit error shows first there), the largest excursion from its centre lately (a clip sits at it), the same value
    again (a held value of a signal at its own, slower rate, twin.record.fresh_mask: suspect until it moves)."""
    for j in range(zk.shape[0]):
        R[j] = ch[j, H_R_FLOOR]
        innov[j] = np.nan
        Sd[j] = np.nan
        nu[j] = np.nan
    for j in range(zk.shape[0]):
        zj = zk[j]
        st = int(ch[j, H_STATUS])
        unit_like[j] = False
        if not math.isfinite(zj):
            use[j] = False
            continue
        use[j] = st in (S_OK, S_NOISY)
        zsi = zj * scale[mia[j]]
        if zsi < out_lo[j] or zsi > out_hi[j]:
            use[j] = False
            unit_like[j] = True
        cen = out_centre[j]
        ch[j, H_EXT] = max(abs(zj - cen), ch[j, H_EXT] * (1.0 - max(dtk, dt0) / 30.0))
        if zj == ch[j, H_LAST_RAW]:
            ch[j, H_RUN_SAME] += 1.0
        else:
            ch[j, H_RUN_SAME] = 0.0
        ch[j, H_LAST_RAW] = zj
        if ch[j, H_RUN_SAME] >= 1.0:
            use[j] = False


@nb.njit(inline="always")
def _innovations(zk, x, P, mia, nmod, R, innov, Sd, nu, share, by_share):
    """The innovation of every finite output, its variance and its normalised value (for the detectors), and the
    sensor noise's share of that variance."""
    for j in range(zk.shape[0]):
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


@nb.njit(inline="always")
def _outliers(zk, fs, ch, cfg, innov, nu, use, unit_like):
    """Per-output outliers: this output far off while another agrees with the model, in a filter that was
    consistent (while it converges, a large innovation on one output is the model's, not the sensor's); a power of
    ten off the prediction is a unit error."""
    q = zk.shape[0]
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
                pred = zk[j] - innov[j]
                if abs(pred) > 1e-9 and abs(zk[j]) > 0.0:
                    l10 = math.log10(abs(zk[j] / pred))
                    if abs(l10) >= 1.9 and abs(l10 - round(l10)) < 0.1:
                        unit_like[j] = True
                continue
        ch[j, H_OUT_RUN] = 0.0


@nb.njit(inline="always")
def _sensor_status(zk, ch, cfg, out_centre, innov, nu, use, unit_like):
    """Each sensor's status moves on (unit, offset, clipped, stuck, noisy, back to ok); returns whether any is
    faulty or noisy (the drift test then holds)."""
    any_fault = False
    for j in range(zk.shape[0]):
        st = int(ch[j, H_STATUS])
        zj = zk[j]
        if not math.isfinite(zj):
            continue
        ch[j, H_UNIT_RUN] = ch[j, H_UNIT_RUN] + 1.0 if unit_like[j] else 0.0
        run = ch[j, H_RUN_SAME]
        nuj = nu[j]
        if st in (S_OK, S_NOISY):
            centre = out_centre[j]
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
        if st != S_OK:
            any_fault = True
    return any_fault


@nb.njit(inline="always")
def _learn_noise(fs, ch, cfg, nu, share, use, dtk, dt0, nis, m):
    """Noise learning on the normalised innovations and the consistency guard's averages of the NIS.

    noise_share: an innovation tells of the sensor's noise in proportion to that noise's share of its variance
    (while the model's own uncertainty dominates, a small innovation says the prior was wide, not that the sensor
    is quiet); off: every innovation counts fully."""
    w_n = min(1.0, max(dtk, dt0) / cfg[C_TAU_NOISE])
    for j in range(nu.shape[0]):
        if not use[j] or not math.isfinite(nu[j]):
            continue
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


@nb.njit(inline="always")
def _diverged(x, fs, cfg, ns, p_count):
    """Divergence: enormous innovations for a while, a parameter pinned at a bound, or a state not finite."""
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]):
            return True
    for j in range(p_count):
        if abs(x[ns + j]) > cfg[C_ZPIN]:
            return True
    return fs[F_NIS_FAST] > cfg[C_DIV_NIS]


@nb.njit(inline="always")
def _guard_code(any_fault, fs, ch, cfg):
    """Why the drift test holds at this sample (G_OK: it does not)."""
    if any_fault:
        return G_SENSOR
    if fs[F_SETTLE] > 0.0 or fs[F_T] < cfg[C_WARM_S]:
        return G_SETTLE
    if fs[F_NIS_EMA] > cfg[C_NIS_HI]:
        return G_NIS
    gcode = G_OK
    for j in range(ch.shape[0]):
        cj = ch[j, H_C]
        if cj > 0.0 and abs(ch[j, H_R1] / cj) > cfg[C_RHO_HI]:
            gcode = G_COLOUR
    return gcode


@nb.njit(inline="always")
def _checkpoint(gcode, fs, cfg, x, P, x_ck, P_ck):
    """A checkpoint once the filter has been consistent for ``ck_s`` without a break."""
    if gcode != G_OK:
        fs[F_CK_T] = fs[F_T]
    elif fs[F_T] - fs[F_CK_T] >= cfg[C_CK_S]:
        n = x.shape[0]
        for i in range(n):
            x_ck[i] = x[i]
            for j in range(n):
                P_ck[i, j] = P[i, j]
        fs[F_CK_T] = fs[F_T]
        fs[F_CK_OK] = 1.0


@nb.njit(inline="always")
def _sample_status(status, us, any_fault, drive_ok, ch):
    """The sample's status: the prediction's, else the update's; a faulty sensor; a missing drive."""
    if status == ST_OK:
        if us in (ST_GATED, ST_STALE):
            status = us
        elif us == ST_FROZEN:
            status = ST_FROZEN
    if any_fault and status in (ST_OK, ST_FROZEN, ST_GATED):
        for j in range(ch.shape[0]):
            if int(ch[j, H_STATUS]) not in (S_OK, S_NOISY):
                status = ST_SENSOR
    if not drive_ok and status in (ST_OK, ST_GATED, ST_FROZEN, ST_GAP):
        status = ST_STALE
    return status


@nb.njit(inline="always")
def _write_out(k, x, P, ch, zk, innov, Sd, use, reinit, X_out, Pd_out, innov_out, S_out, sens_out, sig_out,
               used_out):
    """This sample's states, variances and per-output outputs."""
    for i in range(x.shape[0]):
        X_out[k, i] = x[i]
        Pd_out[k, i] = P[i, i]
    for j in range(zk.shape[0]):
        innov_out[k, j] = innov[j]
        S_out[k, j] = Sd[j]
        sens_out[k, j] = int(ch[j, H_STATUS]) if math.isfinite(zk[j]) else S_MISSING
        sig_out[k, j] = ch[j, H_SIG]
        used_out[k, j] = use[j] and not reinit


@nb.njit(inline="always")
def _feed_next(u_k, xref_k, zk, a_now, dtk, dt0, closed, fs, x, use, scale, fb, fb_col, demand_gain, excitation,
               tau_excite):
    """This sample's drive and measurement feed the next prediction: the measured output the controller reads,
    the excitation averages (rod motion, the drive's rate, a load), the drive window."""
    if fb_col >= 0 and math.isfinite(zk[fb_col]) and use[fb_col]:
        fs[F_XM1] = zk[fb_col] * scale[fb]
    elif fb >= 0:
        fs[F_XM1] = x[fb] * scale[fb]
    u_exc = u_k if math.isfinite(u_k) else (demand_gain * (xref_k - fs[F_XM1]) if closed else fs[F_U1])
    du = abs(u_exc - fs[F_R1]) / max(dtk, dt0) if fs[F_UPREV_OK] > 0.0 and math.isfinite(u_exc) else 0.0
    alpha = min(1.0, max(dtk, dt0) / tau_excite)
    e0 = 0.0
    e2 = 0.0
    for i in range(scale.shape[0]):
        e0 += excitation[0, i] * (x[i] * scale[i])
        e2 += excitation[2, i] * (x[i] * scale[i])
    fs[F_EXC0] += alpha * (abs(e0) - fs[F_EXC0])
    fs[F_EXC1] += alpha * (du - fs[F_EXC1])
    fs[F_EXC2] += alpha * (abs(e2) - fs[F_EXC2])
    if math.isfinite(u_exc):
        fs[F_R1] = u_exc
        fs[F_UPREV_OK] = 1.0
    fs[F_U2] = fs[F_U1] if math.isfinite(fs[F_U1]) else a_now
    fs[F_U1] = a_now
    fs[F_HAVE_PREV] = 1.0


@nb.njit(inline="always")
def _step_window(wnd, fs, a_now):
    """The drive around one log interval: the samples k-2 and k-1, this one repeated (the next is not known)."""
    wnd[0] = fs[F_U2]
    wnd[1] = fs[F_U1]
    wnd[2] = a_now
    wnd[3] = a_now


@nb.njit
def _predict_gap(x, P, fs, ch, wnd, a_now, nint, closed, ticks, mode, pw, idx, lo_log, width, scale, dt0, nsub, Q,
                 Wm, Wc, lam, floor, nmod, a_pow, L, A, sig, sf, si, so, ctrl, nc, fast, W, S_l, TH, rows, central, fb):
    """Predict across a gap of ``nint`` log periods, one step per period with the drive linear from the last sample
    to this one (the process noise ``Q`` over the whole gap, shared out); returns the last step's status (< 0:
    lost)."""
    for j in range(ch.shape[0]):
        a_pow[j] = ch[j, H_A]
    for i in range(x.shape[0]):
        Q[i, i] /= nint
    ps = ST_OK
    for s_i in range(nint):
        _gap_window(wnd, fs, a_now, s_i, nint)
        xm = fs[F_XM1] if s_i == 0 or fb < 0 else x[fb] * scale[fb]
        ps = _predict(x, P, wnd, closed, ticks, min(mode, 1), pw, idx, lo_log, width, scale, dt0, nsub, xm, Q, Wm,
                      Wc, lam, floor, nmod, a_pow, L, A, sig, sf, si, so, ctrl, nc, fast, W, S_l, TH, rows, central)
        _carry_controller(ctrl, fs, closed, ps, nc)
        if ps < 0:
            break
    return ps


@nb.njit(inline="always")
def _restart(x, P, zk, mia, a_now, closed, setup, ch, fs, nmod, cfg, p_count):
    """The model states re-initialised from the measurement (the parameters kept, their covariance inflated); the
    filter settles before its drift test counts again."""
    _reinit_states(x, P, zk, mia, a_now if not closed else np.nan, setup, ch, nmod, cfg[C_INFLATE], p_count)
    fs[F_SETTLE] = cfg[C_SETTLE_S]
    fs[F_GATED_RUN] = 0.0


@nb.njit(inline="always")
def _exogenous(EXO, k, exo_idx, pw):
    """An exogenous input (the oil's temperature) sets its parameter while it is fresh."""
    for j in range(exo_idx.shape[0]):
        if math.isfinite(EXO[k, j]):
            pw[exo_idx[j]] = EXO[k, j]


@nb.njit(inline="always")
def _drive(u_k, xref_k, closed, fs):
    """The drive at this sample (the demand in closed loop) and whether it was logged; the last one if not."""
    a_now = xref_k if closed else u_k
    if math.isfinite(a_now):
        return a_now, True
    return fs[F_U1], False


@nb.njit(inline="always")
def _recover(x, P, x_ck, P_ck, zk, mia, a_now, closed, setup, ch, fs, nmod, cfg, p_count):
    """After a divergence: back to the last consistent checkpoint, the states re-initialised, the guard's averages
    reset; False when there is no checkpoint (the filter is lost)."""
    if fs[F_CK_OK] <= 0.0 or not _restore(x, P, x_ck, P_ck):
        return False
    _restart(x, P, zk, mia, a_now, closed, setup, ch, fs, nmod, cfg, p_count)
    fs[F_RECOVERIES] += 1.0
    fs[F_NIS_EMA] = 1.0
    fs[F_NIS_FAST] = 1.0
    return True


@nb.njit
def filter_loop(setup, carry, block, closed, ticks, mode, out):
    """Filter the ``T`` samples of ``block`` in place (:func:`_filter_loop`, in fresh work arrays)."""
    ns, nc, n, q, p_count = setup.scale.shape[0], carry.fs.shape[0] - F_CTRL, carry.x.shape[0], block.Z.shape[1], \
        setup.idx.shape[0]
    work = _work(n, ns, q, p_count, nc, setup.lanes, setup.lane_work)
    return _filter_loop(setup, carry, block, closed, ticks, mode, out, work, setup.pvec.copy(),
                        lanes_apply(setup.pvec))


@nb.njit(**NO_REFCOUNT)
def _filter_loop(setup, carry, block, closed, ticks, mode, out, work, pw, fast):
    """Filter the ``T`` samples of ``block`` in place; ``carry`` carries over between calls; returns the index of
    an unrecoverable sample, or -1.

    ``block.U[k]`` the logged drive (NaN if missing), ``block.XREF[k]`` the demand (the drive when ``closed``),
    ``block.Z[k]`` scaled measurements (NaN = missing) of the model states ``setup.mia``, ``block.DT[k]`` seconds
    since the previous sample (NaN for the first sample ever).  Per sample, in this order: the exogenous inputs,
    the drive, the frozen parameters, the prediction, the raw checks, a re-initialisation, the innovations, the
    outliers, the sensors' status, the update and noise learning, divergence and recovery, the guard, the
    checkpoint, the outputs, and what feeds the next prediction.
    """
    x, P, fs, ch, x_ck, P_ck = carry.x, carry.P, carry.fs, carry.ch, carry.x_ck, carry.P_ck
    U, XREF, Z, DT, EXO = block.U, block.XREF, block.Z, block.DT, block.EXO
    mia, dt0, idx, lo_log, width, scale = setup.mia, setup.dt0, setup.idx, setup.lo_log, setup.width, setup.scale
    nsub, q_state, q_param, Wm, Wc, lam = setup.nsub, setup.q_state, setup.q_param, setup.Wm, setup.Wc, setup.lam
    floor, chan, thresh, cfg, fb, fb_col = setup.floor, setup.chan, setup.thresh, setup.cfg, setup.fb_state, setup.fb_col
    out_lo, out_hi, out_centre, exo_idx = setup.out_lo, setup.out_hi, setup.out_centre, setup.exo_idx
    gate, max_gated, demand_gain, excitation = setup.gate, setup.max_gated, setup.demand_gain, setup.excitation
    tau_excite = setup.tau_excite
    X_out, Pd_out, nis_out, ll_out, st_out, innov_out = out.X, out.Pd, out.nis, out.ll, out.status, out.innov
    S_out, frozen_out, guard_out, sens_out, sig_out, used_out = out.S, out.frozen, out.guard, out.sensors, out.noise, \
        out.used
    ns, nc, p_count = scale.shape[0], fs.shape[0] - F_CTRL, idx.shape[0]
    nmod = ns + p_count
    (L, A, Q, B, si, so, ctrl, sig, sf, W, S_l, TH, rows, sel, WQ, WN, inn2, sd2, freeze, innov, Sd, nu, share, use,
     R, a_pow, unit_like, wnd) = work
    for j in range(nc):
        ctrl[nc + j] = fs[F_CTRL + j]
    by_share, central = cfg[C_NSHARE] > 0.0, cfg[C_CENTRAL] > 0.0
    for k in range(U.shape[0]):
        _exogenous(EXO, k, exo_idx, pw)
        a_now, drive_ok = _drive(U[k], XREF[k], closed, fs)
        _freeze_flags(fs, chan, thresh, freeze, frozen_out, k, ns)
        nint, dtk, reinit = _interval(fs, DT[k], dt0, cfg[C_GAP_MAX])
        status = ST_GAP if nint > 1 else ST_OK
        if nint >= 1:
            _process_noise(x, P, ch, Q, a_pow, q_state, q_param, width, dt0, dtk, nint, ns, nmod)
            if nint == 1:
                _step_window(wnd, fs, a_now)
                ps = _predict(x, P, wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, dt0, nsub, fs[F_XM1], Q,
                              Wm, Wc, lam, floor, nmod, a_pow, L, A, sig, sf, si, so, ctrl, nc, fast, W, S_l, TH, rows,
                              central)
                _carry_controller(ctrl, fs, closed, ps, nc)
            else:
                ps = _predict_gap(x, P, fs, ch, wnd, a_now, nint, closed, ticks, mode, pw, idx, lo_log, width, scale,
                                  dt0, nsub, Q, Wm, Wc, lam, floor, nmod, a_pow, L, A, sig, sf, si, so, ctrl, nc, fast,
                                  W, S_l, TH, rows, central, fb)
            if ps < 0:  # not finite, not repairable: back to the last consistent checkpoint
                if fs[F_CK_OK] <= 0.0 or not _restore(x, P, x_ck, P_ck):
                    return k
                reinit, status = True, ST_RECOVERED
                fs[F_RECOVERIES] += 1.0
            elif ps == ST_REPAIRED:
                status = ST_REPAIRED
        fs[F_T] += dtk if fs[F_HAVE_PREV] > 0.0 else 0.0
        zk = Z[k]
        _raw_checks(zk, ch, mia, scale, out_lo, out_hi, out_centre, R, innov, Sd, nu, use, unit_like, dtk, dt0)
        if reinit:  # after a long gap (or after an unrepairable prediction)
            _restart(x, P, zk, mia, a_now, closed, setup, ch, fs, nmod, cfg, p_count)
            if status != ST_RECOVERED:
                status = ST_REINIT
                fs[F_REINITS] += 1.0
        _innovations(zk, x, P, mia, nmod, R, innov, Sd, nu, share, by_share)
        _outliers(zk, fs, ch, cfg, innov, nu, use, unit_like)
        any_fault = _sensor_status(zk, ch, cfg, out_centre, innov, nu, use, unit_like)
        us, nis, ll = ST_STALE, np.nan, np.nan
        if not reinit:
            g = gate if fs[F_GATED_RUN] < max_gated else np.inf
            us, nis, ll, m = _update_into(x, P, zk, mia, nmod, R, use, freeze, g, inn2, sd2, sel, WQ, WN, B)
            fs[F_GATED_RUN] = fs[F_GATED_RUN] + 1.0 if us == ST_GATED else 0.0
            _learn_noise(fs, ch, cfg, nu, share, use, dtk, dt0, nis, m)
        if _diverged(x, fs, cfg, ns, p_count):
            if not _recover(x, P, x_ck, P_ck, zk, mia, a_now, closed, setup, ch, fs, nmod, cfg, p_count):
                return k
            status, gcode = ST_RECOVERED, G_DIVERGED
        else:
            gcode = _guard_code(any_fault, fs, ch, cfg)
        if fs[F_SETTLE] > 0.0:
            fs[F_SETTLE] -= max(dtk, dt0)
        _checkpoint(gcode, fs, cfg, x, P, x_ck, P_ck)
        _write_out(k, x, P, ch, zk, innov, Sd, use, reinit, X_out, Pd_out, innov_out, S_out, sens_out, sig_out,
                   used_out)
        nis_out[k], ll_out[k], guard_out[k] = nis, ll, gcode
        st_out[k] = _sample_status(status, us, any_fault, drive_ok, ch)
        _feed_next(U[k], XREF[k], zk, a_now, dtk, dt0, closed, fs, x, use, scale, fb, fb_col, demand_gain,
                   excitation, tau_excite)
    return -1
