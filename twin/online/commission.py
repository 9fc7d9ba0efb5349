"""Commissioning a rig's twin: what the tracker and the drift test start from.

A commissioning fit (``twin fit --save FIT.json``: ``{"model", "effects", "free", "params", "timing",
"noise"}``, each value ``{"value", "unit"}`` in SI, a fitted parameter's with its ``"std"``; the older
``"params"`` of bare numbers with ``"std"`` beside is read too) says

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

from fpdd.errors import ConfigError, ParameterError
from twin.models import DEFAULT_MODEL, REGISTRY, get_model, trackable_models
from twin.models.base import Timing
from twin.online.confirm import BURN_S

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
    model: str = DEFAULT_MODEL
    #: what the fit warned (``twin fit --save`` keeps it): a model that does not represent the rig, an output
    #: barely fitted
    warnings: tuple[str, ...] = ()
    #: the column map (``--map``'s items, with their units) the commissioning record was read with: a later
    #: ``twin track other.csv --params FILE`` reads another file of the same logger through it
    map: tuple[str, ...] = ()

    def __repr__(self) -> str:
        """One line: the model, the fitted values, the noise levels, the timing, where it came from."""
        fitted = ", ".join(f"{n}={v:.4g}" for n, (v, _) in list(self.fitted.items())[:6])
        more = ", ..." if len(self.fitted) > 6 else ""
        noise = ", ".join(f"{k}={v:.3g}" for k, v in self.noise.items())
        return (f"Commission(model={self.model!r}, fitted: {fitted}{more} (SI); noise: {noise or 'none'}; "
                f"timing={self.timing.label if self.timing is not None else None}; "
                f"map={list(self.map)}; source={self.source!r})")

    def baseline(self, names: Sequence[str], rel_band: Mapping[str, float] | None = None, k_sigma: float = 3.0):
        """Healthy bands of ``names`` centred on the fitted (or known) values."""
        from twin.online.baseline import Baseline, default_band

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


def check_unit(source: str, field: str, v: Mapping, unit: str) -> None:
    """A saved ``{"value", "unit"}`` must be in the SI unit ``unit`` (values are saved and read in SI)."""
    if "unit" in v and v["unit"] != unit:
        raise ConfigError(f"{source}: {field}.unit is {v['unit']!r}, expected {unit!r} (values are saved in SI)")


def from_dict(doc: Mapping, source: str = "<fit>") -> Commission:
    """A :class:`Commission` from the JSON document of ``twin fit --save``."""
    if not isinstance(doc, Mapping):
        raise ConfigError(f"{source}: expected a JSON object written by twin fit --save")
    model = doc.get("model", DEFAULT_MODEL)
    if model not in REGISTRY or not get_model(model).TRACKABLE:
        raise ConfigError(f"{source}: model: a fit of {model!r}; the online twin runs "
                          f"{', '.join(trackable_models())}")
    params_in = doc.get("params", {})
    if not isinstance(params_in, Mapping) or not params_in:
        raise ConfigError(f"{source}: params must be an object of parameter values")
    std_in = doc.get("std", {}) or {}
    if not isinstance(std_in, Mapping):
        raise ConfigError(f"{source}: std must be an object of standard errors")
    effects = tuple(doc.get("effects") or ())
    unknown = [e for e in effects if not isinstance(e, str) or e not in get_model(model).EFFECTS]
    if unknown:
        raise ConfigError(f"{source}: effects: {unknown[0]!r} is no effect of the {model} model; known: "
                          f"{', '.join(get_model(model).EFFECTS)}")
    extended = get_model(model).params(effects)  # an extended model is a model: its effects' parameters too
    known = extended.names
    specs = {sp.name: sp for sp in extended.specs}
    params, fitted = {}, {}
    for n, v in params_in.items():
        if isinstance(v, Mapping):  # FitResult.saved() / to_dict(): {"value", "unit"[, "std"]} in SI
            val = _number(source, f"params.{n}.value", v.get("value"))
            if n in specs:
                check_unit(source, f"params.{n}", v, specs[n].unit)
            if "std" in v:  # a fitted parameter (a known one has no std)
                sd = v.get("std")
                fitted[n] = (val, float(sd) if isinstance(sd, (int, float)) else math.nan)
        else:
            val = _number(source, f"params.{n}", v)
            if n in std_in and std_in[n] is not None:
                fitted[n] = (val, _number(source, f"std.{n}", std_in[n]))
        if n not in known:
            raise ConfigError(f"{source}: params.{n}: the {model} model has no parameter {n!r}")
        params[n] = val
    noise = {}
    filt = get_model(model).FILTER
    measured = tuple(filt.measures) if filt is not None else NOISE_KEYS
    for k, v in (doc.get("noise") or {}).items():
        if k not in measured:
            continue
        val = _number(source, f"noise.{k}.value", v.get("value")) if isinstance(v, Mapping) else \
            _number(source, f"noise.{k}", v)
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
    warnings = doc.get("warnings") or []
    if not (isinstance(warnings, list) and all(isinstance(w, str) for w in warnings)):
        raise ConfigError(f"{source}: warnings must be a list of strings (the fit's warnings)")
    source_doc = doc.get("source") or {}
    items = source_doc.get("map") if isinstance(source_doc, Mapping) else None
    if items is not None and not (isinstance(items, list) and all(isinstance(m, str) for m in items)):
        raise ConfigError(f"{source}: source.map must be a list of --map items (\"x=pos_mm:mm\"), got {items!r}")
    return Commission(params, fitted, noise, timing, effects, source, model, tuple(warnings), tuple(items or ()))


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


def saved_map(params_path: str | None, data_path: str) -> list[str]:
    """The column map (``--map``'s items) a ``twin fit --save`` file keeps (``source.map``) when ``data_path`` is a
    file a map applies to (a CSV, a text file, a CAN log); ``[]`` when there is none or it does not apply."""
    if not params_path:
        return []
    from replay import formats

    try:
        if not formats.takes_map(data_path):
            return []
    except Exception:  # an unknown kind of file: its reader names the problem
        return []
    doc = read_saved(params_path, "parameter file")
    source = doc.get("source") if isinstance(doc, Mapping) else None
    items = source.get("map") if isinstance(source, Mapping) else None
    if items is None:
        return []
    if not (isinstance(items, list) and all(isinstance(m, str) for m in items)):
        raise ConfigError(f"{params_path}: source.map must be a list of --map items (\"x=pos_mm:mm\"), got {items!r}")
    return list(items)


def tracker_params(c: Commission, tracked: Sequence[str]) -> tuple[dict[str, float], dict[str, float]]:
    """(known parameters, starting values of the tracked ones) from a commissioning fit; the parameters of the
    fit's effects (``c.effects``: an extended model) are among the known ones, held at the fitted values unless
    tracked."""
    params = {k: v for k, v in c.params.items()}
    return params, {t: params[t] for t in tracked if t in params}


#: The least peak-to-peak movement of the position in a commissioning window [m]: less is no excitation.
MIN_STROKE_M = 1e-4
#: A fitted parameter known worse than this (relative standard error) was not excited enough.
MAX_REL_STD = 0.5
# The window's first BURN_S seconds are simulated, not counted, as in the confirmation's windows and for the same
# reason (the fit's loop starts from a state read off the first samples; :data:`twin.online.confirm.BURN_S`). A
# service started on a rig already moving gathers a window that starts mid-motion: counted, that start refused 49
# of 120 commissionings of the reference simulator (verification seeds 1000-1039, 12-s windows from 2.71, 6.43 and
# 11.9 s) and put 26 of the 71 accepted leakages more than 3 standard errors off their truth; not counted, 4 of 120
# refused and 1 of 116 off. Windows starting at rest: 0 of 40 refused either way (python -m
# benchmarks.commission_start).
#: At most this many samples are gathered for a commissioning fit, whatever ``commission_s`` says (memory).
MAX_WINDOW_SAMPLES = 1_000_000


class Window:
    """The first ``seconds`` (of sample time) of a rig's samples, gathered for its commissioning fit.

    Memory is bounded: the window ends at ``seconds`` or at ``max_samples``
    samples, whichever comes first; :meth:`add` hands back what lies beyond it.
    """

    def __init__(self, seconds: float, max_samples: int = MAX_WINDOW_SAMPLES) -> None:
        self.seconds = float(seconds)
        self.max_samples = int(max_samples)
        self._blocks: list = []
        self._n = 0
        self._t0_ns: int | None = None
        self._t_last_ns: int | None = None
        self.full = False

    @property
    def gathered_s(self) -> float:
        if self._t0_ns is None or self._t_last_ns is None:
            return 0.0
        return (self._t_last_ns - self._t0_ns) * 1e-9

    def __len__(self) -> int:
        return self._n

    def add(self, samples):
        """Gather ``samples`` up to the end of the window; returns the samples beyond it (``None``: none)."""
        import numpy as np

        if self.full:
            return samples
        if len(samples) == 0:
            return None
        if self._t0_ns is None:
            self._t0_ns = int(samples.t_ns[0])
        end_ns = self._t0_ns + int(round(self.seconds * 1e9))
        k = int(np.searchsorted(samples.t_ns, end_ns, side="left"))
        k = min(k, self.max_samples - self._n)
        if k > 0:
            part = samples if k >= len(samples) else samples.slice(0, k)
            self._blocks.append(part)
            self._n += len(part)
            self._t_last_ns = int(part.t_ns[-1])
        if k < len(samples):
            self.full = True
            return samples.slice(k, len(samples)) if k > 0 else samples
        return None

    def samples(self):
        """The gathered samples, in one block."""
        from replay.base import Samples

        return Samples.concat(self._blocks)


def fit_window(samples, tracked: Sequence[str], params: Mapping[str, float] | None = None,
               timing: Timing | None = None, rig: str = "", model_name: str = DEFAULT_MODEL,
               burn_s: float = BURN_S) -> tuple[dict | None, str]:
    """The commissioning fit of a rig's first samples: ``(document, "")`` or ``(None, why it cannot be used)``.

    The document is what ``twin fit --save`` writes (``model, effects, params,
    std, timing, noise``, plus ``commissioned``: the window's first and last
    sample time, its length and sample count) and :func:`from_dict` reads.
    It is refused, with the reason, when the position hardly moved (less than
    :data:`MIN_STROKE_M` peak to peak: no excitation), the fit did not
    converge, a parameter ended at a bound, or one is known worse than
    :data:`MAX_REL_STD` relatively (too little excitation for it). Runs in a
    worker process of the service (everything in and out is plain data).
    """
    import numpy as np

    from twin.estimation.fit_checked import fit
    from twin.record import Record

    n = len(samples)
    if n < 100:
        return None, f"only {n} samples gathered; at least 100 are needed"
    t_ns = np.asarray(samples.t_ns)
    seconds = (int(t_ns[-1]) - int(t_ns[0])) * 1e-9
    dt = float(np.median(np.diff(t_ns))) * 1e-9
    sig = {k: np.asarray(v, float) for k, v in samples.signals.items()}
    model = get_model(model_name)
    if "x" in sig:
        x = sig["x"][np.isfinite(sig["x"])]
        stroke = float(np.ptp(x)) if x.size else 0.0
        if stroke < MIN_STROKE_M:
            return None, (f"too little excitation: the position moved {stroke * 1e3:.3f} mm peak to peak in "
                          f"{seconds:.1f} s (at least {MIN_STROKE_M * 1e3:g} mm needed; run the rig's "
                          "identification demand while it commissions)")
    rec = Record(dt, sig, f"commissioning {rig}".strip())
    rec.burn_start(burn_s, model.OUTPUTS)
    try:
        base = model.params((), **dict(params or {}))
        res = fit(model, [rec], tuple(tracked), base=base, timing=timing)
    except (ParameterError, ValueError) as exc:
        return None, f"the fit cannot run: {exc}"
    if not res.success:
        return None, f"the fit did not converge ({res.message})"
    at_bound = [k for k in tracked if not math.isfinite(float(res.std.get(k, math.nan)))]
    if at_bound:
        return None, f"the fit left {', '.join(at_bound)} at a bound (no standard error): {res.message}"
    weak = [f"{k} +-{100 * res.std[k] / res.estimate[k]:.0f} %" for k in tracked
            if not res.std[k] <= MAX_REL_STD * abs(res.estimate[k])]
    if weak:
        return None, f"too little excitation: {', '.join(weak)} (at most +-{100 * MAX_REL_STD:.0f} % usable)"
    doc = {**res.saved(),  # the twin fit --save format: values with their units, SI
           "commissioned": {"rig": rig, "first_t_ns": int(t_ns[0]), "last_t_ns": int(t_ns[-1]),
                            "seconds": seconds, "samples": n, "fit_pct": dict(res.fit_pct)}}
    return doc, ""


def commission_from_samples(samples, seconds: float, tracked: Sequence[str], params: Mapping[str, float] | None = None,
                            timing: Timing | None = None, model: str = DEFAULT_MODEL) -> Commission:
    """Fit the free parameters on the first ``seconds`` of ``samples`` (the rig's first minutes in service).

    :raises ConfigError: the window cannot commission the rig (:func:`fit_window` says why).
    """
    w = Window(seconds)
    w.add(samples)
    doc, problem = fit_window(w.samples(), tracked, params, timing, model_name=model)
    if doc is None:
        raise ConfigError(f"commission_s = {seconds:g}: {problem}")
    return from_dict(doc, "commissioning fit")


def apply_commission(rig, com: Commission):
    """The rig configuration commissioned by ``com``: its values, noise and timing (``commission``: the
    saved file) and bands centred on the fit, but the bands ``[rig.baseline.NAME]`` set explicitly."""
    baseline = com.baseline(rig.track)
    baseline.update({n: b for n, b in rig.baseline.items() if n in rig.baseline_set})
    return dataclasses.replace(rig, commission=com.source, baseline=baseline)


def describe(c: Commission, names: Sequence[str]) -> str:
    """One line: the fitted values with their standard errors and the noise levels, in display units."""
    ps = get_model(c.model).params()
    parts = []
    for n in names:
        if n in c.fitted:
            v, sd = c.fitted[n]
            show = ps.spec(n).show
            parts.append(f"{n} {show(float(f'{v:.4g}'))} +- {show(float(f'{sd:.2g}'))}")
    noise_units = {"x": (1e6, "um"), "pA": (1e-3, "kPa"), "pB": (1e-3, "kPa")}
    noise = [f"{o} {v * noise_units[o][0]:.3g} {noise_units[o][1]}" for o, v in c.noise.items() if o in noise_units]
    text = ", ".join(parts)
    return f"{text}; noise {', '.join(noise)}" if noise else text


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
    effects: tuple[str, ...] = ()
    if isinstance(com, str) and com:
        com = load_fit(com)
    if isinstance(com, Commission):
        p, st = tracker_params(com, tracked)
        params = {**p, **params}
        effects = com.effects
        noise.update(com.noise)
        timing = timing or com.timing
    noise.update(dict(getattr(rig, "noise", None) or {}))
    if isinstance(timing, str):
        timing = Timing.parse(timing)
    kw: dict[str, Any] = {"params": params, "dt": dt, "noise": noise or None, "timing": timing}
    if effects:
        kw["effects"] = effects
    if tracked:
        kw["tracked"] = tracked
    try:
        return OnlineTracker(getattr(rig, "model", DEFAULT_MODEL), start={**st, **dict(start or {})} or None, **kw)
    except ParameterError:
        if not start:
            raise
        return OnlineTracker(getattr(rig, "model", DEFAULT_MODEL), **kw)
