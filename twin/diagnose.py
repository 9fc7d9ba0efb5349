"""Diagnose what a simulation gets wrong: name the physical cause, extend the model, measure the gain.

The method (``twin diagnose DATA --model msp25|oscillator``):

1. **Split** every record: the first ``1 - holdout`` (75 %) is fitting data, the
   rest is held out; held-out figures come from simulating the whole record
   with the fitted parameters and scoring only its tail.
2. **Fit the nominal model** (its phenomenological parameters free) by output
   error and analyse its residuals (:mod:`twin.residuals`): whiteness
   (Ljung-Box), cross-correlations, where they concentrate.
3. **Screen the catalogue** with a score (Lagrange-multiplier) test.  In one
   batched simulation the model is run at the estimate, at a small step of
   every free parameter (the Jacobian ``J``) and at probes of every candidate
   effect: a small step of its parameter away from the neutral value (the
   sensitivity ``s`` at the nominal model) plus secants to a few plausible
   magnitudes (needed where the derivative at the neutral value vanishes, e.g.
   a spool stroke limit that is never reached, and useful for non-smooth
   effects such as an overlap).  With the weighted residual ``r`` and
   ``s_perp`` = ``s`` with the span of ``J`` projected out,

       LM = (s_perp' r)^2 / (sigma^2 s_perp' s_perp),   sigma^2 = r'r / (N - p),

   is chi-square(1) when the effect is absent; ``s_perp' r / s_perp' s_perp`` is
   the one-step (Gauss-Newton) estimate of its parameter, used as a start.  An
   effect whose parameter can only move one way from neutral (a friction
   coefficient, a stroke limit) scores 0 when the residual points the other way.
4. **Fit the promising extensions** (screen p-value below ``alpha`` after a
   Bonferroni correction over all probe columns; if the residuals are not white
   and nothing passes, the two best anyway): nominal free parameters plus the
   effect's own, from the screen's estimate.
5. **Decide**: an extension is accepted when its likelihood-ratio test against
   the current model has ``p < alpha``, its AICc on the fitting data is lower,
   its held-out weighted error is lower, and it removes at least
   ``min_share`` of the current model's *excess* misfit (the part of the
   residual power above the noise floor, estimated from sample differences),
   so that an effect that merely soaks up a little of an out-of-catalogue error
   is not named (the share is judged only while the residuals are not white).
   Among accepted ones the lowest AICc wins; then the screen is run again on
   the extended model (greedy), until nothing passes.  When no single effect
   passes but two are significant, the pair is fitted together (some effects
   are recognisable only together: a sensor delay bends the valve parameters
   while a friction is fitted alone); it is accepted if it passes the same
   tests and each effect is significant (LR) within the pair.
6. **Verdict**: ``causes`` are the accepted effects; ``unexplained`` is true when
   the final model's residuals on the fitting data are still not white
   (Ljung-Box ``p < alpha`` on some output): then the residual signature is
   shown instead of a forced name.

:func:`diagnose` returns a :class:`Diagnosis`; :func:`add_diagnose_arguments`
and :func:`run_diagnose` are the command line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy import stats

from twin.cliutil import dump
from twin.cliutil import json_default as _json_default
from twin.cliutil import kv as _kv
from twin.cliutil import names as _names
from twin.errors import DataError, ParameterError
from twin.fit import FitResult, fit, likelihood_ratio, resolve_outputs
from twin.models import Model, get_model
from twin.params import ParameterSet, check_names
from twin.record import Record
from twin.residuals import ResidualAnalysis, analyse
from twin.simulate import DEFAULT_NOISE

#: significance level of the screen (before Bonferroni), the LR test and the whiteness test
ALPHA = 1e-3
#: share of the current model's excess misfit an extension must remove to be named
MIN_SHARE = 0.5
#: multiples of an effect's typical magnitude used as secant probes in the screen
SECANTS = (0.3, 1.0, 3.0)
#: multiples of a secondary parameter's typical value tried in the screen (e.g. Stribeck velocity)
SECONDARY = (1.0 / 3.0, 1.0, 3.0)
#: regime variable against which each effect's signature is plotted
SIGNATURE_AXIS = {
    "viscous_friction": "velocity", "stribeck_friction": "velocity", "laminar_leakage": "dp",
    "spool_deadband": "spool_opening", "valve_null_bias": "spool_opening", "supply_pressure_droop": "velocity",
    "specimen_stiffness": "position", "sensor_delay": "velocity", "entrained_air": "dp",
    "spool_saturation": "spool_opening", "coulomb_friction": "velocity", "cubic_stiffness": "position",
    "input_delay": "velocity",
}


#: SI units of the outputs, for plot labels
UNITS = {"x": "m", "pA": "Pa", "pB": "Pa", "y": "m"}
#: effects whose signature is best seen as a residual force (A times the pressure-difference residual)
FORCE_EFFECTS = ("viscous_friction", "stribeck_friction", "specimen_stiffness")


# --- data --------------------------------------------------------------------------------
@dataclasses.dataclass
class _Data:
    model: Model
    records: list[Record]
    n_fit: list[int]
    outputs: tuple[str, ...]
    sigma: dict[str, float]
    drive: str

    @property
    def parts(self) -> list[Record]:
        return [r.slice(0, n) for r, n in zip(self.records, self.n_fit)]

    def drives(self, records: Sequence[Record] | None = None) -> list[tuple[str, np.ndarray]]:
        return [self.model.drive_signal(r.signals, self.drive) for r in (records or self.records)]


@dataclasses.dataclass
class ModelState:
    """One model of the greedy path: its parameters, fit, held-out figures and residual analysis."""

    params: ParameterSet
    free: tuple[str, ...]
    fit: FitResult
    predicted: list[dict[str, np.ndarray]] = dataclasses.field(repr=False)  # whole records
    holdout: dict = dataclasses.field(default_factory=dict)
    analysis: ResidualAnalysis | None = None          # on the fitting data (first record)
    excess: float = 0.0                               # weighted residual power above the noise floor

    @property
    def effects(self) -> tuple[str, ...]:
        return self.params.effects

    def param_table(self, names: Sequence[str] | None = None) -> dict:
        out = {}
        for n in (names or self.free):
            spec = self.params.spec(n)
            out[n] = {"value": self.fit.estimate.get(n, self.params[n]), "std": self.fit.std.get(n, 0.0),
                      "unit": spec.unit, "shown": spec.show(self.fit.estimate.get(n, self.params[n]))}
        return out

    def summary(self) -> dict:
        return {"effects": list(self.effects), "params": self.param_table(),
                "aicc": self.fit.aicc, "aic": self.fit.aic, "loglik": self.fit.loglik, "n_par": self.fit.n_par,
                "fit_pct": self.fit.fit_pct, "nrmse": self.fit.nrmse, "converged": self.fit.success,
                "holdout": self.holdout,
                "residuals": self.analysis.summary() if self.analysis is not None else None}


@dataclasses.dataclass
class ScreenRow:
    """Score-test result of one candidate effect."""

    effect: str
    lm: float
    p: float                   # chi-square(1) p-value of the best probe column
    p_adjusted: float          # Bonferroni over all probe columns of the screen
    probe: str                 # "derivative" or "secant@<value>"
    estimate: dict[str, float]  # one-step estimate of the effect's parameters (a fit start)
    share: float               # share of the excess misfit the linearised effect would remove

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class Trial:
    """A fitted extension of the current model by one effect, and how it compares."""

    effect: str
    state: ModelState
    lr: float
    p: float
    df: int
    delta_aicc: float
    holdout_gain: float        # relative reduction of the held-out weighted squared error
    share: float               # share of the current model's excess misfit removed
    accepted: bool = False
    reason: str = ""

    def to_dict(self) -> dict:
        return {"effect": self.effect, "lr": self.lr, "p": self.p, "df": self.df,
                "delta_aicc": self.delta_aicc, "holdout_gain": self.holdout_gain, "share": self.share,
                "accepted": self.accepted, "reason": self.reason,
                "params": self.state.param_table(get_model(self.state.params.model).EFFECTS[self.effect].names)}


@dataclasses.dataclass
class Diagnosis:
    """What :func:`diagnose` found: causes, whether something is left unexplained, the models and gains."""

    model: str
    causes: list[str]
    unexplained: bool
    nominal: ModelState
    final: ModelState
    path: list[ModelState]                 # nominal, then one state per accepted effect
    screens: list[list[ScreenRow]]
    trials: list[list[Trial]]
    gains: dict[str, dict]                 # per cause: gain of the step that added it
    outputs: tuple[str, ...]
    holdout: float
    time_s: float
    records: list[Record] = dataclasses.field(repr=False, default_factory=list)
    n_fit: list[int] = dataclasses.field(repr=False, default_factory=list)
    plots: list[str] = dataclasses.field(default_factory=list)

    def effect_params(self, effect: str) -> dict:
        return self.final.param_table(get_model(self.model).EFFECTS[effect].names)

    def extended_params(self) -> dict:
        """The extended model as JSON usable by ``twin fit`` and the tracker (effects by name + values)."""
        ps = self.final.params
        return {"model": self.model, "effects": list(ps.effects), "params": ps.as_dict(),
                "std": dict(self.final.fit.std),
                "set": ",".join(f"{k}={v:.10g}" for k, v in ps.as_dict().items()
                                if k in self.final.free),
                "free": list(self.final.free)}

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "causes": list(self.causes),
            "unexplained": bool(self.unexplained),
            "effects": {c: {"params": self.effect_params(c), "gain": self.gains[c]} for c in self.causes},
            "nominal": self.nominal.summary(),
            "extended": self.final.summary() if self.causes else None,
            "overall_gain": _gain(self.nominal, self.final) if self.causes else None,
            "extended_params": self.extended_params(),
            "screens": [[row.to_dict() for row in s] for s in self.screens],
            "trials": [[t.to_dict() for t in ts] for ts in self.trials],
            "signature": (self.final.analysis.summary() if self.unexplained and self.final.analysis else None),
            "holdout_fraction": self.holdout,
            "outputs": list(self.outputs),
            "time_s": self.time_s,
            "plots": list(self.plots),
        }

    def text(self) -> str:
        lines = [f"model {self.model}: nominal fit of {', '.join(self.nominal.free)} "
                 f"on the first {100 * (1 - self.holdout):.0f} % of {len(self.records)} record(s)"]
        lines.append(self.nominal.fit.table())
        lines.append("nominal residuals (fitting data):")
        lines.append(self.nominal.analysis.text() if self.nominal.analysis else "  -")
        for i, (scr, trials) in enumerate(zip(self.screens, self.trials)):
            against = ", ".join(self.path[min(i, len(self.path) - 1)].effects) or "the nominal model"
            lines.append(f"screen {i + 1} (score test against {against}):")
            for row in scr[:6]:
                lines.append(f"  {row.effect:<22} LM={row.lm:11.4g} p_adj={row.p_adjusted:9.3g} "
                             f"share~{row.share:6.3f} ({row.probe})")
            for t in trials:
                lines.append(f"  fitted {t.effect:<18} LR={t.lr:10.4g} p={t.p:9.3g} dAICc={t.delta_aicc:10.4g} "
                             f"held-out gain={100 * t.holdout_gain:7.2f}% share={t.share:6.3f} "
                             f"-> {'ACCEPTED' if t.accepted else 'rejected'} {t.reason}")
        if self.causes:
            lines.append(f"causes: {', '.join(self.causes)}")
            for c in self.causes:
                g = self.gains[c]
                lines.append(f"  {c}: LR={g['lr']:.4g} (df {g['df']}) p={g['p']:.3g} dAICc={g['delta_aicc']:.4g}")
                for p, v in self.effect_params(c).items():
                    spec = self.final.params.spec(p)
                    lines.append(f"    {p:<10} {v['shown']:>18} +/- {spec.show(v['std'])}")
                for o in self.outputs:
                    b, a = g["holdout"]["before"][o], g["holdout"]["after"][o]
                    lines.append(f"    held-out {o:<3} Fit {b['fit_pct']:8.3f}% -> {a['fit_pct']:8.3f}%   "
                                 f"NRMSE {b['nrmse']:.4g} -> {a['nrmse']:.4g}")
        else:
            lines.append("causes: none")
        if self.unexplained:
            left = "after the extension " if self.causes else ""
            lines.append(f"UNEXPLAINED: the residuals are still not white {left}and no catalogue effect explains "
                         "what is left; residual signature:")
            lines.append(self.final.analysis.text() if self.final.analysis else "  -")
        elif not self.causes:
            lines.append("the nominal model is adequate (residuals white at the noise floor)")
        for p in self.plots:
            lines.append(f"plot: {p}")
        return "\n".join(lines)


# --- helpers -------------------------------------------------------------------------------
def _simulate(data: _Data, ps: ParameterSet) -> list[dict[str, np.ndarray]]:
    """Whole-record predictions of ``ps`` (outputs and inputs)."""
    P = data.model.vector(ps)[None, :]
    out = []
    for rec, (name, drive) in zip(data.records, data.drives()):
        sim = data.model.simulate_batch(P, name, drive, rec.dt)
        d = {o: sim.outputs[o][0] for o in data.model.OUTPUTS}
        for k, v in sim.inputs.items():
            d[k] = np.asarray(v)[0] if np.ndim(v) == 2 else np.asarray(v)
        out.append(d)
    return out


def _holdout(data: _Data, pred: list[dict[str, np.ndarray]]) -> dict:
    """Held-out Fit %, NRMSE per output and the weighted squared error, on the records' tails."""
    out: dict = {}
    cost = 0.0
    for o in data.outputs:
        y = np.concatenate([r[o][n:] for r, n in zip(data.records, data.n_fit)])
        yh = np.concatenate([p[o][n:] for p, n in zip(pred, data.n_fit)])
        e = y - yh
        den = float(np.linalg.norm(y - y.mean()))
        out[o] = {"fit_pct": 100.0 * (1.0 - float(np.linalg.norm(e)) / den) if den > 0 else float("nan"),
                  "nrmse": float(np.sqrt(np.mean(e * e)) / np.std(y)) if np.std(y) > 0 else float("nan"),
                  "rms": float(np.sqrt(np.mean(e * e)))}
        cost += float(np.sum((e / data.sigma[o]) ** 2))
    out["weighted_sse"] = cost
    return out


