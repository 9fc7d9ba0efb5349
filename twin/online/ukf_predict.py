"""The filter's prediction: the unscented transform of the augmented state through one log interval of the rig
model (filterpy's ``UnscentedKalmanFilter.predict`` with Merwe's sigma points), compiled.

The model comes as the globals ``advance``, ``applicable`` and ``lanes_fn`` (its compiled filter interface's
``advance``, ``lanes_applicable`` and ``lanes``, see :attr:`twin.models.base.FilterSpec.functions`), imported in
the one line marked ``# kernel: the model's interface``.  Here that line names the model slot
(:mod:`twin.online.ukf_model`); :func:`twin.online.ukf.kernel_for` compiles a copy of this module whose marked
line names a model's module instead (numba caches a function that calls dispatchers it finds as globals;
dispatchers handed down as arguments become first-class function values, which it does not cache).
"""

from __future__ import annotations

import math

import numba as nb

from twin.online.ukf_linalg import NO_REFCOUNT, _chol_lower, _repair, theta_of
from twin.online.ukf_model import advance, lanes as lanes_fn, lanes_applicable as applicable  # kernel: the model's interface
from twin.online.ukf_status import ST_OK, ST_REPAIRED


@nb.njit
def lanes_apply(p):
    """True when the model's side-by-side lanes are exact for the kernel vector ``p``."""
    return applicable(p)


@nb.njit(**NO_REFCOUNT)
def fx_into(sig, r, wnd, closed, ticks, mode, p, idx, lo_log, width, scale, h, nsub, xm, ctrl, nc, si, so, sf,
            nmod):
    """One log interval of the augmented state ``sig[r]`` with the drive window ``wnd`` (the drive at samples k-2,
    k-1, k, k; index 1 is the interval's start).

    Writes the model states and parameters of ``sf[r]`` (``nmod`` entries); ``p`` is overwritten at ``idx``; no
    allocation (the rows are indexed, not sliced: a slice handed to a compiled call is a new array, reference
    counted on the way in and out, 2n+1 times an interval).  ``ctrl``: the model's controller memory (``nc``
    entries) followed, when it is longer, by the rig controller's memory carried from sample to sample (the
    interval starts from it; else from rest).
    """
    ns = scale.shape[0]
    for j in range(idx.shape[0]):
        p[idx[j]] = theta_of(sig[r, ns + j], lo_log[j], width[j])
    for j in range(ns):
        si[j] = sig[r, j] * scale[j]
    carried = ctrl.shape[0] >= 2 * nc
    for j in range(nc):
        ctrl[j] = ctrl[nc + j] if carried else 0.0
    advance(si, 1, wnd, closed, ticks, mode, p, h, nsub, xm, ctrl, so)
    for j in range(ns):
        sf[r, j] = so[j] / scale[j]
    for j in range(ns, nmod):
        sf[r, j] = sig[r, j]


@nb.njit(**NO_REFCOUNT)
def _lanes(sig, sf, rows, m, wnd, mode, pw, idx, lo_log, width, scale, h, nsub, nmod, S, TH, W):
    """The model part of ``sf[rows[ln]]`` for the sigma points ``sig[rows[ln]]``, ``ln < m``, integrated side by
    side by the model's ``lanes``; a parameter at the central point's value (a sigma point along another state)
    reuses its value."""
    ns = scale.shape[0]
    p_count = idx.shape[0]
    r0 = rows[0]
    for ln in range(m):
        r = rows[ln]
        for j in range(p_count):
            zj = sig[r, ns + j]
            TH[ln, j] = TH[0, j] if ln > 0 and zj == sig[r0, ns + j] else theta_of(zj, lo_log[j], width[j])
        for i in range(ns):
            S[ln, i] = sig[r, i] * scale[i]
    lanes_fn(S, TH, m, pw, idx, wnd, mode, h, nsub, W)
    for ln in range(m):
        r = rows[ln]
        for i in range(ns):
            sf[r, i] = S[ln, i] / scale[i]
        for i in range(ns, nmod):
            sf[r, i] = sig[r, i]


@nb.njit(**NO_REFCOUNT)
def _predict(x, P, wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub, xm, Q, Wm, Wc, lam, floor,
             nmod, a_pow, L, A, sig, sf, si, so, ctrl, nc, fast, W, S, TH, rows, central):
    """filterpy's predict over one interval; returns the status (ok or repaired_covariance) or -1.

    ``central``: the predicted mean is the central point's prediction (filterpy's ``x_mean_fn`` returning
    ``sigmas[0]``), the covariance the weighted sum about it; else the points' weighted mean (filterpy's default).
    The weighted mean of Merwe's points (centre weight -10 for 14 states at alpha 0.3) is exact to second order,
    but a parameter the data have not pinned (a prior, a long rest: the leakage's points at 25 times and 1/25 of
    it) moves the rig's stiff pressures by megapascals over one interval, and their mean is then off by tens of
    kPa (README, "The strong-chirp divergence").

    ``fast``: the model's lanes apply (open loop, then all sigma points that move the model at once, when they fit
    in ``S``'s lanes); ``ctrl``: the controller memory (``nc`` entries), the carried memory, and the memory at the
    interval's end along the central point (written here)."""
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
    if not closed and fast and 2 * nmod + 1 <= S.shape[0]:  # the sigma points that move the model, side by side
        m = 0
        for k in range(2 * n + 1):
            if k == 0 or (k - 1) % n < nmod:
                rows[m] = k
                m += 1
        _lanes(sig, sf, rows, m, wnd, mode, pw, idx, lo_log, width, scale, h, nsub, nmod, S, TH, W)
    else:
        fx_into(sig, 0, wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub, xm, ctrl, nc, si, so,
                sf, nmod)
        for j in range(nc):  # the controller's memory at the interval's end, along the central point
            ctrl[2 * nc + j] = ctrl[j]
        for k in range(nmod):
            fx_into(sig, k + 1, wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub, xm, ctrl, nc,
                    si, so, sf, nmod)
            fx_into(sig, n + k + 1, wnd, closed, ticks, mode, pw, idx, lo_log, width, scale, h, nsub, xm, ctrl,
                    nc, si, so, sf, nmod)
    for k in range(nmod, n):  # along a noise state only: the model part is the central point's
        for i in range(nmod):
            sf[k + 1, i] = sf[0, i]
            sf[n + k + 1, i] = sf[0, i]
    for k in range(2 * n + 1):
        for i in range(nmod, n):
            sf[k, i] = a_pow[i - nmod] * sig[k, i]
    if central:
        for i in range(n):
            x[i] = sf[0, i]
    else:
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

