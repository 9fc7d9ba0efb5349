"""Augmented-state unscented Kalman filter of the MSP25 rig, compiled end to end.

State (``n = 6 + p + q``):

* the six model states, scaled so the covariance is well conditioned (spool
  position in mm, spool velocity in 0.1 m/s, pressures in MPa, rod position in
  mm, rod velocity in 0.1 m/s);
* ``p`` tracked phenomenological parameters, each as a *logit between its
  physical bounds*: ``theta = lo * (hi/lo) ** sigmoid(z)``.  An estimate can
  never leave ``[lo, hi]`` (the bounds are a property of the physics, see
  :meth:`twin.models.base.Model.tracking_bounds`), and no sigma point can either;
* ``q`` sensor-noise states, one per measured output: an AR(1) process
  ``eta' = a eta + w``, ``var(eta) = sigma^2`` (scaled units).  ``a = 0`` is
  white noise; ``a > 0`` is coloured noise, which the filter then separates
  from the signal instead of reading it as a parameter change.  The
  measurement is ``z = (model output) + eta + v`` with a small white floor ``v``.

The algorithm is filterpy's ``UnscentedKalmanFilter`` with
``MerweScaledSigmaPoints`` (sigma points from the Cholesky factor of
``(lambda + n) P``, mean and covariance by the unscented transform plus
``Q``).  The noise states come last: a sigma point along one of them differs
from the mean only in noise coordinates (the Cholesky factor is triangular),
so the rig model is integrated for ``2 (6 + p) + 1`` sigma points only, and on
the open-loop path of a rig without effects they are integrated side by side,
vectorised across sigma points (:func:`lean_lanes`; the same numbers as one
point at a time, bit for bit).  The
measurement function ``H x`` (model output plus noise state) is linear: the
unscented update is then exactly the Kalman update, which is what we compute.

Prediction honours the loop's timing and the time between samples, read on
the nominal grid (a step is the nearest whole number of sample periods; the
rest is time-stamp jitter, :func:`twin.record.grid_steps`):
one log interval is advanced with :func:`twin.models.msp25.advance` (digital
controller at the log's rate, N times faster, or continuous; logged inputs
held, linear or cubic between samples).  A logged ``u`` between samples k-1
and k is interpolated from ``u[k-2], u[k-1], u[k]``: the filter has sample k
when it predicts up to it, so ``foh`` is exact, and ``cubic`` uses a one-sided
end slope (no look-ahead beyond the sample being filtered).  Driven by the
demand, the rig's controller (PID with derivative filter, feed-forward,
output limit) keeps its memory from sample to sample (``fs[F_CTRL:]``, moved
on along the central sigma point).  A longer
interval (dropped rows, lost frames) is predicted in as many log steps as it
spans with the input linear across the gap; beyond ``gap_max`` seconds the
model states are re-initialised from the measurement with the prior
covariance (status ``reinitialised``), the parameters keep their estimates
with an inflated covariance.

Per sample the kernel reports innovation, its variance, NIS, log-likelihood,
a filter status (:data:`STATUS`), a guard code (:data:`GUARD`: why the drift
test must hold its evidence on this sample, 0 = it need not) and a sensor
status per output (:data:`SENSOR`).

The consistency guard watches the normalised innovations: an exponential
average of the NIS per measurement (each sample clipped at ``nis_clip`` so a
short transient of a real change does not count as inconsistency) and the
lag-one autocorrelation of each output's normalised innovation (whiteness).
While either is out of its band the filter is ``inconsistent`` with the data
(model mismatch, unlearnt noise): the drift test holds.  A fast average of
the NIS beyond ``div_nis``, a parameter pinned at a bound, or a non-finite
state is *divergence*: the filter goes back to its last consistent checkpoint
(parameters and their covariance, inflated), re-reads the model states from
the measurement, and says ``recovered``.

Noise learning (covariance matching over a window): per output, the average
of the squared normalised innovation ``c`` drives ``log sigma^2`` towards
``c = 1`` and the lag-one autocorrelation ``rho`` drives the AR coefficient
``a`` towards white innovations, both with time constant ``tau_noise``.

Sensor faults are named from the signal and the innovations, per output:
``stuck`` (the same value repeated while the model says it moves),
``clipped`` (held at a value the model says it passes), ``offset`` (this
output alone far from the model for a while), ``wrong_unit`` (off by a power
of ten, or outside the physical range), ``noisy`` (learnt noise beyond
``noisy_factor`` times the rig's nominal).  A faulty output (other than
noisy) is not used in the update until it is consistent again.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from twin.models import msp25 as M
from twin.models.intersample import input_at
from twin.models import intersample as _intersample_src
from twin.models import base as _base_src
from twin.models.jitcache import keep_fresh

# the machine code cached for this module inlines these modules' compiled code and constants
keep_fresh(__file__, M.__file__, _intersample_src.__file__, _base_src.__file__)

#: state scales (SI per filter unit) of the six model states
STATE_SCALE = np.array([1e-3, 0.1, 1e6, 1e6, 1e-3, 0.1])
#: measured outputs and their state index
MEAS_INDEX = {"x": 4, "pA": 2, "pB": 3}
#: the parameters the kernel can track: those whose spec declares a Tracking (twin/models/msp25.py)
TRACKABLE = M.MODEL.trackable
#: excitation channels (``chan`` of the kernel) follow :data:`twin.params.EXCITATION`: 0 rod motion,
#: 1 valve command, 2 pressure difference; each parameter's is declared in its spec's Tracking
#: largest standard deviation (log units) the parameter random walk grows a parameter's uncertainty to
PARAM_STD_CAP = 1.0
STATUS = ("ok", "gated", "repaired_covariance", "stale_input", "frozen", "gap", "reinitialised", "recovered",
          "sensor_fault")
(ST_OK, ST_GATED, ST_REPAIRED, ST_STALE, ST_FROZEN, ST_GAP, ST_REINIT, ST_RECOVERED,
 ST_SENSOR) = range(len(STATUS))
#: why the drift test holds its evidence on a sample (0: it need not)
GUARD = ("consistent", "settling", "inconsistent_nis", "inconsistent_colour", "sensor_fault", "diverged")
G_OK, G_SETTLE, G_NIS, G_COLOUR, G_SENSOR, G_DIVERGED = range(len(GUARD))
#: sensor status per output
SENSOR = ("ok", "noisy", "stuck", "clipped", "offset", "wrong_unit", "missing")
S_OK, S_NOISY, S_STUCK, S_CLIPPED, S_OFFSET, S_UNIT, S_MISSING = range(len(SENSOR))

# guard / detector settings (array CFG): index names
(C_NIS_CLIP, C_NIS_HI, C_RHO_HI, C_TAU_GUARD, C_DIV_NIS, C_TAU_DIV, C_SETTLE_S, C_CK_S, C_INFLATE, C_GAP_MAX,
 C_TAU_NOISE, C_ADAPT, C_NOISY, C_OUT_NU, C_OFF_N, C_STUCK_N, C_CLEAR_N, C_ZPIN, C_SIG_LO, C_SIG_HI,
 C_A_MAX, C_STROKE, C_PMIN, C_PMAX, C_WARM_S) = range(25)
N_CFG = 25
# carried float state (array FS)
(F_NIS_EMA, F_NIS_FAST, F_SETTLE, F_CK_T, F_T, F_HAVE_PREV, F_U1, F_U2, F_R1, F_R2, F_XM1, F_EXC0, F_EXC1,
 F_EXC2, F_UPREV_OK, F_GATED_RUN, F_RECOVERIES, F_REINITS, F_CK_OK) = range(19)
F_CTRL = 19  # the rig controller's memory (twin.models.msp25.N_CTRL entries) when the drive is the demand
N_FS = F_CTRL + M.N_CTRL
# per-output carried state (array CH [q, N_CH])
(H_SIG, H_A, H_C, H_R1, H_NU_PREV, H_LAST_RAW, H_RUN_SAME, H_OUT_RUN, H_CLEAR_RUN, H_STATUS, H_UNIT_RUN,
 H_SIG_NOM, H_R_FLOOR, H_HAVE_NU, H_EXT) = range(15)
N_CH = 15


@nb.njit(cache=True)
def _chol_lower(A, L):
    """Cholesky factor ``L`` (lower) of ``A``; returns False if ``A`` is not positive definite."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0) or not math.isfinite(s):
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@nb.njit(cache=True)
def _repair(P, floor):
    """Symmetrise ``P`` and clip its eigenvalues to ``floor``; False if it is not finite."""
    n = P.shape[0]
    for i in range(n):
        for j in range(n):
            if not math.isfinite(P[i, j]):
                return False
    S = 0.5 * (P + P.T)
    w, V = np.linalg.eigh(S)
    for i in range(n):
        if w[i] < floor[i]:
            w[i] = floor[i]
    P[:, :] = (V * w) @ V.T
    return True