def _excess(data: _Data, pred: list[dict[str, np.ndarray]]) -> float:
    """Weighted residual power above the noise floor on the fitting data (sum over outputs)."""
    total = 0.0
    for o in data.outputs:
        for r, p, n in zip(data.records, pred, data.n_fit):
            e = (r[o][:n] - p[o][:n]) / data.sigma[o]
            nz = float(np.std(np.diff(e)) / math.sqrt(2.0))
            total += float(np.sum(e * e)) - n * nz * nz
    return max(total, 0.0)


def _state(data: _Data, res: FitResult, free: tuple[str, ...]) -> ModelState:
    pred = _simulate(data, res.params)
    st = ModelState(res.params, free, res, pred)
    st.holdout = _holdout(data, pred)
    st.analysis = analyse(data.model.name, data.records[0], pred[0], data.outputs, 0, data.n_fit[0])
    st.excess = _excess(data, pred)
    return st


def _gain(before: ModelState, after: ModelState) -> dict:
    lr, p, df = likelihood_ratio(before.fit, after.fit)
    def figures(st: ModelState) -> dict:
        return {o: {k: st.holdout[o][k] for k in ("fit_pct", "nrmse")} for o in st.fit.outputs}

    return {"holdout": {"before": figures(before), "after": figures(after)},
            "holdout_fit_pct_gain": {o: after.holdout[o]["fit_pct"] - before.holdout[o]["fit_pct"]
                                     for o in after.fit.outputs},
            "holdout_gain": 1.0 - after.holdout["weighted_sse"] / before.holdout["weighted_sse"],
            "delta_aicc": after.fit.aicc - before.fit.aicc, "lr": lr, "p": p, "df": df}


