"""Commissioning a rig's twin: what the tracker and the drift test start from.

A commissioning fit (``twin fit --save FIT.json``:
``{"model", "effects", "params", "std", "timing", "noise"}``) says

* the rig's parameter values (known and fitted), which become the tracker's
  reference values and starting point;
* the healthy bands of the tracked parameters: centred on the fitted values,
  as wide as each parameter's tracking band in the model, widened to 3 standard errors of the fit;
* the sensor noise per output (the fit's residual RMS), the tracker's
  nominal noise (which it goes on learning online);
* the loop's timing (controller rate, intersample).

:func:`load_fit` reads such a file, :func:`commission_from_samples` fits the
free parameters on the first seconds of a record (``commission_s`` in
``rigs.toml``), and :func:`tracker_for` builds the tracker of a rig
configuration (the one place the service and ``twin track`` build it).
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any
from collections.abc import Mapping, Sequence

from twin.errors import ConfigError, ParameterError
from twin.models import MODELS, get_model, trackable_models
from twin.models.base import Timing

NOISE_KEYS = ("x", "pA", "pB")


@dataclasses.dataclass
class Commission:
    """What a commissioning fit says about a rig (SI)."""

    params: dict[str, float]                  # every parameter value the fit knew or found
    fitted: dict[str, tuple[float, float]]    # free parameter -> (value, std)
    noise: dict[str, float]                   # output -> noise standard deviation
    timing: Timing | None
    effects: tuple[str, ...] = ()
    source: str = ""
    model: str = "msp25"

    def baseline(self, names: Sequence[str], rel_band: Mapping[str, float] | None = None, k_sigma: float = 3.0):
        """Healthy bands of ``names`` centred on the fitted (or known) values."""
        from twin.online.drift import Baseline, default_band

        bands = {**{n: default_band(self.model, n) for n in names}, **dict(rel_band or {})}
        out = {}
        for n in names:
            v, sd = self.fitted.get(n, (self.params.get(n, math.nan), math.nan))
            if not (v > 0 and math.isfinite(v)):
                raise ConfigError(f"{self.source}: params.{n} (={v}) is not a positive number; no band around it")
            r = float(bands[n])
            if math.isfinite(sd):
                r = max(r, k_sigma * sd / v)
            out[n] = Baseline(v, v / (1.0 + r), v * (1.0 + r))
        return out


def _number(path: str, field: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{path}: {field} must be a finite number, got {v!r}")
    return float(v)


def from_dict(doc: Mapping, source: str = "<fit>") -> Commission:
    """A :class:`Commission` from the JSON document of ``twin fit --save``."""
    if not isinstance(doc, Mapping):
        raise ConfigError(f"{source}: expected a JSON object written by twin fit --save")
    model = doc.get("model", "msp25")
    if model not in MODELS or not get_model(model).TRACKABLE:
        raise ConfigError(f"{source}: model: a fit of {model!r}; the online twin runs "
                          f"{', '.join(trackable_models())}")
    params_in = doc.get("params", {})
    if not isinstance(params_in, Mapping) or not params_in:
        raise ConfigError(f"{source}: params must be an object of parameter values")
    std_in = doc.get("std", {}) or {}
    if not isinstance(std_in, Mapping):
        raise ConfigError(f"{source}: std must be an object of standard errors")
    known = get_model(model).params().names
    params, fitted = {}, {}
    for n, v in params_in.items():
        if isinstance(v, Mapping):  # FitResult.to_dict(): {"value", "std", ...}
            val = _number(source, f"params.{n}.value", v.get("value"))
            sd = v.get("std")
            fitted[n] = (val, float(sd) if isinstance(sd, (int, float)) else math.nan)
        else:
            val = _number(source, f"params.{n}", v)
            if n in std_in and std_in[n] is not None:
                fitted[n] = (val, _number(source, f"std.{n}", std_in[n]))
        if n not in known:
            raise ConfigError(f"{source}: params.{n}: the msp25 has no parameter {n!r}")
        params[n] = val
    noise = {}
    for k, v in (doc.get("noise") or {}).items():
        if k not in NOISE_KEYS:
            continue
        val = _number(source, f"noise.{k}", v)
        if not val > 0:
            raise ConfigError(f"{source}: noise.{k} must be a positive standard deviation (SI), got {val}")
        noise[k] = val
    timing = None
    t = doc.get("timing")
    if isinstance(t, Mapping) and t:
        try:
            timing = Timing(t.get("controller", "digital"), t.get("rate_hz"), t.get("intersample"))
        except ParameterError as exc:
            raise ConfigError(f"{source}: timing: {exc}") from None
    effects = tuple(doc.get("effects") or ())
    return Commission(params, fitted, noise, timing, effects, source, model)


def read_saved(path: str, what: str) -> Any:
    """The JSON document of a ``twin fit --save`` / ``twin diagnose --save`` file; errors name the file and
    say it is ``what``."""
    try:
        with open(path) as f:
            return json.load(f)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what} ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path}: not JSON ({exc})") from None


def load_fit(path: str) -> Commission:
    """Read a ``twin fit --save`` file; errors name the file and the field."""
    return from_dict(read_saved(path, "commissioning fit"), path)


def tracker_params(c: Commission, tracked: Sequence[str]) -> tuple[dict[str, float], dict[str, float]]:
    """(known parameters, starting values of the tracked ones) from a commissioning fit."""
    if c.effects:
        raise ConfigError(f"{c.source}: effects {list(c.effects)}: the tracker follows the nominal rig model; "
                          "refit without effects, or correct the rig (e.g. re-zero the pressure sensors) first")
    params = {k: v for k, v in c.params.items()}
    return params, {t: params[t] for t in tracked if t in params}


def commission_from_samples(samples, seconds: float, tracked: Sequence[str], params: Mapping[str, float] | None = None,
                            timing: Timing | None = None) -> Commission:
    """Fit the free parameters on the first ``seconds`` of ``samples`` (the rig's first minute in service)."""
    import numpy as np

    from twin.estimation.fit import fit
    from twin.record import Record

    t = (np.asarray(samples.t_ns) - samples.t_ns[0]) * 1e-9
    n = int(np.searchsorted(t, seconds))
    if n < 100:
        raise ConfigError(f"commission_s = {seconds:g}: only {n} samples in that time; need at least 100")
    dt = float(np.median(np.diff(samples.t_ns[:n]))) * 1e-9
    sig = {k: np.asarray(v[:n], float) for k, v in samples.signals.items()}
    rec = Record(dt, sig, "commissioning")
    model = get_model("msp25")
    base = model.params((), **dict(params or {}))
    res = fit(model, [rec], tuple(tracked), base=base, timing=timing)
    noise = {}
    for o in NOISE_KEYS:
        if o in sig and res.predicted:
            r = sig[o] - np.asarray(res.predicted[0][o])
            r = r[np.isfinite(r)]
            if r.size:
                noise[o] = float(np.sqrt(np.mean(r * r)))
    allp = base.as_dict()
    allp.update({k: float(v) for k, v in res.estimate.items()})
    fitted = {k: (float(res.estimate[k]), float(res.std.get(k, math.nan))) for k in tracked}
    return Commission(allp, fitted, noise, timing, (), "commissioning fit", model.name)


def tracker_for(rig, dt: float | None = None, start: Mapping[str, float] | None = None):
    """The :class:`twin.online.tracker.OnlineTracker` of a rig configuration.

    Reads ``rig.params``, ``rig.track`` and, where the configuration has them,
    ``rig.noise`` (output -> SI standard deviation), ``rig.timing`` (a
    :class:`Timing`), ``rig.commission`` (a :class:`Commission` or the path of a
    ``twin fit --save`` file: known values, starting point, noise and timing).
    """
    from twin.online.tracker import OnlineTracker

    params = dict(getattr(rig, "params", {}) or {})
    tracked = tuple(getattr(rig, "track", ()) or ())
    noise: dict[str, float] = {}
    timing = getattr(rig, "timing", None)
    com = getattr(rig, "commission", None)
    st: dict[str, float] = {}
    if isinstance(com, str) and com:
        com = load_fit(com)
    if isinstance(com, Commission):
        p, st = tracker_params(com, tracked)
        params = {**p, **params}
        noise.update(com.noise)
        timing = timing or com.timing
    noise.update(dict(getattr(rig, "noise", None) or {}))
    if isinstance(timing, str):
        timing = Timing.parse(timing)
    kw: dict[str, Any] = {"params": params, "dt": dt, "noise": noise or None, "timing": timing}
    if tracked:
        kw["tracked"] = tracked
    try:
        return OnlineTracker(getattr(rig, "model", "msp25"), start={**st, **dict(start or {})} or None, **kw)
    except ParameterError:
        if not start:
            raise
        return OnlineTracker(getattr(rig, "model", "msp25"), **kw)
