"""95 % intervals of the campaign's figures (:mod:`benchmarks.campaign`).

* a proportion ``k / n``: Wilson's score interval (:func:`wilson`) and the exact Clopper-Pearson one
  (:func:`clopper_pearson`, the beta quantiles); the campaign states Clopper-Pearson, which never undercovers;
* a count of events over an exposure (events per hour): the exact Poisson interval (:func:`poisson_rate`,
  Garwood: chi-square quantiles ``chi2(a/2; 2k) / 2`` and ``chi2(1 - a/2; 2k + 2) / 2`` over the exposure);
* a median of delays: the distribution-free interval of order statistics (:func:`median_interval`: the
  binomial ranks that hold the median with at least 95 %), the sample's range when it is too small for one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from scipy import stats

Z95 = 1.959963984540054


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval of a proportion ``k / n`` (``(0, 1)`` when ``n`` is 0)."""
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    den = 1.0 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, mid - half), min(1.0, mid + half)


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper-Pearson) interval of a proportion ``k / n`` (``(0, 1)`` when ``n`` is 0)."""
    if n <= 0:
        return 0.0, 1.0
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(stats.beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(stats.beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def poisson_rate(k: int, exposure: float, level: float = 0.95) -> tuple[float, float]:
    """The exact (Garwood) interval of an event rate: ``k`` events over ``exposure`` (e.g. hours)."""
    if exposure <= 0:
        return 0.0, math.inf
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(stats.chi2.ppf(a / 2, 2 * k)) / 2.0
    hi = float(stats.chi2.ppf(1 - a / 2, 2 * k + 2)) / 2.0
    return lo / exposure, hi / exposure


def median_interval(values: Sequence[float], level: float = 0.95) -> tuple[float | None, float | None, float | None]:
    """(median, lower, upper): the order statistics ``x_(r) <= median <= x_(s)`` holding the median with at least
    ``level`` (binomial ranks); fewer values than that needs: the sample's range."""
    x = sorted(float(v) for v in values)
    n = len(x)
    if not n:
        return None, None, None
    med = x[n // 2] if n % 2 else 0.5 * (x[n // 2 - 1] + x[n // 2])
    # the widest symmetric ranks r..n+1-r (1-based) with P(r <= B < n + 1 - r) >= level, B ~ Bin(n, 1/2)
    best = None
    for r in range(1, n // 2 + 1):
        cover = float(stats.binom.cdf(n - r, n, 0.5) - stats.binom.cdf(r - 1, n, 0.5))
        if cover >= level:
            best = r
    if best is None:
        return med, x[0], x[-1]
    return med, x[best - 1], x[n - best]
