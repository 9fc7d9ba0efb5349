"""Augmented-state unscented Kalman filter of the MSP25 rig, compiled end to end.

State (``n = 6 + p``): the six model states, scaled so the covariance is well
conditioned (spool position in mm, spool velocity in 0.1 m/s, pressures in MPa,
rod position in mm, rod velocity in 0.1 m/s), then ``p`` tracked
phenomenological parameters as ``z = log(theta / theta_ref)``: an estimate can
never leave the positive range, and ``std(z)`` is the relative uncertainty.

The algorithm is filterpy's ``UnscentedKalmanFilter`` with
``MerweScaledSigmaPoints`` (sigma points from the upper Cholesky factor of
``(lambda + n) P``, mean and covariance by the unscented transform plus
``Q``).  The measurement function selects ``x``, ``pA``, ``pB`` (whichever are
present in a sample), which is linear: the unscented update is then exactly the
Kalman update ``S = H P H' + R``, ``K = P H' S^-1`` (filterpy's re-drawn sigma
points reproduce ``H x`` and ``H P H'`` exactly), which is what we compute.
The tests run filterpy's own filter with the same ``fx`` and ``hx`` beside it.

Per sample the kernel reports the innovation, its covariance, NIS,
log-likelihood and a status code (:data:`STATUS`):

* ``ok``;
* ``gated``: an isolated outlier (NIS beyond a chi-square level at 1e-9) is
  not used; a run of them is accepted as a real change;
* ``repaired_covariance``: the covariance stopped being positive definite
  (filterpy would raise in ``cholesky``); it is symmetrised, its eigenvalues
  clipped, and the filter goes on;
* ``stale_input``: a sample without a usable input (u and x_ref missing): the
  previous input is held;
* ``frozen``: some parameters were not excited and got no update (Schmidt
  "consider" update with the Joseph form, so the covariance stays honest).

The random walk of a parameter stops adding variance once its standard
deviation has reached :data:`PARAM_STD_CAP` (log units).  A frozen parameter
gets no information, so without the cap its variance grows without bound while
the rig rests (0.3 log units per sqrt(s) for friction: a std of 18 after an
hour) and the first sigma points after the rest carry friction and valve
parameters to ``exp(+-18)`` times their values, where the model is no longer
finite.  The cap (a factor e at one sigma) lies above the default prior
(0.7, +-50 % inside one sigma) and is measured to be safe for the first
sigma points after a rest (1.5 is not); it never binds while a parameter is
observed or at the default prior, so the filterpy equivalence is untouched.

Excitation (what lets each parameter be seen) is measured on the data with
exponential moving averages over ``tau_excite`` seconds: friction needs the rod
moving, the valve parameters need the command changing, leakage needs a
pressure difference across the piston.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from twin.models import msp25 as M

#: state scales (SI per filter unit) of the six model states
STATE_SCALE = np.array([1e-3, 0.1, 1e6, 1e6, 1e-3, 0.1])
#: measured outputs and their state index
MEAS_INDEX = {"x": 4, "pA": 2, "pB": 3}
TRACKABLE = M.PHENOMENOLOGICAL
#: which excitation channel each parameter needs: 0 rod motion, 1 valve command, 2 pressure difference
EXCITE_CHANNEL = {"Ffric": 0, "CdAleak": 2, "Cd": 1, "zeta": 1, "wn": 1}
#: largest standard deviation (log units) the parameter random walk grows a parameter's uncertainty to
PARAM_STD_CAP = 1.0
STATUS = ("ok", "gated", "repaired_covariance", "stale_input", "frozen")
ST_OK, ST_GATED, ST_REPAIRED, ST_STALE, ST_FROZEN = range(5)


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
def fx_one(s, u, pvec, idx, ref, scale, dt, nsub, out):
    """Propagate one augmented (scaled) state over ``dt`` with input ``u`` held."""
    fx_into(s, u, pvec.copy(), idx, ref, scale, dt, nsub, out, np.empty(6), np.empty(6))


@nb.njit(cache=True)
def fx_into(s, u, p, idx, ref, scale, dt, nsub, out, si, so):
    """:func:`fx_one` with caller-owned work arrays (``p`` is overwritten at ``idx``): no allocation."""
    for j in range(idx.shape[0]):
        p[idx[j]] = ref[j] * math.exp(s[6 + j])
    for j in range(6):
        si[j] = s[j] * scale[j]
    M.step(si, u, p, dt, nsub, so)
    for j in range(6):
        out[j] = so[j] / scale[j]
    for j in range(6, s.shape[0]):
        out[j] = s[j]


@nb.njit(cache=True)
def _predict(x, P, u, pw, idx, ref, scale, dt, nsub, Q, Wm, Wc, lam, floor, L, A, sig, sf, si, so):
    """filterpy's predict; returns the status (ok or repaired_covariance) or -1 if unrepairable."""
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
    for k in range(2 * n + 1):
        fx_into(sig[k], u, pw, idx, ref, scale, dt, nsub, sf[k], si, so)
    for i in range(n):
        acc = 0.0
        for k in range(2 * n + 1):
            acc += Wm[k] * sf[k, i]
        x[i] = acc
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(2 * n + 1):
                acc += Wc[k] * (sf[k, i] - x[i]) * (sf[k, j] - x[j])
            q = Q[i, j]
            if i == j and i >= 6 and acc + q > PARAM_STD_CAP * PARAM_STD_CAP:
                q = max(0.0, PARAM_STD_CAP * PARAM_STD_CAP - acc)  # the random walk stops at the cap
            P[i, j] = acc + q
            P[j, i] = P[i, j]
    for i in range(n):
        if not math.isfinite(x[i]):
            return -1
    return status


