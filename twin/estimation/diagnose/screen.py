"""The score-test (Lagrange-multiplier) screen of the catalogue against the current model."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import stats

from twin.models import Model
from twin.record import as_logged
from twin.estimation.noise_model import (NoiseModel, fit_noise_model,
                                         long_run_variance)
from twin.estimation.diagnose.constants import CONDITION_ON, LIMITS, LIMIT_QUANTILES, SECANTS, SECONDARY
from twin.estimation.diagnose.data import ModelState, _Data, _fd_step, holm
from twin.estimation.diagnose.adequacy import _innovations
from twin.estimation.diagnose.results import ScreenRow


# --- the score-test screen --------------------------------------------------------------
def _probe_params(E) -> list[int]:
    """Indices of an effect's parameters probed by a derivative: those whose typical value differs from the
    neutral one, and those that can move either way from a neutral inside their bounds (an offset of the
    other transducer)."""
    out = [j for j, (n, t) in enumerate(zip(E.neutral, E.typical)) if n != t] or [0]
    for j, s in enumerate(E.params):
        two_sided = s.lo < E.neutral[j] < s.hi
        if j not in out and two_sided and E.typical[j] == E.neutral[j] and s.unit == E.params[out[0]].unit:
            out.append(j)
    return out


def _limit_levels(model: Model, name: str, state: ModelState, data: _Data) -> list[float] | None:
    """Probe levels of a limit parameter (``LIMITS``): quantiles of the limited state's magnitude in the
    current model's simulation of the fitting data, so that a probe clips a plausible share of the record;
    ``None`` for a parameter that is not a limit."""
    key = LIMITS.get(name)
    if key is None or f"state:{key}" not in state.predicted[0]:
        return None
    mag = np.concatenate([np.abs(p[f"state:{key}"][:n]) for p, n in zip(state.predicted, data.n_fit)])
    mag = mag[np.isfinite(mag)]
    if not mag.size or not np.max(mag) > 0:
        return []
    return sorted({float(v) for v in np.quantile(mag, LIMIT_QUANTILES)}, reverse=True)


def screen(data: _Data, state: ModelState, candidates: Sequence[str]) -> list[ScreenRow]:
    """Score-test every candidate effect against ``state`` in one batched simulation per record, on the
    one-step prediction errors of ``state``'s noise model (module docstring)."""
    model = data.model
    ps = state.params
    base = model.vector(ps)
    rows = [base]
    jac_cols = []
    for name in state.free:
        i = model.kernel_index(name)
        spec = ps.spec(name)
        h = _fd_step(spec, base[i], spec.typical)
        v = base.copy()
        v[i] += h
        rows.append(v)
        jac_cols.append(h)
    probes = []  # (effect, label, denominator, values dict, spec of the moved parameter, neutral)
    for eff in candidates:
        E = data.effect(eff)
        movers = _probe_params(E)
        prim = movers[0]
        pspec = E.params[prim]
        neutral, typical = E.neutral[prim], E.typical[prim]
        direction = 1.0 if typical > neutral else -1.0
        sec_idx = [j for j in range(len(E.params)) if j not in movers]
        sec_grid: list[dict[str, float]] = [{}]
        for j in sec_idx:
            s = E.params[j]
            vals = sorted({float(np.clip(E.typical[j] * f, s.lo, s.hi)) for f in SECONDARY})
            sec_grid = [dict(g, **{s.name: v}) for g in sec_grid for v in vals]
        pvals = []
        levels = _limit_levels(model, pspec.name, state, data)
        if levels is None:  # a limit's derivative at neutral (no clipping) vanishes: probed by levels only
            pvals.append(("derivative", pspec, neutral, neutral + direction * 1e-4 * abs(typical - neutral)))
            # secants to a few plausible magnitudes: multiples of the typical deviation from neutral
            levels = [neutral + f * (typical - neutral) for f in SECANTS]
        for lv in levels:
            pv = float(np.clip(lv, pspec.lo, pspec.hi))
            if pv != neutral:
                pvals.append((f"secant@{pspec.show(pv)}", pspec, neutral, pv))
        for j in movers[1:]:  # a parameter that moves either way from neutral (e.g. the other offset)
            s = E.params[j]
            step = 1e-4 * abs(typical - neutral)
            pvals.append((f"derivative:{s.name}", s, E.neutral[j], E.neutral[j] + step))
        for g in sec_grid:
            for label, sp, neut, pv in pvals:
                v = base.copy()
                for j, s in enumerate(E.params):
                    v[model.kernel_index(s.name)] = g.get(s.name, E.neutral[j])
                v[model.kernel_index(sp.name)] = pv
                rows.append(v)
                extra = "" if not g else " " + ",".join(f"{k}={_show(E, k, x)}" for k, x in g.items())
                probes.append((eff, label + extra, pv - neut, dict(g, **{sp.name: pv}), sp, neut))
    P = np.ascontiguousarray(np.array(rows))
    raw = []
    for rec, n, (dname, drive), init in zip(data.records, data.n_fit, data.drives(), data.init(ps)):
        S0 = model.initial_state(P, init)  # each row from its own sensor errors
        exo = {k: v[:n] for k, v in model.exogenous_of(rec.signals).items()}
        sim = model.simulate_batch(P, dname, drive[:n], rec.dt, S0, None, state.timing, exo)
        Y = np.stack([as_logged(rec, o, sim.outputs[o]) / data.sigma[o] for o in data.outputs], axis=1)  # [K, m, n]
        y = np.array([rec[o][:n] / data.sigma[o] for o in data.outputs])
        raw.append(np.concatenate([(y - Y[0])[None], Y[1:] - Y[0]], axis=0))
    nm = _clean_noise_model(data, raw) or state.noise
    assert nm is not None  # the state's model was fitted with its noise model
    _set_noise(data, state, nm)
    R, C = [], []
    for r_i, (W, n) in enumerate(zip(raw, data.n_fit)):
        W = nm.whiten(W, data.fresh(r_i, n))  # [K, m, n - p], the samples where every output is a measurement
        R.append(W[0])
        C.append(W[1:])
    r2 = np.concatenate(R, axis=1)             # [m, n]
    C2 = np.concatenate(C, axis=2)             # [K-1, m, n]
    m_out, n_t = r2.shape
    r = r2.reshape(-1)
    Cf = C2.reshape(C2.shape[0], -1)
    nj = len(jac_cols)
    J = (Cf[:nj] / np.array(jac_cols)[:, None]).T
    S = Cf[nj:]
    N = r.size
    ok = np.isfinite(r).all() and np.isfinite(J).all()
    Q, _ = np.linalg.qr(J) if nj and ok else (np.zeros((N, 0)), None)
    r_perp = r - Q @ (Q.T @ r)
    sigma2 = float(r_perp @ r_perp) / max(N - nj, 1)
    excess = max(state.excess, math.sqrt(2.0 * N))
    # marginal scores: every probe against the current model (its free parameters projected out)
    perp = []
    marginal = []
    for k, (_eff, _label, denom, _values, pspec, neutral) in enumerate(probes):
        s = S[k] / denom
        s_perp = s - Q @ (Q.T @ s) if np.isfinite(s).all() else None
        perp.append(s_perp)
        marginal.append(_score(s_perp, r_perp, m_out, n_t, neutral, pspec))
    # conditional scores: every probe with the strongest other effects' best directions projected out too.  An
    # error of one effect can point another's score the wrong way: an un-modelled force offset makes a
    # free-running axis drift, and against that drift the dry friction's direction looks negative; the marginal
    # one-sided score of the friction is then exactly 0 although the friction is in the record
    lead = sorted(((lm, k) for k, (lm, _d) in enumerate(marginal) if lm > 0), reverse=True)
    leaders: list[tuple[str, int]] = []
    for _lm, k in lead:
        if probes[k][0] not in {e for e, _ in leaders}:
            leaders.append((probes[k][0], k))
    conditional = []
    for k, (eff, *_rest, pspec, neutral) in enumerate(probes):
        others = [j for e, j in leaders if e != eff][:CONDITION_ON]
        got = []
        for j in others:
            u = perp[j]
            if perp[k] is None or u is None or not float(u @ u) > 0:
                continue
            u = u / math.sqrt(float(u @ u))
            got.append(_score(perp[k] - u * float(u @ perp[k]), r_perp - u * float(u @ r_perp), m_out, n_t,
                              neutral, pspec))
        conditional.append(max(got, default=(0.0, 0.0)))
    best: dict[str, ScreenRow] = {}
    n_probes: dict[str, int] = {}
    for k, (eff, label, _denom, values, pspec, neutral) in enumerate(probes):
        n_probes[eff] = n_probes.get(eff, 0) + 1 + CONDITION_ON  # Bonferroni over marginal and conditional
        (lm, delta), cond = marginal[k], False
        if conditional[k][0] > lm:
            (lm, delta), cond = conditional[k], True
        pval = float(stats.chi2.sf(lm, 1))
        est = dict(values)
        if label.startswith("derivative") and lm > 0:  # one Gauss-Newton step from neutral
            est[pspec.name] = float(np.clip(neutral + delta, pspec.lo, pspec.hi))
        share = min(lm * sigma2 / excess, 10.0)
        row = ScreenRow(eff, lm, pval, 1.0, 1.0, label + (" | others" if cond else ""), est, share)
        if eff not in best or lm > best[eff].lm:
            if eff in best and label.startswith("derivative:"):  # keep both offsets' one-step estimates
                row.estimate = {**best[eff].estimate, **est}
            best[eff] = row
        elif label.startswith("derivative:") and lm > 0:
            best[eff].estimate[pspec.name] = est[pspec.name]
    out = sorted(best.values(), key=lambda row: -row.lm)
    for row in out:
        row.p_effect = min(1.0, row.p * n_probes[row.effect])
    for row, pa in zip(out, holm([row.p_effect for row in out])):
        row.p_adjusted = pa
    return out


