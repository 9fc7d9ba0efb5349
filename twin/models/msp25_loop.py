"""The MSP25's loop, compiled: the industrial PID (:func:`pid_tick`), one log interval under any loop timing
(:func:`advance`: a digital controller at the log's rate or ``N`` times faster, or a continuous one; logged
inputs held, linear or cubic between samples), the simulation of many parameter vectors
(:func:`simulate_kernel`) and the pressure transducers' lag (:func:`sensor_lag`).

The right-hand side it integrates is :mod:`twin.models.msp25_rhs`; the kernel vector's layout
:mod:`twin.models.msp25_params`.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from twin.models import base as _base_src
from twin.models import intersample as _intersample_src
from twin.models import msp25_params as _params_src
from twin.models import msp25_rhs as _rhs_src
from twin.models.intersample import input_at, slope_at
from twin.models.jitcache import keep_fresh
from twin.models.msp25_params import (
    I_A, I_AB, I_CSUP, I_DMEAS, I_KD, I_KDP, I_KFF, I_KI, I_KP, I_KXM, I_PAOFF, I_PBOFF, I_TAUX, I_TF, I_UMAX, NS,
)
from twin.models.msp25_rhs import (
    deriv_line, line_advance, line_pieces, rk4_combine, step, step_line, store6,
)

# the machine code cached for this module inlines these modules' compiled code and constants
keep_fresh(__file__, _rhs_src.__file__, _params_src.__file__, _intersample_src.__file__, _base_src.__file__)


@nb.njit(cache=True)
def _delayed(hist, k, tau, dt):
    """Linear interpolation of the sampled history ``hist[:k+1]`` at ``t_k - tau``."""
    if tau <= 0.0:
        return hist[k]
    d = tau / dt
    j = int(d)
    f = d - j
    i0 = k - j
    if i0 <= 0:
        return hist[0]
    return (1.0 - f) * hist[i0] + f * hist[i0 - 1]


#: controller memory entries: integral of the error, previous error, started flag, derivative filter state (the
#: filtered derivative of a digital controller, the filtered signal of a continuous one), previous measurement
N_CTRL = 5
#: the supply line's memory after the controller's (port sag [Pa], hose flow [m^3/s]; effect ``supply_dynamics``):
#: a simulation's memory has ``N_CTRL + N_LINE`` entries; the online filter's has ``N_CTRL`` and refuses the effect
N_LINE = 2


@nb.njit(cache=True)
def _shape_output(u, rdot, pa, pb, p):
    """The PID output ``u`` with velocity feed-forward of the demand's rate ``rdot``, pressure feedback of the
    measured ``pa``, ``pb`` (the load pressure pA - pB AB/A) and the output limit."""
    if p[I_KFF] != 0.0:
        u = u + p[I_KFF] * rdot
    if p[I_KDP] != 0.0:
        ratio = p[I_AB] / p[I_A] if p[I_AB] > 0.0 else 1.0
        u = u - p[I_KDP] * (pa - pb * ratio)
    um = p[I_UMAX]
    if u > um:
        u = um
    elif u < -um:
        u = -um
    return u


@nb.njit(cache=True)
def pid_tick(r, rdot, xm, pa, pb, h, p, ctrl):
    """One tick of the digital controller (period ``h``): output ``u`` [V] from the demand ``r``, its rate
    ``rdot``, the measured displacement ``xm`` and chamber pressures ``pa``, ``pb``; ``ctrl`` (:data:`N_CTRL`)
    updated.  The derivative (of the error, or of minus the measurement) is a backward difference through the
    first-order filter ``Tf``: ``D_k = (Tf D_{k-1} + s_k - s_{k-1}) / (Tf + h)`` (``Tf = 0``: the raw difference)."""
    e = r - xm
    ctrl[0] += e * h
    if p[I_DMEAS] > 0.0:
        ds = ctrl[4] - xm
    else:
        ds = e - ctrl[1]
    if ctrl[2] > 0.0:
        tf = p[I_TF]
        de = (tf * ctrl[3] + ds) / (tf + h)
    else:
        de = 0.0
    ctrl[1] = e
    ctrl[2] = 1.0
    ctrl[3] = de
    ctrl[4] = xm
    u = p[I_KP] * e + p[I_KI] * ctrl[0] + p[I_KD] * de
    return _shape_output(u, rdot, pa, pb, p)


@nb.njit(cache=True)
def _d_signal(a4, a5, k, f, drive, mode, p, dt):
    """A continuous controller's measured displacement, error, demand rate, the signal its derivative acts on
    and that signal's rate."""
    g = p[I_KXM]
    xm = g * (a4 - p[I_TAUX] * a5)  # x(t - tau) to first order
    e = input_at(drive, k, f, mode) - xm
    rdot = slope_at(drive, k, f, mode, dt)
    if p[I_DMEAS] > 0.0:
        return xm, e, rdot, -xm, -g * a5
    return xm, e, rdot, e, rdot - g * a5