@nb.njit(cache=True)
def _all_finite(x, P):
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]):
            return False
        for j in range(x.shape[0]):
            if not math.isfinite(P[i, j]):
                return False
    return True


@nb.njit(cache=True, inline="always")
def sigmoid(z):
    if z >= 0.0:
        return 1.0 / (1.0 + math.exp(-z))
    e = math.exp(z)
    return e / (1.0 + e)


@nb.njit(cache=True, inline="always")
def theta_of(z, lo_log, width):
    """Parameter value (SI) of the logit coordinate ``z`` between ``exp(lo_log)`` and ``exp(lo_log + width)``."""
    return math.exp(lo_log + width * sigmoid(z))


@nb.njit(cache=True, inline="always")
def dlog_dz(z, width):
    """d log(theta) / dz: converts the logit's standard deviation to a relative one."""
    s = sigmoid(z)
    return width * s * (1.0 - s)


@nb.njit(cache=True, inline="always")
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


@nb.njit(cache=True, inline="always")
def _lean_deriv(xs, vs, pA, pB, x, v, u, c):
    """:func:`twin.models.msp25.deriv` with every effect at its neutral value, constants precomputed in ``c``
    (see :func:`_lean_consts`); the tracker's hot path. Tested equal to the model's right-hand side."""
    dxs = vs
    dvs = c[0] * (c[2] * u - xs) - c[1] * vs
    g = c[3]
    pP = c[4]
    pT = c[5]
    dl2 = c[6]
    if xs >= 0.0:
        d1 = pP - pA
        d2 = pB - pT
        qPA = g * xs * (d1 / math.sqrt(math.sqrt(d1 * d1 + dl2)))
        qBT = g * xs * (d2 / math.sqrt(math.sqrt(d2 * d2 + dl2)))
        qAT = 0.0
        qPB = 0.0
    else:
        d1 = pA - pT
        d2 = pP - pB
        qAT = -g * xs * (d1 / math.sqrt(math.sqrt(d1 * d1 + dl2)))
        qPB = -g * xs * (d2 / math.sqrt(math.sqrt(d2 * d2 + dl2)))
        qPA = 0.0
        qBT = 0.0
    dpAB = pA - pB
    qAB = c[7] * (dpAB / math.sqrt(math.sqrt(dpAB * dpAB + c[8])))
    qA = qPA - qAT - qAB
    qB = qPB - qBT + qAB
    A = c[10]
    V0 = c[11]
    AB = c[16]
    V0B = c[17]
    VA = max(V0 + A * x, 1e-3 * V0)
    VB = max(V0B - AB * x, 1e-3 * V0B)
    dpA = c[9] * (qA - A * v) / VA
    dpB = c[9] * (qB + AB * v) / VB
    Ffr = c[13] * fast_tanh(v * c[14])
    dv = (dpAB * A - pB * (AB - A) - Ffr - c[15]) * c[12]
    return dxs, dvs, dpA, dpB, v, dv


