"""A parsed rigs.toml made into what the service runs (:class:`ServiceConfig`, one :class:`RigConfig` a rig):
the files it points to loaded (a commissioning fit, a DBC, signing keys; relative paths to the configuration
file) and the rig's parameters, tracked parameters, noise levels and healthy bands built from its model.

What the text alone decides was checked by :mod:`twin.service.config_parse`; what needs the model or a file
is checked here, each refusal one :class:`~fpdd.errors.ConfigError` line naming the file, the rig and the key.
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Any

from fpdd.errors import ConfigError, ParameterError
from twin.models import REGISTRY, Model, get_model, trackable_models
from twin.models.base import Timing
from twin.online.baseline import Baseline, default_band, default_baseline
from twin.service.config_parse import NOISE_KEYS, ParsedBand, ParsedConfig, ParsedRig, Quantity
from twin.service.config_values import suggest, unit_number
from twin.service.ownership import FailoverConfig

if TYPE_CHECKING:
    from twin.online.commission import Commission


@dataclasses.dataclass(frozen=True)
class RigConfig:
    name: str
    model: str
    source: str
    dbc: str | None
    speed: float
    track: tuple[str, ...]
    params: dict[str, float]
    baseline: dict[str, Baseline]
    noise: dict[str, float] = dataclasses.field(default_factory=dict)
    """Sensor noise standard deviations (SI) per output; learnt online on top."""
    timing: Timing | None = None
    """The loop's timing (``controller``, ``intersample``); None: digital at the log's rate, or the fit's."""
    commission: str | Commission | None = None
    """A ``twin fit --save`` file (or, once a rig commissioned in service, what it found): known values, bands centred on the fit, noise levels and timing."""
    commission_s: float | None = None
    """Commission the rig on its first ``commission_s`` seconds in service (``None``: no)."""
    baseline_set: tuple[str, ...] = ()
    """The parameters whose band ``[rig.baseline.NAME]`` sets explicitly (a commissioning keeps them)."""
    signing_key: str | None = None
    """The rig's private Ed25519 key file: its alarms are signed (``None``: unsigned; see twin.service.signing)."""
    map: tuple[str, ...] = ()
    """The source's columns (CSV, text, MATLAB files) or CAN signals (CAN logs, ``can://``) mapped onto the rig's
    signals, ``NAME=COLUMN[:UNIT][*GAIN][+OFFSET]`` items as ``--map`` takes them."""
    forecast_horizon_s: float = 3600.0
    """Horizon of the early warning [s]: ``early`` when a parameter leaves its band within it with probability 0.9."""

    def source_options(self) -> dict:
        """Reader options of the rig's source from ``dbc`` and ``map``."""
        from replay.formats import CAN_LOG_SUFFIXES

        is_can = self.source.lower().startswith("can://") or self.source.lower().endswith(CAN_LOG_SUFFIXES)
        opts: dict[str, Any] = {"dbc": self.dbc} if self.dbc and is_can else {}  # a DBC decodes CAN frames only
        if self.map:
            from replay.csvio import parse_map

            opts["mapping"] = parse_map(self.map)
        return opts


@dataclasses.dataclass(frozen=True)
class ServiceConfig:
    path: str
    zenoh_mode: str | None
    """``None``: not given (the ZENOH_CONFIG file's mode, else peer)."""
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    journal_dir: str
    out_dir: str | None
    estimate_every: int
    rigs: tuple[RigConfig, ...]
    workers: int | None = 0
    """Worker processes: 0 = rigs in threads of the service's process, ``None`` = auto."""
    checkpoint_s: float = 1.0
    block_s: float = 0.1
    lag_warn_s: float = 1.0
    stale_s: float = 1.0
    signals_hz: float = 0.0
    """Rig signals put on ``fpdd/<rig>/signals`` for live views, at most this many samples per second and rig
    (0: none; ``twin serve --foxglove`` sets it)."""
    failover: FailoverConfig | None = None
    """``[failover]``: rigs shared with other services, one runs each (:mod:`twin.service.ownership`)."""


def resolve_config(parsed: ParsedConfig) -> ServiceConfig:
    """The service's configuration of a parsed file: every rig resolved, its signing key loaded."""
    rigs = _signing_keys([resolve_rig(r) for r in parsed.rigs], parsed.signing_keys, parsed.path)
    return ServiceConfig(
        path=parsed.path, zenoh_mode=parsed.zenoh_mode, listen=parsed.listen, connect=parsed.connect,
        journal_dir=parsed.journal_dir, out_dir=parsed.out_dir, estimate_every=parsed.estimate_every,
        rigs=tuple(rigs), workers=parsed.workers, checkpoint_s=parsed.checkpoint_s, block_s=parsed.block_s,
        lag_warn_s=parsed.lag_warn_s, stale_s=parsed.stale_s, failover=parsed.failover,
    )


