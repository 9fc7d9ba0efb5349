"""Rig configuration (``RIG.toml``) for ``twin serve``: which rigs, where their data come from,
which parameters to track, their healthy baselines, and how to reach Zenoh.

Example (every key but ``rig.name`` and ``rig.source`` has a default)::

    [zenoh]
    mode = "peer"                       # or "client" to go through a site router
    listen = ["tcp/127.0.0.1:7447"]
    connect = []

    [service]
    journal_dir = "/var/lib/fpdd"       # alarm journals, one per rig
    out_dir = "/var/lib/fpdd/records"   # MCAP of estimates and alarms (optional)
    estimate_every = 50                 # publish an estimate every N samples

    [[rig]]
    name = "msp25-a"
    model = "msp25"
    source = "can://socketcan/can0"     # or zenoh://KEYEXPR, or a log file (replayed)
    dbc = ""                            # default: the MSP25 DBC shipped with replay
    speed = 1.0                         # replay speed for log sources (0 = as fast as possible)
    track = ["Ffric", "CdAleak", "Cd", "zeta", "wn"]
    [rig.params]                        # known parameters that differ from the nominal MSP25
    KP = 400.0
    [rig.baseline.Ffric]                # healthy band (default: nominal value, +-30 %)
    value = 50.0
    rel_band = 0.3
"""

from __future__ import annotations

import dataclasses
import os
import tomllib
from typing import Any

from twin.errors import ConfigError, ParameterError
from twin.models import MODELS, get_model

DEFAULT_REL_BAND = {"Ffric": 0.5, "CdAleak": 2.0, "Cd": 0.15, "zeta": 0.3, "wn": 0.15}


@dataclasses.dataclass(frozen=True)
class Baseline:
    """Healthy value of one parameter and its band [lo, hi] (SI units)."""

    value: float
    lo: float
    hi: float


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


@dataclasses.dataclass(frozen=True)
class ServiceConfig:
    path: str
    zenoh_mode: str
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    journal_dir: str
    out_dir: str | None
    estimate_every: int
    rigs: tuple[RigConfig, ...]


def default_baseline(model_name: str, params: dict[str, float] | None = None,
                     names: tuple[str, ...] | None = None) -> dict[str, Baseline]:
    """Bands around the rig configuration's values (the paper's Table 9 for the MSP25)."""
    model = get_model(model_name)
    ps = model.params(**(params or {}))
    out = {}
    for n in names or model.PHENOMENOLOGICAL:
        v = ps[n]
        r = DEFAULT_REL_BAND.get(n, 0.3)
        out[n] = Baseline(v, v / (1 + r), v * (1 + r))
    return out


def _get(d: dict, key: str, typ, where: str, default: Any = ...) -> Any:
    if key not in d:
        if default is ...:
            raise ConfigError(f"{where}: missing key {key!r}")
        return default
    v = d[key]
    if typ is float and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, typ):
        raise ConfigError(f"{where}.{key}: expected {getattr(typ, '__name__', typ)}, got {v!r}")
    return v


def load_config(path: str) -> ServiceConfig:
    """Read and validate a rig configuration; errors name the file and the key."""
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the configuration ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return parse_config(doc, path)


def parse_config(doc: dict, path: str = "<config>") -> ServiceConfig:
    z = _get(doc, "zenoh", dict, path, {})
    s = _get(doc, "service", dict, path, {})
    mode = _get(z, "mode", str, f"{path}: zenoh", "peer")
    if mode not in ("peer", "client", "router"):
        raise ConfigError(f"{path}: zenoh.mode must be peer, client or router, got {mode!r}")
    rigs_doc = _get(doc, "rig", list, path)
    if not rigs_doc:
        raise ConfigError(f"{path}: at least one [[rig]] is needed")
    rigs = []
    seen = set()
    for i, r in enumerate(rigs_doc):
        where = f"{path}: rig[{i}]"
        if not isinstance(r, dict):
            raise ConfigError(f"{where}: expected a table")
        name = _get(r, "name", str, where)
        if not name or "/" in name or "*" in name or name in seen:
            raise ConfigError(f"{where}.name: {name!r} must be unique, non-empty, without '/' or '*'")
        seen.add(name)
        where = f"{path}: rig {name!r}"
        model_name = _get(r, "model", str, where, "msp25")
        if model_name not in MODELS:
            raise ConfigError(f"{where}.model: {model_name!r} is not one of {', '.join(MODELS)}")
        model = get_model(model_name)
        params = {k: float(v) for k, v in _get(r, "params", dict, where, {}).items()}
        try:
            model.params(**params)
        except ParameterError as exc:
            raise ConfigError(f"{where}.params: {exc}") from None
        track = tuple(_get(r, "track", list, where, list(model.PHENOMENOLOGICAL)))
        bad = [t for t in track if t not in model.PHENOMENOLOGICAL]
        if bad:
            raise ConfigError(f"{where}.track: {bad} not among the trackable {', '.join(model.PHENOMENOLOGICAL)}")
        baseline = default_baseline(model_name, params, track)
        for pname, b in _get(r, "baseline", dict, where, {}).items():
            if pname not in track:
                raise ConfigError(f"{where}.baseline.{pname}: not a tracked parameter ({', '.join(track)})")
            bw = f"{where}.baseline.{pname}"
            if not isinstance(b, dict):
                raise ConfigError(f"{bw}: expected a table with value and rel_band or lo/hi")
            v = _get(b, "value", float, bw, baseline[pname].value)
            if "lo" in b or "hi" in b:
                lo, hi = _get(b, "lo", float, bw), _get(b, "hi", float, bw)
            else:
                rb = _get(b, "rel_band", float, bw, DEFAULT_REL_BAND.get(pname, 0.3))
                lo, hi = v / (1 + rb), v * (1 + rb)
            if not lo < v < hi:
                raise ConfigError(f"{bw}: the band [{lo:g}, {hi:g}] must contain the value {v:g}")
            baseline[pname] = Baseline(v, lo, hi)
        speed = _get(r, "speed", float, where, 1.0)
        if speed < 0:
            raise ConfigError(f"{where}.speed: must be >= 0 (0 = as fast as possible), got {speed}")
        dbc = _get(r, "dbc", str, where, "") or None
        rigs.append(RigConfig(name, model_name, _get(r, "source", str, where), dbc, speed, track, params, baseline))
    every = _get(s, "estimate_every", int, f"{path}: service", 50)
    if every < 1:
        raise ConfigError(f"{path}: service.estimate_every must be >= 1, got {every}")
    return ServiceConfig(
        path=path, zenoh_mode=mode,
        listen=tuple(_get(z, "listen", list, f"{path}: zenoh", [])),
        connect=tuple(_get(z, "connect", list, f"{path}: zenoh", [])),
        journal_dir=_get(s, "journal_dir", str, f"{path}: service", os.path.join(".", "fpdd-journal")),
        out_dir=_get(s, "out_dir", str, f"{path}: service", "") or None,
        estimate_every=every, rigs=tuple(rigs))