@nb.njit(cache=True, inline="always")
def _lean_consts(p, c):
    wn = p[M.I_WN]
    c[0] = wn * wn
    c[1] = 2.0 * p[M.I_ZETA] * wn
    c[2] = p[M.I_KE] * p[M.I_KSP]
    c[3] = p[M.I_CD] * p[M.I_B] * math.sqrt(2.0 / p[M.I_RHO])
    c[4] = p[M.I_PP]
    c[5] = p[M.I_PT]
    c[6] = p[M.I_DPL] * p[M.I_DPL]
    c[7] = p[M.I_CDALEAK] * math.sqrt(2.0 / p[M.I_RHO])
    c[8] = p[M.I_DPLL] * p[M.I_DPLL]
    c[9] = p[M.I_BULK]
    c[10] = p[M.I_A]
    c[11] = p[M.I_V0]
    c[12] = 1.0 / p[M.I_M]
    c[13] = p[M.I_FFRIC]
    c[14] = 1.0 / p[M.I_VREF]
    c[15] = p[M.I_FEXT]
    c[16] = p[M.I_AB] if p[M.I_AB] > 0.0 else p[M.I_A]
    c[17] = p[M.I_V0B] if p[M.I_V0B] > 0.0 else p[M.I_V0]


@nb.njit(cache=True)
def lean_applicable(p):
    """True when every effect of the kernel vector ``p`` sits at its neutral value (the lean path is exact)."""
    return (p[M.I_CVISC] == 0.0 and p[M.I_FBRK] == 0.0 and p[M.I_KLAM] == 0.0 and p[M.I_XSDB] == 0.0
            and p[M.I_XSBIAS] == 0.0 and p[M.I_RSUP] == 0.0 and p[M.I_KSPEC] == 0.0 and p[M.I_TAUX] == 0.0
            and p[M.I_EPS] == 0.0 and p[M.I_XSMAX] >= 1.0 and p[M.I_KXM] == 1.0 and p[M.I_KSUP2] == 0.0)


@nb.njit(cache=True, inline="always")
def _stage_inputs(wnd, f0, fh, mode):
    """The logged input at an RK4 substep's start, middle and end (window ``wnd``, index 1 = this sample;
    ``f0``, ``fh``: the substep's start and length as fractions of the sample interval)."""
    if mode == 0:
        u = wnd[1]
        return u, u, u
    return input_at(wnd, 1, f0, mode), input_at(wnd, 1, f0 + 0.5 * fh, mode), input_at(wnd, 1, f0 + fh, mode)


@nb.njit(cache=True)
def lean_step(s, wnd, mode, c, dt, nsub, out):
    """One log interval, open loop, of the logged input ``wnd`` (index 1 = this sample) interpolated by
    ``mode``: :func:`twin.models.msp25.advance` with ``closed=False`` for a rig without effects."""
    h = dt / nsub
    fh = 1.0 / nsub
    a0, a1, a2, a3, a4, a5 = s[0], s[1], s[2], s[3], s[4], s[5]
    for j in range(nsub):
        f0 = j * fh
        u1, u2, u4 = _stage_inputs(wnd, f0, fh, mode)
        k1 = _lean_deriv(a0, a1, a2, a3, a4, a5, u1, c)
        k2 = _lean_deriv(a0 + 0.5 * h * k1[0], a1 + 0.5 * h * k1[1], a2 + 0.5 * h * k1[2],
                         a3 + 0.5 * h * k1[3], a4 + 0.5 * h * k1[4], a5 + 0.5 * h * k1[5], u2, c)
        k3 = _lean_deriv(a0 + 0.5 * h * k2[0], a1 + 0.5 * h * k2[1], a2 + 0.5 * h * k2[2],
                         a3 + 0.5 * h * k2[3], a4 + 0.5 * h * k2[4], a5 + 0.5 * h * k2[5], u2, c)
        k4 = _lean_deriv(a0 + h * k3[0], a1 + h * k3[1], a2 + h * k3[2],
                         a3 + h * k3[3], a4 + h * k3[4], a5 + h * k3[5], u4, c)
        a0, a1, a2, a3, a4, a5 = M.rk4_combine(a0, a1, a2, a3, a4, a5, k1, k2, k3, k4, h)
    M.store6(out, a0, a1, a2, a3, a4, a5)