def resolve_rig(rig: ParsedRig) -> RigConfig:
    """A parsed ``[[rig]]`` with its model's parameters, tracked parameters, noise and bands, its commissioning
    fit loaded and its DBC found."""
    model = _model(rig)
    params = _params(model, rig)
    commission = _beside(rig.path, rig.commission)
    com = _load_fit(commission)
    track = _track(model, rig, params, com, commission)
    baseline = com.baseline(track) if com is not None else default_baseline(rig.model, params, track)
    noise = _noise(model, rig)
    for pname, band in rig.baseline.items():
        baseline[pname] = _band(model, rig, params, track, pname, band, baseline)
    dbc = _beside(rig.path, rig.dbc)
    if dbc is not None and not os.path.isfile(dbc):
        raise ConfigError(f"{rig.where}.dbc: {dbc} is not a file (a CAN database, .dbc)")
    return RigConfig(name=rig.name, model=rig.model, source=rig.source, dbc=dbc, speed=rig.speed, track=track,
                     params=params, baseline=baseline, noise=noise, timing=rig.timing, commission=commission,
                     commission_s=rig.commission_s, baseline_set=tuple(rig.baseline), signing_key=rig.signing_key,
                     map=rig.map, forecast_horizon_s=rig.forecast_horizon_s)


# --------------------------------------------------------------------------- the model's parts

def _model(rig: ParsedRig) -> Model:
    if rig.model not in REGISTRY or not get_model(rig.model).TRACKABLE:
        raise ConfigError(f"{rig.where}.model: {rig.model!r} is not a model the online twin runs; it runs "
                          f"{', '.join(trackable_models())}")
    return get_model(rig.model)


def _params(model: Model, rig: ParsedRig) -> dict[str, float]:
    """``[rig.params]`` in SI, each a parameter of the model and together a valid parameter set."""
    where = f"{rig.where}.params"
    names = model.params().names
    params: dict[str, float] = {}
    for k, q in rig.params.items():
        if k not in names:
            raise ConfigError(f"{where}: unknown parameter {k!r} of model {rig.model}{suggest(k, names)}")
        params[k] = _si(q, where, k, k)
    try:
        model.params((), **params)
    except ParameterError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    return params


def _track(model: Model, rig: ParsedRig, params: dict[str, float], com: Commission | None,
           commission: str | None) -> tuple[str, ...]:
    """The tracked parameters: as listed, else the model's trackable ones that are not held at 0.  A parameter
    held at exactly 0 (a spring of 0: a free mass, as twin fit --set k=0) is held, not tracked: the twin follows
    a parameter relative to its value."""
    where, trackable = rig.where, model.PHENOMENOLOGICAL
    known = {**(com.params if com is not None else {}), **params}
    held = tuple(n for n in trackable if known.get(n) == 0 and n not in (com.fitted if com else {}))
    track = rig.track or tuple(n for n in trackable if n not in held)
    if rig.track == ():
        raise ConfigError(f"{where}.track: the list is empty; name at least one of {', '.join(trackable)}")
    if not track:
        raise ConfigError(f"{where}.params: every trackable parameter ({', '.join(trackable)}) is held "
                          "at 0; nothing is left to track")
    bad = [t for t in track if t not in trackable]
    if bad:
        raise ConfigError(f"{where}.track: {bad} not among the trackable {', '.join(trackable)}"
                          f"{suggest(bad[0], trackable) if len(bad) == 1 else ''}")
    if len(set(track)) != len(track):
        raise ConfigError(f"{where}.track: {list(track)} names a parameter twice")
    zero = [t for t in track if t in held]
    if zero:
        src = f"params.{zero[0]}" if zero[0] in params else f"the commissioning fit {commission}"
        raise ConfigError(f"{where}.track: {zero[0]} is held at exactly 0 by {src}; a parameter at 0 is not "
                          f"tracked (the twin follows a parameter relative to its value): drop it from track or "
                          f"give it a positive value")
    return track


def _noise(model: Model, rig: ParsedRig) -> dict[str, float]:
    """``noise``: standard deviations (SI) of the model's measured outputs."""
    from twin.units import to_si

    where = f"{rig.where}.noise"
    measured = tuple(model.FILTER.measures) if model.FILTER is not None else NOISE_KEYS  # the rig model's outputs
    noise: dict[str, float] = {}
    for k, q in rig.noise.items():
        if k not in measured:
            raise ConfigError(f"{where}: unknown output {k!r} of the {rig.model} model; known: "
                              f"{', '.join(measured)}{suggest(k, measured)}")
        try:
            noise[k] = to_si(k, q) if isinstance(q, str) else float(q)
        except ParameterError as exc:
            raise ConfigError(f"{where}.{k}: {exc}") from None
        if not noise[k] > 0:
            raise ConfigError(f"{where}.{k}: expected a positive standard deviation (SI or with a unit, "
                              f"e.g. \"2um\"), got {q!r}")
        unit_number({k: q}, k, where, k)
    return noise


