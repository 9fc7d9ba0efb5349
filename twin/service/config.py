"""Rig configuration (``rigs.toml``) for ``twin serve``: which rigs, where their data come from,
which parameters to track, their healthy baselines, and how to reach Zenoh.

Example (every key but ``rig.name`` and ``rig.source`` has a default)::

    [zenoh]                             # optional; with ZENOH_CONFIG=FILE set, only the keys
    mode = "peer"                       #   given here override that file
    listen = ["tcp/127.0.0.1:7447"]     # "client" mode goes through a site router (connect)
    connect = []

    [service]
    journal_dir = "/var/lib/fpdd/journal"  # one SQLite journal per rig: alarms and checkpoints
    out_dir = "/var/lib/fpdd/records"   # MCAP of estimates and alarms (optional)
    estimate_every = 50                 # publish an estimate every N samples
    workers = "auto"                    # worker processes: "auto", 0 = threads in this process, N
    checkpoint_s = 1.0                  # checkpoint each rig's state this often (wall clock)
    block_s = 0.1                       # samples are filtered in blocks of this much time (latency)
    lag_warn_s = 1.0                    # status 'degraded' when a rig is this far behind real time
    stale_s = 1.0                       # a live input quiet this long is 'stale_input'

    [failover]                          # optional: these rigs are shared with other services, one runs
    priority = 100                      #   each, the others stand by (keys: twin/service/ownership.py)

    [[rig]]
    name = "hall1-a"
    model = "..."                       # a registered model the online twin runs (default the product's rig)
    source = "can://socketcan/can0"     # or zenoh://KEYEXPR, or a log file (replayed)
    dbc = ""                            # default: the DBC shipped with replay (relative to this file)
    map = ["x=pos_mm:mm", "t=time:ms"]  # a log's columns (CSV, text, MATLAB) or CAN signals (logs, can://)
                                        #   under other names, units, gains (as --map; or a table:
                                        #   map = { x = "pos_mm:mm", t = "time:ms", u = "vir*35.15N/V" })
    speed = 1.0                         # replay speed for log sources (0 = as fast as possible)
    track = ["Ffric", "CdAleak", "Cd", "zeta", "wn"]
    commission = "commissioning.json"   # a `twin fit --save` file (relative to this file): bands
                                        # centred on the fit, its noise levels and its timing
    # commission_s = 120                # or: commission the rig on its first 120 s in service
                                        # (status 'commissioning', no alarms until the fit is done;
                                        # saved as <journal_dir>/<rig>.commission.json and reused on
                                        # restart; a failed fit falls back to the configured bands)
    controller = "digital"              # the loop's timing: digital, digital:5000, continuous
    intersample = "zoh"                 # logged inputs between samples: zoh, foh, cubic
    forecast_horizon_s = 3600           # early warning when a parameter leaves its band within this
    noise = { x = "2um", pA = "20kPa", pB = "20kPa" }   # sensor noise (learnt online on top)
    [rig.params]                        # known parameters that differ from the model's nominal ones
    KP = 400.0                          # a bare number is SI; or with a unit: A = "2000mm^2"
    [rig.baseline.Ffric]                # healthy band (default: nominal value, the parameter's tracking band)
    value = 50.0                        # SI, or with a unit ("50N"; CdAleak = "0.0033mm^2"); a value outside
    rel_band = 0.3                      #   the parameter's bounds is refused; or lo = ..., hi = ...

Every error is one line naming the file, the key and what was expected; an
unknown key is an error that suggests the closest known one
(``rig 'a': unknown key 'trak' (did you mean 'track'?)``); numbers must be
finite (TOML's ``nan`` and ``inf`` are refused).
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from typing import TYPE_CHECKING, Any

from fpdd.errors import ConfigError, ParameterError
from twin.service.config_values import _check_keys, _get, _number, suggest, unit_number
from twin.models import DEFAULT_MODEL
from twin.online.baseline import Baseline, default_band, default_baseline
from twin.online.events import RIG_PATTERN
from twin.models import REGISTRY, get_model, trackable_models
from twin.models.base import Timing

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

if TYPE_CHECKING:
    from twin.online.commission import Commission
    from twin.service.ownership import FailoverConfig

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

    def source_options(self) -> dict:
        """Reader options of the rig's source from ``dbc`` and ``map``."""
        from replay.formats import CAN_LOG_SUFFIXES

        is_can = self.source.lower().startswith("can://") or self.source.lower().endswith(CAN_LOG_SUFFIXES)
        opts: dict[str, Any] = {"dbc": self.dbc} if self.dbc and is_can else {}  # a DBC decodes CAN frames only
        if self.map:
            from replay.csvio import parse_map

            opts["mapping"] = parse_map(self.map)
        return opts
    forecast_horizon_s: float = 3600.0
    """Horizon of the early warning [s]: ``early`` when a parameter leaves its band within it with probability 0.9."""


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


