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
    #: what the fit cannot tell apart, whatever the record (a free parameter that an un-modelled effect of the
    #: catalogue can mimic: a transducer gain and Cd): said beside every such fit, healthy or not, so apart from
    #: ``warnings`` (which say the fit or the model failed this record)
    caveats: list[str] = dataclasses.field(default_factory=list)
    #: the noise level (SI std) that weighted each output's residuals: the sensor noise the fit assumed
    noise: dict[str, float] = dataclasses.field(default_factory=dict)
    #: the adequacy tests of the fitted model (:func:`twin.estimation.diagnose.check.fit_adequacy`; empty when
    #: not judged): ``adequate``, ``reasons``, ``tests``
    adequacy: dict = dataclasses.field(default_factory=dict)
    #: how the fitted records were read (``{"map": ["x=pos_mm:mm", ...]}``: the column map with its units), saved
    #: so that later commands read another file of the same logger alike; empty when nothing was mapped
    source: dict = dataclasses.field(default_factory=dict)

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
            "warnings": self.warnings, "caveats": self.caveats, "adequacy": self.adequacy or None,
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
        out: dict = {"model": self.model, "effects": list(self.params.effects), "free": list(self.free),
               "params": params, "timing": self.timing,
               "noise": {o: {"value": float(np.sqrt(self.mse[o])), "unit": SIGNAL_UNITS.get(o, "")}
                         for o in self.outputs}}
        if self.warnings:  # a commissioning read back says what the fit warned
            out["warnings"] = list(self.warnings)
        if self.caveats:
            out["caveats"] = list(self.caveats)
        out["fit_pct"] = {o: float(v) for o, v in self.fit_pct.items()}
        out["corr"] = {"names": list(self.free), "matrix": np.round(np.asarray(self.corr, dtype=float), 6).tolist()}
        out["n_obs"], out["success"], out["message"] = int(self.n_obs), bool(self.success), str(self.message)
        if self.source:  # how the record was read: a later command reads the same kind of file alike
            out["source"] = dict(self.source)
        return out

    def save(self, path: str, *, map: object = None) -> str:  # noqa: A002
        """Write :meth:`saved` as JSON to ``path`` (as ``twin fit --save``); returns the path.

        ``map``: the column map the fitted records were read with (``--map``'s items, ``["x=pos_mm:mm",
        "t=time:ms"]``, or a mapping in the direction of ``load_records(map=...)``), kept in the file with its units
        so that ``twin track other.csv --params FILE`` reads another file of the same logger alike."""
        from fpdd import jsonio

        if map:
            self.source = {**self.source, "map": map_items(map)}
        return jsonio.write(path, self.saved())

    @classmethod
    def load(cls, path: str) -> FitResult:
        """The fit a ``twin fit --save`` file (:meth:`save`) holds: its model and parameter set (effects
        included), the free parameters with their estimates and standard errors, the noise level per output,
        the loop timing, warnings, Fit % and correlation when saved, and ``source`` (the column map).  What the
        file does not keep (history, predictions, information criteria) is empty or NaN.  Errors name the file
        and the field (:class:`~fpdd.errors.ConfigError`)."""
        import json
        import math

        from fpdd.errors import ConfigError, ParameterError, TwinError
        from twin.models import get_model

        try:
            with open(path, encoding="utf-8") as f:
                doc = json.load(f)
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read the saved fit ({exc.strerror or exc})") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: not JSON ({exc})") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("params"), dict):
            raise ConfigError(f"{path}: expected the JSON object twin fit --save writes (model, params, ...)")
        nan = math.nan
        try:
            from twin.models import DEFAULT_MODEL

            model = get_model(str(doc.get("model", DEFAULT_MODEL)))
            ps = model.params(effects=tuple(doc.get("effects") or ()))
            values: dict[str, float | str] = {}
            std: dict[str, float] = {}
            for name, v in doc["params"].items():
                if name not in ps.names:
                    raise ConfigError(f"{path}: params.{name}: the {model.name} model has no parameter {name!r}")
                if isinstance(v, dict):
                    if v.get("unit", ps.spec(name).unit) != ps.spec(name).unit:
                        raise ConfigError(f"{path}: params.{name}.unit is {v.get('unit')!r}, expected "
                                          f"{ps.spec(name).unit!r} (values are saved in SI)")
                    values[name] = v["value"] if isinstance(v.get("value"), (int, float, str)) else math.nan
                    if v.get("std") is not None:
                        std[name] = float(v["std"])
                else:
                    values[name] = v
            ps = ps.update(values)
        except TwinError as exc:
            if isinstance(exc, ConfigError):
                raise
            raise ConfigError(f"{path}: {exc}") from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise ConfigError(f"{path}: params: {exc}") from None
        free = tuple(doc.get("free") or std)
        bad = [n for n in free if n not in ps.names]
        if bad:
            raise ConfigError(f"{path}: free: {bad[0]!r} is no parameter of the {model.name} model")
        noise = {o: float(v["value"] if isinstance(v, dict) else v) for o, v in (doc.get("noise") or {}).items()}
        corr_doc = doc.get("corr") or {}
        corr = np.full((len(free), len(free)), nan)
        if isinstance(corr_doc, dict) and list(corr_doc.get("names") or ()) == list(free):
            corr = np.asarray(corr_doc["matrix"], dtype=float).reshape(len(free), len(free))
        timing: dict = doc["timing"] if isinstance(doc.get("timing"), dict) else {}
        try:
            from twin.models.base import Timing

            if timing:
                Timing(timing.get("controller", "digital"), timing.get("rate_hz"), timing.get("intersample"))
        except ParameterError as exc:
            raise ConfigError(f"{path}: timing: {exc}") from None
        fit_pct = {o: float(v) for o, v in (doc.get("fit_pct") or {}).items()}
        return cls(model=model.name, params=ps, free=free, estimate={n: ps[n] for n in free},
                   std={n: std.get(n, nan) for n in free}, corr=corr, outputs=tuple(noise or fit_pct),
                   fit_pct=fit_pct, mse={o: v * v for o, v in noise.items()}, nrmse={}, loglik=nan, aic=nan, aicc=nan,
                   bic=nan, fpe=nan, n_obs=int(doc.get("n_obs", 0)), n_par=len(free), cost=nan,
                   success=bool(doc.get("success", True)), status=0, message=str(doc.get("message", f"loaded from {path}")),
                   nfev=0, history=[], starts=[], init=[], time_s=nan, timing=dict(timing),
                   warnings=list(doc.get("warnings") or ()), caveats=list(doc.get("caveats") or ()), noise=noise,
                   source=dict(doc["source"]) if isinstance(doc.get("source"), dict) else {})

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
        rows.extend(f"CAVEAT: {c}" for c in self.caveats)
        return "\n".join(rows)


def map_items(map: object) -> list[str]:  # noqa: A002
    """A column map as ``--map``'s items (``["x=pos_mm:mm", "t=time:ms"]``) from those items, one such string,
    or a mapping ``{signal: "column[:unit]"}`` (``load_records(map=...)``'s direction)."""
    from collections.abc import Mapping

    if isinstance(map, str):
        return [map]
    if isinstance(map, Mapping):
        return [f"{k}={v}" if isinstance(v, str) else f"{k}={v[0]}:{v[1]}" for k, v in map.items()]
    return [str(m) for m in map]  # type: ignore[attr-defined]


def _squared(unit: str) -> str:
    """The unit of a mean square: ``m`` -> ``m^2``, ``Pa`` -> ``Pa^2``; dimensionless stays ``""``."""
    return f"{unit}^2" if unit and unit != "1" else ""
