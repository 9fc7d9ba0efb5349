"""The filter's update: the Kalman update of a linear measurement (model state plus sensor-noise state) with
per-output selection, gating and frozen (consider) rows, and the variance of a held-still parameter's error."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from twin.online.ukf_linalg import NO_REFCOUNT, _chol_lower
from twin.online.ukf_status import ST_FROZEN, ST_GATED, ST_OK, ST_STALE


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


@nb.njit(cache=True, **NO_REFCOUNT)
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
