"""Compiled intersample behaviour of a sampled input (MATLAB iddata's InterSample).

``mode`` 0: zero-order hold; 1: first-order hold (linear); 2: C1 piecewise
cubic through the samples (Catmull-Rom slopes), which reproduces a smooth
signal to third order.  Codes as :data:`twin.models.base.INTERSAMPLE_CODE`.
"""

from __future__ import annotations

import numba as nb


@nb.njit(cache=True)
def input_at(a, k, f, mode):
    """A sampled input between samples ``k`` and ``k+1`` at fraction ``f`` in [0, 1].

    ``mode`` 0: zero-order hold; 1: first-order hold (linear); 2: C1 piecewise
    cubic through the samples (Catmull-Rom slopes), which reproduces a smooth
    signal to third order.
    """
    if mode == 0 or f <= 0.0:
        return a[k]
    n = a.shape[0]
    return input_between(a[k - 1 if k > 0 else 0], a[k], a[k + 1 if k + 1 < n else n - 1],
                         a[k + 2 if k + 2 < n else n - 1], f, mode)


@nb.njit(cache=True)
def input_between(a0, a1, a2, a3, f, mode):
    """:func:`input_at` from the four samples around the interval, ``a0 = a[k-1]``, ``a1 = a[k]``, ``a2 = a[k+1]``,
    ``a3 = a[k+2]`` (clamped at the ends): for a compiled caller that reads them once per interval (an array handed
    to a compiled function is reference-counted at each call, and an interval evaluates the input several
    times)."""
    if mode == 0 or f <= 0.0:
        return a1
    if mode == 1:
        return a1 + f * (a2 - a1)
    m0 = 0.5 * (a2 - a0)
    m1 = 0.5 * (a3 - a1)
    f2 = f * f
    f3 = f2 * f
    return ((2.0 * f3 - 3.0 * f2 + 1.0) * a1 + (f3 - 2.0 * f2 + f) * m0
            + (3.0 * f2 - 2.0 * f3) * a2 + (f3 - f2) * m1)


@nb.njit(cache=True)
def slope_at(a, k, f, mode, dt):
    """Time derivative of :func:`input_at` [unit/s]."""
    if mode == 0:
        return 0.0
    n = a.shape[0]
    k1 = k + 1 if k + 1 < n else n - 1
    if mode == 1:
        return (a[k1] - a[k]) / dt
    k0 = k - 1 if k > 0 else 0
    k2 = k + 2 if k + 2 < n else n - 1
    m0 = 0.5 * (a[k1] - a[k0])
    m1 = 0.5 * (a[k2] - a[k])
    f2 = f * f
    return ((6.0 * f2 - 6.0 * f) * a[k] + (3.0 * f2 - 4.0 * f + 1.0) * m0
            + (6.0 * f - 6.0 * f2) * a[k1] + (3.0 * f2 - 2.0 * f) * m1) / dt
