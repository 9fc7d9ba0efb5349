"""Comparing identified models with the data, as MATLAB's ``compare`` does: Fit %, k-step-ahead prediction
beside simulation, and several candidate models (or effect sets) fitted on one record and ranked.

* :func:`fit_percent`: ``100 (1 - |y - yhat| / |y - mean y|)``, MATLAB's normalised root mean square Fit.
* :func:`predict`: the ``k``-step-ahead prediction ``yhat(t | t - k)`` of a fitted parameter set on a record,
  with the physical model as the deterministic part and a disturbance model as the rest (MATLAB's
  ``y = G u + H e``): the simulation error ``e = y - G u`` of each output is an AR process (order by Schwarz's
  Bayesian criterion, :func:`noise_model`), and ``yhat(t | t - k) = (G u)(t) + ehat(t | t - k)``, the AR model's
  ``k``-step prediction from the errors up to ``t - k`` (about their mean).  ``k = inf`` is the simulation.
  A white error (an exact model under white noise) gives a ``k``-step Fit near the simulation's; a slow model error
  is predicted away at small ``k``, which is why a 1-step Fit far above the simulation's tells little about
  the physical model (MATLAB's caveat alike) while ``k = inf`` tests it alone.
* :func:`compare_models`: each candidate (a model and a set of effects) fitted on the estimation records,
  then simulated on held-out records (the second half of the record when only one is given, as
  ``z(1:N/2)``/``z(N/2+1:N)`` in the System Identification Toolbox): Fit % per output on the estimation data,
  held-out simulation RMS per output (SI, unit named) and Fit %, AIC and BIC.  The lowest BIC is marked
  best (BIC: the penalty ``p ln N`` grows with the record, so an extra effect must explain more than noise).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from fpdd.errors import DataError, ParameterError
from twin.models import DEFAULT_MODEL, Model, get_model
from twin.models.base import Timing
from twin.params import ParameterSet
from twin.record import Record

#: the horizons (samples) of :func:`fit_by_horizon` by default; ``inf`` is the simulation
DEFAULT_HORIZONS: tuple[float, ...] = (1, 10, math.inf)
#: the highest order of the disturbance model (AR) the Bayesian criterion chooses among
MAX_AR_ORDER = 30


def fit_percent(y: np.ndarray, yh: np.ndarray) -> float:
    """MATLAB's Fit: ``100 (1 - |y - yhat| / |y - mean y|)`` [%] (``nan`` for a constant ``y``)."""
    y = np.asarray(y, dtype=np.float64)
    e = y - np.asarray(yh, dtype=np.float64)
    den = float(np.linalg.norm(y - y.mean()))
    return 100.0 * (1.0 - float(np.linalg.norm(e)) / den) if den > 0 else float("nan")


def _timing(timing: Timing | Mapping | None) -> Timing | None:
    if timing is None or isinstance(timing, Timing):
        return timing
    return Timing(str(timing.get("controller") or "digital"), timing.get("rate_hz"), timing.get("intersample"))


def simulate_record(model: Model | str, params: ParameterSet, record: Record, drive: str = "auto",
                    timing: Timing | Mapping | None = None, init: Mapping[str, float] | None = None):
    """The simulation (``k = inf``) of ``record``: from its first samples (or ``init``), driven as a fit drives
    it; returns the model's :class:`~twin.models.base.SimResult` (outputs ``[T]``, states ``[T, n]``)."""
    model = get_model(model) if isinstance(model, str) else model
    name, u = model.drive_signal(record.signals, drive)
    init = dict(init) if init is not None else model.initial_from_data(record.signals, record.dt)
    return model.simulate(params, name, u, record.dt, init=init, timing=_timing(timing),
                          exogenous=model.exogenous_of(record.signals))


