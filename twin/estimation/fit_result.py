"""The outcome of a grey-box fit (:func:`twin.estimation.fit.fit`): estimates, standard errors, Fit %,
information criteria, and its text, JSON, saved form and report."""

from __future__ import annotations

import dataclasses

import numpy as np

from twin.params import ParameterSet

#: SI units of the initial-state quantities (``FitResult.init``)
INIT_UNITS = {"x0": "m", "v0": "m/s", "dp0": "Pa", "pA0": "Pa", "pB0": "Pa", "u0": "V"}


@dataclasses.dataclass
class FitResult:
    """Outcome of a fit (``scipy.optimize.OptimizeResult`` in spirit)."""

    model: str
    params: ParameterSet                 # all parameters, free ones at their estimates
    free: tuple[str, ...]
    estimate: dict[str, float]
    std: dict[str, float]                # HAC (sandwich) standard errors
    corr: np.ndarray
    outputs: tuple[str, ...]
    fit_pct: dict[str, float]
    mse: dict[str, float]
    nrmse: dict[str, float]
    loglik: float
    aic: float
    aicc: float
    bic: float
    fpe: float
    n_obs: int
    n_par: int
    cost: float
    success: bool
    status: int
    message: str
    nfev: int
    history: list[dict]
    starts: list[dict]
    init: list[dict[str, float]]
    time_s: float
    predicted: list[dict[str, np.ndarray]] = dataclasses.field(repr=False, default_factory=list)
    std_white: dict[str, float] = dataclasses.field(default_factory=dict)  # s^2 (J'J)^-1, white residuals
    timing: dict = dataclasses.field(default_factory=dict)
    #: what the text, the JSON and the report must say beside a converged fit (e.g. an output barely fitted)
    warnings: list[str] = dataclasses.field(default_factory=list)
    #: the noise level (SI std) that weighted each output's residuals: the sensor noise the fit assumed
    noise: dict[str, float] = dataclasses.field(default_factory=dict)
    #: the adequacy tests of the fitted model (:func:`twin.estimation.diagnose.check.fit_adequacy`; empty when
    #: not judged): ``adequate``, ``reasons``, ``tests``
    adequacy: dict = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict:
        """Every number in SI with its unit beside it: ``{"value", "unit"}``, a sibling ``"unit"``, or a
        sibling ``"<key>_unit"`` naming the unit of each entry of ``<key>`` (``mse_unit``, ``theta_unit``)."""
        from fpdd.units import SIGNAL_UNITS

        specs = {s.name: s for s in self.params.specs}
        theta_unit = {n: specs[n].unit for n in self.free}
        out_unit = {o: SIGNAL_UNITS.get(o, "") for o in self.outputs}
        init_units = {k: INIT_UNITS.get(k, "") for d in self.init for k in d}
        return {
            "model": self.model,
            "params": {n: {"value": self.estimate[n], "std": self.std[n], "std_white": self.std_white.get(n),
                           "unit": specs[n].unit, "shown": specs[n].show(self.estimate[n])} for n in self.free},
            "timing": self.timing,
            "effects": list(self.params.effects),
            "corr": {"names": list(self.free), "matrix": np.round(self.corr, 6).tolist()},
            "outputs": list(self.outputs),
            "fit_pct": self.fit_pct, "mse": self.mse, "mse_unit": {o: _squared(u) for o, u in out_unit.items()},
            "nrmse": self.nrmse,
            "noise_levels": {o: {"value": v, "unit": out_unit.get(o, "")} for o, v in self.noise.items()},
            "loglik": self.loglik, "aic": self.aic, "aicc": self.aicc, "bic": self.bic, "fpe": self.fpe,
            "n_obs": self.n_obs, "n_par": self.n_par, "cost": self.cost,
            "success": self.success, "status": self.status, "message": self.message, "nfev": self.nfev,
            "warnings": self.warnings, "adequacy": self.adequacy or None,
            "time_s": self.time_s, "init": self.init, "init_unit": init_units,
            "starts": [dict(d, theta_unit=theta_unit) for d in self.starts],
            "history": [dict(d, theta_unit=theta_unit) for d in self.history],
        }

    def __repr__(self) -> str:
        """One line: the estimates ± std in display units, Fit % per output, converged or not."""
        specs = {s.name: s for s in self.params.specs}
        est = ", ".join(f"{n}={specs[n].show(self.estimate[n])} ± {specs[n].show(self.std[n])}" for n in self.free)
        fits = ", ".join(f"{k} {self.fit_pct[k]:.1f} %" for k in self.outputs)
        return (f"FitResult(model={self.model!r}, {est}; Fit: {fits}; "
                f"{'converged' if self.success else 'NOT converged'}, nfev={self.nfev}, {self.time_s:.2f} s)")

    def saved(self) -> dict:
        """What :meth:`save` writes (``twin fit --save``): every parameter as ``{"value", "unit"}`` in SI, the
        fitted ones with their ``"std"``; loop timing; the residual noise level per output as ``{"value",
        "unit"}``; the fit's ``warnings`` when it gave any.  Read back by ``--params`` and the tracker (``twin track
        --params``)."""
        from fpdd.units import SIGNAL_UNITS

        params: dict[str, dict] = {}
        for s, v in zip(self.params.specs, self.params.values):
            params[s.name] = {"value": float(v), "unit": s.unit}
            if s.name in self.free:
                params[s.name]["std"] = float(self.std[s.name])
        out = {"model": self.model, "effects": list(self.params.effects), "free": list(self.free),
               "params": params, "timing": self.timing,
               "noise": {o: {"value": float(np.sqrt(self.mse[o])), "unit": SIGNAL_UNITS.get(o, "")}
                         for o in self.outputs}}
        if self.warnings:  # a commissioning read back says what the fit warned
            out["warnings"] = list(self.warnings)
        return out

    def save(self, path: str) -> str:
        """Write :meth:`saved` as JSON to ``path`` (as ``twin fit --save``); returns the path."""
        from fpdd import jsonio

        return jsonio.write(path, self.saved())

    def table(self) -> str:
        specs = {s.name: s for s in self.params.specs}
        rows = [f"{'parameter':<10} {'estimate':>16} {'std':>14} {'rel std':>9}"]
        for n in self.free:
            v, s = self.estimate[n], self.std[n]
            rel = abs(s / v) * 100 if v else float("nan")
            rows.append(f"{n:<10} {specs[n].show(v):>16} {specs[n].show(s):>14} {rel:8.3g}%")
        rows.append("  ".join(f"Fit({k})={self.fit_pct[k]:.3f}%" for k in self.outputs))
        rows.append(f"AIC={self.aic:.6g} AICc={self.aicc:.6g} BIC={self.bic:.6g} FPE={self.fpe:.4g} "
                    f"N={self.n_obs} p={self.n_par} nfev={self.nfev} {self.time_s:.2f}s "
                    f"{'converged' if self.success else 'NOT CONVERGED'}: {self.message}")
        rows.extend(f"WARNING: {w}" for w in self.warnings)
        return "\n".join(rows)


def _squared(unit: str) -> str:
    """The unit of a mean square: ``m`` -> ``m^2``, ``Pa`` -> ``Pa^2``; dimensionless stays ``""``."""
    return f"{unit}^2" if unit and unit != "1" else ""
