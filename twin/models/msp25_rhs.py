"""The MSP25's right-hand side and its fixed-input RK4 step, compiled: the one definition of the rig's physics
(valve, orifices, leakage, oil compressibility, rod and friction, every effect of the catalogue neutral when off).

The kernel vector ``p`` is laid out by :mod:`twin.models.msp25_params`; the controller and the loop's timing
that drive it are :mod:`twin.models.msp25_loop`.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from twin.models import msp25_params as _params_src
from twin.models.jitcache import keep_fresh
from twin.models.msp25_params import (
    I_A, I_AB, I_B, I_BULK, I_BVISC, I_CD, I_CDALEAK, I_CVISC, I_DPL, I_DPLL, I_DSTR, I_EPS, I_FBRK, I_FEXT,
    I_FFRIC, I_KBT, I_KE, I_KLAM, I_KSP, I_KSPEC, I_KSUP2, I_M, I_PP, I_PT, I_RHO, I_RSUP, I_TOIL, I_TREF, I_V0,
    I_V0B, I_VREF, I_VSTR, I_WN, I_XSBIAS, I_XSDB, I_XSMAX, I_ZETA, KAPPA_AIR, NS, P_ATM, I_CSUP, I_LSUP,
    I_RHOSE,
)

# the machine code cached for this module inlines these modules' constants
keep_fresh(__file__, _params_src.__file__)


@nb.njit(cache=True)
def _sqrt_reg(dp, dpl):
    """sgn(dp) sqrt(|dp|) regularised in a laminar band dpl."""
    return dp / math.sqrt(math.sqrt(dp * dp + dpl * dpl))


@nb.njit(cache=True)
def _bulk(p, B, eps):
    if eps <= 0.0:
        return B
    pe = max(p, P_ATM)
    air = eps * (P_ATM / pe) ** (1.0 / KAPPA_AIR)
    return 1.0 / (1.0 / B + air / (KAPPA_AIR * pe))


@nb.njit(cache=True)
def _port_pressure(pP, pT, R, K2, pin, go, dpl):
    """The supply port's pressure ``pe = pP - R q - K2 q^2`` at the flow ``q = go sqrt_reg(pe - pin)`` it passes into
    a chamber at ``pin < pP`` through an opening of conductance ``go``.  With the orifice's square root unregularised
    the root is closed form: ``s = sqrt(pe - pin)`` solves ``(1 + K2 go^2) s^2 + R go s - (pP - pin) = 0``; two
    Newton steps on the regularised law follow (its band ``dpl`` moves the root by far less than a pascal outside
    it).  A single pass ``pP - R q(pP)`` instead left 3-10 % of the sag at the catalogue's sizes."""
    D = pP - pin
    a = R * go
    s = 2.0 * D / (a + math.sqrt(a * a + 4.0 * (1.0 + K2 * go * go) * D))
    pe = pin + s * s
    for _ in range(2):
        d = pe - pin
        r = d * d + dpl * dpl
        rq = math.sqrt(math.sqrt(r))
        q = go * d / rq
        dq = go * (0.5 * d * d + dpl * dpl) / (r * rq)
        pe -= (pe - pP + R * q + K2 * q * q) / (1.0 + (R + 2.0 * K2 * q) * dq)
    return max(pe, pT)


@nb.njit(cache=True)
def fast_tanh(x):
    """tanh through one exp (libm's tanh costs about 100 ns between 1 and 19); equal to 1e-15."""
    a = abs(x)
    if a > 19.1:
        return math.copysign(1.0, x)
    if a < 0.02:  # series: 1 - 2/(e^2a + 1) loses digits near zero
        a2 = a * a
        return x * (1.0 - a2 * (1.0 / 3.0 - a2 * (2.0 / 15.0 - a2 * (17.0 / 315.0))))
    t = 1.0 - 2.0 / (math.exp(2.0 * a) + 1.0)
    return math.copysign(t, x)


@nb.njit(cache=True)
def _opening(xs, p):
    """The spool's effective opening: null bias, stroke limit, overlap."""
    o = xs + p[I_XSBIAS]
    xm = p[I_XSMAX]
    if o > xm:
        o = xm
    elif o < -xm:
        o = -xm
    db = p[I_XSDB]
    if db > 0.0:
        if o > db:
            o = o - db
        elif o < -db:
            o = o + db
        else:
            o = 0.0
    return o