def _fd_step(spec, value: float, typical: float | None) -> float:
    h = 1e-6 * max(abs(value), abs(typical or 0.0), 1e-300)
    if value + h > spec.hi:
        h = -h
    return h


# --- the score-test screen --------------------------------------------------------------
def screen(data: _Data, state: ModelState, candidates: Sequence[str]) -> list[ScreenRow]:
    """Score-test every candidate effect against ``state`` in one batched simulation per record."""
    model = data.model
    ps = state.params
    base = model.vector(ps)
    rows = [base]
    jac_cols = []  # (kernel index, step)
    for name in state.free:
        i = model.kernel_index(name)
        spec = ps.spec(name)
        h = _fd_step(spec, base[i], spec.typical)
        v = base.copy()
        v[i] += h
        rows.append(v)
        jac_cols.append(h)
    probes = []  # (effect, label, denominators per primary, values dict)
    for eff in candidates:
        E = model.EFFECTS[eff]
        prim = next((j for j, (n, t) in enumerate(zip(E.neutral, E.typical)) if n != t), 0)
        pspec = E.params[prim]
        neutral, typical = E.neutral[prim], E.typical[prim]
        direction = 1.0 if typical > neutral else -1.0
        sec_idx = [j for j in range(len(E.params)) if j != prim]
        sec_grid = [{}]
        for j in sec_idx:
            s = E.params[j]
            vals = sorted({float(np.clip(E.typical[j] * f, s.lo, s.hi)) for f in SECONDARY})
            sec_grid = [dict(g, **{s.name: v}) for g in sec_grid for v in vals]
        pvals = [("derivative", neutral + direction * 1e-4 * abs(typical - neutral))]
        for f in SECANTS:
            pv = float(np.clip(typical * f, pspec.lo, pspec.hi))
            if pv != neutral:
                pvals.append((f"secant@{pspec.show(pv)}", pv))
        for g in sec_grid:
            for label, pv in pvals:
                v = base.copy()
                for j, s in enumerate(E.params):
                    v[model.kernel_index(s.name)] = g.get(s.name, E.neutral[j])
                v[model.kernel_index(pspec.name)] = pv
                rows.append(v)
                extra = "" if not g else " " + ",".join(f"{k}={_show(E, k, x)}" for k, x in g.items())
                probes.append((eff, label + extra, pv - neutral, dict(g, **{pspec.name: pv}), pspec, neutral))
    P = np.ascontiguousarray(np.array(rows))
    R, cols = [], []
    for rec, n, (dname, drive) in zip(data.records, data.n_fit, data.drives()):
        sim = model.simulate_batch(P, dname, drive[:n], rec.dt)
        for o in data.outputs:
            Y = sim.outputs[o]
            R.append((rec[o][:n] - Y[0]) / data.sigma[o])
            cols.append((Y[1:] - Y[0]) / data.sigma[o])
    r = np.concatenate(R)
    C = np.concatenate(cols, axis=1)  # [columns, N]
    nj = len(jac_cols)
    J = (C[:nj] / np.array(jac_cols)[:, None]).T
    S = C[nj:]
    N, p = r.size, nj
    sigma2 = float(r @ r) / max(N - p, 1)
    Q, _ = np.linalg.qr(J) if nj else (np.zeros((N, 0)), None)
    r_perp = r - Q @ (Q.T @ r)
    excess = max(state.excess, math.sqrt(2.0 * N))
    best: dict[str, ScreenRow] = {}
    n_cols = len(probes)
    for k, (eff, label, denom, values, pspec, neutral) in enumerate(probes):
        s = S[k] / denom
        s_perp = s - Q @ (Q.T @ s)
        ss = float(s_perp @ s_perp)
        if not ss > 0 or not math.isfinite(ss):
            lm, delta = 0.0, 0.0
        else:
            sr = float(s_perp @ r_perp)
            delta = sr / ss
            lm = sr * sr / (sigma2 * ss)
        one_sided_up = neutral <= pspec.lo
        one_sided_down = neutral >= pspec.hi
        if (one_sided_up and delta <= 0) or (one_sided_down and delta >= 0):
            lm = 0.0
        pval = float(stats.chi2.sf(lm, 1))
        est = dict(values)
        if label.startswith("derivative") and lm > 0:  # one Gauss-Newton step from neutral
            est[pspec.name] = float(np.clip(neutral + delta, pspec.lo, pspec.hi))
        # a secant's start is its probe value: the effect is non-linear between neutral and there
        share = min(lm * sigma2 / excess, 10.0)
        row = ScreenRow(eff, lm, pval, min(1.0, pval * n_cols), label, est, share)
        if eff not in best or lm > best[eff].lm:
            best[eff] = row
    return sorted(best.values(), key=lambda row: -row.lm)


