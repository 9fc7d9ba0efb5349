"""The records of a diagnosis, their fitting and held-out parts, the model state of a step, and simulations."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from fpdd.units import SIGNAL_UNITS
from twin.estimation.fit_result import FitResult
from twin.models import Model
from twin.models.base import DEFAULT_TIMING, Timing
from twin.estimation.noise_model import (NoiseModel)
from twin.params import Effect, ParameterSet
from twin.record import Record, as_logged
from twin.estimation.residuals import ResidualAnalysis
from twin.estimation.diagnose.constants import ALPHA, LIMITS


# --- data --------------------------------------------------------------------------------
@dataclasses.dataclass
class _Data:
    model: Model
    records: list[Record]
    n_fit: list[int]
    outputs: tuple[str, ...]
    sigma: dict[str, float]
    drive: str
    timing: Timing = DEFAULT_TIMING
    alpha: float = ALPHA
    seed: int = 0
    exo_cache: dict = dataclasses.field(default_factory=dict, repr=False)
    #: each effect's typical size on these records (from the fitted nominal model; the catalogue's until then)
    typical: dict[str, tuple[float, ...]] = dataclasses.field(default_factory=dict)

    def effect(self, name: str) -> Effect:
        """The catalogue's effect ``name`` with its typical size on these records."""
        E = self.model.EFFECTS[name]
        t = self.typical.get(name)
        return dataclasses.replace(E, typical=tuple(t)) if t is not None else E

    def scales(self) -> dict[str, float]:
        """The order of magnitude of every effect parameter on these records (a fit's coordinate scale)."""
        out = {}
        for name in self.model.EFFECTS:
            E = self.effect(name)
            for n, neutral, t in zip(E.names, E.neutral, E.typical):
                out[n] = abs(t - neutral) or abs(t)
        return out

    @property
    def parts(self) -> list[Record]:
        return [r.slice(0, n) for r, n in zip(self.records, self.n_fit)]

    def drives(self, records: Sequence[Record] | None = None) -> list[tuple[str, np.ndarray]]:
        return [self.model.drive_signal(r.signals, self.drive) for r in (records or self.records)]

    def fresh(self, r: int, n: int | None = None) -> np.ndarray | None:
        """``[m, n]`` which samples of each output of record ``r`` (its first ``n``) are measurements; None when
        every one is (a signal logged at its own rate and held onto the grid: :func:`twin.record.fresh_mask`)."""
        rec = self.records[r]
        masks = [rec.fresh_of(o) for o in self.outputs]
        if all(f is None for f in masks):
            return None
        stop = len(rec) if n is None else n
        return np.array([np.ones(stop, dtype=bool) if f is None else np.asarray(f[:stop], dtype=bool)
                         for f in masks])

    def init(self, ps: ParameterSet) -> list[dict]:
        from twin.estimation.fit import initial_from_data

        return [initial_from_data(self.model, r, ps) for r in self.records]


def _timing_label(t: Timing) -> str:
    return t.label


@dataclasses.dataclass
class ModelState:
    """One model of the greedy path: parameters, timing, fit, noise model, held-out figures, adequacy."""

    params: ParameterSet
    free: tuple[str, ...]
    fit: FitResult
    predicted: list[dict[str, np.ndarray]] = dataclasses.field(repr=False)  # whole records
    timing: Timing = DEFAULT_TIMING
    holdout: dict = dataclasses.field(default_factory=dict)
    analysis: ResidualAnalysis | None = None          # output-error residuals on the fitting data (first record)
    noise: NoiseModel | None = None                    # fitted to this model's residuals on the fitting data
    adequacy: dict = dataclasses.field(default_factory=dict)
    excess: float = 0.0                               # weighted residual power above the noise floor
    wcost: float = 0.0                                # innovations' sum of squares on the fitting data
    n_w: int = 0                                      # number of innovations (samples x outputs)

    @property
    def effects(self) -> tuple[str, ...]:
        return self.params.effects

    @property
    def adequate(self) -> bool:
        return bool(self.adequacy.get("adequate", False))

    @property
    def converged(self) -> bool:
        return bool(self.fit.success)

    def param_table(self, names: Sequence[str] | None = None) -> dict:
        out = {}
        for n in (names or self.free):
            spec = self.params.spec(n)
            v = self.fit.estimate.get(n, self.params[n])
            out[n] = {"value": v, "std": self.fit.std.get(n, 0.0), "std_white": self.fit.std_white.get(n),
                      "unit": spec.unit, "shown": spec.show(v)}
        return out

    def summary(self) -> dict:
        return {"effects": list(self.effects), "timing": self.timing.to_dict(), "params": self.param_table(),
                "aicc": self.fit.aicc, "aic": self.fit.aic, "loglik": self.fit.loglik, "n_par": self.fit.n_par,
                "fit_pct": self.fit.fit_pct, "nrmse": self.fit.nrmse, "converged": self.fit.success,
                "fit_message": self.fit.message,
                "holdout": {o: dict(v, rms_unit=SIGNAL_UNITS.get(o, "")) if isinstance(v, dict) and "rms" in v else v
                            for o, v in self.holdout.items()},
                "innovations_ss": self.wcost, "n_innovations": self.n_w,
                "noise_model": self.noise.summary() if self.noise is not None else None,
                "adequacy": self.adequacy,
                "residuals": self.analysis.summary() if self.analysis is not None else None}


