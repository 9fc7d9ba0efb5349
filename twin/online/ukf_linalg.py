"""The filter's small linear algebra and its parameter coordinates, compiled: a Cholesky factor that says when a
matrix is not positive definite, an eigenvalue repair, and the logit between physical bounds
(``theta = lo * (hi/lo) ** sigmoid(z)``) in which the parameters move."""

from __future__ import annotations

import math
from typing import Any

import numba as nb
import numpy as np

#: numba's option compiling a function without its runtime's reference counting (``@nb.njit(**NO_REFCOUNT)``): for
#: the filter's per-sample functions, which allocate nothing; each array they name, in an inlined stage or a call,
#: is otherwise counted in and out with an atomic operation sample by sample (a quarter of a small model's kernel)
NO_REFCOUNT: dict[str, Any] = {"_nrt": False}
#: the option back on, for a function such a caller may reach that allocates (numba compiles a callee with its
#: caller's options unless the callee sets them)
REFCOUNT: dict[str, Any] = {"_nrt": True}


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


@nb.njit(cache=True, **REFCOUNT)
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

