"""Noise model use and adequacy: one-step prediction errors, whiteness, held-out and exogeneity tests, a
model state's figures, and the likelihood-ratio and held-out gain of one model over another."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.special import chdtrc, ndtr, ndtri  # chi2.sf, norm.sf, norm.isf without scipy.stats

from twin.estimation.fit import FitResult
from twin.models.base import Timing
from twin.estimation.noise_model import ORDERS as NOISE_ORDERS
from twin.estimation.hac import bartlett_lag
from twin.estimation.noise_model import NoiseModel, fit_noise_model, long_run_variance
from twin.estimation.residuals import analyse, ljung_box
from twin.estimation.diagnose.constants import (EXO_LAGS, EXO_R2, GAIN_COVERAGE, LB_LAGS, NOISE_RAISE,
                                                WHITE_R2)
from twin.estimation.diagnose.data import ModelState, _Data, _blocks, _excess, _holdout, _simulate


def _innovations(data: _Data, nm: NoiseModel, pred: list[dict[str, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Normalised innovations ``[m, n]`` on the fitting data and on the held-out tails (whole records
    filtered, so the tail's predictor sees the samples before it)."""
    fit_parts, hold_parts = [], []
    for r, (B, n) in enumerate(zip(_blocks(data, pred, "all"), data.n_fit)):
        fresh = data.fresh(r)  # a held sample is not a measurement: its innovation is not kept
        E = nm.whiten(B, fresh)
        cut = int(np.count_nonzero(nm.kept(fresh, B.shape[1])[: max(n - nm.order, 0)]))
        fit_parts.append(E[:, :cut])
        hold_parts.append(E[:, cut:])
    return np.concatenate(fit_parts, axis=1), np.concatenate(hold_parts, axis=1)


def _kept_order(data: _Data, order: int, i: int, n_kept: int) -> int:
    """Output ``i``'s autoregression order, counted in the innovations' samples: its own measurements per
    kept innovation (2 for x when the pressures are held at half its rate) shorten it, so the whiteness test
    looks at the same time span beyond the model it did on the grid."""
    fresh = [data.fresh(r, n) for r, n in enumerate(data.n_fit)]
    if all(f is None for f in fresh):
        return order  # every sample a measurement: the innovations are the grid's
    own = sum(int(n if f is None else np.count_nonzero(f[i])) for f, n in zip(fresh, data.n_fit))
    ratio = own / max(n_kept, 1)
    return int(math.ceil(order / ratio)) if ratio > 1.0 else order


def _whiteness(e: np.ndarray, order: int) -> dict:
    """Ljung-Box test of one output's prediction errors ``e`` at the ``LB_LAGS`` lags beyond its noise model's
    ``order``, and the share of their variance their past predicts, in all (``r2``) and beyond chance
    (``r2_excess``, ``(Q - df) / n``: white errors give ``E Q = df``); ``material`` above ``WHITE_R2``."""
    lb = ljung_box(e, LB_LAGS + order, df=LB_LAGS)
    n_e = max(e.size, 1)
    r2_excess = max(float(lb["Q"]) - float(lb["df"]), 0.0) / n_e
    return {"Q": lb["Q"], "df": lb["df"], "lags": lb["lags"], "p": lb["p"], "ar_order": order,
            "r2": float(lb["Q"]) / n_e, "r2_excess": r2_excess, "material": bool(r2_excess > WHITE_R2)}


def _simulation_holdout(data: _Data, pred: list[dict[str, np.ndarray]]) -> dict:
    """Per output: is the simulation's (output) error larger on the held-out tails than on the fitting data?
    One-sided test of the mean squared weighted error, Newey-West variances with a lag of at least 0.1 s (the
    errors are coloured by the loop noise).  A slow error the noise model follows step by step (a sensor
    drifting during the record) leaves the one-step prediction errors white; the simulation shows it.  The
    increase counts when significant at the family's level (no ratio threshold: the test of ``ratio > 1`` is
    the rule)."""
    out = {}
    lag_min = int(round(0.1 / data.records[0].dt))
    blocks = _blocks(data, pred, "all")
    for i, o in enumerate(data.outputs):
        qf = np.concatenate([B[i, :n] ** 2 for B, n in zip(blocks, data.n_fit)])
        qh = np.concatenate([B[i, n:] ** 2 for B, n in zip(blocks, data.n_fit)])
        if qh.size <= 10 or not (np.all(np.isfinite(qf)) and np.all(np.isfinite(qh))):
            out[o] = {"ratio": float("nan"), "z": 0.0, "p": 1.0}
            continue
        var = sum(long_run_variance(q - q.mean(), max(bartlett_lag(q), lag_min)) / q.size for q in (qf, qh))
        mf, mh = float(qf.mean()), float(qh.mean())
        z = (mh - mf) / math.sqrt(var) if var > 0 else 0.0
        ratio = mh / mf if mf > 0 else float("inf")
        out[o] = {"ratio": ratio, "z": z, "p": float(ndtr(-z))}
    return out