@nb.njit(cache=True)
def line_pieces(xs, pA, pB, p, sag, h):
    """Pieces a step of ``h`` is cut into so that the supply line's coupling to the valve stays stable: the rig is
    integrated with the port's sag held, then the line, so a piece's sag moves the draw by ``h |dq/dsag| / C_sup``
    of itself; at most 0.5 (the draw's slope grows as the chamber's pressure nears the port's: ``q`` follows
    the square root of the drop)."""
    o = _opening(xs, p)
    if o == 0.0:
        return 1
    pin = pA if o > 0.0 else pB
    d = p[I_PP] - sag - pin
    dpl = p[I_DPL]
    r = d * d + dpl * dpl
    slope = p[I_CD] * p[I_B] * math.sqrt(2.0 / p[I_RHO]) * abs(o) * (0.5 * d * d + dpl * dpl) / (r * math.sqrt(math.sqrt(r)))
    k = 2.0 * h * slope / p[I_CSUP]
    return 1 if k <= 1.0 else min(int(math.ceil(k)), 256)


@nb.njit(cache=True)
def deriv(xs, vs, pA, pB, x, v, u, p):
    """Right-hand side of one state (scalars in, tuple of six derivatives out): :func:`deriv_line` with the
    supply port at ``pP``."""
    d = deriv_line(xs, vs, pA, pB, x, v, u, p, 0.0)
    return d[0], d[1], d[2], d[3], d[4], d[5]


@nb.njit(cache=True)
def deriv_line(xs, vs, pA, pB, x, v, u, p, sag):
    """Right-hand side of one state with the valve's supply port ``sag`` [Pa] below ``pP`` (the supply line's
    state, :func:`line_advance`): the six derivatives and the flow drawn from the supply [m^3/s].

    The one definition of the rig's physics: the filter's side-by-side form (:mod:`twin.models.msp25_lanes`)
    computes, with every effect neutral, the same operations in the same order (``tests/test_models.py`` checks
    it bit for bit), so the reciprocals ``1 / vref`` and ``1 / m`` are multiplied, not divided by."""
    rho = p[I_RHO]
    A = p[I_A]
    V0 = p[I_V0]
    dpl = p[I_DPL]
    pT = p[I_PT]
    wn = p[I_WN]
    # servo-valve, second order (eq. 4)
    dxs = vs
    dvs = wn * wn * (p[I_KE] * p[I_KSP] * u - xs) - 2.0 * p[I_ZETA] * wn * vs
    # spool opening: null bias, stroke limit, overlap
    o = _opening(xs, p)
    g = p[I_CD] * p[I_B] * math.sqrt(2.0 / rho)
    pP = p[I_PP] - sag
    qPA = 0.0
    qBT = 0.0
    qAT = 0.0
    qPB = 0.0
    if o >= 0.0:
        qPA = g * o * _sqrt_reg(pP - pA, dpl)
        qBT = g * o * _sqrt_reg(pB - pT, dpl)
    else:
        qAT = -g * o * _sqrt_reg(pA - pT, dpl)
        qPB = -g * o * _sqrt_reg(pP - pB, dpl)
    R = p[I_RSUP]
    K2 = p[I_KSUP2]
    if R > 0.0 or K2 > 0.0:  # supply droop (R q) and turbulent line loss (K2 q^2) at the port's own flow
        qs = qPA + qPB
        if qs > 0.0:
            pPe = _port_pressure(pP, pT, R, K2, pA if o >= 0.0 else pB, g * abs(o), dpl)
            if o >= 0.0:
                qPA = g * o * _sqrt_reg(pPe - pA, dpl)
            else:
                qPB = -g * o * _sqrt_reg(pPe - pB, dpl)
    qs = qPA + qPB
    dpAB = pA - pB
    # the oil's temperature: bulk modulus and leakage at T_oil (factors exactly 1 at T_ref)
    dT = p[I_TOIL] - p[I_TREF]
    lf = math.exp(p[I_BVISC] * dT) if dT != 0.0 else 1.0
    qAB = p[I_CDALEAK] * lf * math.sqrt(2.0 / rho) * _sqrt_reg(dpAB, p[I_DPLL]) + p[I_KLAM] * lf * dpAB
    qA = qPA - qAT - qAB
    qB = qPB - qBT + qAB
    AB = p[I_AB] if p[I_AB] > 0.0 else A
    V0B = p[I_V0B] if p[I_V0B] > 0.0 else V0
    VA = max(V0 + A * x, 1e-3 * V0)
    VB = max(V0B - AB * x, 1e-3 * V0B)
    eps = p[I_EPS]
    Bt = p[I_BULK] * (1.0 - p[I_KBT] * dT)
    dpA = _bulk(pA, Bt, eps) * (qA - A * v) / VA
    dpB = _bulk(pB, Bt, eps) * (qB + AB * v) / VB
    # rod (eq. 11-12) with the friction extensions
    ff = p[I_FFRIC]
    fb = p[I_FBRK]
    if fb > 0.0:  # Stribeck: exp(-(|v| / v_str)^delta), Gaussian (delta 2) by default
        r = abs(v) / p[I_VSTR]
        dl = p[I_DSTR]
        ff = ff + fb * math.exp(-(r * r if dl == 2.0 else r ** dl))
    Ffr = ff * fast_tanh(v * (1.0 / p[I_VREF])) + p[I_CVISC] * v
    # pA A - pB AB, written so that a symmetric cylinder (AB = A) gives the same numbers as (pA - pB) A
    dv = (dpAB * A - pB * (AB - A) - Ffr - p[I_FEXT] - p[I_KSPEC] * x) * (1.0 / p[I_M])
    return dxs, dvs, dpA, dpB, v, dv, qs