@nb.njit(cache=True)
def _update(x, P, z, meas_idx, R, freeze, gate, innov, Sdiag):
    """Kalman update with the measured components ``z`` (NaN = missing) of states ``meas_idx``.

    Returns (status, nis, loglik, m) with m the number of measurements used.
    ``freeze[j]`` True: state ``j`` gets no update (consider update, Joseph form).
    """
    n = x.shape[0]
    mall = meas_idx.shape[0]
    use = np.empty(mall, dtype=np.int64)
    m = 0
    for i in range(mall):
        if math.isfinite(z[i]):
            use[m] = i
            m += 1
    if m == 0:
        return ST_STALE, np.nan, np.nan, 0
    S = np.empty((m, m))
    y = np.empty(m)
    PHt = np.empty((n, m))
    for a in range(m):
        ia = meas_idx[use[a]]
        y[a] = z[use[a]] - x[ia]
        for b in range(m):
            S[a, b] = P[ia, meas_idx[use[b]]]
        S[a, a] += R[use[a]]
        for i in range(n):
            PHt[i, a] = P[i, ia]
    # S^-1 and log det S from S's Cholesky factor (m <= 3: cheaper than LAPACK's call overhead)
    Ls = np.zeros((m, m))
    if not _chol_lower(S, Ls):
        return ST_GATED, np.inf, -np.inf, m
    Li = np.zeros((m, m))
    logdet = 0.0
    for i in range(m):
        logdet += 2.0 * math.log(Ls[i, i])
        Li[i, i] = 1.0 / Ls[i, i]
        for j in range(i):
            acc = 0.0
            for k in range(j, i):
                acc -= Ls[i, k] * Li[k, j]
            Li[i, j] = acc / Ls[i, i]
    SI = np.zeros((m, m))
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
        innov[use[a]] = y[a]
        Sdiag[use[a]] = S[a, a]
    if nis > gate:
        return ST_GATED, nis, loglik, m
    K = np.zeros((n, m))
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
    if not any_frozen:  # P -= K S K' = K (P H')': K S = P H'
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for a in range(m):
                    acc += K[i, a] * PHt[j, a]
                P[i, j] -= acc
    else:  # Joseph form: P = (I - K H) P (I - K H)' + K R K'
        IKH = np.eye(n)
        for i in range(n):
            for a in range(m):
                IKH[i, meas_idx[use[a]]] -= K[i, a]
        KRK = np.zeros((n, n))
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for a in range(m):
                    acc += K[i, a] * R[use[a]] * K[j, a]
                KRK[i, j] = acc
        P[:, :] = IKH @ P @ IKH.T + KRK
    for i in range(n):
        for j in range(i + 1, n):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v
    return ST_FROZEN if any_frozen else ST_OK, nis, loglik, m