def _band(model: Model, rig: ParsedRig, params: dict[str, float], track: tuple[str, ...], pname: str,
          band: ParsedBand, defaults: dict[str, Baseline]) -> Baseline:
    """``[rig.baseline.NAME]``: the healthy band of a tracked parameter, within its bounds and within what the
    twin can estimate; what it leaves out is the default band's (``defaults``: the fit's or the model's)."""
    bw = f"{rig.where}.baseline.{pname}"
    if pname not in track:
        raise ConfigError(f"{bw}: not a tracked parameter ({', '.join(track)})"
                          f"{suggest(pname, track) if pname not in model.PHENOMENOLOGICAL else ''}")
    spec = model.params().spec(pname)
    v = _si(band.value, bw, "value", pname, spec, defaults[pname].value, positive=True)
    if band.lo is not None or band.hi is not None:
        lo = _si(band.lo, bw, "lo", pname, spec, positive=True)
        hi = _si(band.hi, bw, "hi", pname, spec, positive=True)
    else:
        rb = band.rel_band if band.rel_band is not None else default_band(rig.model, pname)
        lo, hi = v / (1 + rb), v * (1 + rb)
    if not lo < v < hi:
        raise ConfigError(f"{bw}: the band [{lo:g}, {hi:g}] must contain the value {v:g}")
    t_lo, t_hi = model.tracking_bounds(model.params((), **params), pname)
    if not t_lo < lo or not hi < t_hi:
        side, edge, limit = ("lower", lo, t_lo) if not t_lo < lo else ("upper", hi, t_hi)
        raise ConfigError(f"{bw}: the band's {side} edge {edge:g} is beyond what the twin can estimate "
                          f"({t_lo:g} .. {t_hi:g} SI): that side could never alarm; give a narrower band")
    return Baseline(v, lo, hi)


def _si(q: Quantity | None, where: str, key: str, pname: str, spec=None, default: Any = ...,
        positive: bool = False) -> float:
    """``q`` (at ``where.key``): a number (SI) or a string with a unit (``"2000mm^2"``) for parameter ``pname``,
    in SI (``None``: ``default``); with ``spec`` it must lie within the parameter's bounds (a bare number that
    does not is most often a value in display units: the message says how to write one)."""
    if q is None:
        if default is ...:
            raise ConfigError(f"{where}: missing key {key!r}")
        v = float(default)
    elif isinstance(q, str):
        from twin.units import to_si

        try:
            v = to_si(pname, q, spec.unit if spec is not None else None)
        except ParameterError as exc:
            reason = str(exc).removeprefix(f"{pname}: ")
            raise ConfigError(f"{where}.{key}: expected a number or a value with a unit, got {q!r}: "
                              f"{reason}") from None
    else:
        v = float(q)
        unit_number({key: q}, key, where, pname, spec)
    if positive and not v > 0:
        raise ConfigError(f"{where}.{key}: must be > 0, got {v:g}")
    if spec is not None and not spec.lo <= v <= spec.hi:
        hint = ""
        if not isinstance(q, str) and spec.display_unit and spec.lo <= v / spec.display_scale <= spec.hi:
            hint = (f"; a bare number is SI ({spec.unit}): for {v:g} {spec.display_unit} write "
                    f"\"{v:g}{spec.display_unit}\"")
        raise ConfigError(f"{where}.{key}: {v:g} {spec.unit} is outside {pname}'s bounds "
                          f"[{spec.lo:g}, {spec.hi:g}] {spec.unit}{hint}")
    return v


# --------------------------------------------------------------------------- the files it points to

def _beside(config_path: str, path: str | None) -> str | None:
    """``path`` as given in the configuration file ``config_path``: a relative one is relative to that file."""
    if path is None or os.path.isabs(path):
        return path
    return os.path.join(os.path.dirname(os.path.abspath(config_path)), path)


def _load_fit(commission: str | None) -> Commission | None:
    if commission is None:
        return None
    from twin.online.commission import load_fit

    return load_fit(commission)


def _signing_keys(rigs: list[RigConfig], directory: str | None, path: str) -> list[RigConfig]:
    """Each rig's ``signing_key`` (its own, else ``<service.signing_keys>/<rig>.key``), checked by loading it."""
    from twin.service.signing import load_signer

    out = []
    for r in rigs:
        key = _beside(path, r.signing_key or (os.path.join(directory, f"{r.name}.key") if directory else None))
        if key is not None:
            load_signer(key, r.name)  # one line naming the file now, not when the first alarm is due
            r = dataclasses.replace(r, signing_key=key)
        out.append(r)
    return out