@nb.njit(cache=True)
def fx_into(s, wnd, closed, ticks, mode, p, idx, lo_log, width, scale, h, nsub, xm, ctrl, si, so, out, nmod):
    """One log interval of one augmented state with the drive window ``wnd`` (see :func:`_drive_window`).

    Writes the model states and parameters of ``out`` (``nmod = 6 + p`` entries); ``p`` is overwritten at
    ``idx``; no allocation.
    """
    for j in range(idx.shape[0]):
        p[idx[j]] = theta_of(s[6 + j], lo_log[j], width[j])
    for j in range(6):
        si[j] = s[j] * scale[j]
    if not closed and ctrl.shape[0] > K_FLAG and ctrl[K_FLAG] > 0.0:  # lean path: open loop, no effects
        _lean_consts(p, ctrl[K_LEAN:])
        lean_step(si, wnd, mode, ctrl[K_LEAN:], h, nsub, so)
    else:
        # the controller starts the interval from the rig controller's memory (carried by the kernel; a bare
        # memory array starts at rest)
        for j in range(M.N_CTRL):
            ctrl[j] = ctrl[K_CARRY + j] if ctrl.shape[0] >= N_K else 0.0
        M.advance(si, 1, wnd, closed, ticks, mode, p, h, nsub, xm, ctrl, so)
    for j in range(6):
        out[j] = so[j] / scale[j]
    for j in range(6, nmod):
        out[j] = s[j]


