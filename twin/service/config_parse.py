"""rigs.toml as written: the TOML text read into plain typed dataclasses (:class:`ParsedConfig`, one
:class:`ParsedRig` a ``[[rig]]``), with every key and value that the text alone decides checked: known keys,
types, finite numbers and their bounds, paths, the sources' URIs, the loop's timing, the map.

Nothing here opens a model or a file that the configuration points to (a fit, a DBC, a signing key): what
the rig's model must judge (its parameters, outputs, trackable parameters and bands) is kept as written, a
number or a string with a unit (:data:`Quantity`), for :mod:`twin.service.config_resolve`.  Every refusal is
one :class:`~fpdd.errors.ConfigError` line naming the file, the rig, the key and what was expected.
"""

from __future__ import annotations

import dataclasses
import os
import re
import tomllib
from typing import Any

from fpdd.errors import ConfigError, ParameterError
from twin.models import DEFAULT_MODEL
from twin.models.base import Timing
from twin.online.events import RIG_PATTERN
from twin.service.config_values import _check_keys, _get, _number
from twin.service.ownership import FailoverConfig, parse_failover

#: The shortest commissioning window ``commission_s`` [s].
MIN_COMMISSION_S = 5.0
#: Replay speeds a log source may have (besides 0 = as fast as possible): a thousandth to ten thousand times
#: real time (beyond, a sample interval is below a microsecond of wall clock or above an hour).
SPEED_RANGE = (1e-3, 1e4)
#: The fastest digital controller accepted [Hz]: ten times the fastest servo-hydraulic test controllers
#: (5-10 kHz); the loop model integrates every controller period, so a faster one never finishes a sample.
MAX_CONTROLLER_HZ = 100e3
#: Longest rig name (one Zenoh key chunk, also a file name of the journal) and longest path, in characters;
#: one path component at most NAME_MAX (255 bytes on Linux).
MAX_RIG_NAME = 64
MAX_PATH = 4096
MAX_PATH_COMPONENT = 255

TOP_KEYS = ("zenoh", "service", "rig", "failover")
ZENOH_KEYS = ("mode", "listen", "connect")
SERVICE_KEYS = ("journal_dir", "out_dir", "estimate_every", "workers", "checkpoint_s", "block_s", "lag_warn_s",
                "stale_s", "signing_keys")
RIG_KEYS = ("name", "model", "source", "dbc", "map", "speed", "track", "params", "baseline", "noise", "controller",
            "intersample", "commission", "commission_s", "signing_key", "forecast_horizon_s")
#: The noise keys of a model that declares no filter map (a model's own are its measured outputs).
NOISE_KEYS = ("x", "pA", "pB")
BASELINE_KEYS = ("value", "rel_band", "lo", "hi")

#: A value as written: a number (SI; an integer stays as written) or a string with a unit (``"2000mm^2"``),
#: converted to SI once the rig's model names the quantity's unit.
Quantity = float | str


@dataclasses.dataclass(frozen=True)
class ParsedBand:
    """``[rig.baseline.NAME]`` as written: ``value`` with ``rel_band``, or ``lo`` and ``hi`` (``None``: not
    given; the resolver's defaults are the model's)."""

    value: Quantity | None = None
    rel_band: float | None = None
    lo: Quantity | None = None
    hi: Quantity | None = None


@dataclasses.dataclass(frozen=True)
class ParsedRig:
    """One ``[[rig]]`` as written, its paths as written (relative ones to the configuration file, ``path``)."""

    path: str
    name: str
    model: str
    source: str
    dbc: str | None = None
    map: tuple[str, ...] = ()
    speed: float = 1.0
    track: tuple[str, ...] | None = None
    """``None``: not given (the model's trackable parameters that are not held at 0)."""
    params: dict[str, Quantity] = dataclasses.field(default_factory=dict)
    baseline: dict[str, ParsedBand] = dataclasses.field(default_factory=dict)
    noise: dict[str, Quantity] = dataclasses.field(default_factory=dict)
    timing: Timing | None = None
    commission: str | None = None
    commission_s: float | None = None
    signing_key: str | None = None
    forecast_horizon_s: float = 3600.0

    @property
    def where(self) -> str:
        """How messages name the rig: ``FILE: rig 'NAME'``."""
        return f"{self.path}: rig {self.name!r}"