TOP_KEYS = ("zenoh", "service", "rig", "failover")
ZENOH_KEYS = ("mode", "listen", "connect")
SERVICE_KEYS = ("journal_dir", "out_dir", "estimate_every", "workers", "checkpoint_s", "block_s", "lag_warn_s",
                "stale_s", "signing_keys")
RIG_KEYS = ("name", "model", "source", "dbc", "map", "speed", "track", "params", "baseline", "noise", "controller",
            "intersample", "commission", "commission_s", "signing_key", "forecast_horizon_s")
NOISE_KEYS = ("x", "pA", "pB")
BASELINE_KEYS = ("value", "rel_band", "lo", "hi")


# --------------------------------------------------------------------------- validation helpers

def _si(d: dict, key: str, where: str, pname: str, spec=None, default: Any = ..., positive: bool = False) -> float:
    """``d[key]``: a number (SI) or a string with a unit (``"2000mm^2"``) for parameter ``pname``, in SI; with
    ``spec`` it must lie within the parameter's bounds (a bare number that does not is most often a value in
    display units: the message says how to write one)."""
    v = d.get(key, default)
    if v is ...:
        raise ConfigError(f"{where}: missing key {key!r}")
    if isinstance(v, str):
        from twin.units import to_si

        try:
            v = to_si(pname, v, spec.unit if spec is not None else None)
        except ParameterError as exc:
            reason = str(exc).removeprefix(f"{pname}: ")
            raise ConfigError(f"{where}.{key}: expected a number or a value with a unit, got {d[key]!r}: "
                              f"{reason}") from None
    else:
        v = _get(d, key, float, where, default)
        unit_number(d, key, where, pname, spec)
    if positive and not v > 0:
        raise ConfigError(f"{where}.{key}: must be > 0, got {v:g}")
    if spec is not None and not spec.lo <= v <= spec.hi:
        hint = ""
        if not isinstance(d.get(key), str) and spec.display_unit and spec.lo <= v / spec.display_scale <= spec.hi:
            hint = (f"; a bare number is SI ({spec.unit}): for {v:g} {spec.display_unit} write "
                    f"\"{v:g}{spec.display_unit}\"")
        raise ConfigError(f"{where}.{key}: {v:g} {spec.unit} is outside {pname}'s bounds "
                          f"[{spec.lo:g}, {spec.hi:g}] {spec.unit}{hint}")
    return v


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


def _check_source(source: str, where: str) -> None:
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


def _endpoints(z: dict, key: str, where: str) -> tuple[str, ...]:
    from fpdd.zenohconf import check_endpoint

    items = _strings(z, key, where)
    for i, item in enumerate(items):
        check_endpoint(item, f"{where}.{key}[{i}]", listen=key == "listen")
    return tuple(items)


# --------------------------------------------------------------------------- loading


def load_config(path: str) -> ServiceConfig:
    """Read and validate a rig configuration; errors name the file and the key."""
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
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not a rig configuration: arrays or tables nested too deeply") from None
    return parse_config(doc, path)


