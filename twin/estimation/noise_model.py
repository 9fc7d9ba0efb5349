"""Noise models of output-error residuals: one-step-ahead prediction errors (Box-Jenkins style).

An output-error fit of a closed loop whose controller reads the noisy measured
displacement leaves *coloured* residuals even when the model is exact: the
sensor noise goes round the loop (the x residual is the noise through the
loop's sensitivity, the pressures see it too) and a sensor may itself be
coloured.  Whiteness of output-error residuals is then no test of the model,
and least-squares statistics that assume white residuals (LR, score, AICc)
are wildly overconfident.

:func:`fit_noise_model` fits a vector autoregression

    r_t = sum_{k=1..p} A_k r_{t-k} + e_t,     cov(e_t) = Sigma = L L'

to the weighted residuals ``r_t`` (one entry per output; records are
independent blocks), its order ``p`` chosen by BIC.  It captures loop noise
shared by several outputs (the same sensor noise moves x and both
pressures).  :meth:`NoiseModel.whiten` turns residuals (or sensitivities of
residuals, with the same filter) into normalised innovations
``L^-1 e_t``: one-step-ahead prediction errors, iid standard normal when
the model and the noise model are right.  Statistics on whitened residuals and
whitened sensitivities are generalised-least-squares statistics, valid on
coloured data.

Helpers: :func:`long_run_variance` (Newey-West with Bartlett weights) for
what whitening leaves, :func:`block_bootstrap` for a moving-block bootstrap.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from twin.estimation.hac import bartlett_lag

#: orders of the autoregression tried (BIC picks one)
ORDERS = (0, 1, 2, 3, 4, 6, 8, 12, 16, 20, 25, 30, 40, 50, 60)


@dataclasses.dataclass
class NoiseModel:
    """A vector autoregression of the residuals of ``m`` outputs (see the module docstring)."""

    outputs: tuple[str, ...]
    order: int
    A: np.ndarray          # [p, m, m]
    sigma: np.ndarray      # innovation covariance [m, m] (of the weighted residuals)
    chol_inv: np.ndarray   # L^-1 [m, m]
    bic: dict[int, float]  # (unused by the per-output fit)
    orders: dict[str, int] = dataclasses.field(default_factory=dict)   # AR order per output
    aic: dict[str, dict] = dataclasses.field(default_factory=dict)      # AIC per order tried, per output
    raises: int = 0        # times the orders were raised above AIC's while the errors stayed predictable

    @property
    def m(self) -> int:
        return len(self.outputs)

    def whiten(self, X: np.ndarray, fresh: np.ndarray | None = None) -> np.ndarray:
        """Normalised innovations of ``X [..., m, T]`` -> ``[..., m, T - p]`` (the first ``p`` samples are
        lost: the predictor needs a past).

        ``fresh [m, T]``: which samples of each output are measurements (a signal logged at its own, slower rate
        and held onto the grid: :func:`twin.record.fresh_mask`).  A held output's autoregression runs over its
        fresh samples only (its lags are its previous measurements), and the innovations keep the samples
        where every output is a measurement (:meth:`kept`): a held value is never taken for a prediction error,
        and the counts of the statistics on the innovations are those of measurements, as in the fit."""
        X = np.asarray(X, dtype=float)
        p = self.order
        T = X.shape[-1]
        if fresh is None or bool(np.all(fresh)):
            E = X[..., p:].copy()
            for k in range(1, p + 1):
                # e_t -= A_k r_{t-k}
                E -= np.einsum("ij,...jt->...it", self.A[k - 1], X[..., p - k: T - k])
            return np.einsum("ij,...jt->...it", self.chol_inv, E)
        E = np.zeros(X.shape[:-1] + (max(T - p, 0),))
        for i in range(self.m):
            q = int(self.orders.get(self.outputs[i], p)) if self.orders else p
            a = self.A[:q, i, i]
            idx = np.flatnonzero(fresh[i])
            xf = X[..., i, idx]
            ef = xf[..., q:].copy()
            for k in range(1, q + 1):
                ef -= a[k - 1] * xf[..., q - k: idx.size - k]
            pos = idx[q:]
            use = pos >= p
            E[..., i, pos[use] - p] = ef[..., use]
        keep = self.kept(fresh, T)
        return np.einsum("ij,...jt->...it", self.chol_inv, E[..., keep])

    def kept(self, fresh: np.ndarray | None, T: int) -> np.ndarray:
        """``[T - p]`` bool: the samples ``p ... T - 1`` whose innovations :meth:`whiten` keeps under ``fresh``
        (every output a measurement there, with the past its autoregression needs)."""
        p = self.order
        keep = np.ones(max(T - p, 0), dtype=bool)
        if fresh is None:
            return keep
        for i in range(self.m):
            f = np.asarray(fresh[i], dtype=bool)
            if f.all():
                continue
            q = int(self.orders.get(self.outputs[i], p)) if self.orders else p
            ok = f.copy()
            first = np.flatnonzero(f)[:q]  # a measurement without q earlier ones has no prediction
            ok[first] = False
            keep &= ok[p:]
        return keep

    def whiten_blocks(self, blocks: Sequence[np.ndarray]) -> np.ndarray:
        """Whitened innovations of several independent records ``[..., m, T_r]``, concatenated in time."""
        return np.concatenate([self.whiten(b) for b in blocks], axis=-1)

    def spectrum_gain(self, f_over_fs: np.ndarray) -> np.ndarray:
        """``|H(e^{jw})|`` of each output's own noise filter (diagonal of ``A(q)^-1 L``), for reports."""
        z = np.exp(-2j * np.pi * np.asarray(f_over_fs))
        Aq = np.repeat(np.eye(self.m)[None].astype(complex), z.size, axis=0)
        for k in range(1, self.order + 1):
            Aq -= self.A[k - 1][None] * (z ** k)[:, None, None]
        H = np.linalg.solve(Aq, np.repeat(np.linalg.cholesky(self.sigma)[None].astype(complex), z.size, axis=0))
        return np.abs(np.diagonal(H, axis1=1, axis2=2))

    def summary(self) -> dict:
        sd = np.sqrt(np.diag(self.sigma))
        # the colour of each output's residual: its variance over its one-step prediction error variance
        return {"kind": "autoregression of each output's output-error residual (AIC order), innovations "
                        "correlated across outputs",
                "order": int(self.order), "orders": dict(self.orders), "raises": int(self.raises),
                "outputs": list(self.outputs),
                "innovation_std": dict(zip(self.outputs, sd.round(6).tolist()))}