@dataclasses.dataclass(frozen=True)
class ParsedConfig:
    """The whole file as written: ``[zenoh]``, ``[service]``, ``[failover]`` and the rigs."""

    path: str
    zenoh_mode: str | None
    listen: tuple[str, ...]
    connect: tuple[str, ...]
    journal_dir: str
    out_dir: str | None
    estimate_every: int
    workers: int | None
    checkpoint_s: float
    block_s: float
    lag_warn_s: float
    stale_s: float
    signing_keys: str | None
    """``service.signing_keys``: a directory of ``<rig>.key`` files, as written."""
    failover: FailoverConfig | None
    rigs: tuple[ParsedRig, ...]


# --------------------------------------------------------------------------- the file and the text

def parse_file(path: str) -> ParsedConfig:
    """Read ``path`` (UTF-8 TOML) and parse it; errors name the file."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the configuration ({exc.strerror or exc})") from None
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")) or (len(raw) > 1 and (raw[0] == 0 or raw[1] == 0)):
        raise ConfigError(f"{path}: the configuration is UTF-16 text; TOML must be UTF-8 (save it as UTF-8)")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}: {raw[exc.start:exc.start + 1]!r}); "
                          "TOML must be UTF-8") from None
    return parse_text(text, path)


def parse_text(text: str, path: str = "<rigs.toml>") -> ParsedConfig:
    """Parse TOML ``text``; ``path`` names it in messages and anchors its relative paths."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not a rig configuration: arrays or tables nested too deeply") from None
    return parse_doc(doc, path)


def parse_doc(doc: dict, path: str = "<config>") -> ParsedConfig:
    """Check a TOML document (the tables ``tomllib`` made of the text) and read it into a :class:`ParsedConfig`."""
    _check_keys(doc, TOP_KEYS, path)
    z = _get(doc, "zenoh", dict, path, {})
    s = _get(doc, "service", dict, path, {})
    sw = f"{path}: service"
    _check_keys(z, ZENOH_KEYS, f"{path}: zenoh")
    _check_keys(s, SERVICE_KEYS, sw)
    mode, listen, connect = _zenoh(z, path)
    rigs = _rigs(doc, path)
    signing_keys = _get(s, "signing_keys", str, sw, "") or None
    every = _get(s, "estimate_every", int, sw, 50)
    if every < 1:
        raise ConfigError(f"{path}: service.estimate_every must be >= 1, got {every}")
    if every > 1_000_000:
        raise ConfigError(f"{path}: service.estimate_every: {every} samples; at most 1000000 (an estimate every "
                          "17 min at 1 kHz)")
    workers = _workers(s.get("workers", "auto"), path)
    journal_dir = _path(s, "journal_dir", sw, os.path.join(".", "fpdd-journal"))
    if not journal_dir.strip():
        raise ConfigError(f"{path}: service.journal_dir: expected a directory path, got an empty string")
    failover = parse_failover(doc, path, journal_dir)
    return ParsedConfig(
        path=path, zenoh_mode=mode, listen=listen, connect=connect, journal_dir=journal_dir,
        out_dir=_path(s, "out_dir", sw, "") or None, estimate_every=every, workers=workers,
        checkpoint_s=_at_most(_number(s, "checkpoint_s", sw, 1.0, lo=0.0, lo_open=True, what=" seconds"),
                              3600.0, f"{sw}.checkpoint_s", "an hour: the state a restart would lose"),
        block_s=_at_most(_number(s, "block_s", sw, 0.1, lo=0.001, what=" seconds"), 10.0, f"{sw}.block_s",
                         "the latency of every estimate and alarm"),
        lag_warn_s=_at_most(_number(s, "lag_warn_s", sw, 1.0, lo=0.0, lo_open=True, what=" seconds"), 86400.0,
                            f"{sw}.lag_warn_s", "a day"),
        stale_s=_at_most(_number(s, "stale_s", sw, 1.0, lo=0.05, what=" seconds"), 86400.0, f"{sw}.stale_s",
                         "a day: a dead input must be noticed"),
        signing_keys=signing_keys, failover=failover, rigs=rigs,
    )


# --------------------------------------------------------------------------- [zenoh] and [service]

