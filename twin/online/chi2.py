"""The chi-square quantiles the online path needs (innovation gates), without importing scipy.

For an integer number of degrees of freedom ``k`` the survival function has a closed form
(Abramowitz & Stegun 26.4.4-26.4.5): with ``h = x / 2``,

* ``k`` even: ``Q = exp(-h) * sum_{i < k/2} h^i / i!``
* ``k`` odd:  ``Q = erfc(sqrt(h)) + exp(-h) * sum_{i < (k-1)/2} h^(i+1/2) / Gamma(i + 3/2)``

and the quantile is found by bisection on ``log Q`` (monotone in ``x``), to a relative 1e-15.
``scipy.special`` costs about as much to import as numba itself, and a spawned worker pays it
again; ``tests/test_tracker.py`` checks these quantiles against ``scipy.stats.chi2.isf``.
"""

from __future__ import annotations

import math


def _log_sf(x: float, k: int) -> float:
    h = 0.5 * x
    if k % 2 == 0:
        terms = [i * math.log(h) - math.lgamma(i + 1) for i in range(k // 2)] if h > 0 else [0.0]
        base = -h
    else:
        terms = [(i + 0.5) * math.log(h) - math.lgamma(i + 1.5) for i in range((k - 1) // 2)] if h > 0 else []
        base = -h
        erfc = math.erfc(math.sqrt(h))
        if erfc > 0.0:
            terms.append(math.log(erfc) + h)  # folded into the common exp(-h)
        elif not terms:
            return -math.inf
    top = max(terms)
    return base + top + math.log(sum(math.exp(t - top) for t in terms))


def isf(p: float, k: int) -> float:
    """The ``x`` with ``P(chi2_k > x) = p`` (``k`` a positive integer, ``0 <= p <= 1``)."""
    if k < 1 or int(k) != k:
        raise ValueError(f"degrees of freedom (={k}) must be a positive integer")
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"probability (={p}) must be in [0 ... 1]")
    if p == 0.0:
        return math.inf
    if p == 1.0:
        return 0.0
    target = math.log(p)
    lo, hi = 0.0, max(1.0, float(k))
    while _log_sf(hi, k) > target:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _log_sf(mid, k) > target:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-15 * hi:
            break
    return 0.5 * (lo + hi)