def _ar_fit(blocks: Sequence[np.ndarray], orders: Sequence[int]) -> tuple[int, np.ndarray, dict[int, float]]:
    """Autoregression of one output's residual blocks ``[T_r]``: order by AIC, coefficients ``a [p]``."""
    p_max = max(orders)
    Ys, Xs = [], []
    for r in blocks:
        T = r.size
        Ys.append(r[p_max:])
        Xs.append(np.stack([r[p_max - k: T - k] for k in range(1, p_max + 1)], axis=1)
                  if p_max else np.zeros((T - p_max, 0)))
    Y = np.concatenate(Ys)
    X = np.concatenate(Xs)
    # an intercept per record: a constant model error (an offset) must not be taken for noise
    ones = np.zeros((Y.size, len(blocks)))
    row = 0
    for j, r in enumerate(blocks):
        ones[row: row + r.size - p_max, j] = 1.0
        row += r.size - p_max
    X = np.concatenate([X, ones], axis=1)
    n = Y.size
    # normal equations once; every order is a sub-block (LAPACK least squares is needlessly slow here)
    G = X.T @ X
    b = X.T @ Y
    yy = float(Y @ Y)
    aic: dict[int, float] = {}
    coefs = {}
    for p in orders:
        cols = np.r_[np.arange(p), np.arange(p_max, X.shape[1])]
        Gs = G[np.ix_(cols, cols)]
        bs = b[cols]
        try:
            c = np.linalg.solve(Gs + 1e-12 * np.trace(Gs) / Gs.shape[0] * np.eye(cols.size), bs)
        except np.linalg.LinAlgError:
            continue
        v = (yy - 2.0 * float(c @ bs) + float(c @ Gs @ c)) / n
        if not v > 0:
            continue
        aic[p] = n * math.log(v) + 2.0 * p
        coefs[p] = c[:p]
    p = min(aic, key=lambda q: aic[q])
    return p, coefs[p], aic