def parse_config(doc: dict, path: str = "<config>") -> ServiceConfig:
    _check_keys(doc, TOP_KEYS, path)
    z = _get(doc, "zenoh", dict, path, {})
    s = _get(doc, "service", dict, path, {})
    zw, sw = f"{path}: zenoh", f"{path}: service"
    _check_keys(z, ZENOH_KEYS, zw)
    _check_keys(s, SERVICE_KEYS, sw)
    mode = _get(z, "mode", str, zw, None)
    if mode is not None and mode not in ("peer", "client", "router"):
        raise ConfigError(f"{path}: zenoh.mode must be peer, client or router, got {mode!r}")
    listen = _endpoints(z, "listen", zw)
    connect = _endpoints(z, "connect", zw)
    if mode == "client" and listen:
        raise ConfigError(f"{path}: zenoh.listen: a client cannot listen (got {list(listen)}); "
                          "use mode = \"peer\" or remove listen")
    if "rig" not in doc:
        raise ConfigError(f"{path}: no [[rig]]: at least one rig is needed")
    rigs_doc = doc["rig"]
    if isinstance(rigs_doc, dict):
        raise ConfigError(f"{path}: rig: write [[rig]] (an array of tables), not [rig]")
    if not isinstance(rigs_doc, list):
        raise ConfigError(f"{path}: rig: expected [[rig]] tables, got {rigs_doc!r}")
    if not rigs_doc:
        raise ConfigError(f"{path}: at least one [[rig]] is needed")
    rigs = []
    seen: set[str] = set()
    for i, r in enumerate(rigs_doc):
        rigs.append(_parse_rig(r, i, path, seen))
    rigs = _signing_keys(rigs, _get(s, "signing_keys", str, sw, "") or None, path)
    every = _get(s, "estimate_every", int, sw, 50)
    if every < 1:
        raise ConfigError(f"{path}: service.estimate_every must be >= 1, got {every}")
    if every > 1_000_000:
        raise ConfigError(f"{path}: service.estimate_every: {every} samples; at most 1000000 (an estimate every "
                          "17 min at 1 kHz)")
    workers_raw = s.get("workers", "auto")
    if workers_raw == "auto":
        workers = None
    elif isinstance(workers_raw, int) and not isinstance(workers_raw, bool) and 0 <= workers_raw <= 256:
        workers = workers_raw
    else:
        raise ConfigError(f"{path}: service.workers: expected \"auto\" or an integer 0..256 "
                          f"(0 = threads in the service's process), got {workers_raw!r}")
    journal_dir = _path(s, "journal_dir", sw, os.path.join(".", "fpdd-journal"))
    if not journal_dir.strip():
        raise ConfigError(f"{path}: service.journal_dir: expected a directory path, got an empty string")
    from twin.service.ownership import parse_failover

    failover = parse_failover(doc, path, journal_dir)
    return ServiceConfig(
        path=path, zenoh_mode=mode, listen=listen, connect=connect,
        journal_dir=journal_dir,
        out_dir=_path(s, "out_dir", sw, "") or None,
        estimate_every=every, rigs=tuple(rigs), workers=workers,
        checkpoint_s=_at_most(_number(s, "checkpoint_s", sw, 1.0, lo=0.0, lo_open=True, what=" seconds"),
                              3600.0, f"{sw}.checkpoint_s", "an hour: the state a restart would lose"),
        block_s=_at_most(_number(s, "block_s", sw, 0.1, lo=0.001, what=" seconds"), 10.0, f"{sw}.block_s",
                         "the latency of every estimate and alarm"),
        lag_warn_s=_at_most(_number(s, "lag_warn_s", sw, 1.0, lo=0.0, lo_open=True, what=" seconds"), 86400.0,
                            f"{sw}.lag_warn_s", "a day"),
        stale_s=_at_most(_number(s, "stale_s", sw, 1.0, lo=0.05, what=" seconds"), 86400.0, f"{sw}.stale_s",
                         "a day: a dead input must be noticed"),
        failover=failover,
    )