@nb.njit(cache=True)
def line_advance(line, qbar, p, h):
    """The supply line over ``h`` with the valve drawing ``qbar`` [m^3/s] (exact for a constant draw).

    The pump holds ``pP`` at the far end of a hose of inertance ``L_sup`` and resistance ``R_hose``; the hose fills
    the compliance ``C_sup`` at the valve's supply port, from which the valve draws.  With ``y`` the port's sag
    below ``pP`` and ``q`` the hose's flow: ``C y' = qbar - q``, ``L q' = y - R q``, whose rest under a steady draw
    is ``q = qbar``, ``y = R qbar``; the deviation from it decays and rings at ``1 / sqrt(L C)`` with damping
    ``R / 2 sqrt(C / L)``.  ``line``: ``[y, q]``, updated in place (``exp(A h)`` in closed form, stable at any
    ``h``)."""
    C = p[I_CSUP]
    L = p[I_LSUP]
    R = p[I_RHOSE]
    e0 = line[0] - R * qbar
    e1 = line[1] - qbar
    # A = [[0, -1/C], [1/L, -R/L]]: exp(A h) = exp(m h) (c0 I + c1 (A - m I)), m the half trace
    m = -0.5 * R / L
    disc = m * m - 1.0 / (L * C)
    if disc < 0.0:
        w = math.sqrt(-disc)
        c0 = math.cos(w * h)
        c1 = math.sin(w * h) / w
    elif disc > 0.0:
        w = math.sqrt(disc)
        c0 = math.cosh(w * h)
        c1 = math.sinh(w * h) / w
    else:
        c0 = 1.0
        c1 = h
    f = math.exp(m * h)
    n0 = f * ((c0 - c1 * m) * e0 - c1 / C * e1)
    n1 = f * (c1 / L * e0 + (c0 + c1 * (-R / L - m)) * e1)
    line[0] = R * qbar + n0
    line[1] = qbar + n1


@nb.njit(cache=True)
def rk4_combine(a0, a1, a2, a3, a4, a5, k1, k2, k3, k4, h):
    """The RK4 update of the six states from the four stage derivatives (the one copy every RK4 step of the
    rig uses: :func:`step`, :func:`step_varying`, the filter's lean step)."""
    c = h / 6.0
    return (a0 + c * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0]),
            a1 + c * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1]),
            a2 + c * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2]),
            a3 + c * (k1[3] + 2.0 * k2[3] + 2.0 * k3[3] + k4[3]),
            a4 + c * (k1[4] + 2.0 * k2[4] + 2.0 * k3[4] + k4[4]),
            a5 + c * (k1[5] + 2.0 * k2[5] + 2.0 * k3[5] + k4[5]))


@nb.njit(cache=True)
def store6(out, a0, a1, a2, a3, a4, a5):
    out[0] = a0
    out[1] = a1
    out[2] = a2
    out[3] = a3
    out[4] = a4
    out[5] = a5