def _show(E, name: str, value: float) -> str:
    for s in E.params:
        if s.name == name:
            return s.show(value)
    return f"{value:g}"


# --- fitting an extension -----------------------------------------------------------------
def _plausible_start(model: Model, effect: str, est: Mapping[str, float]) -> dict[str, float]:
    """The screen's one-step estimate, pulled into [typical/100, 100 typical] of the effect."""
    E = model.EFFECTS[effect]
    out = {}
    for s, n, t in zip(E.params, E.neutral, E.typical):
        v = float(est.get(s.name, t))
        if n != t and t != 0:
            mag = abs(v - n)
            ref = abs(t - n)
            if not (ref / 100 <= mag <= 100 * ref):
                v = n + math.copysign(min(max(mag, ref / 100), 100 * ref), v - n if v != n else t - n)
        lo_in = s.lo + 1e-9 * (abs(s.lo) + 1e-300)
        hi_in = s.hi - 1e-9 * (abs(s.hi) + 1e-300)
        out[s.name] = float(np.clip(v, lo_in, hi_in))
    return out


def _fit_state(data: _Data, ps: ParameterSet, free: tuple[str, ...], start: Mapping[str, float],
               n_starts: int, seed: int) -> ModelState:
    res = fit(data.model, data.parts, free, base=ps, start=start, outputs=data.outputs, noise=data.sigma,
              drive=data.drive, n_starts=n_starts, n_refine=1 if n_starts <= 2 else 2, spread=1.5, seed=seed,
              max_nfev=80)
    return _state(data, res, free)


