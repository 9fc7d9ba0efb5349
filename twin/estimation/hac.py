"""Andrews' bandwidth: how many lags a Newey-West (Bartlett-weighted) long-run variance sums.

One function for every heteroskedasticity-and-autocorrelation-consistent estimate of the product: the
fit's standard errors (:func:`twin.estimation.fit.hac_covariance`), the long-run variance of what
whitening leaves (:func:`twin.estimation.noise_model.long_run_variance`) and the diagnosis's tests.
"""

from __future__ import annotations

import math

import numpy as np


def bartlett_lag(g: np.ndarray) -> int:
    """Andrews' (1991) AR(1) plug-in bandwidth for Bartlett weights of a series ``g [n]`` or the score
    series ``g [n, p]`` (its columns weighted alike), at most ``n/4``.

    Its floor is none (0: Andrews' rule as published).  A caller that knows its series carries memory an
    AR(1) does not see raises the lag at its call, with its reason beside it: the fit's scores of a closed
    loop are white sensor noise plus the slower response of the loop to the noise its controller read
    (at least ``sqrt(n)`` there).  A column that is not finite (a diverged candidate's scores) has no
    weight; a series of fewer than 8 samples, or none finite, gives 0.
    """
    g = np.asarray(g, dtype=float)
    cols = g.reshape(g.shape[0], -1) if g.ndim else g.reshape(0, 1)
    n = cols.shape[0]
    if n < 8:
        return 0
    vr: list[tuple[float, float]] = []  # each column's log sum of squares and lag-1 autocorrelation
    for a in range(cols.shape[1]):
        x = cols[:, a]
        if not np.all(np.isfinite(x)):
            continue
        x = x - np.mean(x)
        big = float(np.max(np.abs(x)))
        if not 0 < big < math.inf:
            continue
        x = x / big  # scale-free: a diverged candidate's finite but huge scores overflowed their squares
        v = float(x @ x)
        vr.append((math.log(v) + 2.0 * math.log(big), float(np.clip(x[1:] @ x[:-1] / v, -0.97, 0.97))))
    if not vr:
        return 0
    top = max(lv for lv, _ in vr)
    num = den = 0.0
    for lv, rho in vr:
        # innovation variance squared, relative to the largest column's (the common factor cancels)
        s4 = math.exp(2.0 * (lv - top)) * (1 - rho * rho) ** 2
        num += 4 * rho * rho * s4 / ((1 - rho) ** 6 * (1 + rho) ** 2)
        den += s4 / (1 - rho) ** 4
    if den <= 0:
        return 0
    return int(min(max(1.1447 * (num / den * n) ** (1 / 3), 0), n // 4))
