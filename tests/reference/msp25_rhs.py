"""Right-hand side of the MSP25 reference model (model-spec section 2, exact orifice law), compiled.

State vector (SI), fixed layout: ``xs, vs`` spool position and velocity, ``pA, pB``
chamber pressures (gauge), ``x, v`` rod, ``x2, v2`` second mass (mechanical
resonance), ``zi`` integral of the control error, ``zd`` low-passed error (analog
derivative term), ``z0..z3`` Pade delay states, ``pAm, pBm`` the pressure transducers'
readings (a first-order sensor, when it has a time constant).  Unused states have zero
derivative.

The supply (when ``SUP_ON``; its pressure is not logged): a pressure-compensated pump (full flow ``PUMP_Q`` up to
``PUMP_BAND`` below ``pP``, none at ``pP``) fills its outlet volume ``PUMP_V``; a hose of length ``HOSE_L`` and
bore ``HOSE_D`` (the oil's inertia, laminar Hagen-Poiseuille resistance with viscosity ``MU``, half its oil volume
at each end) leads to a gas accumulator at the valve (gas volume ``ACC_V`` at its pre-charge ``ACC_P``, polytropic
exponent ``ACC_N``), from which the valve draws.

Oil temperature ``T`` (when ``TEMP_ON``): the oil's bulk modulus falls linearly,
``B(T) = B0 (1 - a (T - T0))`` (``a`` about 0.006/K for mineral oil), and the leakage flows (the
orifice and the laminar term together) scale as the inverse of the viscosity,
``nu(T) = nu0 exp(-b (T - T0))``, so ``q_leak(T) = q_leak(T0) exp(b (T - T0))``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .signals import sig_eval, tv_eval

NS = 19
S_XS, S_VS, S_PA, S_PB, S_X, S_V, S_X2, S_V2, S_ZI, S_ZD, S_Z0 = range(11)
S_PAM, S_PBM = 14, 15
# the supply (when SUP_ON): pressure at the valve's supply port, flow in the hose, pressure at the pump's outlet
S_PV, S_QH, S_PU = 16, 17, 18

# parameter vector layout
(RHO, V0, AREA, MASS, BULK, VREF, KE, KSP, PORT, PP, PT, FEXT,
 KP, KI, KD, TD, MODE, UHELD, SEG,
 CVISC, FSTR, VSTR, GLAM, OVERLAP, BIAS, RSUP, KSPEC, GAIN, AIR, XSMAX, M2, K2, C2,
 PADE_N, PA0, PA1, PA2, PA3, PC0, PC1, PC2, PC3, PD, PTAU, DPREG, PATM, NOISE_ON,
 AREA_B, V0_B, KTURB, TAUP, TEMP_ON, TREF, ABULK, BVISC,
 SUP_ON, HOSE_L, HOSE_D, MU, ACC_V, ACC_P, ACC_N, PUMP_V, PUMP_Q, PUMP_BAND) = range(65)
NP = 65
# time-varying free parameters, rows of the TV table; then the oil temperature [K], the specimen's stiffness [N/m]
TV_FFRIC, TV_CDALEAK, TV_CD, TV_ZETA, TV_WN, TV_TEMP, TV_KSPEC = range(7)
FREE_ORDER = ("Ffric", "CdAleak", "Cd", "zeta", "wn")
# controller modes
M_ANALOG, M_HELD, M_SIGNAL = 0, 1, 2


@nb.njit(cache=True, inline="always")
def ssqrt(dp, d):
    """sgn(dp) sqrt(|dp|), exact for |dp| >= d; below, an odd cubic matching value and slope at d."""
    a = abs(dp)
    if a >= d:
        return math.copysign(math.sqrt(a), dp)
    r = dp / d
    return dp / math.sqrt(d) * (1.25 - 0.25 * r * r)


@nb.njit(cache=True, inline="always")
def _soft_relu(z, w):
    """max(z, 0) with a rounded corner of width w."""
    return 0.5 * (z + math.sqrt(z * z + w * w))


@nb.njit(cache=True, inline="always")
def _bulk(p, P, B):
    """Effective bulk modulus: oil of modulus B with isothermal free air (fraction AIR at atmospheric pressure)."""
    eps = P[AIR]
    if eps <= 0.0:
        return B
    p0 = P[PATM]
    pa = max(p + p0, 0.05 * p0)
    r0 = eps / (1.0 - eps)
    return (1.0 + r0 * p0 / pa) / (1.0 / B + r0 * p0 / (pa * pa))


@nb.njit(cache=True)
def measured_nonoise(y, P):
    """The displacement sensor's noise-free output: gain * x, Pade-delayed when PADE_N > 0."""
    w = P[GAIN] * y[S_X]
    n = int(P[PADE_N])
    if n == 0:
        return w
    out = P[PD] * w
    for i in range(n):
        out += P[PC0 + i] * y[S_Z0 + i]
    return out