@nb.njit(cache=True)
def _u_stage(a2, a3, a4, a5, k, f, drive, closed, mode, p, integ, dflt, dt):
    """Controller output at a stage of a continuous loop (closed) or an interpolated logged input (open).
    ``dflt``: the derivative filter's state (the filtered signal) when ``Tf > 0``."""
    if not closed:
        return input_at(drive, k, f, mode)
    xm, e, rdot, sig, dsig = _d_signal(a4, a5, k, f, drive, mode, p, dt)
    tf = p[I_TF]
    d = dsig if tf <= 0.0 else (sig - dflt) / tf
    u = p[I_KP] * e + p[I_KI] * integ + p[I_KD] * d
    return _shape_output(u, rdot, a2 + p[I_PAOFF], a3 + p[I_PBOFF], p)


@nb.njit(cache=True)
def step_varying(s, k, drive, closed, mode, p, dt, nsub, ctrl, out):
    """Advance ``s`` from sample ``k`` to ``k+1`` with the input varying inside the interval.

    ``closed``: a continuous controller reads the state at every stage (its memory ``ctrl``, integral and
    derivative filter, updated per substep); else the logged input ``drive`` is interpolated by ``mode``.
    """
    h0 = dt / nsub
    fh0 = 1.0 / nsub
    a0, a1, a2, a3, a4, a5 = s[0], s[1], s[2], s[3], s[4], s[5]
    integ = ctrl[0]
    dflt = ctrl[3]
    tf = p[I_TF]
    line = p[I_CSUP] > 0.0  # the supply line's memory follows the controller's (N_LINE entries)
    y = 0.0
    for j in range(nsub):
        # with the supply line, a substep is cut where its coupling to the valve needs it (line_pieces)
        m = line_pieces(a0, a2, a3, p, ctrl[N_CTRL], h0) if line else 1
        h = h0 / m
        fh = fh0 / m
        for i in range(m):
            f0 = j * fh0 + i * fh
            if line:
                y = ctrl[N_CTRL]
            u1 = _u_stage(a2, a3, a4, a5, k, f0, drive, closed, mode, p, integ, dflt, dt)
            k1 = deriv_line(a0, a1, a2, a3, a4, a5, u1, p, y)
            b2 = a2 + 0.5 * h * k1[2]
            b3 = a3 + 0.5 * h * k1[3]
            b4 = a4 + 0.5 * h * k1[4]
            b5 = a5 + 0.5 * h * k1[5]
            u2 = _u_stage(b2, b3, b4, b5, k, f0 + 0.5 * fh, drive, closed, mode, p, integ, dflt, dt)
            k2 = deriv_line(a0 + 0.5 * h * k1[0], a1 + 0.5 * h * k1[1], b2, b3, b4, b5, u2, p, y)
            c2 = a2 + 0.5 * h * k2[2]
            c3 = a3 + 0.5 * h * k2[3]
            c4 = a4 + 0.5 * h * k2[4]
            c5 = a5 + 0.5 * h * k2[5]
            u3 = _u_stage(c2, c3, c4, c5, k, f0 + 0.5 * fh, drive, closed, mode, p, integ, dflt, dt)
            k3 = deriv_line(a0 + 0.5 * h * k2[0], a1 + 0.5 * h * k2[1], c2, c3, c4, c5, u3, p, y)
            d2 = a2 + h * k3[2]
            d3 = a3 + h * k3[3]
            d4 = a4 + h * k3[4]
            d5 = a5 + h * k3[5]
            u4 = _u_stage(d2, d3, d4, d5, k, f0 + fh, drive, closed, mode, p, integ, dflt, dt)
            k4 = deriv_line(a0 + h * k3[0], a1 + h * k3[1], d2, d3, d4, d5, u4, p, y)
            if closed:
                _, e0, _, s0, _ = _d_signal(a4, a5, k, f0, drive, mode, p, dt)
                _, e1, _, s1, _ = _d_signal(d4, d5, k, f0 + fh, drive, mode, p, dt)
                integ += 0.5 * h * (e0 + e1)
                if tf > 0.0:  # the filter over the substep, its input linear between the ends
                    dflt += (1.0 - math.exp(-h / tf)) * (0.5 * (s0 + s1) - dflt)
            a0, a1, a2, a3, a4, a5 = rk4_combine(a0, a1, a2, a3, a4, a5, k1, k2, k3, k4, h)
            if line:
                line_advance(ctrl[N_CTRL:], (k1[6] + 2.0 * k2[6] + 2.0 * k3[6] + k4[6]) / 6.0, p, h)
    store6(out, a0, a1, a2, a3, a4, a5)
    ctrl[0] = integ
    ctrl[3] = dflt