def fit_noise_model(blocks: Sequence[np.ndarray], outputs: Sequence[str], orders: Sequence[int] = ORDERS,
                    max_order: int | None = None, min_orders: dict[str, int] | None = None,
                    fresh: Sequence[np.ndarray | None] | None = None) -> NoiseModel:
    """A noise model of residual blocks ``[m, T_r]`` (one per record): an autoregression per output (order
    by AIC, at least ``min_orders[output]`` where given) and the innovations' covariance across outputs.
    ``fresh``: per block, ``[m, T_r]`` measurements (None: all); a held output's autoregression is fitted
    over its measurements only (:meth:`NoiseModel.whiten`)."""
    blocks = [np.asarray(b, dtype=float) for b in blocks]
    fr = list(fresh) if fresh is not None else [None] * len(blocks)
    m = blocks[0].shape[0]

    def series(i: int) -> list[np.ndarray]:
        return [b[i] if f is None else b[i][np.asarray(f[i], dtype=bool)] for b, f in zip(blocks, fr)]

    T_min = min(min(s.size for s in series(i)) for i in range(m))
    cap = max_order if max_order is not None else max(orders)
    cap = min(cap, max(0, T_min // 20))
    cand = [p for p in orders if p <= cap] or [0]
    low = min_orders or {}
    per = [_ar_fit(series(i), [p for p in cand if p >= low.get(o, 0)] or [max(cand)])
           for i, o in enumerate(outputs)]
    p = max(q for q, _, _ in per)
    A = np.zeros((p, m, m))
    for i, (q, c, _) in enumerate(per):
        A[:q, i, i] = c
    nm = NoiseModel(tuple(outputs), p, A, np.eye(m), np.eye(m), {})
    nm.orders = {o: int(q) for o, (q, _, _) in zip(outputs, per)}
    E = np.concatenate([nm.whiten(b, f) for b, f in zip(blocks, fr)], axis=1)
    S = E @ E.T / E.shape[1]
    L = np.linalg.cholesky(S)
    nm.sigma = S
    nm.chol_inv = np.linalg.inv(L)
    nm.orders = {o: int(q) for o, (q, _, _) in zip(outputs, per)}
    nm.aic = {o: {str(k): v for k, v in a.items()} for o, (_, _, a) in zip(outputs, per)}
    return nm


# --- statistics of what whitening leaves ---------------------------------------------------------
def long_run_variance(g: np.ndarray, lag: int | None = None) -> float:
    """Newey-West long-run variance of the mean-zero score series ``g [n]``: ``Var(sum g) / n``."""
    g = np.asarray(g, dtype=float)
    n = g.size
    if n == 0:
        return 0.0
    L = min(bartlett_lag(g) if lag is None else int(lag), n - 1)
    if L <= 64:
        s = float(g @ g)
        for k in range(1, L + 1):
            s += 2.0 * (1.0 - k / (L + 1.0)) * float(g[k:] @ g[:-k])
        return max(s, 0.0) / n
    # many lags (a simulation error's memory: thousands of samples): the autocovariances by one FFT, zero-padded
    # against the wrap-around, instead of a product per lag (the same sums to rounding)
    m = 1 << int(math.ceil(math.log2(n + L + 1)))
    f = np.fft.rfft(g, m)
    ac = np.fft.irfft(f.real * f.real + f.imag * f.imag, m)[: L + 1]
    lags = np.arange(1, L + 1)
    s = float(ac[0]) + 2.0 * float(np.sum((1.0 - lags / (L + 1.0)) * ac[1:]))
    return max(s, 0.0) / n


def block_bootstrap(d: np.ndarray, block: int, n_boot: int, seed: int) -> np.ndarray:
    """Moving-block bootstrap of the sum of ``d [n]``: ``n_boot`` resampled sums (blocks of ``block``).

    ``d [m, n]`` (several series of the same samples) resamples the same blocks for every series and returns
    ``[n_boot, m]`` sums (a ratio of sums is then resampled jointly)."""
    d = np.asarray(d, dtype=float)
    one = d.ndim == 1
    d = np.atleast_2d(d)
    n = d.shape[1]
    block = int(max(1, min(block, n)))
    c = np.concatenate([np.zeros((d.shape[0], 1)), np.cumsum(d, axis=1)], axis=1)
    sums = c[:, block:] - c[:, :-block]    # sum of each block starting at i, per series
    k = int(math.ceil(n / block))
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, sums.shape[1], size=(n_boot, k))
    out = sums[:, idx].sum(axis=2).T * (n / (k * block))   # [n_boot, m]
    return out[:, 0] if one else out