@nb.njit(cache=True)
def control(t, y, P, sigp, sc, nzp, nzc):
    """Valve voltage in force at ``t``: analog PID on the measured x, held value, or input signal."""
    mode = int(P[MODE])
    if mode == M_HELD:
        return P[UHELD]
    seg = int(P[SEG])
    if mode == M_SIGNAL:
        return sig_eval(sigp, sc, t, seg)
    r = sig_eval(sigp, sc, t, seg)
    xm = measured_nonoise(y, P)
    if P[NOISE_ON] > 0.0:
        xm += sig_eval(nzp, nzc, t, -1)
    e = r - xm
    u = P[KP] * e
    if P[KI] != 0.0:
        u += P[KI] * y[S_ZI]
    if P[KD] != 0.0:
        u += P[KD] * (e - y[S_ZD]) / P[TD]
    return u


@nb.njit(cache=True)
def valve_flows(xs, pA, pB, P, Cd, pS):
    """Flows into chamber A and out of chamber B through the valve, and the supply flow (supply port at ``pS``)."""
    o = xs + P[BIAS]
    L = P[XSMAX]
    if L > 0.0:  # spool stroke limit, rounded corners of 2 % of the limit
        w = 0.02 * L
        o = 0.5 * (math.sqrt((o + L) ** 2 + w * w) - math.sqrt((o - L) ** 2 + w * w))
    ov = P[OVERLAP]
    if ov > 0.0:  # overlap: a port opens only past the lap, rounded corner of 1 % of the lap
        w = 0.01 * ov
        a = _soft_relu(abs(o) - ov, w)
        o = math.copysign(a, o)
    g = Cd * P[PORT] * math.sqrt(2.0 / P[RHO])
    d = P[DPREG]
    pP = pS
    pT = P[PT]
    ao = abs(o)
    if o >= 0.0:
        pin, pout = pA, pB  # P -> A, B -> T
    else:
        pin, pout = pB, pA  # P -> B, A -> T
    D = pP - pin
    R = P[RSUP]
    K = P[KTURB]
    if (R > 0.0 or K > 0.0) and ao > 0.0:
        # supply line: linear resistance and turbulent loss, pS = pP - R q - K q^2, q = G sqrt(pS - pin),
        # G = g ao: with s = sqrt(pS - pin), (1 + K G^2) s^2 + R G s - D = 0, solved in closed form
        G = g * ao
        a = R * G
        c = 1.0 + K * G * G
        s = 2.0 * abs(D) / (a + math.sqrt(a * a + 4.0 * c * abs(D)))
        qsup = math.copysign(G * s, D)
    else:
        qsup = g * ao * ssqrt(D, d)
    qret = g * ao * ssqrt(pout - pT, d)
    if o >= 0.0:
        return qsup, qret, qsup
    return -qret, -qsup, qsup