@nb.njit(cache=True)
def advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm_k, ctrl, out):
    """One log interval from sample ``k`` to ``k+1`` under any loop timing; returns ``u`` at ``t_k``.

    ``ticks``: controller ticks per sample (1: digital at the log's rate, N: a
    digital controller N times faster, 0: continuous).  ``mode``: intersample of
    ``drive`` (0 zoh, 1 foh, 2 cubic).  ``xm_k``: the measured displacement at
    ``t_k``.  ``ctrl``: controller memory (:data:`N_CTRL` entries: integral,
    previous error, started, derivative filter, previous measurement), then, with
    the supply line's dynamics on, the line's (:data:`N_LINE`), updated in place.  ``out`` may be ``s``.  A digital controller's feed-forward reads the
    demand's rate as the cubic's slope (at a sample: the central difference).
    """
    line = p[I_CSUP] > 0.0  # the supply line's dynamics: its memory follows the controller's
    if not closed:
        u = drive[k]
        if mode == 0:
            if line:
                step_line(s, u, p, dt, nsub, out, ctrl[N_CTRL:])
            else:
                step(s, u, p, dt, nsub, out)
        else:
            step_varying(s, k, drive, False, mode, p, dt, nsub, ctrl, out)
        return u
    if ticks == 0:
        if ctrl[2] <= 0.0:  # the derivative filter starts at its input
            ctrl[3] = _d_signal(s[4], s[5], k, 0.0, drive, mode, p, dt)[3]
            ctrl[2] = 1.0
        e = drive[k] - xm_k
        rdot = slope_at(drive, k, 0.0, mode, dt)
        tf = p[I_TF]
        sig = -xm_k if p[I_DMEAS] > 0.0 else e
        d = (-p[I_KXM] * s[5] if p[I_DMEAS] > 0.0 else rdot - p[I_KXM] * s[5]) if tf <= 0.0 else \
            (sig - ctrl[3]) / tf
        u = p[I_KP] * e + p[I_KI] * ctrl[0] + p[I_KD] * d
        u = _shape_output(u, rdot, s[2] + p[I_PAOFF], s[3] + p[I_PBOFF], p)
        step_varying(s, k, drive, True, mode, p, dt, nsub, ctrl, out)
        return u
    h = dt / ticks
    nsub_t = max(1, (nsub + ticks - 1) // ticks)
    u0 = 0.0
    for i in range(ticks):
        if i == 0:
            xm = xm_k
            pa = s[2] + p[I_PAOFF]
            pb = s[3] + p[I_PBOFF]
        else:
            xm = p[I_KXM] * (out[4] - p[I_TAUX] * out[5])
            pa = out[2] + p[I_PAOFF]
            pb = out[3] + p[I_PBOFF]
        rdot = slope_at(drive, k, i / ticks, 2, dt) if p[I_KFF] != 0.0 else 0.0
        u = pid_tick(input_at(drive, k, i / ticks, mode), rdot, xm, pa, pb, h, p, ctrl)
        if i == 0:
            u0 = u
        src = s if i == 0 else out
        if line:
            step_line(src, u, p, h, nsub_t, out, ctrl[N_CTRL:])
        else:
            step(src, u, p, h, nsub_t, out)
    return u0


@nb.njit(cache=True)
def _simulate_one(s0, p, drive, closed, ticks, mode, dt, nsub, S, U, XM, exo_idx, EXO):
    T = drive.shape[0]
    s = s0.copy()
    if exo_idx.shape[0] > 0:  # logged signals set parameters sample by sample: this record's own vector
        p = p.copy()
    xhist = np.empty(T)
    ctrl = np.zeros(N_CTRL + N_LINE)
    tau = p[I_TAUX]
    g = p[I_KXM]
    for k in range(T):
        for j in range(NS):
            S[k, j] = s[j]
        xhist[k] = s[4]
        xm = g * _delayed(xhist, k, tau, dt)
        XM[k] = xm
        for j in range(exo_idx.shape[0]):  # held over the interval from sample k (NaN: the last value holds)
            if math.isfinite(EXO[k, j]):
                p[exo_idx[j]] = EXO[k, j]
        if k + 1 < T:
            U[k] = advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm, ctrl, s)
        elif closed:  # the last sample: the controller's output at t_k, no step
            c = ctrl.copy()
            if ticks != 1:
                c[2] = 0.0
            rdot = slope_at(drive, k, 0.0, 2, dt) if p[I_KFF] != 0.0 else 0.0
            U[k] = pid_tick(drive[k], rdot, xm, s[2] + p[I_PAOFF], s[3] + p[I_PBOFF], dt, p, c)
        else:
            U[k] = drive[k]