def _rank_starts(data: _Data, ps: ParameterSet, starts: Sequence[Mapping[str, float]]) -> list[dict[str, float]]:
    """Starts sorted by weighted cost on the fitting data, all evaluated in one batch per record."""
    model = data.model
    P = np.ascontiguousarray(np.array([model.vector(ps.update(s)) for s in starts]))
    cost = np.zeros(len(starts))
    for rec, n, (dname, drive) in zip(data.records, data.n_fit, data.drives()):
        sim = model.simulate_batch(P, dname, drive[:n], rec.dt)
        for o in data.outputs:
            e = (sim.outputs[o] - rec[o][None, :n]) / data.sigma[o]
            cost += np.sum(e * e, axis=1)
    cost = np.where(np.isfinite(cost), cost, np.inf)
    return [dict(starts[i]) for i in np.argsort(cost, kind="stable")]


def _effect_starts(model: Model, effect: str, est: Mapping[str, float]) -> list[dict[str, float]]:
    """The screen's estimate, the typical magnitude and a tenth of it (close to neutral) of ``effect``."""
    E = model.EFFECTS[effect]
    out = [_plausible_start(model, effect, est), dict(zip(E.names, E.typical))]
    small = {}
    for s, n, t in zip(E.params, E.neutral, E.typical):
        small[s.name] = t if n == t else (n + 0.1 * (t - n) if n < t else min(s.hi, 10.0 * t))
    out.append(_plausible_start(model, effect, small))
    return out


def _try(data: _Data, cur: ModelState, row: ScreenRow, seed: int, alpha: float, min_share: float,
         configured: ParameterSet) -> Trial:
    model = data.model
    E = model.EFFECTS[row.effect]
    free = cur.free + E.names
    ps = model.params(effects=cur.effects + (row.effect,)).update(cur.params.as_dict())
    # starts: the effect at the screen's estimate, its typical magnitude and close to neutral; the
    # other free parameters at the current estimates (which may have bent to mimic the effect) or
    # as configured.  All screened in one batch; the best is refined, and the second best too
    # when the first does not make the extension pass.
    base_starts = [dict(cur.fit.estimate), {n: configured[n] for n in cur.free if n in configured}]
    ranked = _rank_starts(data, ps, [{**b, **e} for b in base_starts
                                     for e in _effect_starts(model, row.effect, row.estimate)])
    # a fit that ends worse than the nested model is a failed fit: then also start next to neutral,
    # where the extended model is the current one and the fit can only improve on it
    near = dict(cur.fit.estimate)
    for s, n, v in zip(E.params, E.neutral, E.typical):
        near[s.name] = n + 1e-3 * (v - n) if n < v else (n if n == v else min(s.hi, 10.0 * v))
    t = None
    for attempt, start in enumerate(ranked[:2] + [near]):
        if attempt == 2 and t.state.fit.cost < cur.fit.cost:
            break
        st = _fit_state(data, ps.update(start), free, start, 1, seed)
        cand = _judge(row.effect, cur, st, alpha, min_share)
        if t is None or cand.state.fit.cost < t.state.fit.cost:
            t = cand
        if t.accepted:
            break
    return t


def _try_pair(data: _Data, cur: ModelState, a: Trial, b: Trial, seed: int, alpha: float, min_share: float,
              configured: ParameterSet) -> tuple[Trial, bool]:
    """Fit ``cur`` extended by both effects of trials ``a`` and ``b``.

    For effects that are only recognisable together (each alone is mimicked by bending the
    nominal parameters, e.g. a sensor delay bending the valve dynamics while a friction is
    fitted).  Returns the pair's trial (judged against ``cur``) and whether each effect is
    also significant within the pair (LR of the pair against the other effect alone).
    """
    model = data.model
    effects = (a.effect, b.effect)
    names = cur.free + tuple(n for e in effects for n in model.EFFECTS[e].names)
    ps = model.params(effects=cur.effects + effects).update(cur.params.as_dict())
    eff_vals = {n: a.state.fit.estimate[n] for n in model.EFFECTS[a.effect].names}
    eff_vals.update({n: b.state.fit.estimate[n] for n in model.EFFECTS[b.effect].names})
    typical = {n: v for e in effects for n, v in zip(model.EFFECTS[e].names, model.EFFECTS[e].typical)}
    base_starts = [dict(cur.fit.estimate), {n: configured[n] for n in cur.free if n in configured},
                   {n: a.state.fit.estimate[n] for n in cur.free}, {n: b.state.fit.estimate[n] for n in cur.free}]
    ranked = _rank_starts(data, ps, [{**bs, **ev} for bs in base_starts for ev in (eff_vals, typical)])
    best = None
    for start in ranked[:2]:
        st = _fit_state(data, ps.update(start), names, start, 1, seed)
        t = _judge("+".join(effects), cur, st, alpha, min_share)
        if best is None or t.state.fit.cost < best.state.fit.cost:
            best = t
        if best.accepted:
            break
    each = all(likelihood_ratio(single.state.fit, best.state.fit)[1] < alpha for single in (a, b))
    return best, each