@nb.njit(cache=True)
def step(s, u, p, dt, nsub, out):
    """Advance state ``s[6]`` by ``dt`` with ``nsub`` RK4 substeps, input ``u`` held; write ``out``."""
    h = dt / nsub
    a0, a1, a2, a3, a4, a5 = s[0], s[1], s[2], s[3], s[4], s[5]
    for _ in range(nsub):
        k1 = deriv(a0, a1, a2, a3, a4, a5, u, p)
        k2 = deriv(a0 + 0.5 * h * k1[0], a1 + 0.5 * h * k1[1], a2 + 0.5 * h * k1[2],
                   a3 + 0.5 * h * k1[3], a4 + 0.5 * h * k1[4], a5 + 0.5 * h * k1[5], u, p)
        k3 = deriv(a0 + 0.5 * h * k2[0], a1 + 0.5 * h * k2[1], a2 + 0.5 * h * k2[2],
                   a3 + 0.5 * h * k2[3], a4 + 0.5 * h * k2[4], a5 + 0.5 * h * k2[5], u, p)
        k4 = deriv(a0 + h * k3[0], a1 + h * k3[1], a2 + h * k3[2],
                   a3 + h * k3[3], a4 + h * k3[4], a5 + h * k3[5], u, p)
        a0, a1, a2, a3, a4, a5 = rk4_combine(a0, a1, a2, a3, a4, a5, k1, k2, k3, k4, h)
    store6(out, a0, a1, a2, a3, a4, a5)


@nb.njit(cache=True)
def step_line(s, u, p, dt, nsub, out, line):
    """:func:`step` with the supply line's dynamics: each substep, cut into :func:`line_pieces`, integrates the rig
    with the port's sag ``line[0]`` held, then the line (:func:`line_advance`) under the piece's mean draw (the RK4
    weights of the stages' draws); the line's own frequency is far below the substep's."""
    h0 = dt / nsub
    a0, a1, a2, a3, a4, a5 = s[0], s[1], s[2], s[3], s[4], s[5]
    for _ in range(nsub):
        m = line_pieces(a0, a2, a3, p, line[0], h0)
        h = h0 / m
        for _piece in range(m):
            a0, a1, a2, a3, a4, a5 = _line_piece(a0, a1, a2, a3, a4, a5, u, p, line, h)
    store6(out, a0, a1, a2, a3, a4, a5)


@nb.njit(cache=True)
def _line_piece(a0, a1, a2, a3, a4, a5, u, p, line, h):
    """One RK4 step of the rig with the port's sag held, then the line under the step's mean draw."""
    y = line[0]
    k1 = deriv_line(a0, a1, a2, a3, a4, a5, u, p, y)
    k2 = deriv_line(a0 + 0.5 * h * k1[0], a1 + 0.5 * h * k1[1], a2 + 0.5 * h * k1[2],
                    a3 + 0.5 * h * k1[3], a4 + 0.5 * h * k1[4], a5 + 0.5 * h * k1[5], u, p, y)
    k3 = deriv_line(a0 + 0.5 * h * k2[0], a1 + 0.5 * h * k2[1], a2 + 0.5 * h * k2[2],
                    a3 + 0.5 * h * k2[3], a4 + 0.5 * h * k2[4], a5 + 0.5 * h * k2[5], u, p, y)
    k4 = deriv_line(a0 + h * k3[0], a1 + h * k3[1], a2 + h * k3[2],
                    a3 + h * k3[3], a4 + h * k3[4], a5 + h * k3[5], u, p, y)
    a0, a1, a2, a3, a4, a5 = rk4_combine(a0, a1, a2, a3, a4, a5, k1, k2, k3, k4, h)
    line_advance(line, (k1[6] + 2.0 * k2[6] + 2.0 * k3[6] + k4[6]) / 6.0, p, h)
    return a0, a1, a2, a3, a4, a5


@nb.njit(cache=True)
def rhs_batch(S, U, P):
    """Derivatives of a batch: ``S [K, 6]``, ``U [K]``, ``P [K, NP]`` -> ``[K, 6]``."""
    K = S.shape[0]
    out = np.empty((K, NS))
    for k in range(K):
        d = deriv(S[k, 0], S[k, 1], S[k, 2], S[k, 3], S[k, 4], S[k, 5], U[k], P[k])
        for j in range(NS):
            out[k, j] = d[j]
    return out


@nb.njit(cache=True)
def step_batch(S, U, P, dt, nsub):
    """One sample step of a batch: ``S [K, 6]``, ``U [K]``, ``P [K, NP]`` -> ``[K, 6]``."""
    K = S.shape[0]
    out = np.empty((K, NS))
    for k in range(K):
        step(S[k], U[k], P[k], dt, nsub, out[k])
    return out