def _adequacy(data: _Data, nm: NoiseModel, E_fit: np.ndarray, E_hold: np.ndarray, exo: dict | None = None,
              sim: dict | None = None) -> dict:
    """Are the one-step prediction errors white, and no larger on held-out data than on fitting data?"""
    white = {o: _whiteness(E_fit[i], _kept_order(data, int(nm.orders.get(o, nm.order)), i, E_fit.shape[1]))
             for i, o in enumerate(data.outputs)}
    q_fit = np.sum(E_fit * E_fit, axis=0)
    q_hold = np.sum(E_hold * E_hold, axis=0)
    if q_hold.size > 10:
        mf, mh = float(np.mean(q_fit)), float(np.mean(q_hold))
        var = long_run_variance(q_fit - mf) / q_fit.size + long_run_variance(q_hold - mh) / q_hold.size
        z = (mh - mf) / math.sqrt(var) if var > 0 else 0.0
        hold = {"ratio": mh / mf if mf > 0 else float("inf"), "z": z, "p": float(ndtr(-z))}
    else:
        hold = {"ratio": 1.0, "z": 0.0, "p": 1.0}
    sim = sim or {}
    n_tests = len(white) + 1 + (exo is not None) + len(sim)
    ps = [v["p"] for v in white.values()] + [hold["p"]] + [v["p"] for v in sim.values()]
    # white: no output's remaining dependence both significant and material; held-out: not significantly worse,
    # neither the one-step prediction errors nor the simulation's errors (each test's verdict kept beside it)
    for v in white.values():
        v["dependent"] = bool(v["p"] * n_tests < data.alpha and v["material"])
    hold["worse"] = bool(hold["p"] * n_tests < data.alpha)
    for v in sim.values():
        v["worse"] = bool(v["p"] * n_tests < data.alpha)
    adequate = (not any(v["dependent"] for v in white.values()) and not hold["worse"]
                and not any(v["worse"] for v in sim.values()))
    out = {"whiteness": white, "holdout": hold, "simulation_holdout": sim, "n_tests": n_tests}
    if exo is not None:
        # a deterministic error the noise model soaked up: the innovations follow the exogenous drive, by a
        # share of their variance that matters (a slight formulation mismatch is significant on long records)
        exo["dependent"] = bool(exo["p"] * n_tests < data.alpha and exo["r2_excess"] > EXO_R2)
        adequate = adequate and not exo["dependent"]
        out["exogenous"] = exo
        ps.append(exo["p"])
    out.update({"p_min_bonferroni": min(1.0, min(ps) * n_tests), "adequate": bool(adequate)})
    return out


def _exogenous(data: _Data, nm: NoiseModel, pred: list[dict[str, np.ndarray]]) -> dict | None:
    """Are the one-step prediction errors on the fitting data independent of the exogenous drive (the
    reference ``x_ref`` of a closed loop, the logged input of an open one)?  Each output's innovations are
    regressed on the drive's increments at lags ``0 ... EXO_LAGS``; with white innovations and an exogenous
    drive, ``Q = T sum_outputs R^2`` is chi-square(m x rank) under independence.  ``r2`` is the largest share
    of an output's innovation variance the drive's history explains."""
    L = EXO_LAGS
    Es, Xs = [], []
    for r, (rec, n, (_name, drive), p) in enumerate(zip(data.records, data.n_fit, data.drives(), pred)):
        start = nm.order + L
        if n - start < 10 * L:
            continue
        key = (id(rec), n, start)
        if key not in data.exo_cache:
            d = np.diff(np.asarray(drive[:n], float), prepend=float(drive[0]))
            sd = float(np.std(d))
            if not sd > 0:
                return None
            d = d / sd
            data.exo_cache[key] = np.stack([d[start - lag: n - lag] for lag in range(L + 1)], axis=1)
        B = np.array([(rec[o][:n] - p[o][:n]) / data.sigma[o] for o in data.outputs])
        fresh = data.fresh(r, n)
        kept = nm.kept(fresh, n)                              # samples order ... n - 1 whose innovations count
        keep = kept[start - nm.order:]                        # of samples start ... n - 1
        E = nm.whiten(B, fresh)[:, int(np.count_nonzero(kept[: start - nm.order])):]
        if not np.all(np.isfinite(E)):
            return None
        Es.append(E)
        Xs.append(data.exo_cache[key][keep])
    if not Es:
        return None
    E = np.concatenate(Es, axis=1)
    E = E - E.mean(axis=1, keepdims=True)
    X = np.concatenate(Xs, axis=0)
    X = X - X.mean(axis=0)
    # the projection of each output's innovations on the span of the drive's lags, through the (L+1)-square Gram
    # matrix: a tall SVD of X cost 25 ms on one thread and 0.1-0.7 s on a loaded machine's threaded LAPACK, the
    # Gram matrix and its eigenvectors 2 ms; directions below 1e-5 of the largest singular value do not count
    w, V = np.linalg.eigh(X.T @ X)
    top = float(w[-1]) if w.size else 0.0
    if not top > 0:
        return None
    k = w > 1e-10 * top
    proj = (E @ X) @ (V[:, k] / np.sqrt(w[k]))              # [m, rank]: E projected on X's left singular vectors
    rank = int(np.count_nonzero(k))
    r2 = np.sum(proj * proj, axis=1) / np.sum(E * E, axis=1)
    T = E.shape[1]
    q = float(T * np.sum(r2))
    df = int(rank * E.shape[0])
    # the share explained beyond what chance explains under independence (rank / T per output)
    return {"Q": q, "df": df, "lags": L, "p": float(chdtrc(df, q)), "r2": float(np.max(r2)),
            "r2_excess": float(np.max(r2) - rank / T), "dependent": False}