def _parse_rig(r: Any, i: int, path: str, seen: set[str]) -> RigConfig:
    import re

    from replay.factory import FILE_SUFFIXES, URI_SCHEMES
    from replay.formats import suffix_of, takes_map

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
    where = f"{path}: rig {name!r}"
    _check_keys(r, RIG_KEYS, where)
    model_name = _get(r, "model", str, where, DEFAULT_MODEL)
    if model_name not in REGISTRY or not get_model(model_name).TRACKABLE:
        raise ConfigError(f"{where}.model: {model_name!r} is not a model the online twin runs; it runs "
                          f"{', '.join(trackable_models())}")
    model = get_model(model_name)
    params_doc = _get(r, "params", dict, where, {})
    names = model.params().names
    params: dict[str, Any] = {}
    for k in params_doc:
        if k not in names:
            raise ConfigError(f"{where}.params: unknown parameter {k!r} of model {model_name}{suggest(k, names)}")
        params[k] = _si(params_doc, k, f"{where}.params", k)
    try:
        model.params(**params)
    except ParameterError as exc:
        raise ConfigError(f"{where}.params: {exc}") from None
    commission = _path(r, "commission", where, "") or None
    commission_s = _number(r, "commission_s", where, None, lo=MIN_COMMISSION_S,
                           what=" seconds (the commissioning fit needs a few periods of the demand)")
    if commission is not None and commission_s is not None:
        raise ConfigError(f"{where}: give either commission (a saved fit) or commission_s (commission on the "
                          "first seconds in service), not both")
    com = None
    if commission is not None:
        from twin.online.commission import load_fit

        if not os.path.isabs(commission):
            commission = os.path.join(os.path.dirname(os.path.abspath(path)), commission)
        com = load_fit(commission)
    # a parameter held at exactly 0 (a spring of 0: a free mass, as twin fit --set k=0) is held, not
    # tracked: the twin follows a parameter relative to its value
    known = {**(com.params if com is not None else {}), **params}
    held = tuple(n for n in model.PHENOMENOLOGICAL if known.get(n) == 0 and n not in (com.fitted if com else {}))
    track = tuple(_strings(r, "track", where) or [n for n in model.PHENOMENOLOGICAL if n not in held])
    if "track" in r and not r["track"]:
        raise ConfigError(f"{where}.track: the list is empty; name at least one of "
                          f"{', '.join(model.PHENOMENOLOGICAL)}")
    if not track:
        raise ConfigError(f"{where}.params: every trackable parameter ({', '.join(model.PHENOMENOLOGICAL)}) is held "
                          "at 0; nothing is left to track")
    bad = [t for t in track if t not in model.PHENOMENOLOGICAL]
    if bad:
        raise ConfigError(f"{where}.track: {bad} not among the trackable {', '.join(model.PHENOMENOLOGICAL)}"
                          f"{suggest(bad[0], model.PHENOMENOLOGICAL) if len(bad) == 1 else ''}")
    if len(set(track)) != len(track):
        raise ConfigError(f"{where}.track: {list(track)} names a parameter twice")
    zero = [t for t in track if t in held]
    if zero:
        src = f"params.{zero[0]}" if zero[0] in params else f"the commissioning fit {commission}"
        raise ConfigError(f"{where}.track: {zero[0]} is held at exactly 0 by {src}; a parameter at 0 is not "
                          f"tracked (the twin follows a parameter relative to its value): drop it from track or "
                          f"give it a positive value")
    if com is not None:
        baseline = com.baseline(track)
    else:
        baseline = default_baseline(model_name, params, track)
    noise: dict[str, float] = {}
    measured = tuple(model.FILTER.measures) if model.FILTER is not None else NOISE_KEYS  # the rig model's outputs
    for k, v in _get(r, "noise", dict, where, {}).items():
        if k not in measured:
            raise ConfigError(f"{where}.noise: unknown output {k!r} of the {model_name} model; known: "
                              f"{', '.join(measured)}{suggest(k, measured)}")
        if isinstance(v, str):
            from twin.units import to_si

            try:
                noise[k] = to_si(k, v)
            except ParameterError as exc:
                raise ConfigError(f"{where}.noise.{k}: {exc}") from None
        else:
            noise[k] = _number(r["noise"], k, f"{where}.noise")
        if not noise[k] > 0:
            raise ConfigError(f"{where}.noise.{k}: expected a positive standard deviation (SI or with a unit, "
                              f"e.g. \"2um\"), got {v!r}")
        unit_number(r["noise"], k, f"{where}.noise", k)
    timing = None
    if "controller" in r or "intersample" in r:
        try:
            timing = Timing.parse(_get(r, "controller", str, where, "digital"),
                                  _get(r, "intersample", str, where, "") or None)
        except ParameterError as exc:
            raise ConfigError(f"{where}.controller: {exc}") from None
        if timing.rate_hz is not None and timing.rate_hz > MAX_CONTROLLER_HZ:
            raise ConfigError(f"{where}.controller: a digital controller at {timing.rate_hz:g} Hz; at most "
                              f"{MAX_CONTROLLER_HZ:g} Hz (servo-hydraulic controllers run at 1-10 kHz)")
    for pname, b in _get(r, "baseline", dict, where, {}).items():
        if pname not in track:
            raise ConfigError(f"{where}.baseline.{pname}: not a tracked parameter ({', '.join(track)})"
                              f"{suggest(pname, track) if pname not in model.PHENOMENOLOGICAL else ''}")
        bw = f"{where}.baseline.{pname}"
        if not isinstance(b, dict):
            raise ConfigError(f"{bw}: expected a table with value and rel_band, or lo and hi")
        _check_keys(b, BASELINE_KEYS, bw)
        spec = model.params().spec(pname)
        v = _si(b, "value", bw, pname, spec, baseline[pname].value, positive=True)
        if "lo" in b or "hi" in b:
            if "rel_band" in b:
                raise ConfigError(f"{bw}: give either rel_band or lo and hi, not both")
            lo = _si(b, "lo", bw, pname, spec, positive=True)
            hi = _si(b, "hi", bw, pname, spec, positive=True)
        else:
            rb = _number(b, "rel_band", bw, default_band(model_name, pname), lo=0.0, lo_open=True,
                         what=" (the band is value/(1+rel_band) .. value*(1+rel_band))")
            lo, hi = v / (1 + rb), v * (1 + rb)
        if not lo < v < hi:
            raise ConfigError(f"{bw}: the band [{lo:g}, {hi:g}] must contain the value {v:g}")
        t_lo, t_hi = model.tracking_bounds(model.params(**params), pname)
        if not t_lo < lo or not hi < t_hi:
            side, edge, limit = ("lower", lo, t_lo) if not t_lo < lo else ("upper", hi, t_hi)
            raise ConfigError(f"{bw}: the band's {side} edge {edge:g} is beyond what the twin can estimate "
                              f"({t_lo:g} .. {t_hi:g} SI): that side could never alarm; give a narrower band")
        baseline[pname] = Baseline(v, lo, hi)
    speed = _number(r, "speed", where, 1.0, lo=0.0, what=" (0 = as fast as possible)")
    if speed != 0 and not SPEED_RANGE[0] <= speed <= SPEED_RANGE[1]:
        raise ConfigError(f"{where}.speed: {speed:g}; expected 0 (as fast as possible) or {SPEED_RANGE[0]:g} to "
                          f"{SPEED_RANGE[1]:g} times real time")
    dbc = _path(r, "dbc", where, "") or None
    if dbc is not None:
        if not os.path.isabs(dbc):  # relative to the configuration, as commission
            dbc = os.path.join(os.path.dirname(os.path.abspath(path)), dbc)
        if not os.path.isfile(dbc):
            raise ConfigError(f"{where}.dbc: {dbc} is not a file (a CAN database, .dbc)")
    col_map = _map(r, where)
    source = _path(r, "source", where)
    if not source.strip():
        raise ConfigError(f"{where}.source: expected a log file, can://INTERFACE/CHANNEL or zenoh://KEYEXPR, "
                          "got an empty string")
    if "://" in source:
        scheme = source.split("://", 1)[0].lower()
        if scheme not in URI_SCHEMES or not source.split("://", 1)[1].strip("/"):
            raise ConfigError(f"{where}.source: {source!r} is not can://INTERFACE/CHANNEL or zenoh://KEYEXPR")
        _check_source(source, where)
    elif suffix_of(source) not in FILE_SUFFIXES:
        raise ConfigError(f"{where}.source: {source!r} is not a log of a known format "
                          f"({', '.join(FILE_SUFFIXES)}) nor a can:// or zenoh:// URI")
    if col_map and not (source.lower().startswith("can://") or ("://" not in source and takes_map(source))):
        raise ConfigError(f"{where}.map: maps the columns of CSV, text and MATLAB files and the signals of CAN logs "
                          f"and can:// buses; the source {source!r} names its signals itself")
    horizon = _number(r, "forecast_horizon_s", where, 3600.0, lo=0.0, lo_open=True,
                      what=" seconds (the early warning's horizon)")
    return RigConfig(name, model_name, source, dbc, speed, track, params, baseline, noise, timing, commission,
                     commission_s, tuple(_get(r, "baseline", dict, where, {})),
                     signing_key=_get(r, "signing_key", str, where, "") or None, map=col_map,
                     forecast_horizon_s=horizon)