def _zenoh(z: dict, path: str) -> tuple[str | None, tuple[str, ...], tuple[str, ...]]:
    """``(mode, listen, connect)`` of ``[zenoh]``."""
    zw = f"{path}: zenoh"
    mode = _get(z, "mode", str, zw, None)
    if mode is not None and mode not in ("peer", "client", "router"):
        raise ConfigError(f"{path}: zenoh.mode must be peer, client or router, got {mode!r}")
    listen = _endpoints(z, "listen", zw)
    connect = _endpoints(z, "connect", zw)
    if mode == "client" and listen:
        raise ConfigError(f"{path}: zenoh.listen: a client cannot listen (got {list(listen)}); "
                          "use mode = \"peer\" or remove listen")
    return mode, listen, connect


def _endpoints(z: dict, key: str, where: str) -> tuple[str, ...]:
    from fpdd.zenohconf import check_endpoint

    items = _strings(z, key, where)
    for i, item in enumerate(items):
        check_endpoint(item, f"{where}.{key}[{i}]", listen=key == "listen")
    return tuple(items)


def _workers(raw: Any, path: str) -> int | None:
    """``service.workers``: ``"auto"`` (``None``) or 0..256."""
    if raw == "auto":
        return None
    if isinstance(raw, int) and not isinstance(raw, bool) and 0 <= raw <= 256:
        return raw
    raise ConfigError(f"{path}: service.workers: expected \"auto\" or an integer 0..256 "
                      f"(0 = threads in the service's process), got {raw!r}")


def _rigs(doc: dict, path: str) -> tuple[ParsedRig, ...]:
    if "rig" not in doc:
        raise ConfigError(f"{path}: no [[rig]]: at least one rig is needed")
    rigs_doc = doc["rig"]
    if isinstance(rigs_doc, dict):
        raise ConfigError(f"{path}: rig: write [[rig]] (an array of tables), not [rig]")
    if not isinstance(rigs_doc, list):
        raise ConfigError(f"{path}: rig: expected [[rig]] tables, got {rigs_doc!r}")
    if not rigs_doc:
        raise ConfigError(f"{path}: at least one [[rig]] is needed")
    seen: set[str] = set()
    return tuple(parse_rig(r, i, path, seen) for i, r in enumerate(rigs_doc))


# --------------------------------------------------------------------------- [[rig]]

def parse_rig(r: Any, i: int, path: str, seen: set[str]) -> ParsedRig:
    """The ``i``-th ``[[rig]]`` table of ``path``; ``seen``: the names of the rigs before it (a name is unique)."""
    name = _rig_name(r, i, path, seen)
    where = f"{path}: rig {name!r}"
    _check_keys(r, RIG_KEYS, where)
    model = _get(r, "model", str, where, DEFAULT_MODEL)
    params = _quantities(r, "params", where)
    commission = _path(r, "commission", where, "") or None
    commission_s = _number(r, "commission_s", where, None, lo=MIN_COMMISSION_S,
                           what=" seconds (the commissioning fit needs a few periods of the demand)")
    if commission is not None and commission_s is not None:
        raise ConfigError(f"{where}: give either commission (a saved fit) or commission_s (commission on the "
                          "first seconds in service), not both")
    track = tuple(_strings(r, "track", where)) if "track" in r else None
    noise = _quantities(r, "noise", where)
    timing = _timing(r, where)
    baseline = {pname: _band(b, f"{where}.baseline.{pname}")
                for pname, b in _get(r, "baseline", dict, where, {}).items()}
    speed = _number(r, "speed", where, 1.0, lo=0.0, what=" (0 = as fast as possible)")
    if speed != 0 and not SPEED_RANGE[0] <= speed <= SPEED_RANGE[1]:
        raise ConfigError(f"{where}.speed: {speed:g}; expected 0 (as fast as possible) or {SPEED_RANGE[0]:g} to "
                          f"{SPEED_RANGE[1]:g} times real time")
    dbc = _path(r, "dbc", where, "") or None
    col_map = _map(r, where)
    source = _source(r, where, col_map)
    horizon = _number(r, "forecast_horizon_s", where, 3600.0, lo=0.0, lo_open=True,
                      what=" seconds (the early warning's horizon)")
    return ParsedRig(path=path, name=name, model=model, source=source, dbc=dbc, map=col_map, speed=speed,
                     track=track, params=params, baseline=baseline, noise=noise, timing=timing,
                     commission=commission, commission_s=commission_s,
                     signing_key=_get(r, "signing_key", str, where, "") or None, forecast_horizon_s=horizon)