# --- the sigma points of the lean path, all at once --------------------------------------------------------------
# One work vector ``W [N_W * LANES]``: row ``r`` (one quantity) of lane ``ln`` (one sigma point that needs the model)
# at ``r * LANES + ln``.  The right-hand side then runs over the lanes in one loop the compiler vectorises (square
# roots and divisions of 8 sigma points per instruction): a constant row stride lets it prove that the rows do not
# overlap, and a constant lane count leaves no scalar remainder.  Each lane computes exactly what :func:`lean_step`
# computes for its sigma point (the same operations in the same order); unused lanes repeat lane 0.
LANES = 8 * ((2 * (6 + len(TRACKABLE)) + 1 + 7) // 8)
N_LEAN = 18  # constants of the lean right-hand side (:func:`_lean_consts`)
W_A, W_Y, W_ACC, W_K, W_C, W_TH, W_P0 = 0, 6, 12, 18, 24, 24 + N_LEAN, 25 + N_LEAN  # W_P0: the central point's
N_W = 26 + N_LEAN
# the controller work array ``ctrl`` of the kernel: the model's controller memory (working copy), the lean-path
# flag, the lean constants, the controller memory at the interval's start (the rig's controller, carried from
# sample to sample) and at its end along the central sigma point
K_FLAG = M.N_CTRL
K_LEAN = K_FLAG + 1
K_CARRY = K_LEAN + N_LEAN
K_NEXT = K_CARRY + M.N_CTRL
N_K = K_NEXT + M.N_CTRL
# the lanes recompute only the constants (:func:`_lean_consts`) of these parameters per sigma point
assert set(TRACKABLE) <= {"Ffric", "CdAleak", "Cd", "zeta", "wn"}, "a new trackable parameter: see _lean_sigmas"


@nb.njit(cache=True, error_model="numpy")
def _lanes_deriv(W, u):
    """:func:`_lean_deriv` of every lane at the stage input (rows ``W_Y``) into rows ``W_K``."""
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
        # the valve's two flow paths as selects: the numbers of _lean_deriv's branches
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


@nb.njit(cache=True, error_model="numpy")
def lean_lanes(W, wnd, mode, dt, nsub):
    """:func:`lean_step` of every lane of ``W`` (states in rows ``W_A``, constants in rows ``W_C``), in place."""
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
def _lean_sigmas(sig, sf, rows, m, wnd, mode, pw, idx, lo_log, width, scale, h, nsub, W, c, nmod):
    """The model part (``nmod`` entries) of ``sf[rows[ln]]`` for the sigma points ``sig[rows[ln]]``, ``ln < m <=
    LANES``: :func:`fx_into` on the lean path for all of them at once.

    Only the constants of the tracked parameters differ between lanes (:func:`_lean_consts`' expressions); a
    parameter at the central point's value (a sigma point along a later state) reuses its value."""
    p_count = idx.shape[0]
    s0 = sig[rows[0]]
    for j in range(p_count):
        pw[idx[j]] = theta_of(s0[6 + j], lo_log[j], width[j])
    _lean_consts(pw, c)
    for i in range(N_LEAN):
        for ln in range(LANES):
            W[(W_C + i) * LANES + ln] = c[i]
    s2r = math.sqrt(2.0 / pw[M.I_RHO])
    for ln in range(LANES):
        s = sig[rows[ln if ln < m else 0]]
        for j in range(p_count):
            zj = s[6 + j]
            pw[idx[j]] = W[W_P0 * LANES + j] if ln > 0 and zj == s0[6 + j] else theta_of(zj, lo_log[j], width[j])
            if ln == 0:
                W[W_P0 * LANES + j] = pw[idx[j]]
        wn = pw[M.I_WN]
        W[W_C * LANES + ln] = wn * wn
        W[(W_C + 1) * LANES + ln] = 2.0 * pw[M.I_ZETA] * wn
        W[(W_C + 3) * LANES + ln] = pw[M.I_CD] * pw[M.I_B] * s2r
        W[(W_C + 7) * LANES + ln] = pw[M.I_CDALEAK] * s2r
        W[(W_C + 13) * LANES + ln] = pw[M.I_FFRIC]
        for i in range(6):
            W[(W_A + i) * LANES + ln] = s[i] * scale[i]
    lean_lanes(W, wnd, mode, h, nsub)
    for ln in range(m):
        r = rows[ln]
        for i in range(6):
            sf[r, i] = W[(W_A + i) * LANES + ln] / scale[i]
        for i in range(6, nmod):
            sf[r, i] = sig[r, i]


def fx_one(s, u_prev, u_now, pvec, idx, lo_log, width, scale, dt, nsub, noise_a, closed=False, ticks=1, mode=0,
           u_before=None, xm=0.0):
    """Propagate one augmented state over one log interval (for tests and filterpy): returns the new state.

    ``u_before``, ``u_prev``, ``u_now``: the drive at samples k-2, k-1, k; ``noise_a``: AR coefficients.
    """
    n = s.shape[0]
    nmod = 6 + idx.shape[0]
    out = np.empty(n)
    wnd = np.array([u_prev if u_before is None else u_before, u_prev, u_now, u_now], dtype=np.float64)
    fx_into(np.ascontiguousarray(s, dtype=np.float64), wnd, closed, ticks, mode, pvec.copy(), idx, lo_log, width,
            scale, dt, nsub, xm, np.zeros(M.N_CTRL), np.empty(6), np.empty(6), out, nmod)
    for j in range(nmod, n):
        out[j] = noise_a[j - nmod] * s[j]
    return out


@nb.njit(cache=True)
def _predict(x, P, wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub, xm, Q, Wm, Wc, lam, floor,
             nmod, a_pow, L, A, sig, sf, si, so, ctrl, W, rows):
    """filterpy's predict over one interval; returns the status (ok or repaired_covariance) or -1."""
    n = x.shape[0]
    status = ST_OK
    for i in range(n):
        for j in range(n):
            A[i, j] = (lam + n) * P[i, j]
    if not _chol_lower(A, L):
        if not _repair(P, floor):
            return -1
        status = ST_REPAIRED
        for i in range(n):
            for j in range(n):
                A[i, j] = (lam + n) * P[i, j]
        if not _chol_lower(A, L):
            return -1
    for i in range(n):
        sig[0, i] = x[i]
    for k in range(n):
        for i in range(n):
            sig[k + 1, i] = x[i] + L[i, k]
            sig[n + k + 1, i] = x[i] - L[i, k]
    if not closed and ctrl[K_FLAG] > 0.0 and 2 * nmod + 1 <= LANES:  # lean path: the sigma points that move the model
        m = 0
        for k in range(2 * n + 1):
            if k == 0 or (k - 1) % n < nmod:
                rows[m] = k
                m += 1
        _lean_sigmas(sig, sf, rows, m, wnd, mode, pw, idx, lo_log, width, scale, h, nsub, W, ctrl[K_LEAN:], nmod)
    else:
        fx_into(sig[0], wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub, xm, ctrl, si, so, sf[0],
                nmod)
        for j in range(M.N_CTRL):  # the controller's memory at the interval's end, along the central point
            ctrl[K_NEXT + j] = ctrl[j]
        for k in range(nmod):
            fx_into(sig[k + 1], wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub, xm, ctrl, si, so,
                    sf[k + 1], nmod)
            fx_into(sig[n + k + 1], wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub, xm, ctrl, si,
                    so, sf[n + k + 1], nmod)
    for k in range(nmod, n):  # along a noise state only: the model part is the central point's
        for i in range(nmod):
            sf[k + 1, i] = sf[0, i]
            sf[n + k + 1, i] = sf[0, i]
    for k in range(2 * n + 1):
        for i in range(nmod, n):
            sf[k, i] = a_pow[i - nmod] * sig[k, i]
    for i in range(n):
        acc = 0.0
        for k in range(2 * n + 1):
            acc += Wm[k] * sf[k, i]
        x[i] = acc
    for k in range(2 * n + 1):  # deviations from the mean, in place (sig is not needed any more)
        for i in range(n):
            sig[k, i] = sf[k, i] - x[i]
    for i in range(n):
        for j in range(i, n):
            P[i, j] = Q[i, j]
    for k in range(2 * n + 1):
        w = Wc[k]
        for i in range(n):
            a = w * sig[k, i]
            for j in range(i, n):
                P[i, j] += a * sig[k, j]
    for i in range(n):
        for j in range(i + 1, n):
            P[j, i] = P[i, j]
    for i in range(n):
        if not math.isfinite(x[i]):
            return -1
    return status


@nb.njit(cache=True)
def _update(x, P, z, meas_idx, eta0, R, use, freeze, gate, innov, Sdiag):
    """Kalman update with outputs ``use`` (model state ``meas_idx[j]`` plus noise state ``eta0 + j``).

    Returns (status, nis, loglik, m) with m the number of measurements used.
    ``freeze[j]`` True: state ``j`` gets no update (consider update, Joseph form).
    ``eta0 < 0``: no noise states (white measurement noise ``R`` only).
    """
    n = x.shape[0]
    q = meas_idx.shape[0]
    return _update_into(x, P, z, meas_idx, eta0, R, use, freeze, gate, innov, Sdiag, np.empty(q, dtype=np.int64),
                        np.empty((4 * q + 1, q)), np.empty((2 * n, q)), np.empty((n, n)))


@nb.njit(cache=True)
def _update_into(x, P, z, meas_idx, eta0, R, use, freeze, gate, innov, Sdiag, sel, WQ, WN, B):
    """:func:`_update` in preallocated work arrays: ``sel [q]``, ``WQ [4q + 1, q]``, ``WN [2n, q]``, ``B [n, n]``."""
    n = x.shape[0]
    mall = meas_idx.shape[0]
    m = 0
    for i in range(mall):
        if use[i]:
            sel[m] = i
            m += 1
    if m == 0:
        return ST_STALE, np.nan, np.nan, 0
    S = WQ[:m, :m]
    Ls = WQ[mall:mall + m, :m]
    Li = WQ[2 * mall:2 * mall + m, :m]
    SI = WQ[3 * mall:3 * mall + m, :m]
    y = WQ[4 * mall, :m]
    PHt = WN[:n, :m]
    K = WN[n:2 * n, :m]
    for a in range(m):
        ja = sel[a]
        ia = meas_idx[ja]
        ea = eta0 + ja
        pred = x[ia] + (x[ea] if eta0 >= 0 else 0.0)
        y[a] = z[ja] - pred
        for i in range(n):
            PHt[i, a] = P[i, ia] + (P[i, ea] if eta0 >= 0 else 0.0)
    for a in range(m):
        ia = meas_idx[sel[a]]
        ea = eta0 + sel[a]
        for b in range(m):
            S[a, b] = PHt[ia, b] + (PHt[ea, b] if eta0 >= 0 else 0.0)
        S[a, a] += R[sel[a]]
    if not _chol_lower(S, Ls):
        return ST_GATED, np.inf, -np.inf, m
    logdet = 0.0
    for i in range(m):
        logdet += 2.0 * math.log(Ls[i, i])
        Li[i, i] = 1.0 / Ls[i, i]
        for j in range(i):
            acc = 0.0
            for k in range(j, i):
                acc -= Ls[i, k] * Li[k, j]
            Li[i, j] = acc / Ls[i, i]
    for a in range(m):
        for b in range(m):
            acc = 0.0
            for k in range(max(a, b), m):
                acc += Li[k, a] * Li[k, b]
            SI[a, b] = acc
    nis = 0.0
    for a in range(m):
        for b in range(m):
            nis += y[a] * SI[a, b] * y[b]
    loglik = -0.5 * (nis + logdet + m * math.log(2.0 * math.pi))
    for a in range(m):
        innov[sel[a]] = y[a]
        Sdiag[sel[a]] = S[a, a]
    if nis > gate:
        return ST_GATED, nis, loglik, m
    for i in range(n):
        for b in range(m):
            acc = 0.0
            for a in range(m):
                acc += PHt[i, a] * SI[a, b]
            K[i, b] = acc
    any_frozen = False
    for i in range(n):
        if freeze[i]:
            any_frozen = True
            for a in range(m):
                K[i, a] = 0.0
    for i in range(n):
        acc = 0.0
        for a in range(m):
            acc += K[i, a] * y[a]
        x[i] += acc
    if not any_frozen:  # P -= K S K' = K (P H')'
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for a in range(m):
                    acc += K[i, a] * PHt[j, a]
                P[i, j] -= acc
    else:  # Joseph form: P = (I - K H) P (I - K H)' + K R K', H picking model state plus noise state
        for i in range(n):  # B = (I - K H) P = P - K (P H')'
            for j in range(n):
                acc = 0.0
                for a in range(m):
                    acc += K[i, a] * PHt[j, a]
                B[i, j] = P[i, j] - acc
        for i in range(n):  # P = B (I - K H)' + K R K'
            for j in range(n):
                acc = 0.0
                kr = 0.0
                for a in range(m):
                    bh = B[i, meas_idx[sel[a]]] + (B[i, eta0 + sel[a]] if eta0 >= 0 else 0.0)
                    acc += bh * K[j, a]
                    kr += K[i, a] * R[sel[a]] * K[j, a]
                P[i, j] = B[i, j] - acc + kr
    for i in range(n):
        for j in range(i + 1, n):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v
    return ST_FROZEN if any_frozen else ST_OK, nis, loglik, m


@nb.njit(cache=True)
def _reinit_states(x, P, z, meas_idx, u, pvec, scale, prior_mod, ch, nmod, inflate, p_count, pmid):
    """Model states from the measurement (rest otherwise), prior covariance; parameters kept, inflated."""
    n = x.shape[0]
    q = meas_idx.shape[0]
    for i in range(6):
        x[i] = 0.0
    x[2] = pmid / scale[2]
    x[3] = pmid / scale[3]
    if math.isfinite(u):
        x[0] = pvec[M.I_KE] * pvec[M.I_KSP] * u / scale[0]
    for j in range(q):
        if math.isfinite(z[j]) and ch[j, H_STATUS] in (S_OK, S_NOISY):
            x[meas_idx[j]] = z[j]
    for j in range(nmod, n):
        x[j] = 0.0
    for i in range(n):
        for j in range(n):
            if i < 6 or j < 6 or i >= nmod or j >= nmod:
                P[i, j] = 0.0
    for i in range(6):
        P[i, i] = prior_mod[i] * prior_mod[i]
    for j in range(q):
        P[nmod + j, nmod + j] = ch[j, H_SIG] * ch[j, H_SIG]
    for i in range(6, nmod):
        for j in range(6, nmod):
            P[i, j] *= inflate


@nb.njit(cache=True, inline="always")
def _carry_controller(ctrl, fs, closed, ps):
    """After a prediction driven by the demand: the rig controller's memory moves on to the interval's end."""
    if closed and ps >= 0:
        for j in range(M.N_CTRL):
            ctrl[K_CARRY + j] = ctrl[K_NEXT + j]
            fs[F_CTRL + j] = ctrl[K_NEXT + j]


@nb.njit(cache=True, nogil=True)
def run_kernel(x, P, fs, ch, x_ck, P_ck, U, XREF, Z, DT, mia, closed, ticks, mode, dt0, pvec, idx, lo_log, width, scale,
               nsub, q_state, q_param, prior_mod, Wm, Wc, lam, floor, gate, max_gated, chan, thresh, tau_excite,
               x_col, cfg, X_out, Pd_out, nis_out, ll_out, st_out, innov_out, S_out, frozen_out, guard_out, sens_out,
               sig_out, used_out):
    """Filter ``T`` samples in place; ``x``, ``P``, ``fs``, ``ch``, ``x_ck``, ``P_ck`` carry over between calls.

    ``U[k]`` the logged controller output (NaN if missing), ``XREF[k]`` the demand (the drive when
    ``closed``), ``Z[k]`` scaled measurements (NaN = missing) of model states ``mia``, ``DT[k]`` seconds
    since the previous sample (NaN for the first sample ever), ``x_col`` the column of Z holding x (-1: not measured).
    Returns the index of an unrecoverable sample, or -1.
    """
    n = x.shape[0]
    T = U.shape[0]
    q = Z.shape[1]
    p_count = idx.shape[0]
    nmod = 6 + p_count
    L = np.zeros((n, n))
    A = np.empty((n, n))
    Q = np.zeros((n, n))
    pw = pvec.copy()
    si = np.empty(6)
    so = np.empty(6)
    ctrl = np.zeros(N_K)  # controller memory, lean-path flag, lean constants, carried memory (K_*)
    ctrl[K_FLAG] = 1.0 if lean_applicable(pvec) else 0.0
    for j in range(M.N_CTRL):
        ctrl[K_CARRY + j] = fs[F_CTRL + j]
    sig = np.empty((2 * n + 1, n))
    sf = np.empty((2 * n + 1, n))
    W = np.empty(N_W * LANES)
    rows = np.empty(2 * n + 1, dtype=np.int64)
    sel = np.empty(q, dtype=np.int64)
    WQ = np.empty((4 * q + 1, q))
    WN = np.empty((2 * n, q))
    B = np.empty((n, n))
    freeze = np.zeros(n, dtype=np.bool_)
    innov = np.empty(q)
    Sd = np.empty(q)
    nu = np.empty(q)
    use = np.zeros(q, dtype=np.bool_)
    R = np.empty(q)
    a_pow = np.empty(q)
    wnd = np.empty(4)
    unit_like = np.zeros(q, dtype=np.bool_)
    inn2 = np.empty(q)
    sd2 = np.empty(q)
    pmid = 0.5 * (pvec[M.I_PP] + pvec[M.I_PT])
    for k in range(T):
        dtk = DT[k]
        status = ST_OK
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
                freeze[6 + j] = True
            frozen_out[k, j] = freeze[6 + j]
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
                # process noise over the whole interval
                for i in range(n):
                    for j in range(n):
                        Q[i, j] = 0.0
                for i in range(6):
                    Q[i, i] = q_state[i] * dtk / dt0
                for j in range(p_count):
                    g = 1.0 / max(dlog_dz(x[6 + j], width[j]), 1e-12)
                    add = q_param[j] * dtk * g * g
                    cap = PARAM_STD_CAP * PARAM_STD_CAP * g * g
                    if P[6 + j, 6 + j] + add > cap:  # the random walk stops at the cap
                        add = max(0.0, cap - P[6 + j, 6 + j])
                    Q[6 + j, 6 + j] = add
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
                                  fs[F_XM1], Q, Wm, Wc, lam, floor, nmod, a_pow, L, A, sig, sf, si, so, ctrl, W, rows)
                    _carry_controller(ctrl, fs, closed, ps)
                else:  # across a gap: the drive linear from the last sample to this one
                    for j in range(q):
                        a_pow[j] = ch[j, H_A]
                    for i in range(n):
                        for j in range(n):
                            Q[i, j] /= nint
                    for s_i in range(nint):
                        f0 = s_i / nint
                        f1 = (s_i + 1) / nint
                        wnd[0] = fs[F_U1] + f0 * (a_now - fs[F_U1])
                        wnd[1] = wnd[0]
                        wnd[2] = fs[F_U1] + f1 * (a_now - fs[F_U1])
                        wnd[3] = wnd[2]
                        xm = fs[F_XM1] if s_i == 0 else x[4] * scale[4]
                        ps = _predict(x, P, wnd, closed, ticks, min(mode, 1), pw, idx, lo_log, width, scale, h,
                                      nsub, xm, Q, Wm, Wc, lam, floor, nmod, a_pow, L, A, sig, sf, si, so, ctrl, W,
                                      rows)
                        _carry_controller(ctrl, fs, closed, ps)
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
            if (j == x_col and abs(zj * scale[4]) > cfg[C_STROKE]) or \
                    (j != x_col and (zj * 1e6 < cfg[C_PMIN] or zj * 1e6 > cfg[C_PMAX])):
                use[j] = False
                unit_like[j] = True
            else:
                unit_like[j] = False
            # the largest excursion of the signal from its centre lately (a clip sits at it)
            cen = 0.0 if j == x_col else pmid / 1e6
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
            _reinit_states(x, P, zk, mia, a_now if not closed else np.nan, pvec, scale,
                           prior_mod, ch, nmod, cfg[C_INFLATE], p_count, pmid)
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
                centre = 0.0 if j == x_col else pmid / 1e6
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
                v2 = min(nu[j] * nu[j], 100.0)
                ch[j, H_C] += w_n * (v2 - ch[j, H_C])
                if ch[j, H_HAVE_NU] > 0.0:
                    r1 = max(-10.0, min(10.0, nu[j] * ch[j, H_NU_PREV]))
                    ch[j, H_R1] += w_n * (r1 - ch[j, H_R1])
                ch[j, H_NU_PREV] = nu[j]
                ch[j, H_HAVE_NU] = 1.0
                if cfg[C_ADAPT] > 0.0 and fs[F_SETTLE] <= 0.0:
                    cj = max(ch[j, H_C], 1e-3)
                    sg = ch[j, H_SIG] * math.exp(0.5 * w_n * math.log(min(max(cj, 0.25), 4.0)))
                    ch[j, H_SIG] = min(max(sg, cfg[C_SIG_LO] * ch[j, H_SIG_NOM]), cfg[C_SIG_HI] * ch[j, H_SIG_NOM])
                    rho = ch[j, H_R1] / cj
                    ch[j, H_A] = min(max(ch[j, H_A] + 2.0 * w_n * rho, 0.0), cfg[C_A_MAX])
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
            if abs(x[6 + j]) > cfg[C_ZPIN]:
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
            _reinit_states(x, P, zk, mia, a_now if not closed else np.nan, pvec, scale, prior_mod, ch, nmod,
                           cfg[C_INFLATE], p_count, pmid)
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
        if x_col >= 0 and math.isfinite(zk[x_col]) and use[x_col]:
            fs[F_XM1] = zk[x_col] * scale[4]
        else:
            fs[F_XM1] = x[4] * scale[4]
        u_exc = U[k] if math.isfinite(U[k]) else (pvec[M.I_KP] * (XREF[k] - fs[F_XM1]) if closed else fs[F_U1])
        du = abs(u_exc - fs[F_R1]) / max(dtk, dt0) if fs[F_UPREV_OK] > 0.0 and math.isfinite(u_exc) else 0.0
        alpha = min(1.0, max(dtk, dt0) / tau_excite)
        fs[F_EXC0] += alpha * (abs(x[5] * scale[5]) - fs[F_EXC0])
        fs[F_EXC1] += alpha * (du - fs[F_EXC1])
        fs[F_EXC2] += alpha * (abs(x[2] - x[3]) * scale[2] - fs[F_EXC2])
        if math.isfinite(u_exc):
            fs[F_R1] = u_exc
            fs[F_UPREV_OK] = 1.0
        fs[F_U2] = fs[F_U1] if math.isfinite(fs[F_U1]) else a_now
        fs[F_U1] = a_now
        fs[F_HAVE_PREV] = 1.0
    return -1