def noise_model(residuals: Sequence[np.ndarray], max_order: int = MAX_AR_ORDER) -> np.ndarray:
    """The disturbance model of one output: AR coefficients ``a`` (``e(t) = sum a_i e(t - i) + w(t)``) of the
    simulation residuals of each record, by Yule-Walker (Levinson-Durbin) with the order chosen by Schwarz's
    criterion ``N ln sigma_p^2 + p ln N`` up to ``max_order`` (``[]``: a white residual; BIC, unlike AIC, does
    not keep spurious lags of a white error as the record grows)."""
    res = [np.asarray(r, dtype=np.float64) - float(np.mean(r)) for r in residuals if len(r) > 1]
    n = sum(r.size for r in res)
    if n < 10:
        return np.zeros(0)
    order = int(min(max_order, n // 10))
    acov = np.zeros(order + 1)
    for r in res:
        m = r.size
        nfft = 1 << int(math.ceil(math.log2(2 * m)))
        f = np.fft.rfft(r, nfft)
        ac = np.fft.irfft(f * np.conj(f), nfft)[: order + 1]
        acov[: min(order + 1, m)] += ac[: min(order + 1, m)]
    acov /= n
    if acov[0] <= 0:
        return np.zeros(0)
    # Levinson-Durbin: every order's coefficients and innovation variance in one pass
    a = np.zeros(0)
    v = acov[0]
    best, best_bic = a, n * math.log(v)
    for p in range(1, order + 1):
        kappa = (acov[p] - float(a @ acov[p - 1:0:-1])) / v if p > 1 else acov[1] / v
        a = np.concatenate([a - kappa * a[::-1], [kappa]])
        v *= 1.0 - kappa * kappa
        if v <= 0:
            break
        bic = n * math.log(v) + p * math.log(n)
        if bic < best_bic:
            best, best_bic = a.copy(), bic
    return best


def ahead_coefficients(a: np.ndarray, k: int) -> np.ndarray:
    """``b`` with ``ehat(t | t - k) = sum_i b_i e(t - k - i)`` for the AR model ``a`` (first row of the
    companion matrix to the power ``k``)."""
    p = a.size
    if p == 0:
        return np.zeros(0)
    A = np.zeros((p, p))
    A[0] = a
    A[1:, :-1] = np.eye(p - 1)
    return np.linalg.matrix_power(A, k)[0]


def predict(model: Model | str, params: ParameterSet, record: Record, k: float | None, drive: str = "auto",
            timing: Timing | Mapping | None = None, init: Mapping[str, float] | None = None,
            outputs: Sequence[str] | None = None,
            noise: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """``k``-step-ahead prediction ``yhat(t | t - k)`` of each output over ``record`` (module docstring):
    the simulation plus the disturbance model's prediction of the simulation error from the errors up to
    ``t - k``; ``k = math.inf`` (or ``None``): the simulation.  ``noise``: AR coefficients per output
    (:func:`noise_model`; default: fitted on this record's simulation error)."""
    model = get_model(model) if isinstance(model, str) else model
    sim = simulate_record(model, params, record, drive, timing, init)
    outs = tuple(outputs or [o for o in model.OUTPUTS if o in record])
    pred = {o: np.array(sim.outputs[o], dtype=np.float64) for o in outs}
    if k is None or math.isinf(k):
        return pred
    if k < 1 or k != int(k):
        raise ParameterError(f"prediction horizon k = {k}: expected a whole number of samples >= 1 (or inf)")
    k = int(k)
    return with_disturbance(pred, record, k, noise)


def with_disturbance(sim: Mapping[str, np.ndarray], record: Record, k: int,
                     noise: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """The simulated outputs ``sim`` plus the disturbance model's ``k``-step prediction of their error."""
    out = {}
    for o, ys in sim.items():
        yp = np.array(ys, dtype=np.float64)
        e = record[o] - yp
        a = noise[o] if noise is not None and o in noise else noise_model([e])
        b = ahead_coefficients(np.asarray(a, dtype=np.float64), k)
        mu = float(np.mean(e))
        if b.size and len(record) > k:
            yp[k:] += np.convolve(e - mu, b)[: len(record) - k]  # ehat(t | t - k) at t = k ..
        yp += mu
        out[o] = yp
    return out


def fit_by_horizon(model: Model | str, params: ParameterSet, records: Sequence[Record],
                   horizons: Sequence[float] = DEFAULT_HORIZONS, drive: str = "auto",
                   timing: Timing | Mapping | None = None, inits: Sequence[Mapping[str, float]] | None = None,
                   outputs: Sequence[str] | None = None) -> dict[str, dict[str, float]]:
    """Fit % per output of the ``k``-step-ahead prediction for each ``k`` in ``horizons`` over all records (as
    :attr:`FitResult.fit_pct`), one disturbance model per output for all records:
    ``{"1": {"x": 99.9, ...}, "10": {...}, "inf": {...}}``."""
    model = get_model(model) if isinstance(model, str) else model
    outs = tuple(outputs or [o for o in model.OUTPUTS if all(o in r for r in records)])
    sims = [predict(model, params, rec, None, drive, timing, inits[r] if inits else None, outs)
            for r, rec in enumerate(records)]
    noise = {o: noise_model([rec[o] - s[o] for rec, s in zip(records, sims)]) for o in outs}
    table: dict[str, dict[str, float]] = {}
    for k in horizons:
        preds = sims if k is None or math.isinf(k) else [
            with_disturbance(s, rec, int(k), noise) for s, rec in zip(sims, records)]
        table[horizon_label(k)] = {o: fit_percent(np.concatenate([rec[o] for rec in records]),
                                                  np.concatenate([p[o] for p in preds])) for o in outs}
    return table


def horizon_label(k: float | None) -> str:
    return "inf" if k is None or math.isinf(k) else str(int(k))


# --- several models on one record --------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Candidate:
    """A model to compare: ``model`` with ``effects`` switched on, their parameters fitted with ``free``."""

    name: str
    model: str = DEFAULT_MODEL
    effects: tuple[str, ...] = ()
    free: tuple[str, ...] | None = None  # default: the model's phenomenological parameters + the effects' own

    @classmethod
    def parse(cls, text: str, model: str = DEFAULT_MODEL) -> Candidate:
        """``[MODEL:]EFFECT+EFFECT`` (``none`` or nothing: no effect), e.g. ``MODEL:viscous_friction``."""
        text = text.strip()
        mdl, _, eff = text.rpartition(":") if ":" in text else ("", "", text)
        mdl = mdl or model
        effects = tuple(e for e in (x.strip() for x in eff.split("+")) if e and e != "none")
        m = get_model(mdl)
        unknown = [e for e in effects if e not in m.EFFECTS]
        if unknown:
            raise ParameterError(f"candidate {text!r}: unknown effect(s) {', '.join(unknown)} of {mdl}; known: "
                                 f"{', '.join(m.EFFECTS)}")
        return cls(name=text or "none", model=mdl, effects=effects)

    def free_names(self, free: Sequence[str] | None = None, known: Sequence[str] = (),
                   effects: Sequence[str] = ()) -> tuple[str, ...]:
        """The parameters this candidate fits: its own ``free``; else ``free`` (the user's ``--free``) or the
        model's phenomenological ones, with the parameters of its effects (and of ``effects``, those every
        candidate shares), less those ``known`` (``--set``) unless ``free`` names them."""
        if self.free is not None:
            return self.free
        m = get_model(self.model)
        own = tuple(n for e in (*effects, *self.effects) for n in m.EFFECTS[e].names)
        if free:
            names = {sp.name for sp in m.BASE} | set(own)
            chosen = tuple(n for n in free if n in names)  # an effect's parameter where the candidate has it
            extra = tuple(n for n in own if n not in chosen and n not in known
                          and not any(n in m.EFFECTS[e].names for e in effects))
            return tuple(dict.fromkeys((*chosen, *extra)))
        return tuple(dict.fromkeys(n for n in (*m.PHENOMENOLOGICAL, *own) if n not in known))


def split_half(record: Record) -> tuple[Record, Record]:
    """The first and second half of ``record`` (estimation, validation)."""
    n = len(record) // 2
    a, b = record.slice(0, n), record.slice(n, len(record))
    a.name, b.name = f"{record.name} (first half)", f"{record.name} (second half)"
    return a, b


def compare_models(candidates: Sequence[Candidate], records: Sequence[Record],
                   validation: Sequence[Record] | None = None, *, base: ParameterSet | None = None,
                   drive: str = "auto", timing: Timing | None = None, n_starts: int = 8, seed: int = 0,
                   outputs: Sequence[str] | None = None, progress=None, free: Sequence[str] | None = None,
                   known: Sequence[str] = ()) -> dict:
    """Fit each candidate on ``records`` and simulate it on ``validation`` (default: each record's second
    half, the fit then using the first halves).  ``base``: known parameter values and effects every candidate
    of its model shares; ``free``: the parameters every candidate fits (``--free``; default the model's
    phenomenological ones), each candidate adding its effects' own; ``known``: parameters held at ``base``'s
    values (``--set``), never freed unless ``free`` names them.  Returns the comparison as a JSON-ready dict
    (SI, units named): ``{"rows": [...], "best": name, "criterion": "BIC", "estimation": [...],
    "validation": [...]}``."""
    from twin.estimation.fit import fit

    if not candidates:
        raise ParameterError("compare: no candidate models given")
    if validation is None:
        halves = [split_half(r) for r in records]
        records, validation = [h[0] for h in halves], [h[1] for h in halves]
    for r in list(records) + list(validation):
        if len(r) < 50:
            raise DataError(f"{r.name}: {len(r)} samples are too few to compare models (at least 50)")
    rows: list[dict[str, Any]] = []
    for c in candidates:
        m = get_model(c.model)
        shared = base if base is not None and base.model == c.model else None
        ps = m.params(effects=(*(shared.effects if shared else ()), *c.effects))
        if shared is not None:
            ps = ps.update({n: v for n, v in shared.as_dict().items() if n in ps})
        if progress:
            progress(f"fitting {c.name}")
        names = c.free_names(free, known, shared.effects if shared is not None else ())
        if not names:
            raise ParameterError(f"candidate {c.name!r}: no free parameter (every one is held by --set)")
        res = fit(m, records, names, base=ps, outputs=outputs, drive=drive, n_starts=n_starts, seed=seed,
                  timing=timing)
        rms, vfit = {}, {}
        for o in res.outputs:
            e, ys = [], []
            for rec in validation:
                sim = simulate_record(m, res.params, rec, drive, res.timing)
                e.append(rec[o] - sim.outputs[o])
                ys.append(rec[o])
            ee = np.concatenate(e)
            y = np.concatenate(ys)
            rms[o] = {"value": float(np.sqrt(np.mean(ee * ee))), "unit": get_model(c.model).signal_unit(o)}
            vfit[o] = fit_percent(y, y - ee)
        rows.append({"name": c.name, "model": c.model, "effects": list(c.effects), "free": list(names),
                     "n_par": res.n_par,
                     "fit_pct": dict(res.fit_pct), "validation_fit_pct": vfit, "validation_rms": rms,
                     "aic": res.aic, "bic": res.bic, "converged": res.success, "result": res})
    finite = [r for r in rows if math.isfinite(r["bic"])]
    best = min(finite, key=lambda r: r["bic"])["name"] if finite else None
    for row in rows:
        row["best"] = row["name"] == best
    return {"criterion": "BIC", "best": best, "rows": rows, "estimation": [r.name for r in records],
            "validation": [r.name for r in validation]}