def _rig_name(r: Any, i: int, path: str, seen: set[str]) -> str:
    where = f"{path}: rig[{i}]"
    if not isinstance(r, dict):
        raise ConfigError(f"{where}: expected a table")
    name = _get(r, "name", str, where)
    if len(name) > MAX_RIG_NAME:
        raise ConfigError(f"{where}.name: {name[:20]!r}... has {len(name)} characters, at most {MAX_RIG_NAME}")
    if re.match(RIG_PATTERN, name) is None or name in seen:
        raise ConfigError(f"{where}.name: {name!r} must be unique, non-empty, without '/' or '*' "
                          "(letters, digits, _ . -)")
    seen.add(name)
    return name


def _quantities(r: dict, key: str, where: str) -> dict[str, Quantity]:
    """A table of quantities (``params``, ``noise``): each a finite number or a string, as written."""
    table = _get(r, key, dict, where, {})
    return {k: _quantity(table, k, f"{where}.{key}") for k in table}


def _quantity(d: dict, key: str, where: str) -> Quantity:
    """``d[key]`` as written when it is a string or a finite number."""
    v = d[key]
    if not isinstance(v, str):
        _get(d, key, float, where)
    return v


def _timing(r: dict, where: str) -> Timing | None:
    """The loop's timing of ``controller`` and ``intersample`` (``None``: neither given)."""
    if "controller" not in r and "intersample" not in r:
        return None
    try:
        timing = Timing.parse(_get(r, "controller", str, where, "digital"),
                              _get(r, "intersample", str, where, "") or None)
    except ParameterError as exc:
        raise ConfigError(f"{where}.controller: {exc}") from None
    if timing.rate_hz is not None and timing.rate_hz > MAX_CONTROLLER_HZ:
        raise ConfigError(f"{where}.controller: a digital controller at {timing.rate_hz:g} Hz; at most "
                          f"{MAX_CONTROLLER_HZ:g} Hz (servo-hydraulic controllers run at 1-10 kHz)")
    return timing


def _band(b: Any, bw: str) -> ParsedBand:
    """``[rig.baseline.NAME]`` at ``bw``: its keys and the form of its values (their units and bounds are the
    parameter's, checked by the resolver)."""
    if not isinstance(b, dict):
        raise ConfigError(f"{bw}: expected a table with value and rel_band, or lo and hi")
    _check_keys(b, BASELINE_KEYS, bw)
    if ("lo" in b or "hi" in b) and "rel_band" in b:
        raise ConfigError(f"{bw}: give either rel_band or lo and hi, not both")
    value, lo, hi = (_quantity(b, k, bw) if k in b else None for k in ("value", "lo", "hi"))
    rel_band = _number(b, "rel_band", bw, None, lo=0.0, lo_open=True,
                       what=" (the band is value/(1+rel_band) .. value*(1+rel_band))")
    return ParsedBand(value, rel_band, lo, hi)


def _source(r: dict, where: str, col_map: tuple[str, ...]) -> str:
    """``source``: a log file of a known format, ``can://`` or ``zenoh://``; with ``map``, one whose reader takes
    a map."""
    from replay.factory import FILE_SUFFIXES, URI_SCHEMES
    from replay.formats import suffix_of, takes_map

    source = _path(r, "source", where)
    if not source.strip():
        raise ConfigError(f"{where}.source: expected a log file, can://INTERFACE/CHANNEL or zenoh://KEYEXPR, "
                          "got an empty string")
    if "://" in source:
        scheme = source.split("://", 1)[0].lower()
        if scheme not in URI_SCHEMES or not source.split("://", 1)[1].strip("/"):
            raise ConfigError(f"{where}.source: {source!r} is not can://INTERFACE/CHANNEL or zenoh://KEYEXPR")
        _check_live_source(source, where)
    elif suffix_of(source) not in FILE_SUFFIXES:
        raise ConfigError(f"{where}.source: {source!r} is not a log of a known format "
                          f"({', '.join(FILE_SUFFIXES)}) nor a can:// or zenoh:// URI")
    if col_map and not (source.lower().startswith("can://") or ("://" not in source and takes_map(source))):
        raise ConfigError(f"{where}.map: maps the columns of CSV, text and MATLAB files and the signals of CAN logs "
                          f"and can:// buses; the source {source!r} names its signals itself")
    return source