@nb.njit(cache=True)
def rhs(t, y, P, tv, tab, sigp, sc, nzp, nzc):
    """dy/dt of the 14-state vector (see the module docstring)."""
    out = np.zeros(NS)
    Ffric = tv_eval(tv, tab, TV_FFRIC, t)
    CdAleak = tv_eval(tv, tab, TV_CDALEAK, t)
    Cd = tv_eval(tv, tab, TV_CD, t)
    zeta = tv_eval(tv, tab, TV_ZETA, t)
    wn = tv_eval(tv, tab, TV_WN, t)
    xs = y[S_XS]
    vs = y[S_VS]
    pA = y[S_PA]
    pB = y[S_PB]
    x = y[S_X]
    v = y[S_V]
    u = control(t, y, P, sigp, sc, nzp, nzc)
    # servo-valve, second order
    out[S_XS] = vs
    out[S_VS] = wn * wn * (P[KE] * P[KSP] * u - xs) - 2.0 * zeta * wn * vs
    # valve and leakage flows
    pS = y[S_PV] if P[SUP_ON] > 0.0 else P[PP]
    qA, qB, qS = valve_flows(xs, pA, pB, P, Cd, pS)
    dp = pA - pB
    qL = CdAleak * math.sqrt(2.0 / P[RHO]) * ssqrt(dp, P[DPREG]) + P[GLAM] * dp
    B = P[BULK]
    if P[TEMP_ON] > 0.0:  # warm oil: softer, thinner (module docstring)
        dT = tv_eval(tv, tab, TV_TEMP, t) - P[TREF]
        B *= 1.0 - P[ABULK] * dT
        qL *= math.exp(P[BVISC] * dT)
    A = P[AREA]
    Ab = P[AREA_B]  # the rod side's annulus (a single-rod cylinder: smaller than A)
    V0v = P[V0]
    VA = max(V0v + A * x, 1e-3 * V0v)
    VB = max(P[V0_B] - Ab * x, 1e-3 * P[V0_B])
    out[S_PA] = _bulk(pA, P, B) * (qA - qL - A * v) / VA
    out[S_PB] = _bulk(pB, P, B) * (-qB + qL + Ab * v) / VB
    # rod: dry (tanh) friction, Stribeck rise, viscous, specimen spring, second mass
    fs = P[FSTR]
    fd = Ffric
    if fs > 0.0:
        fd += fs * math.exp(-abs(v) / P[VSTR])
    F = pA * A - pB * Ab - fd * math.tanh(v / P[VREF]) - P[CVISC] * v - P[FEXT] - tv_eval(tv, tab, TV_KSPEC, t) * x
    if P[M2] > 0.0:
        Fc = P[K2] * (x - y[S_X2]) + P[C2] * (v - y[S_V2])
        F -= Fc
        out[S_X2] = y[S_V2]
        out[S_V2] = Fc / P[M2]
    out[S_X] = v
    out[S_V] = F / P[MASS]
    # analog controller states
    if int(P[MODE]) == M_ANALOG and (P[KI] != 0.0 or P[KD] != 0.0):
        r = sig_eval(sigp, sc, t, int(P[SEG]))
        xm = measured_nonoise(y, P)
        if P[NOISE_ON] > 0.0:
            xm += sig_eval(nzp, nzc, t, -1)
        e = r - xm
        out[S_ZI] = e
        out[S_ZD] = (e - y[S_ZD]) / P[TD]
    if P[SUP_ON] > 0.0:  # the supply: pump, hose, accumulator (module docstring)
        ah = 0.25 * math.pi * P[HOSE_D] ** 2
        vh = 0.5 * P[HOSE_L] * ah  # half the hose's oil at each end
        pu = y[S_PU]
        qh = y[S_QH]
        qp = P[PUMP_Q] * min(max((P[PP] - pu) / P[PUMP_BAND], 0.0), 1.0)
        out[S_PU] = B * (qp - qh) / (P[PUMP_V] + vh)
        r_lam = 128.0 * P[MU] * P[HOSE_L] / (math.pi * P[HOSE_D] ** 4)
        out[S_QH] = (pu - pS - r_lam * qh) / (P[RHO] * P[HOSE_L] / ah)
        pabs = max(pS + P[PATM], P[PATM])
        if pabs > P[ACC_P]:  # gas charged: V = V0 (p0 / p)^(1/n), compliance -dV/dp = V / (n p)
            c_gas = P[ACC_V] * (P[ACC_P] / pabs) ** (1.0 / P[ACC_N]) / (P[ACC_N] * pabs)
        else:
            c_gas = 0.0
        out[S_PV] = (qh - qS) / (c_gas + vh / B)
    if P[TAUP] > 0.0:  # pressure transducers: first-order lag of their readings
        out[S_PAM] = (pA - y[S_PAM]) / P[TAUP]
        out[S_PBM] = (pB - y[S_PBM]) / P[TAUP]
    n = int(P[PADE_N])
    if n > 0:  # Pade delay in time normalised by the delay (states of the size of x)
        w = P[GAIN] * x
        itau = 1.0 / P[PTAU]
        for i in range(n - 1):
            out[S_Z0 + i] = y[S_Z0 + i + 1] * itau
        acc = w
        for i in range(n):
            acc -= P[PA0 + i] * y[S_Z0 + i]
        out[S_Z0 + n - 1] = acc * itau
    return out


@nb.njit(cache=True)
def rhs_sub(t, yr, idx, P, tv, tab, sigp, sc, nzp, nzc):
    """:func:`rhs` on the active states ``idx`` only (the others stay zero)."""
    y = np.zeros(NS)
    for i in range(idx.size):
        y[idx[i]] = yr[i]
    d = rhs(t, y, P, tv, tab, sigp, sc, nzp, nzc)
    out = np.empty(idx.size)
    for i in range(idx.size):
        out[i] = d[idx[i]]
    return out