def _signing_keys(rigs: list[RigConfig], directory: str | None, path: str) -> list[RigConfig]:
    """Each rig's ``signing_key`` (its own, else ``<service.signing_keys>/<rig>.key``), checked by loading it."""
    from twin.service.signing import load_signer

    here = os.path.dirname(os.path.abspath(path))
    out = []
    for r in rigs:
        key = r.signing_key or (os.path.join(directory, f"{r.name}.key") if directory else None)
        if key is not None:
            key = key if os.path.isabs(key) else os.path.join(here, key)
            load_signer(key, r.name)  # one line naming the file now, not when the first alarm is due
            r = dataclasses.replace(r, signing_key=key)
        out.append(r)
    return out


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
    from replay.csvio import parse_map
    from fpdd.errors import DataError

    try:
        parse_map(items, option="map item")
    except DataError as exc:
        raise ConfigError(f"{where}.{exc}") from None
    return tuple(items)


def with_commission_s(cfg: ServiceConfig, seconds: float | None) -> ServiceConfig:
    """``cfg`` with ``commission_s = seconds`` for every rig that has neither ``commission`` nor ``commission_s``
    (``twin serve --commission-s``)."""
    if seconds is None:
        return cfg
    if not (math.isfinite(seconds) and seconds >= MIN_COMMISSION_S):
        raise ConfigError(f"--commission-s: must be >= {MIN_COMMISSION_S:g} seconds, got {seconds:g}")
    rigs = tuple(r if (r.commission or r.commission_s) else dataclasses.replace(r, commission_s=float(seconds))
                 for r in cfg.rigs)
    return dataclasses.replace(cfg, rigs=rigs)
