"""The HAC covariance's lag floor (``min_lag``): slowly correlated scores need more lags than sqrt(n)."""

from __future__ import annotations

import numpy as np

from twin.estimation.fit_stats import hac_covariance
from twin.estimation.hac import bartlett_lag


def _ar1(n: int, phi: float, rng: np.random.Generator) -> np.ndarray:
    e = rng.normal(size=n)
    out = np.empty(n)
    acc = 0.0
    for t in range(n):
        acc = phi * acc + e[t]
        out[t] = acc
    return out


def test_a_lag_floor_covers_slowly_correlated_residuals():
    """The mean of an AR(1) with a correlation time of 100 samples, estimated on 4000: the spread over many
    draws is what the sandwich must say.  The automatic lag (sqrt(n) = 64 at least) falls far short of it; a
    floor of 250 lags recovers part of what it missed (Bartlett weights still shrink the slow tail)."""
    rng = np.random.default_rng(7)
    n, phi = 4000, float(np.exp(-1.0 / 100.0))
    J = np.ones((n, 1))
    H_inv = np.linalg.inv(J.T @ J)
    means, auto, floored = [], [], []
    for _ in range(200):
        r = _ar1(n, phi, rng)
        r = r - r.mean()
        means.append(float(np.mean(_ar1(n, phi, rng))))
        auto.append(float(hac_covariance(J, r, [(1, n)], H_inv)[0, 0]))
        floored.append(float(hac_covariance(J, r, [(1, n)], H_inv, min_lag=250)[0, 0]))
    true_var = float(np.var(means))
    a, f = float(np.mean(auto)) / true_var, float(np.mean(floored)) / true_var
    assert a < 0.7  # the automatic lag understates it
    assert 1.1 * a < f < 1.2  # the floor recovers part of it, never overstating
    assert np.all(np.array(floored) >= 0)


def test_the_lag_does_not_depend_on_the_scores_scale_and_huge_scores_do_not_overflow():
    """A diverged candidate's scores can be finite yet so large that their squares overflow (a diagnosis on the
    reference stopped with OverflowError there): the lag is the same at any scale of the series."""
    rng = np.random.default_rng(0)
    g = rng.standard_normal((1000, 3))
    g[:, 1] = np.cumsum(g[:, 1]) * 0.1  # one column with memory
    lag = bartlett_lag(g)
    assert lag > 10
    for scale in (1e-200, 1e200):
        assert bartlett_lag(g * scale) == lag
    mixed = g.copy()
    mixed[:, 2] *= 1e250  # one column far larger than the others: it carries the weight
    assert bartlett_lag(mixed) == bartlett_lag(g[:, 2:])