def _judge(effect: str, cur: ModelState, st: ModelState, alpha: float, min_share: float) -> Trial:
    lr, p, df = likelihood_ratio(cur.fit, st.fit)
    d_aicc = st.fit.aicc - cur.fit.aicc
    hg = 1.0 - st.holdout["weighted_sse"] / cur.holdout["weighted_sse"]
    # share of the excess misfit removed; judged only when the current residuals are not white
    # (when they are, the excess is within its own sampling error and the LR test decides alone)
    floor = math.sqrt(2.0 * cur.fit.n_obs)
    share = (cur.fit.cost - st.fit.cost) * 2.0 / max(cur.excess, floor)
    judge_share = not cur.analysis.adequate
    t = Trial(effect, st, lr, p, df, d_aicc, hg, share)
    reasons = []
    if not p < alpha:
        reasons.append(f"LR p={p:.3g} >= {alpha:g}")
    if not d_aicc < 0:
        reasons.append("AICc not lower")
    if not hg > 0:
        reasons.append("held-out error not lower")
    if judge_share and not share >= min_share:
        reasons.append(f"explains only {100 * share:.0f} % of the excess misfit")
    t.accepted = not reasons
    t.reason = "; ".join(reasons)
    return t


# --- the diagnosis ----------------------------------------------------------------------------
def diagnose(model: Model | str, records: Sequence[Record] | Record, outputs: Sequence[str] | None = None,
             free: Sequence[str] | None = None, base: ParameterSet | None = None,
             candidates: Sequence[str] | None = None, holdout: float = 0.25, alpha: float = ALPHA,
             min_share: float = MIN_SHARE, max_effects: int = 3, max_fits: int = 3,
             noise: Mapping[str, float] | None = None, drive: str = "auto", seed: int = 0,
             progress: Callable[[str], None] | None = None) -> Diagnosis:
    """Fit the nominal model, screen the catalogue, extend greedily, measure the gain (module docstring).

    Candidate models may be unstable on the data (a trial start or fitted extension whose
    simulation diverges); their costs come out infinite and they are rejected, so floating-point
    overflow inside the diagnosis is expected and not reported as a warning.
    """
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return _diagnose(model, records, outputs, free, base, candidates, holdout, alpha, min_share,
                         max_effects, max_fits, noise, drive, seed, progress)


def _diagnose(model, records, outputs, free, base, candidates, holdout, alpha, min_share, max_effects,
              max_fits, noise, drive, seed, progress) -> Diagnosis:
    t0 = time.perf_counter()
    model = get_model(model) if isinstance(model, str) else model
    if isinstance(records, Record):
        records = [records]
    records = list(records)
    if not records:
        raise DataError("diagnose needs at least one record")
    if not 0.0 < holdout < 0.9:
        raise ParameterError(f"holdout (={holdout}) must be a fraction in (0 ... 0.9) of each record")
    base = base or model.params()
    outputs = resolve_outputs(model, records, outputs)
    for r in records:
        r.require(outputs, "diagnose")
        if len(r) < 200:
            raise DataError(f"{r.name}: {len(r)} samples; diagnose needs at least 200 per record")
    free = tuple(free or getattr(model, "PHENOMENOLOGICAL", ()))
    sigma = {o: float((noise or {}).get(o, DEFAULT_NOISE.get(o, 1.0))) for o in outputs}
    n_fit = [int(round(len(r) * (1.0 - holdout))) for r in records]
    data = _Data(model, records, n_fit, outputs, sigma, drive)
    catalogue = [e for e in (candidates or model.EFFECTS) if e not in base.effects]
    check_names(model.EFFECTS, catalogue, f"effect of {model.name}")
    say = progress or (lambda _m: None)

    say(f"fitting the nominal model ({', '.join(free)}) on {sum(n_fit)} samples")
    nominal = _fit_state(data, base, free, {}, 8, seed)
    say(f"nominal: AICc={nominal.fit.aicc:.6g}, residuals {'white' if nominal.analysis.adequate else 'NOT white'}")
    cur = nominal
    path = [nominal]
    screens: list[list[ScreenRow]] = []
    trials_all: list[list[Trial]] = []
    causes: list[str] = []
    gains: dict[str, dict] = {}
    for _ in range(max_effects):
        cands = [e for e in catalogue if e not in cur.effects]
        if not cands:
            break
        scr = screen(data, cur, cands)
        screens.append(scr)
        say("screen: " + ", ".join(f"{r.effect} LM={r.lm:.3g}" for r in scr[:4]))
        promising = [r for r in scr if r.p_adjusted < alpha][:max_fits]
        if not promising and not cur.analysis.adequate:
            promising = [r for r in scr if r.lm > 0][:2]
        if not promising:
            trials_all.append([])
            break
        trials = []
        for row in promising:
            t = _try(data, cur, row, seed, alpha, min_share, base)
            say(f"  {row.effect}: LR={t.lr:.4g} p={t.p:.3g} dAICc={t.delta_aicc:.4g} "
                f"held-out gain {100 * t.holdout_gain:.2f}% share {t.share:.3f} "
                f"{'accepted' if t.accepted else 'rejected: ' + t.reason}")
            trials.append(t)
        trials_all.append(trials)
        ok = [t for t in trials if t.accepted]
        if not ok:
            sig = sorted((t for t in trials if t.p < alpha and t.delta_aicc < 0 and t.holdout_gain > 0),
                         key=lambda t: -t.lr)
            if len(sig) < 2 or len(causes) + 2 > max_effects:
                break
            a, b = sig[0], sig[1]
            pair, each = _try_pair(data, cur, a, b, seed, alpha, min_share, base)
            say(f"  pair {pair.effect}: LR={pair.lr:.4g} p={pair.p:.3g} dAICc={pair.delta_aicc:.4g} "
                f"held-out gain {100 * pair.holdout_gain:.2f}% share {pair.share:.3f} "
                f"each significant: {each} -> {'accepted' if pair.accepted and each else 'rejected'}")
            if not each and pair.accepted:
                pair.accepted = False
                pair.reason = "one of the two is not significant within the pair"
            trials.append(pair)
            if not pair.accepted:
                break
            for first, second in ((a, b), (b, a)):
                gains[first.effect] = _gain(second.state, pair.state) | {"share": pair.share, "pair": pair.effect}
                causes.append(first.effect)
            cur = pair.state
            path.append(cur)
            continue
        win = min(ok, key=lambda t: t.state.fit.aicc)
        for t in ok:
            if t is not win:
                t.accepted = False
                t.reason = f"higher AICc than {win.effect}"
        gains[win.effect] = _gain(cur, win.state) | {"share": win.share}
        causes.append(win.effect)
        cur = win.state
        path.append(cur)
    unexplained = not cur.analysis.adequate
    return Diagnosis(model.name, causes, unexplained, nominal, cur, path, screens, trials_all, gains, outputs,
                     holdout, time.perf_counter() - t0, records, n_fit)