def _noise_model(data: _Data, blocks: list[np.ndarray], pred) -> tuple[NoiseModel, np.ndarray, np.ndarray]:
    """The noise model of a model's residuals and its innovations on the fitting and held-out data.  Each
    output's autoregression has the order AIC picks, raised (along ``ORDERS``) while its innovations keep a
    significant and material dependence at lags beyond it (Box-Jenkins: a noise model is not done while its
    errors are predictable; AIC alone stops short when many small correlations remain)."""
    fresh = [data.fresh(r, n) for r, n in enumerate(data.n_fit)]
    nm = fit_noise_model(blocks, data.outputs, fresh=fresh)
    E_fit, E_hold = _innovations(data, nm, pred)
    nm.raises = 0
    for _ in range(NOISE_RAISE):
        low = {}
        for i, o in enumerate(data.outputs):
            order = int(nm.orders.get(o, nm.order))
            w = _whiteness(E_fit[i], _kept_order(data, order, i, E_fit.shape[1]))
            higher = [p for p in NOISE_ORDERS if p > order]
            if w["p"] * len(data.outputs) < data.alpha and w["material"] and higher:
                low[o] = higher[0]
        if not low:
            break
        raises = nm.raises + 1
        nm = fit_noise_model(blocks, data.outputs, min_orders={**nm.orders, **low}, fresh=fresh)
        nm.raises = raises
        E_fit, E_hold = _innovations(data, nm, pred)
    return nm, E_fit, E_hold


def _state(data: _Data, res: FitResult, free: tuple[str, ...], timing: Timing) -> ModelState:
    pred = _simulate(data, res.params, timing)
    st = ModelState(res.params, free, res, pred, timing)
    st.holdout = _holdout(data, pred)
    st.analysis = analyse(data.model.name, data.records[0], pred[0], data.outputs, 0, data.n_fit[0])
    st.excess = _excess(data, pred)
    blocks = _blocks(data, pred, "fit")
    if all(np.all(np.isfinite(b)) for b in blocks):
        st.noise, E_fit, E_hold = _noise_model(data, blocks, pred)
        st.wcost = float(np.sum(E_fit * E_fit))
        st.n_w = int(E_fit.size)
        st.adequacy = _adequacy(data, st.noise, E_fit, E_hold, _exogenous(data, st.noise, pred),
                                _simulation_holdout(data, pred))
    else:  # a diverged simulation: nothing to judge, never adequate
        st.wcost, st.n_w = float("inf"), 0
        st.adequacy = {"adequate": False, "whiteness": {}, "holdout": {"ratio": float("nan"), "z": float("nan"),
                                                                      "p": 0.0}, "diverged": True}
    return st


def _gain(before: ModelState, after: ModelState, data: _Data | None = None) -> dict:
    """The gain of ``after`` over ``before``: held-out figures, whitened LR, AICc, bootstrap interval."""
    def figures(st: ModelState) -> dict:
        return {o: {k: st.holdout[o][k] for k in ("fit_pct", "nrmse")} for o in st.fit.outputs}

    out: dict[str, Any] = {"holdout": {"before": figures(before), "after": figures(after)},
           "holdout_fit_pct_gain": {o: after.holdout[o]["fit_pct"] - before.holdout[o]["fit_pct"]
                                    for o in after.fit.outputs}}
    if data is not None:
        lr, p, df, d_aicc = _lr(before, after, data)
        g, lo, hi = _holdout_gain(before, after, data)
        out.update({"lr": lr, "p": p, "df": df, "delta_aicc": d_aicc, "holdout_gain": g,
                    "holdout_gain_interval": [lo, hi]})
    return out