def _score(s_perp: np.ndarray | None, r_perp: np.ndarray, m_out: int, n_t: int, neutral: float,
           pspec) -> tuple[float, float]:
    """The LM statistic of one probe direction ``s_perp`` against the residual ``r_perp`` (both with the
    model's free directions projected out; Newey-West variance of the per-sample score) and the one-step
    estimate ``delta``; 0 for a one-sided effect (a friction, a limit) whose step points out of its range."""
    if s_perp is None:
        return 0.0, 0.0
    ss = float(s_perp @ s_perp)
    if not (ss > 0 and math.isfinite(ss)):
        return 0.0, 0.0
    sr = float(s_perp @ r_perp)
    delta = sr / ss
    g = (s_perp * r_perp).reshape(m_out, n_t).sum(axis=0)  # per-sample score, outputs summed
    lrv = long_run_variance(g - delta * (s_perp * s_perp).reshape(m_out, n_t).sum(axis=0))
    lm = sr * sr / (n_t * lrv) if lrv > 0 else 0.0
    if (neutral <= pspec.lo and delta <= 0) or (neutral >= pspec.hi and delta >= 0):
        return 0.0, delta
    return lm, delta


def _clean_noise_model(data: _Data, raw: Sequence[np.ndarray]) -> NoiseModel | None:
    """The noise model fitted to the residuals with every screened direction (free parameters and candidate
    effects, linearised) regressed out: an effect in the catalogue is not taken for coloured noise."""
    cleaned = []
    for W in raw:
        r = W[0].reshape(-1)
        X = W[1:].reshape(W.shape[0] - 1, -1).T
        good = np.all(np.isfinite(X), axis=0)
        if not np.all(np.isfinite(r)):
            return None
        X = X[:, good]
        if X.shape[1]:
            nrm = np.linalg.norm(X, axis=0)
            X = X[:, nrm > 0] / nrm[nrm > 0]
            G = X.T @ X
            beta = np.linalg.solve(G + 1e-10 * np.eye(G.shape[0]), X.T @ r)
            r = r - X @ beta
        cleaned.append(r.reshape(W.shape[1], W.shape[2]))
    return fit_noise_model(cleaned, data.outputs, fresh=[data.fresh(i, n) for i, n in enumerate(data.n_fit)])


def _set_noise(data: _Data, state: ModelState, nm: NoiseModel) -> None:
    """Use ``nm`` as ``state``'s noise model from now on (the tests of its extensions are judged under it)."""
    state.noise = nm
    E_fit, _ = _innovations(data, nm, state.predicted)
    state.wcost = float(np.sum(E_fit * E_fit))
    state.n_w = int(E_fit.size)


def _show(E, name: str, value: float) -> str:
    for s in E.params:
        if s.name == name:
            return s.show(value)
    return f"{value:g}"