# --- plots ------------------------------------------------------------------------------------
def _binned(x: np.ndarray, y: np.ndarray, n: int = 30) -> tuple[np.ndarray, np.ndarray]:
    edges = np.quantile(x, np.linspace(0, 1, n + 1))
    edges = np.unique(edges)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(edges.size - 2, 0))
    cx, cy = [], []
    for j in range(max(edges.size - 1, 1)):
        m = idx == j
        if m.sum() >= 5:
            cx.append(float(np.mean(x[m])))
            cy.append(float(np.mean(y[m])))
    return np.array(cx), np.array(cy)


def plot_report(diag: Diagnosis, out_dir: str) -> list[str]:
    """PNG plots of a diagnosis in ``out_dir`` (matplotlib Agg); returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from twin.residuals import regime_signals

    os.makedirs(out_dir, exist_ok=True)
    paths = []
    rec = diag.records[0]
    n_fit = diag.n_fit[0]
    t = rec.t_s
    nom = diag.nominal.predicted[0]
    fin = diag.final.predicted[0]
    outs = diag.outputs
    # measured vs nominal vs extended (held-out part)
    fig, axes = plt.subplots(len(outs), 1, figsize=(9, 2.4 * len(outs) + 0.6), squeeze=False, sharex=True)
    sl = slice(n_fit, len(rec))
    for ax, o in zip(axes[:, 0], outs):
        ax.plot(t[sl], rec[o][sl], color="0.6", lw=1.6, label="measured")
        ax.plot(t[sl], nom[o][sl], color="C0", lw=0.9, label="nominal")
        if diag.causes:
            ax.plot(t[sl], fin[o][sl], color="C3", lw=0.9, ls="--", label="extended: " + "+".join(diag.causes))
        ax.set_ylabel(f"{o} [{UNITS.get(o, '-')}]")
    axes[0, 0].legend(fontsize=7, ncol=3)
    axes[0, 0].set_title("Held-out part: measured vs nominal vs extended")
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    p = os.path.join(out_dir, "diagnose_response.png")
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)
    # residuals before and after
    fig, axes = plt.subplots(len(outs), 1, figsize=(9, 2.4 * len(outs) + 0.6), squeeze=False, sharex=True)
    for ax, o in zip(axes[:, 0], outs):
        ax.plot(t, rec[o] - nom[o], color="C0", lw=0.6, label="nominal")
        if diag.causes:
            ax.plot(t, rec[o] - fin[o], color="C3", lw=0.6, label="extended")
        ax.axvline(t[n_fit], color="k", lw=0.8, ls=":")
        ax.set_ylabel(f"residual {o} [{UNITS.get(o, '-')}]")
    axes[0, 0].legend(fontsize=7)
    axes[0, 0].set_title("Residuals before and after (dotted: start of the held-out part)")
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    p = os.path.join(out_dir, "diagnose_residuals.png")
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)
    # each effect's own signature: residual before vs the regime variable, and the effect's contribution
    reg = regime_signals(diag.model, rec, nom)
    for i, c in enumerate(diag.causes):
        before = diag.path[i].predicted[0]
        after = diag.path[i + 1].predicted[0]
        var = SIGNATURE_AXIS.get(c, "velocity")
        xv = reg.get(var, reg["velocity"])
        # (residual before, the effect's contribution, noise level) per signal shown
        shown = {o: (rec[o] - before[o], after[o] - before[o], DEFAULT_NOISE.get(o, 1.0)) for o in outs}
        if diag.model == "msp25" and {"pA", "pB"} <= set(outs):
            area = diag.final.params["A"]
            dp = {k: p["pA"] - p["pB"] for k, p in (("rec", rec.signals), ("before", before), ("after", after))}
            shown["force [N]"] = (area * (dp["rec"] - dp["before"]), area * (dp["after"] - dp["before"]),
                                  area * math.sqrt(2.0) * DEFAULT_NOISE["pA"])
        if c in FORCE_EFFECTS and "force [N]" in shown:
            o = "force [N]"
        else:
            o = max(shown, key=lambda k: float(np.std(shown[k][1])) / shown[k][2])
        res_o, contrib, _ = shown[o]
        fig, ax = plt.subplots(figsize=(7, 4))
        ax.plot(xv, res_o, ",", color="0.7", label="residual before (samples)")
        bx, by = _binned(xv, res_o)
        ax.plot(bx, by, "o", color="C0", ms=3, label="residual before (binned mean)")
        cx, cy = _binned(xv, contrib)
        ax.plot(cx, cy, "-", color="C3", label=f"{c} (extended - before)")
        ax.set_xlabel(var)
        ax.set_ylabel(f"residual {o}")
        ax.set_title(f"Signature of {c}")
        ax.legend(fontsize=7)
        fig.tight_layout()
        p = os.path.join(out_dir, f"diagnose_signature_{c}.png")
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
    # the residual signature of the final model (what is left), always: regimes, spectrum, correlation
    an = diag.final.analysis
    if an is not None:
        fin_reg = {k: v[:n_fit] for k, v in regime_signals(diag.model, rec, fin).items()}
        keys = [k for k in ("velocity", "position", "dp", "spool_opening", "force") if k in fin_reg]
        fig, axes = plt.subplots(len(outs), len(keys) + 1, figsize=(3.2 * (len(keys) + 1), 2.6 * len(outs)),
                                 squeeze=False)
        for row, o in enumerate(outs):
            r = an.residuals[o]
            for col, k in enumerate(keys):
                bx, by = _binned(fin_reg[k], r)
                axes[row, col].plot(bx, by, "o-", ms=2, color="C2")
                axes[row, col].set_xlabel(k, fontsize=8)
                axes[row, col].set_ylabel(f"mean residual {o}", fontsize=8)
            ax = axes[row, -1]
            ax.bar(np.arange(1, an.max_lag + 1), an.acf[o][1:], color="C1")
            ax.axhline(an.acf_band, color="k", ls="--", lw=0.7)
            ax.axhline(-an.acf_band, color="k", ls="--", lw=0.7)
            ax.set_xlabel("lag [samples]", fontsize=8)
            ax.set_ylabel(f"acf {o} (LB p={an.ljung_box[o]['p']:.2g})", fontsize=8)
        fig.suptitle(("UNEXPLAINED residual signature" if diag.unexplained else "Final residuals")
                     + " (fitting data)")
        fig.tight_layout()
        p = os.path.join(out_dir, "diagnose_residual_signature.png")
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
    return paths


# --- command line ----------------------------------------------------------------------------
def add_diagnose_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", nargs="+", help="records (CSV, MCAP, CAN logs); parameters are shared")
    p.add_argument("--model", default="msp25", choices=("msp25", "oscillator"))
    p.add_argument("--outputs", help="outputs used, e.g. x or x,pA,pB (default: all present)")
    p.add_argument("--free", help="nominal free parameters (default: the phenomenological ones)")
    p.add_argument("--set", help="known parameter values NAME=VALUE,...")
    p.add_argument("--effects", help="effects known to be present (switched on, not screened)")
    p.add_argument("--candidates", help="restrict the screened catalogue to these effects")
    p.add_argument("--drive", default="auto", choices=("auto", "x_ref", "u"))
    p.add_argument("--noise-levels", help="noise std per output used as residual weights, NAME=STD,...")
    p.add_argument("--holdout", type=float, default=0.25, help="held-out tail of each record (default 0.25)")
    p.add_argument("--alpha", type=float, default=ALPHA, help=f"significance level (default {ALPHA:g})")
    p.add_argument("--max-effects", type=int, default=3, help="most effects named (default 3)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save", metavar="FILE", help="save the extended parameter set (JSON for twin fit / tracker)")
    p.add_argument("--report", metavar="DIR", help="write plots (PNG), diagnosis.json and extended_params.json")
    p.add_argument("--json", action="store_true", help="print the diagnosis as JSON")


def run_diagnose(args) -> int:
    from twin.record import load_records

    model = get_model(args.model)
    records: list[Record] = []
    for path in args.data:
        records.extend(load_records(path, model=model.name))
    base = model.params(effects=_names(args.effects), **_kv(args.set))
    quiet = getattr(args, "quiet", False)
    progress = None if quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    diag = diagnose(model, records, outputs=_names(args.outputs) or None, free=_names(args.free) or None,
                    base=base, candidates=_names(args.candidates) or None, holdout=args.holdout,
                    alpha=args.alpha, max_effects=args.max_effects, noise=_kv(args.noise_levels),
                    drive=args.drive, seed=args.seed, progress=progress)
    if args.report:
        diag.plots = plot_report(diag, args.report)
        with open(os.path.join(args.report, "extended_params.json"), "w") as f:
            json.dump(diag.extended_params(), f, indent=2, default=_json_default)
        with open(os.path.join(args.report, "diagnosis.json"), "w") as f:
            json.dump(diag.to_dict(), f, indent=2, default=_json_default)
    if args.save:
        with open(args.save, "w") as f:
            json.dump(diag.extended_params(), f, indent=2, default=_json_default)
    if args.json:
        dump(diag.to_dict())
    else:
        print(diag.text())
    return 0