# --- helpers -------------------------------------------------------------------------------
def _simulate(data: _Data, ps: ParameterSet, timing: Timing) -> list[dict[str, np.ndarray]]:
    """Whole-record predictions of ``ps`` (outputs and inputs), started where the data start."""
    model = data.model
    P = model.vector(ps)[None, :]
    out = []
    for rec, (name, drive), init in zip(data.records, data.drives(), data.init(ps)):
        S0 = model.initial_state(P, init)
        sim = model.simulate_batch(P, name, drive, rec.dt, S0, None, timing, model.exogenous_of(rec.signals))
        d = {o: as_logged(rec, o, sim.outputs[o][0]) if o in rec else sim.outputs[o][0] for o in model.OUTPUTS}
        for k, v in sim.inputs.items():
            d[k] = np.asarray(v)[0] if np.ndim(v) == 2 else np.asarray(v)
        for j, k in enumerate(getattr(model, "STATES", ())):  # the states a limit probe needs (LIMITS)
            if k in LIMITS.values():
                d[f"state:{k}"] = sim.states[0, :, j]
        out.append(d)
    return out


def _blocks(data: _Data, pred: list[dict[str, np.ndarray]], part: str = "fit") -> list[np.ndarray]:
    """Weighted residuals ``[m, T]`` per record: on the fitting part, or on the whole record."""
    out = []
    for r, p, n in zip(data.records, pred, data.n_fit):
        stop = n if part == "fit" else len(r)
        out.append(np.array([(r[o][:stop] - p[o][:stop]) / data.sigma[o] for o in data.outputs]))
    return out


def _holdout(data: _Data, pred: list[dict[str, np.ndarray]]) -> dict:
    """Held-out Fit %, NRMSE per output and the weighted squared error, on the records' tails."""
    out: dict = {}
    cost = 0.0
    excess = 0.0
    for o in data.outputs:
        y = np.concatenate([r[o][n:] for r, n in zip(data.records, data.n_fit)])
        yh = np.concatenate([p[o][n:] for p, n in zip(pred, data.n_fit)])
        e = y - yh
        den = float(np.linalg.norm(y - y.mean()))
        out[o] = {"fit_pct": 100.0 * (1.0 - float(np.linalg.norm(e)) / den) if den > 0 else float("nan"),
                  "nrmse": float(np.sqrt(np.mean(e * e)) / np.std(y)) if np.std(y) > 0 else float("nan"),
                  "rms": float(np.sqrt(np.mean(e * e)))}
        w = e / data.sigma[o]
        cost += float(np.sum(w * w))
        # above the noise floor (the scatter of the error's increments: a smooth model error has little)
        nz = float(np.std(np.diff(w)) / math.sqrt(2.0)) if w.size > 2 else 0.0
        excess += max(float(np.sum(w * w)) - w.size * nz * nz, 0.0)
    out["weighted_sse"] = cost
    out["weighted_excess"] = excess
    out["n"] = sum(len(r) - n for r, n in zip(data.records, data.n_fit)) * len(data.outputs)
    return out


def _excess(data: _Data, pred: list[dict[str, np.ndarray]]) -> float:
    """Weighted residual power above the noise floor on the fitting data (sum over outputs)."""
    total = 0.0
    for B in _blocks(data, pred, "fit"):
        for e in B:
            nz = float(np.std(np.diff(e)) / math.sqrt(2.0))
            total += float(np.sum(e * e)) - e.size * nz * nz
    return max(total, 0.0)


def _fd_step(spec, value: float, typical: float | None) -> float:
    """A relative step: of the value for a parameter that cannot reach zero (a mass of 5e-6 in a circuit's
    units is stepped by its own size, not the catalogue's), else of the larger of value and typical size."""
    ref = abs(value) if spec.lo > 0 else max(abs(value), abs(typical or 0.0))
    h = 1e-6 * max(ref, 1e-300)
    if value + h > spec.hi:
        h = -h
    return h


def holm(pvals: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (same order as given)."""
    m = len(pvals)
    order = sorted(range(m), key=lambda i: pvals[i])
    out = [1.0] * m
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * pvals[i]))
        out[i] = running
    return out