@nb.njit(cache=True, parallel=True)
def simulate_kernel(S0, P, drive, closed, ticks, mode, dt, nsub, exo_idx, EXO):
    """Simulate ``K`` parameter vectors in parallel.

    Returns states ``[K, T, 6]``, controller output ``[K, T]`` and measured
    displacement ``[K, T]`` (the rod position seen through the sensor).
    """
    K = P.shape[0]
    T = drive.shape[0]
    S = np.empty((K, T, NS))
    U = np.empty((K, T))
    XM = np.empty((K, T))
    for k in nb.prange(K):
        _simulate_one(S0[k], P[k], drive, closed, ticks, mode, dt, nsub, S[k], U[k], XM[k], exo_idx, EXO)
    return S, U, XM


@nb.njit(cache=True)
def sensor_lag(p: np.ndarray, tau: np.ndarray, dt: float) -> np.ndarray:
    """A first-order transducer ``tau y' = p - y`` on each row of ``p [K, T]`` (its own ``tau[k]``),
    settled at the first sample; exact for ``p`` linear between samples:
    ``y[n+1] = a y[n] + p[n+1] - a p[n] - c (p[n+1] - p[n])``, ``a = exp(-dt / tau)``, ``c = tau (1 - a) / dt``."""
    K, T = p.shape
    out = np.empty((K, T))
    for k in range(K):
        t = tau[k]
        out[k, 0] = p[k, 0]
        if t <= 0.0:
            for n in range(1, T):
                out[k, n] = p[k, n]
            continue
        a = math.exp(-dt / t)
        c = t * (1.0 - a) / dt
        for n in range(T - 1):
            out[k, n + 1] = a * out[k, n] + p[k, n + 1] - a * p[k, n] - c * (p[k, n + 1] - p[k, n])
    return out
