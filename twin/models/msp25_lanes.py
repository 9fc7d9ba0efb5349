"""The MSP25's compiled functions for the online filter: one log interval of one state (:func:`advance`, the model's
own), and the same for many sigma points side by side (:func:`lanes`).

A filter needs the rig model at ``2 n + 1`` sigma points per sample.  On the open-loop path of a rig whose effects
are all neutral (:func:`lanes_applicable`) they are integrated together: one work vector ``W [N_W * LANES]``, row
``r`` (one quantity) of lane ``ln`` (one sigma point) at ``r * LANES + ln``.  The right-hand side then runs over the
lanes in one loop the compiler vectorises (square roots and divisions of 8 sigma points per instruction): a constant
row stride lets it prove that the rows do not overlap, and a constant lane count leaves no scalar remainder.

:func:`_lanes_deriv` is :func:`twin.models.msp25.deriv` with every effect neutral, written over lanes: the same
operations in the same order, so each lane's numbers are :func:`advance`'s for its point, bit for bit
(``tests/test_models.py``).  Unused lanes repeat lane 0.

The interface every model's filter module offers (:attr:`twin.models.base.FilterSpec.functions`):
``advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm_k, ctrl, out) -> u``, ``N_CTRL`` (controller memory
entries), ``LANES`` and ``LANE_WORK`` (sizes of the lane arrays, 0 without lanes), ``lanes_applicable(p)`` and
``lanes(S, TH, m, p, idx, wnd, mode, dt, nsub, W)``.
"""

from __future__ import annotations

import math

import numba as nb

from twin.models import base as _base_src
from twin.models import intersample as _intersample_src
from twin.models import msp25 as M
from twin.models.intersample import input_at
from twin.models.jitcache import keep_fresh
from twin.models.msp25 import N_CTRL, advance, fast_tanh  # noqa: F401  (the filter interface)

keep_fresh(__file__, M.__file__, *M.SOURCES, _intersample_src.__file__, _base_src.__file__)

