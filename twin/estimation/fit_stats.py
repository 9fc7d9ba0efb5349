"""Statistics of a least-squares fit: HAC (Newey-West) covariance with an automatic Bartlett lag, and the
likelihood-ratio test of nested fits."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from scipy.special import chdtrc  # chi2.sf, without importing scipy.stats (a second of start-up)

from twin.estimation.hac import bartlett_lag

if TYPE_CHECKING:
    from twin.estimation.fit_result import FitResult


def hac_covariance(J: np.ndarray, r: np.ndarray, blocks: Sequence[tuple[int, int]],
                   H_inv: np.ndarray, n_obs: int | None = None, min_lag: int = 0) -> np.ndarray:
    """Newey-West sandwich ``H^-1 S H^-1`` of least squares with Jacobian ``J [N, p]`` and residuals ``r [N]``.

    ``blocks``: ``(n_outputs, n_samples)`` of each independent record, whose
    residuals lie output after output; the scores of all outputs at one instant
    are summed (so cross-correlations between outputs count), and their
    autocovariances are summed within each record with Bartlett weights up to
    an automatic lag.  ``n_obs``: the number of residuals that are measurements
    (default all; held samples of a slower signal enter as zero residuals).  ``min_lag``: the fewest lags
    summed (samples; a short record whose residuals stay correlated longer than its ``sqrt(n)``).
    """
    Sm = np.zeros((J.shape[1], J.shape[1]))
    start = 0
    for m, n in blocks:
        G = (J[start:start + m * n] * r[start:start + m * n, None]).reshape(m, n, -1).sum(axis=0)
        start += m * n
        Sm += G.T @ G
        # at least sqrt(n): the scores of a closed loop are white sensor noise plus the slower response of the
        # loop to the noise its controller read; an AR(1) fitted to the sum sees mostly the white part and picks
        # a handful of lags, which on the reference simulator left the friction's standard error 20 % short
        # (lag 9 on 12 000 samples; from lag 50 on every parameter's spread matches its standard error)
        L = min(max(bartlett_lag(G), math.ceil(math.sqrt(n)), int(min_lag)), n // 4)
        for lag in range(1, L + 1):
            w = 1.0 - lag / (L + 1.0)
            C = G[lag:].T @ G[:-lag]
            Sm += w * (C + C.T)
    N, p = J.shape
    N = N if n_obs is None else n_obs
    cov = H_inv @ Sm @ H_inv * (N / max(N - p, 1))
    return cov


def likelihood_ratio(nested: FitResult, extended: FitResult) -> tuple[float, float, int]:
    """LR statistic, p-value and degrees of freedom of ``extended`` against ``nested``."""
    df = extended.n_par - nested.n_par
    lr = max(0.0, 2.0 * (extended.loglik - nested.loglik))
    return lr, float(chdtrc(max(df, 1), lr)), df