@nb.njit(cache=True)
def held_variance(V, DT, q, cap, state, out):
    """Variance of each parameter estimate's error *if the parameter has held still* (log units, in ``out``).

    The filter's own variance ``V`` assumes each parameter random-walks at its
    drift rate ``q`` (log units squared per second): that is what lets it follow
    a real change quickly, and what makes its interval too wide for a
    parameter that does not move (in a steady state the error variance of a
    constant parameter is about half of ``V``).  This is the suboptimal-filter
    analysis of the same gain with no random walk, one parameter at a time:
    with ``a = V_post / V_pred`` the filter's variance reduction on a sample,
    the error variance of a constant parameter follows
    ``E <- a^2 E + a (1 - a) V_pred`` (``E = V`` when ``q = 0``); a frozen
    parameter (``a = 1``) keeps ``E``; a covariance the filter inflated
    (re-initialisation, recovery) resets ``E`` to ``V``.  ``V_pred`` is the
    previous ``V`` plus ``q dt``, the random walk stopping at ``cap`` as the
    kernel's does.  ``DT``: seconds since the previous sample (NaN: none);
    ``state [2, p]``: (E, V) of the previous sample, NaN before any, updated.
    """
    T, p = V.shape
    for k in range(T):
        dt = DT[k]
        for j in range(p):
            v = V[k, j]
            e_prev = state[0, j]
            v_prev = state[1, j]
            if not (math.isfinite(v_prev) and math.isfinite(e_prev) and math.isfinite(dt)):
                e = v
            else:
                vp = min(v_prev + q[j] * max(dt, 0.0), max(v_prev, cap))
                if v > vp * (1.0 + 1e-9) or not (vp > 0.0):
                    e = v  # the filter inflated its covariance: the error is as large as the filter says
                else:
                    a = v / vp
                    e = a * a * e_prev + a * (1.0 - a) * vp
            if e > v:
                e = v
            out[k, j] = e
            state[0, j] = e
            state[1, j] = v