def _wcost_under(data: _Data, nm: NoiseModel, pred) -> tuple[float, np.ndarray, np.ndarray]:
    E_fit, E_hold = _innovations(data, nm, pred)
    return float(np.sum(E_fit * E_fit)), E_fit, E_hold


def _n_par(st: ModelState, base_timing: Timing) -> int:
    return st.fit.n_par + (0 if st.timing == base_timing else 1)


def _lr(cur: ModelState, st: ModelState, data: _Data) -> tuple[float, float, int, float]:
    """Whitened LR statistic of ``st`` against ``cur`` (both filtered by ``cur``'s noise model), its
    chi-square p-value, degrees of freedom and the whitened AICc difference."""
    df = max(_n_par(st, data.timing) - _n_par(cur, data.timing), 1)
    if cur.noise is None or not math.isfinite(st.wcost):
        return 0.0, 1.0, df, float("inf")
    c0 = cur.wcost
    c1, _, _ = _wcost_under(data, cur.noise, st.predicted)
    if not math.isfinite(c1):
        return 0.0, 1.0, df, float("inf")
    s2 = c0 / max(cur.n_w, 1)  # ~1: normalised innovations
    lr = max(0.0, (c0 - c1) / s2)
    n = cur.n_w
    k0 = _n_par(cur, data.timing)
    k1 = k0 + df
    aicc = lambda c, k: c / s2 + 2 * k + 2 * k * (k + 1) / max(n - k - 1, 1)  # noqa: E731
    return lr, float(chdtrc(df, lr)), df, aicc(c1, k1) - aicc(c0, k0)


def _holdout_gain(cur: ModelState, st: ModelState, data: _Data) -> tuple[float, float, float]:
    """Relative reduction of the held-out innovations' sum of squares (``cur``'s noise model) and its
    ``GAIN_COVERAGE`` interval (:func:`_holdout_test`)."""
    t = _holdout_test(cur, st, data)
    return t["gain"], t["lo"], t["hi"]


def _holdout_test(cur: ModelState, st: ModelState, data: _Data) -> dict:
    """Is ``st``'s held-out error significantly smaller than ``cur``'s?  A Diebold-Mariano-type test of equal
    predictive accuracy on the held-out tails, on the relative scale: ``d_t = q0_t - q1_t`` are the per-sample
    loss differences of the one-step prediction errors (squared innovations summed over outputs, both filtered
    by ``cur``'s noise model) and ``gain = sum d / sum q0`` the relative reduction; its standard error is the
    delta method's for a ratio of means, ``sqrt(LRV(d - gain q0) / T) / mean(q0)``, with a Newey-West long-run
    variance (Bartlett window of at least ``max(4 x the noise model's order, 0.1 s)``: a wrong model's errors
    are coloured and come in bursts); ``z = gain / se``, one-sided ``p = P(N(0,1) > z)`` (a Wald test of
    ``gain <= 0``: an error that comes in a few bursts makes ``q0`` as variable as ``d``, and the ratio,
    resampled as a ratio, is what is judged).  The interval is ``gain -/+ z_(GAIN_COVERAGE) se``."""
    nan = float("nan")
    if cur.noise is None:
        return {"gain": nan, "lo": nan, "hi": nan, "z": 0.0, "p": 1.0}
    _, _, H0 = _wcost_under(data, cur.noise, cur.predicted)
    _, _, H1 = _wcost_under(data, cur.noise, st.predicted)
    q0 = np.sum(H0 * H0, axis=0)
    q1 = np.sum(H1 * H1, axis=0)
    if not (np.all(np.isfinite(q1)) and q0.sum() > 0 and q0.size > 10):
        inf = float("-inf")
        return {"gain": inf, "lo": inf, "hi": inf, "z": inf, "p": 1.0}  # a diverged or empty comparison
    lag = max(bartlett_lag(q0 - q1), 4 * cur.noise.order, int(round(0.1 / data.records[0].dt)))
    return gain_test(q0, q1, lag)


def gain_test(q0: np.ndarray, q1: np.ndarray, lag: int) -> dict:
    """The relative gain ``sum (q0 - q1) / sum q0`` of per-sample losses ``q1`` over ``q0``, its HAC standard
    error (delta method for a ratio of means, Newey-West with ``lag``), ``z``, the one-sided p-value of
    ``gain <= 0`` and the ``GAIN_COVERAGE`` interval (:func:`_holdout_test`)."""
    d = q0 - q1
    T = d.size
    g = float(d.sum()) / float(q0.sum())
    se = math.sqrt(long_run_variance(d - g * q0, lag) / T) / float(q0.mean())
    z = g / se if se > 0 else (math.inf if g > 0 else 0.0)
    half = float(-ndtri((1.0 - GAIN_COVERAGE) / 2.0)) * se
    return {"gain": g, "lo": g - half, "hi": g + half, "z": z, "p": float(ndtr(-z)), "lag": lag}