def _check_live_source(source: str, where: str) -> None:
    """A live source that can be opened: a CAN interface python-can knows; a Zenoh key expression that is
    valid and does not reach the service's own outputs (``fpdd/<rig>/estimate`` ...)."""
    scheme, rest = source.split("://", 1)
    scheme = scheme.lower()
    if scheme == "can":
        from replay.can.bus import check_can_uri

        try:
            check_can_uri(source)
        except Exception as exc:  # SourceError: one line naming the URI and the known interfaces
            raise ConfigError(f"{where}.source: {exc}") from None
    elif scheme == "zenoh":
        import zenoh

        from twin.service.bus import RigKeys

        try:
            key = zenoh.KeyExpr(rest)
        except Exception as exc:  # zenoh.ZError
            raise ConfigError(f"{where}.source: {source!r}: not a valid Zenoh key expression "
                              f"({str(exc).split(' at ', 1)[0]})") from None
        outs = RigKeys("*")
        hit = next((k for k in (outs.estimate, outs.status, outs.alarm, outs.history, outs.twin)
                    if key.intersects(zenoh.KeyExpr(k))), None)
        if hit is not None:
            raise ConfigError(f"{where}.source: {source!r} would read the service's own outputs ({hit}); "
                              "publish the rig's samples on a key of their own, e.g. zenoh://fpdd/RIG/samples")


def _map(r: dict, where: str) -> tuple[str, ...]:
    """``map``: ``["x=pos_mm:mm", ...]`` or ``{x = "pos_mm:mm", ...}`` as ``NAME=COLUMN[:UNIT][*GAIN][+OFFSET]``
    items, checked."""
    if "map" not in r:
        return ()
    raw = r["map"]
    if isinstance(raw, dict):
        items = []
        for k, v in raw.items():
            if not isinstance(v, str):
                raise ConfigError(f"{where}.map.{k}: expected \"COLUMN[:UNIT][*GAIN][+OFFSET]\", got {v!r}")
            items.append(f"{k}={v}")
    else:
        items = _strings(r, "map", where)
    from fpdd.errors import DataError
    from replay.csvio import parse_map

    try:
        parse_map(items, option="map item")
    except DataError as exc:
        raise ConfigError(f"{where}.{exc}") from None
    return tuple(items)


# --------------------------------------------------------------------------- values

def _at_most(v: float, hi: float, where: str, why: str) -> float:
    if v > hi:
        raise ConfigError(f"{where}: {v:g} seconds; at most {hi:g} ({why})")
    return v


def _strings(d: dict, key: str, where: str) -> list[str]:
    items = _get(d, key, list, where, [])
    for i, item in enumerate(items):
        if not isinstance(item, str):
            raise ConfigError(f"{where}.{key}[{i}]: expected a string, got {item!r}")
    return items


def _path(d: dict, key: str, where: str, default: Any = ...) -> Any:
    """A path string: no NUL or other control character, at most MAX_PATH characters, each component at most
    MAX_PATH_COMPONENT bytes (what the operating system would refuse later, refused here with the key)."""
    v = _get(d, key, str, where, default)
    if not isinstance(v, str) or not v:
        return v
    bad = next((c for c in v if ord(c) < 32 or ord(c) == 127), None)
    if bad is not None:
        raise ConfigError(f"{where}.{key}: control character {bad!r} at position {v.index(bad)} of the path; "
                          "expected a file or directory path")
    if len(v) > MAX_PATH:
        raise ConfigError(f"{where}.{key}: path of {len(v)} characters, at most {MAX_PATH}")
    long = next((c for c in v.replace("\\", "/").split("/") if len(c.encode("utf-8")) > MAX_PATH_COMPONENT), None)
    if long is not None:
        raise ConfigError(f"{where}.{key}: a path component of {len(long.encode('utf-8'))} bytes "
                          f"({long[:20]!r}...), at most {MAX_PATH_COMPONENT}")
    return v