@nb.njit(cache=True, nogil=True)
def run_kernel(x, P, exc, U, XREF, Z, pvec, idx, ref, scale, dt, nsub, Q, R, meas_idx, Wm, Wc, lam,
               floor, gate, max_gated, chan, thresh, alpha_exc, u_prev, gated_run, x_col,
               X_out, Pd_out, nis_out, ll_out, st_out, innov_out, S_out, frozen_out):
    """Filter ``T`` samples in place (``x``, ``P``, excitation state ``exc`` carry over between calls).

    ``U[k]`` the logged controller output (NaN if not logged), ``XREF[k]`` the
    demand (used with ``KP`` of ``pvec`` when ``U[k]`` is NaN), ``Z[k]`` the
    scaled measurements (NaN = missing), column ``x_col`` the displacement (-1: not
    measured; the P controller then uses the estimate).  Returns (last input, gated run, index
    of an unrepairable sample or -1).
    """
    n = x.shape[0]
    T = U.shape[0]
    L = np.zeros((n, n))
    A = np.empty((n, n))
    pw = pvec.copy()
    si = np.empty(6)
    so = np.empty(6)
    sig = np.empty((2 * n + 1, n))
    sf = np.empty((2 * n + 1, n))
    freeze = np.zeros(n, dtype=np.bool_)
    innov = np.empty(meas_idx.shape[0])
    Sd = np.empty(meas_idx.shape[0])
    p_count = n - 6
    for k in range(T):
        status = ST_OK
        # which parameters the recent data excite: EMAs of |v|, |du|/dt and |pA - pB|
        nfz = 0
        for j in range(n):
            freeze[j] = False
        for j in range(p_count):
            c = chan[j]
            if exc[c] < thresh[c]:
                freeze[6 + j] = True
                nfz += 1
            frozen_out[k, j] = freeze[6 + j]
        # predict from the previous sample with the input held since then (none before the first)
        ps = ST_OK
        if math.isfinite(u_prev):
            ps = _predict(x, P, u_prev, pw, idx, ref, scale, dt, nsub, Q, Wm, Wc, lam, floor, L, A, sig, sf, si, so)
            if ps < 0:
                return u_prev, gated_run, k
        # update
        for a in range(meas_idx.shape[0]):
            innov[a] = np.nan
            Sd[a] = np.nan
        g = gate if gated_run < max_gated else np.inf
        us, nis, ll, m = _update(x, P, Z[k], meas_idx, R, freeze, g, innov, Sd)
        if us == ST_GATED:
            gated_run += 1
        else:
            gated_run = 0
        if ps == ST_REPAIRED:
            status = ST_REPAIRED
        elif us == ST_GATED or us == ST_STALE:
            status = us
        elif status == ST_OK and us == ST_FROZEN:
            status = ST_FROZEN
        for i in range(n):
            X_out[k, i] = x[i]
            Pd_out[k, i] = P[i, i]
        for a in range(meas_idx.shape[0]):
            innov_out[k, a] = innov[a]
            S_out[k, a] = Sd[a]
        nis_out[k] = nis
        ll_out[k] = ll
        # the input of this sample drives the next step: logged u, else the digital P controller
        u = U[k]
        if not math.isfinite(u):
            xm = Z[k, x_col] * scale[4] if x_col >= 0 and math.isfinite(Z[k, x_col]) else x[4] * scale[4]
            if math.isfinite(XREF[k]):
                u = pvec[M.I_KP] * (XREF[k] - xm)
            elif math.isfinite(u_prev):
                u = u_prev
                status = ST_STALE
            else:
                u = 0.0
                status = ST_STALE
        du = abs(u - u_prev) / dt if math.isfinite(u_prev) else 0.0
        exc[0] += alpha_exc * (abs(x[5] * scale[5]) - exc[0])
        exc[1] += alpha_exc * (du - exc[1])
        exc[2] += alpha_exc * (abs(x[2] - x[3]) * scale[2] - exc[2])
        u_prev = u
        st_out[k] = status
    return u_prev, gated_run, -1