#: the lanes' parameters: each lane recomputes the constants of these only (:func:`lanes`)
LANE_PARAMS = ("Ffric", "CdAleak", "Cd", "zeta", "wn")
assert set(M.MODEL.trackable) <= set(LANE_PARAMS), "a new trackable parameter: see lanes()"
#: sigma points integrated side by side: all of a filter tracking every trackable parameter, in whole vectors of 8
LANES = 8 * ((2 * (M.NS + len(M.MODEL.trackable)) + 1 + 7) // 8)
N_LEAN = 18  # constants of the lean right-hand side (:func:`_consts`)
W_A, W_Y, W_ACC, W_K, W_C, W_TH = 0, 6, 12, 18, 24, 24 + N_LEAN
N_W = 25 + N_LEAN
#: work entries :func:`lanes` needs
LANE_WORK = N_W * LANES + N_LEAN


@nb.njit(cache=True)
def lanes_applicable(p):
    """True when every effect of the kernel vector ``p`` sits at its neutral value (the lanes are exact)."""
    return (p[M.I_CVISC] == 0.0 and p[M.I_FBRK] == 0.0 and p[M.I_KLAM] == 0.0 and p[M.I_XSDB] == 0.0
            and p[M.I_XSBIAS] == 0.0 and p[M.I_RSUP] == 0.0 and p[M.I_KSPEC] == 0.0 and p[M.I_TAUX] == 0.0
            and p[M.I_EPS] == 0.0 and p[M.I_XSMAX] >= 1.0 and p[M.I_KXM] == 1.0 and p[M.I_KSUP2] == 0.0
            and p[M.I_CSUP] == 0.0)


@nb.njit(cache=True)
def _leak_factor(p):
    """The leakage factor at the oil's temperature (deriv's ``lf``)."""
    dT = p[M.I_TOIL] - p[M.I_TREF]
    return math.exp(p[M.I_BVISC] * dT) if dT != 0.0 else 1.0


@nb.njit(cache=True)
def _consts(p, c):
    """The constants of the right-hand side with every effect neutral (the products :func:`deriv` forms)."""
    wn = p[M.I_WN]
    c[0] = wn * wn
    c[1] = 2.0 * p[M.I_ZETA] * wn
    c[2] = p[M.I_KE] * p[M.I_KSP]
    c[3] = p[M.I_CD] * p[M.I_B] * math.sqrt(2.0 / p[M.I_RHO])
    c[4] = p[M.I_PP]
    c[5] = p[M.I_PT]
    c[6] = p[M.I_DPL] * p[M.I_DPL]
    c[7] = p[M.I_CDALEAK] * _leak_factor(p) * math.sqrt(2.0 / p[M.I_RHO])
    c[8] = p[M.I_DPLL] * p[M.I_DPLL]
    c[9] = p[M.I_BULK] * (1.0 - p[M.I_KBT] * (p[M.I_TOIL] - p[M.I_TREF]))
    c[10] = p[M.I_A]
    c[11] = p[M.I_V0]
    c[12] = 1.0 / p[M.I_M]
    c[13] = p[M.I_FFRIC]
    c[14] = 1.0 / p[M.I_VREF]
    c[15] = p[M.I_FEXT]
    c[16] = p[M.I_AB] if p[M.I_AB] > 0.0 else p[M.I_A]
    c[17] = p[M.I_V0B] if p[M.I_V0B] > 0.0 else p[M.I_V0]


@nb.njit(cache=True, error_model="numpy")
def _lanes_deriv(W, u):
    """:func:`twin.models.msp25.deriv` (effects neutral) of every lane at the stage input (rows ``W_Y``) into rows
    ``W_K``."""
    for ln in range(LANES):  # the friction's tanh (libm's exp: not vectorised)
        W[W_TH * LANES + ln] = fast_tanh(W[(W_Y + 5) * LANES + ln] * W[(W_C + 14) * LANES + ln])
    for ln in range(LANES):
        xs = W[W_Y * LANES + ln]
        vs = W[(W_Y + 1) * LANES + ln]
        pA = W[(W_Y + 2) * LANES + ln]
        pB = W[(W_Y + 3) * LANES + ln]
        x = W[(W_Y + 4) * LANES + ln]
        v = W[(W_Y + 5) * LANES + ln]
        pP = W[(W_C + 4) * LANES + ln]
        pT = W[(W_C + 5) * LANES + ln]
        dl2 = W[(W_C + 6) * LANES + ln]
        # the valve's two flow paths as selects: the numbers of deriv's branches
        pos = xs >= 0.0
        d1 = pP - pA if pos else pA - pT
        d2 = pB - pT if pos else pP - pB
        gx = W[(W_C + 3) * LANES + ln] * xs
        qa = gx * (d1 / math.sqrt(math.sqrt(d1 * d1 + dl2)))
        qb = gx * (d2 / math.sqrt(math.sqrt(d2 * d2 + dl2)))
        dpAB = pA - pB
        qAB = W[(W_C + 7) * LANES + ln] * (dpAB / math.sqrt(math.sqrt(dpAB * dpAB + W[(W_C + 8) * LANES + ln])))
        qA = qa - qAB
        qB = qAB - qb
        A = W[(W_C + 10) * LANES + ln]
        V0 = W[(W_C + 11) * LANES + ln]
        AB = W[(W_C + 16) * LANES + ln]
        V0B = W[(W_C + 17) * LANES + ln]
        VA = max(V0 + A * x, 1e-3 * V0)
        VB = max(V0B - AB * x, 1e-3 * V0B)
        bulk = W[(W_C + 9) * LANES + ln]
        W[W_K * LANES + ln] = vs
        W[(W_K + 1) * LANES + ln] = W[W_C * LANES + ln] * (W[(W_C + 2) * LANES + ln] * u - xs) - \
            W[(W_C + 1) * LANES + ln] * vs
        W[(W_K + 2) * LANES + ln] = bulk * (qA - A * v) / VA
        W[(W_K + 3) * LANES + ln] = bulk * (qB + AB * v) / VB
        W[(W_K + 4) * LANES + ln] = v
        W[(W_K + 5) * LANES + ln] = (dpAB * A - pB * (AB - A) - W[(W_C + 13) * LANES + ln] * W[W_TH * LANES + ln]
                                    - W[(W_C + 15) * LANES + ln]) * W[(W_C + 12) * LANES + ln]


@nb.njit(cache=True)
def _stage_inputs(wnd, f0, fh, mode):
    """The logged input at an RK4 substep's start, middle and end (window ``wnd``, index 1 = this sample;
    ``f0``, ``fh``: the substep's start and length as fractions of the sample interval)."""
    if mode == 0:
        u = wnd[1]
        return u, u, u
    return input_at(wnd, 1, f0, mode), input_at(wnd, 1, f0 + 0.5 * fh, mode), input_at(wnd, 1, f0 + fh, mode)


@nb.njit(cache=True, error_model="numpy")
def _lanes_rk4(W, wnd, mode, dt, nsub):
    """RK4 over one log interval of every lane of ``W`` (states in rows ``W_A``, constants in rows ``W_C``), in
    place: :func:`twin.models.msp25.advance` open loop (``step`` or ``step_varying``), lane by lane."""
    h = dt / nsub
    fh = 1.0 / nsub
    hh = 0.5 * h
    cc = h / 6.0
    for j in range(nsub):
        f0 = j * fh
        u1, u2, u4 = _stage_inputs(wnd, f0, fh, mode)
        for i in range(6 * LANES):
            W[W_Y * LANES + i] = W[W_A * LANES + i]
        _lanes_deriv(W, u1)
        for i in range(6 * LANES):
            k = W[W_K * LANES + i]
            W[W_ACC * LANES + i] = k
            W[W_Y * LANES + i] = W[W_A * LANES + i] + hh * k
        _lanes_deriv(W, u2)
        for i in range(6 * LANES):
            k = W[W_K * LANES + i]
            W[W_ACC * LANES + i] = W[W_ACC * LANES + i] + 2.0 * k
            W[W_Y * LANES + i] = W[W_A * LANES + i] + hh * k
        _lanes_deriv(W, u2)
        for i in range(6 * LANES):
            k = W[W_K * LANES + i]
            W[W_ACC * LANES + i] = W[W_ACC * LANES + i] + 2.0 * k
            W[W_Y * LANES + i] = W[W_A * LANES + i] + h * k
        _lanes_deriv(W, u4)
        for i in range(6 * LANES):
            W[W_A * LANES + i] += cc * (W[W_ACC * LANES + i] + W[W_K * LANES + i])


@nb.njit(cache=True)
def lanes(S, TH, m, p, idx, wnd, mode, dt, nsub, W):
    """One log interval, open loop, of the states ``S[ln]`` (SI) of the rigs ``p`` with the parameters ``idx`` at
    ``TH[ln]``, ``ln < m <= LANES``, in place: :func:`advance` (``closed=False``) for each, at once.

    ``wnd``: the logged input at samples k-1, k (index 1: this sample) and k+1, interpolated by ``mode``.  Only the
    constants of :data:`LANE_PARAMS` differ between lanes; ``p`` is overwritten at ``idx``.  ``W``: work
    (:data:`LANE_WORK` entries)."""
    p_count = idx.shape[0]
    c = W[N_W * LANES:]
    for j in range(p_count):
        p[idx[j]] = TH[0, j]
    _consts(p, c)
    for i in range(N_LEAN):
        ci = c[i]  # read once: c is a view of W, so a read inside the loop is repeated after every store
        for ln in range(LANES):
            W[(W_C + i) * LANES + ln] = ci
    s2r = math.sqrt(2.0 / p[M.I_RHO])
    lf = _leak_factor(p)
    b = p[M.I_B]
    for ln in range(LANES):
        r = ln if ln < m else 0
        for j in range(p_count):
            p[idx[j]] = TH[r, j]
        # the lane's parameters read before W is written (W might be p for all the compiler knows)
        wn, zeta, cd, cdl, ff = p[M.I_WN], p[M.I_ZETA], p[M.I_CD], p[M.I_CDALEAK], p[M.I_FFRIC]
        W[W_C * LANES + ln] = wn * wn
        W[(W_C + 1) * LANES + ln] = 2.0 * zeta * wn
        W[(W_C + 3) * LANES + ln] = cd * b * s2r
        W[(W_C + 7) * LANES + ln] = cdl * lf * s2r
        W[(W_C + 13) * LANES + ln] = ff
        for i in range(6):
            W[(W_A + i) * LANES + ln] = S[r, i]
    _lanes_rk4(W, wnd, mode, dt, nsub)
    for ln in range(m):
        for i in range(6):
            S[ln, i] = W[(W_A + i) * LANES + ln]
