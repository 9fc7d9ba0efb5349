"""Events the twin publishes: alarms, estimates and service status.

Each event is a frozen dataclass with ``to_dict()`` / ``from_dict()`` and a
JSON schema (draft 2020-12, a plain ``dict``) in its ``SCHEMA`` class
attribute. The same schema drives validation: ``from_dict`` checks a decoded
payload against it and raises :class:`~twin.errors.DataError` with a message
that names the event, the field, the value and what was expected, e.g.::

    AlarmEvent.level: 'alrm' is not one of ['ok', 'warning', 'alarm', 'early']

Construction validates too (``__post_init__``), so an event that exists is a
valid event. Unknown extra fields in a payload are ignored (a tolerant reader:
a newer twin may add fields without breaking older subscribers).

Time convention: ``t_ns`` is integer nanoseconds of the ingest clock (Unix
epoch for a live rig, the log's own time for a replay); ``t_s`` is float
seconds from the start of the record. JSON payloads never carry NaN or
infinity (``to_json`` refuses them).

``AlarmEvent.seq`` is the per-rig sequence number assigned by the journal
(:class:`twin.service.journal.AlarmJournal`): 1, 2, 3, ... without gaps. ``seq=0``
means "not yet journaled"; only the journal turns it into a real number, and
an alarm with ``seq=0`` is never serialised for the bus (``from_dict``
requires ``seq >= 1``).
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any, ClassVar, Self

from replay import jsonio
from twin.errors import DataError
from twin.models import DEFAULT_MODEL
from datetime import UTC

__all__ = [
    "ALARM_KINDS",
    "ALARM_LEVELS",
    "EVENT_LEVELS",
    "SERVICE_STATES",
    "AlarmEvent",
    "AlarmIdentity",
    "EstimateEncoder",
    "EstimateEvent",
    "ParamEstimate",
    "StatusEvent",
    "event_to_json",
    "interval95",
    "validate",
]

ALARM_LEVELS: tuple[str, ...] = ("ok", "warning", "alarm")
"""Levels of a drift alarm, in increasing severity."""

EVENT_LEVELS: tuple[str, ...] = (*ALARM_LEVELS, "early")
"""Levels an alarm event may carry: the drift test's, and ``early``, the early warning of
:mod:`twin.online.forecast` (the parameter is still in its band, but forecast to leave it within the horizon)."""

ALARM_KINDS: tuple[str, ...] = ("raised", "escalated", "returned")
"""What happened: a level left ``ok`` (raised), went from warning to alarm
(escalated), or came back down (returned, to ``warning`` or ``ok``)."""

SERVICE_STATES: tuple[str, ...] = (
    "starting", "commissioning", "running", "degraded", "stale_input", "finished", "failed", "stopped",
)
"""Life-cycle states of a twin service for one rig: ``starting``; ``commissioning`` (gathering its
first seconds for the commissioning fit, or fitting them: no alarms yet; counters
``commission_ms`` / ``commission_needed_ms``); ``running``;
``degraded`` (running, but behind real time or unable to journal: the message
says which); ``stale_input`` (no sample for a while: the rig waits, counter
``stale_ms`` says how long); ``finished`` (a replayed log ended); ``failed``
(an unrecoverable error, named in the message; the service exits non-zero);
``stopped`` (told to stop)."""

INT64_MAX = 2**63 - 1
"""Largest ``t_ns`` (and counter): times are int64 nanoseconds everywhere (numpy, SQLite, MCAP)."""

RIG_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$"
"""A rig id is one Zenoh key chunk: letters, digits, ``_ . -`` (no ``/ * $ ? # @``)."""

NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*$"
"""Parameter and counter names are identifiers (``Fc``, ``Kleak``, ``omega_v``)."""

STATUS_PATTERN = r"^[a-z][a-z0-9_]*$"
"""Filter and parameter statuses are lower-case words (``ok``, ``frozen``, ``unresolved``)."""


# --------------------------------------------------------------------------- validation

_TYPE_NAMES = {
    "object": "an object",
    "string": "a string",
    "integer": "an integer",
    "number": "a finite number",
    "null": "null",
}


def _is_type(value: Any, type_name: str) -> bool:
    if type_name == "object":
        return isinstance(value, Mapping)
    if type_name == "string":
        return isinstance(value, str)
    if type_name == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if type_name == "number":
        return (
            isinstance(value, (int, float))
            and not isinstance(value, bool)
            and math.isfinite(value)
        )
    if type_name == "null":
        return value is None
    raise ValueError(f"schema uses unsupported type {type_name!r}")


def validate(value: Any, schema: Mapping[str, Any], where: str) -> None:
    """Check ``value`` against the subset of JSON Schema the event schemas use.

    Supported keywords: ``type`` (a name or a list of names), ``enum``,
    ``minimum``, ``maximum``, ``minLength``, ``pattern``, ``properties``, ``required``,
    ``additionalProperties`` (a schema) and ``propertyNames``. Numbers must be
    finite; booleans are not numbers.

    :param value: the decoded JSON value.
    :param schema: the schema (or sub-schema) to check against.
    :param where: the dotted path used in messages, e.g. ``"AlarmEvent.level"``.
    :raises DataError: naming ``where``, the value and what was expected.
    """
    types = schema.get("type")
    if types is not None:
        names = [types] if isinstance(types, str) else list(types)
        if not any(_is_type(value, t) for t in names):
            expected = " or ".join(_TYPE_NAMES[t] for t in names)
            raise DataError(f"{where}: {value!r} must be {expected}")
    if "enum" in schema and value not in schema["enum"]:
        raise DataError(f"{where}: {value!r} is not one of {list(schema['enum'])}")
    if "minimum" in schema and isinstance(value, (int, float)) and value < schema["minimum"]:
        raise DataError(f"{where}: {value!r} must be >= {schema['minimum']}")
    if "maximum" in schema and isinstance(value, (int, float)) and value > schema["maximum"]:
        raise DataError(f"{where}: {value!r} must be <= {schema['maximum']}")
    if isinstance(value, str):
        if "minLength" in schema and len(value) < schema["minLength"]:
            raise DataError(f"{where}: {value!r} must have at least {schema['minLength']} characters")
        if "pattern" in schema and re.search(schema["pattern"], value) is None:
            raise DataError(f"{where}: {value!r} does not match {schema['pattern']}")
    if isinstance(value, Mapping):
        for name in schema.get("required", ()):
            if name not in value:
                raise DataError(f"{where}.{name}: missing (required field)")
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        names_schema = schema.get("propertyNames")
        for name, item in value.items():
            if names_schema is not None:
                validate(name, names_schema, f"{where} key")
            if name in properties:
                validate(item, properties[name], f"{where}.{name}")
            elif isinstance(extra, Mapping):
                validate(item, extra, f"{where}.{name}")


def _check(cls_name: str, schema: Mapping[str, Any], data: Mapping[str, Any]) -> None:
    validate(data, schema, cls_name)


def _as_mapping(data: Any, cls_name: str) -> Mapping[str, Any]:
    if not isinstance(data, Mapping):
        raise DataError(f"{cls_name}: expected a JSON object, got {type(data).__name__}")
    return data


def format_alarm(event: AlarmEvent, *, model: str = DEFAULT_MODEL, wall_clock: bool = True) -> str:
    """One line a person reads: values in the parameter's display unit (``43 Hz``, ``0.0033 mm^2``).

    The machine outputs (JSON, MCAP, Zenoh) stay SI; this is the one formatter of
    every console and log line about an alarm.
    """
    from datetime import datetime

    from twin.models import get_model

    show: Callable[[float], str]
    try:
        show = get_model(model).params(effects=()).spec(event.parameter).show
    except Exception:  # a parameter of another model or an effect: SI with no unit rather than nothing
        def show(v: float) -> str:
            return f"{v:.6g}"

    def short(v: float) -> str:
        if not math.isfinite(v):
            return "n/a"
        text = show(float(f"{v:.4g}"))
        return text

    when = ""
    wall = event.wall_ns if event.wall_ns is not None else (  # when raised; else an epoch record time after 2000
        event.t_ns if event.t_ns >= 946_684_800 * 10**9 else None)
    if wall_clock and wall is not None:
        stamp = datetime.fromtimestamp(wall / 1e9, tz=UTC)
        when = stamp.isoformat(timespec="milliseconds").replace("+00:00", "Z") + " "
    text = (f"{when}{event.rig} #{event.seq} t={event.t_s:.3f} s {event.level.upper():7s} {event.kind:9s} "
            f"{event.parameter} = {short(event.estimate)} ± {short(event.std)} "
            f"(baseline {short(event.baseline)}, band {short(event.band_lo)} .. {short(event.band_hi)}, "
            f"statistic {event.statistic:.3g})")
    return f"{text} {event.message}" if event.message else text


def _si_unit(parameter: str) -> str:
    """The SI unit of a parameter of any model (``"1"`` if unknown)."""
    from twin.units import _known_units

    return _known_units().get(parameter, "1")


@functools.cache
def _known_displays() -> dict[str, tuple[str, str, float]]:
    """Parameter name -> (SI unit, display unit, display scale) over every model's parameters."""
    from twin.models import MODELS, get_model

    out: dict[str, tuple[str, str, float]] = {}
    for name in MODELS:
        for s in get_model(name).kernel_specs:
            out.setdefault(s.name, (s.unit, s.display_unit or s.unit, float(s.display_scale)))
    return out


def display_of(parameter: str, si_unit: str) -> tuple[str, float]:
    """``(display unit, scale)`` of a parameter known to the models with this SI unit (value in the display
    unit = SI value x scale, e.g. ``("Hz", 1/(2 pi))`` for ``wn``); ``(si_unit, 1.0)`` otherwise."""
    known = _known_displays().get(parameter)
    return (known[1], known[2]) if known is not None and known[0] == si_unit else (si_unit, 1.0)


def _scaled(x: float | None, scale: float) -> float | None:
    return None if x is None else x * scale


def event_to_json(event: AlarmEvent | EstimateEvent | StatusEvent) -> str:
    """Serialise an event to compact JSON (sorted keys, no NaN/inf)."""
    return jsonio.dumps(event.to_dict(), indent=None, sort_keys=True)


def _num(description: str, **extra: Any) -> dict[str, Any]:
    return {"type": "number", "description": description, **extra}


# --------------------------------------------------------------------------- alarms

_ALARM_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "fpdd-twin/alarm-event.schema.json",
    "title": "AlarmEvent",
    "description": "A drift alarm on one phenomenological parameter of one rig "
    "(key fpdd/<rig>/alarm, and replies on fpdd/<rig>/alarm/history).",
    "type": "object",
    "required": [
        "rig", "parameter", "level", "kind", "t_ns", "t_s", "estimate", "std",
        "baseline", "band_lo", "band_hi", "seq", "statistic", "message", "unit", "wall_ns",
    ],
    "properties": {
        "rig": {"type": "string", "pattern": RIG_PATTERN, "description": "rig id"},
        "parameter": {"type": "string", "pattern": NAME_PATTERN, "description": "parameter name"},
        "level": {"type": "string", "enum": list(EVENT_LEVELS), "description": "level after this event"},
        "kind": {"type": "string", "enum": list(ALARM_KINDS), "description": "transition"},
        "t_ns": {"type": "integer", "minimum": 0, "maximum": INT64_MAX, "description": "ingest time [ns]"},
        "t_s": _num("time from the start of the record [s]"),
        "estimate": _num("parameter estimate, SI unit of the parameter"),
        "std": _num("the filter's standard deviation of the estimate under its drift model (the scale the drift "
                    "test standardises by), same unit", minimum=0),
        "baseline": _num("healthy baseline value, same unit"),
        "band_lo": _num("lower edge of the healthy band, same unit"),
        "band_hi": _num("upper edge of the healthy band, same unit"),
        "seq": {"type": "integer", "minimum": 1, "description": "per-rig sequence number, 1, 2, 3, ... without gaps"},
        "statistic": _num("value of the sequential test (CUSUM/GLR) at this event"),
        "message": {"type": "string", "description": "one human-readable line"},
        "unit": {"type": "string", "description": "SI unit of estimate, std, baseline and band, e.g. 'N', "
                                                  "'m^2', 'rad/s', '1'"},
        "signature": {"type": "string", "description": "optional: base64 Ed25519 signature of the rig's key "
                      "over the canonical JSON of every other field (twin.service.signing)"},
        "wall_ns": {"type": ["integer", "null"], "minimum": 0, "maximum": INT64_MAX,
                    "description": "wall-clock time the twin journaled the alarm [ns since the Unix epoch] (beside "
                    "t_ns, the record's time: a replayed log's alarms are raised now about then); null: unknown"},
    },
}


class _FromJson:
    """``from_dict`` shared by the event classes: validate against ``SCHEMA``, then build."""

    __slots__ = ()
    SCHEMA: ClassVar[dict[str, Any]]

    @classmethod
    def from_dict(cls, data: Any) -> Self:
        """Build and validate an event from a decoded JSON payload.

        :raises DataError: naming the field that does not validate.
        """
        data = _as_mapping(data, cls.__name__)
        _check(cls.__name__, cls.SCHEMA, data)
        import dataclasses

        optional = {f.name for f in dataclasses.fields(cls)} - set(cls.SCHEMA["required"])  # type: ignore[arg-type]
        return cls(**{name: data[name] for name in cls.SCHEMA["required"]},
                   **{name: data[name] for name in optional if name in data})


@dataclass(frozen=True, slots=True)
class AlarmIdentity:
    """What makes an alarm the same alarm: rig, parameter, level, kind and the sample time.

    The detector is deterministic, so a rig whose log is processed again (a
    restart before the last checkpoint, a replay of the same log) raises the
    same transitions at the same sample times; the journal keeps one alarm per
    identity, whatever its sequence number would have been.
    """

    rig: str
    parameter: str
    level: str
    kind: str
    t_ns: int

    def __str__(self) -> str:
        return f"{self.rig}/{self.parameter} {self.kind} {self.level} at t_ns={self.t_ns}"


@dataclass(frozen=True, slots=True)
class AlarmEvent(_FromJson):
    """A change of alarm level of one parameter of one rig.

    :ivar rig: rig id (one Zenoh key chunk, see :data:`RIG_PATTERN`).
    :ivar parameter: parameter name, e.g. ``"Kleak"``.
    :ivar level: level after the event, one of :data:`EVENT_LEVELS`.
    :ivar kind: ``raised`` (left ok), ``escalated`` (warning to alarm) or ``returned``.
    :ivar t_ns: ingest time of the sample that triggered the event [ns].
    :ivar t_s: time from the start of the record [s].
    :ivar estimate: the parameter estimate [SI unit of the parameter].
    :ivar std: its standard deviation from the filter's covariance, under the filter's drift model (the
        scale the drift test standardises by) [same unit].
    :ivar baseline: the healthy baseline [same unit].
    :ivar band_lo: lower edge of the healthy band [same unit].
    :ivar band_hi: upper edge of the healthy band [same unit].
    :ivar statistic: value of the sequential test when the event fired [-].
    :ivar message: one human-readable line.
    :ivar seq: per-rig sequence number assigned by the journal; 0 = not journaled yet.
    :ivar signature: base64 Ed25519 signature of the rig's key over every other field
        (:mod:`twin.service.signing`); ``""``: unsigned (the field is then left out of the payload).
    :ivar wall_ns: wall-clock time the journal recorded it [ns since the epoch]; ``None``: not journaled or unknown.
    """

    rig: str
    parameter: str
    level: str
    kind: str
    t_ns: int
    t_s: float
    estimate: float
    std: float
    baseline: float
    band_lo: float
    band_hi: float
    statistic: float
    message: str = ""
    seq: int = 0
    unit: str = ""
    signature: str = ""
    wall_ns: int | None = None

    SCHEMA: ClassVar[dict[str, Any]] = _ALARM_SCHEMA

    def __post_init__(self) -> None:
        if not self.unit:  # the SI unit of the parameter, named beside every value on the wire
            object.__setattr__(self, "unit", _si_unit(self.parameter))
        data = self.to_dict()
        # seq 0 (not journaled yet) is legal in memory, never on the wire.
        _check("AlarmEvent", self.SCHEMA, {**data, "seq": self.seq or 1})
        if self.band_lo > self.band_hi:
            raise DataError(
                f"AlarmEvent.band_lo: {self.band_lo!r} must be <= band_hi ({self.band_hi!r})"
            )
        if self.kind in ("raised", "escalated") and self.level == "ok":
            raise DataError(f"AlarmEvent.level: 'ok' is not a possible level for kind {self.kind!r}")
        if self.kind == "escalated" and self.level != "alarm":
            raise DataError(f"AlarmEvent.level: {self.level!r} must be 'alarm' for kind 'escalated'")

    def to_dict(self) -> dict[str, Any]:
        """The event as a JSON-ready dict (the payload of ``fpdd/<rig>/alarm``)."""
        data = {
            "rig": self.rig,
            "parameter": self.parameter,
            "level": self.level,
            "kind": self.kind,
            "t_ns": self.t_ns,
            "t_s": self.t_s,
            "estimate": self.estimate,
            "std": self.std,
            "baseline": self.baseline,
            "band_lo": self.band_lo,
            "band_hi": self.band_hi,
            "seq": self.seq,
            "statistic": self.statistic,
            "message": self.message,
            "unit": self.unit,
            "wall_ns": self.wall_ns,
        }
        if self.signature:  # an unsigned alarm's payload is as before signatures existed
            data["signature"] = self.signature
        return data

    @classmethod
    def from_dict(cls, data: Any) -> Self:
        """As :meth:`_FromJson.from_dict`; an alarm journaled before units were named gets its parameter's, one
        journaled before wall-clock times were kept ``wall_ns=None``."""
        data = _as_mapping(data, cls.__name__)
        if "unit" not in data and isinstance(data.get("parameter"), str):
            data = {**data, "unit": _si_unit(data["parameter"])}
        if "wall_ns" not in data:  # journaled before wall-clock times were kept: unknown
            data = {**data, "wall_ns": None}
        # slots dataclass: no zero-argument super
        return _FromJson.from_dict.__func__(cls, data)  # type: ignore[attr-defined]

    def with_seq(self, seq: int) -> Self:
        """A copy carrying sequence number ``seq``."""
        return replace(self, seq=seq)

    @property
    def identity(self) -> AlarmIdentity:
        """(rig, parameter, level, kind, t_ns): equal for the same alarm raised twice."""
        return AlarmIdentity(self.rig, self.parameter, self.level, self.kind, self.t_ns)


# --------------------------------------------------------------------------- estimates

_PARAM_ESTIMATE_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["value", "std", "unit"],
    "properties": {
        "value": _num("estimate in the SI unit given by 'unit'"),
        "std": _num("standard deviation of the estimate's error while the parameter holds still, same unit",
                    minimum=0),
        "unit": {"type": "string", "description": "SI unit of every number of the parameter, e.g. 'N', "
                                                  "'m^3/(s*Pa)', '1', 'rad/s'"},
        "lo95": _num("lower end of the 95 % interval, same unit (log-normal for a positive value: "
                     "value*exp(-1.96 std/value), else value - 1.96 std)"),
        "hi95": _num("upper end of the 95 % interval, same unit"),
        "band_lo": {"type": ["number", "null"], "description": "lower edge of the healthy band, same unit "
                                                               "(null: no band)"},
        "band_hi": {"type": ["number", "null"], "description": "upper edge of the healthy band, same unit"},
        "baseline": {"type": ["number", "null"], "description": "healthy baseline value, same unit"},
        "display": {
            "type": "object",
            "required": ["unit", "value", "lo95", "hi95"],
            "description": "the same numbers in the display unit people read (twin params: wn in Hz, CdAleak in "
                           "mm^2): SI value x the parameter's display scale; null stays null",
            "properties": {
                "unit": {"type": "string", "description": "display unit, e.g. 'Hz', 'mm^2', '1'"},
                "value": _num("estimate, display unit"),
                "lo95": _num("lower end of the 95 % interval, display unit"),
                "hi95": _num("upper end of the 95 % interval, display unit"),
                "band_lo": {"type": ["number", "null"], "description": "lower edge of the healthy band, display unit"},
                "band_hi": {"type": ["number", "null"], "description": "upper edge of the healthy band, display unit"},
                "baseline": {"type": ["number", "null"], "description": "healthy baseline value, display unit"},
            },
        },
    },
}

Z95 = 1.959963984540054
"""The two-sided 95 % quantile of the standard normal."""


def interval95(value: float, std: float) -> tuple[float, float]:
    """The 95 % interval of an estimate: log-normal for a positive value (the tracker works in log coordinates),
    ``value*exp(+-1.96 std/value)``; symmetric ``value +- 1.96 std`` otherwise (and for std > 25 value)."""
    if value > 0 and std <= 25.0 * value:  # beyond, exp(1.96 std/value) says nothing and overflows soon
        rel = Z95 * std / value
        return value * math.exp(-rel), value * math.exp(rel)
    return value - Z95 * std, value + Z95 * std


def _band(band: Any) -> tuple[float | None, float | None, float | None]:
    """``(lo, hi, baseline)`` of a band given as a Baseline, ``(lo, hi)``, ``(lo, hi, baseline)`` or ``None``."""
    if band is None:
        return None, None, None
    if hasattr(band, "lo"):
        return float(band.lo), float(band.hi), float(band.value)
    lo, hi, *rest = band
    return (None if lo is None else float(lo), None if hi is None else float(hi),
            float(rest[0]) if rest and rest[0] is not None else None)


_ESTIMATE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "fpdd-twin/estimate-event.schema.json",
    "title": "EstimateEvent",
    "description": "The tracked parameters of one rig at one instant (key fpdd/<rig>/estimate).",
    "type": "object",
    "required": ["rig", "t_ns", "t_s", "params", "nis", "status"],
    "properties": {
        "rig": {"type": "string", "pattern": RIG_PATTERN},
        "t_ns": {"type": "integer", "minimum": 0, "maximum": INT64_MAX, "description": "ingest time [ns]"},
        "t_s": _num("time from the start of the record [s]"),
        "params": {
            "type": "object",
            "propertyNames": {"pattern": NAME_PATTERN},
            "additionalProperties": _PARAM_ESTIMATE_SCHEMA,
            "description": "parameter name -> {value, std, lo95, hi95, band_lo, band_hi, baseline, unit} (SI) "
                           "and display {unit, value, lo95, hi95, band_lo, band_hi, baseline} (display unit)",
        },
        "nis": {"type": ["number", "null"], "minimum": 0, "description": "normalised innovation squared of this step, null before the first update"},
        "status": {"type": "string", "pattern": STATUS_PATTERN, "description": "filter status: ok, gated, repaired_covariance, stale_input, ..."},
    },
}


@dataclass(frozen=True, slots=True)
class ParamEstimate:
    """One tracked parameter: value and standard deviation in SI ``unit``, and the rig's healthy band
    (``band_lo``, ``band_hi``, ``baseline``; ``None`` when the twin has none). Its 95 % interval is
    :func:`interval95` of value and std (:attr:`lo95`, :attr:`hi95`). ``display_unit`` and ``display_scale``
    (default: the parameter's own, :func:`display_of`) give the ``display`` copy of the numbers."""

    value: float
    std: float
    unit: str
    band_lo: float | None = None
    band_hi: float | None = None
    baseline: float | None = None
    name: str = field(default="", compare=False)
    display_unit: str = ""
    display_scale: float = 1.0

    def __post_init__(self) -> None:
        if not self.display_unit:
            du, sc = display_of(self.name, self.unit) if self.name else (self.unit, 1.0)
            object.__setattr__(self, "display_unit", du)
            object.__setattr__(self, "display_scale", sc)
        _check("ParamEstimate", _PARAM_ESTIMATE_SCHEMA, self.to_dict())

    @property
    def lo95(self) -> float:
        return interval95(self.value, self.std)[0]

    @property
    def hi95(self) -> float:
        return interval95(self.value, self.std)[1]

    def to_dict(self) -> dict[str, Any]:
        """``{"value", "std", "lo95", "hi95", "band_lo", "band_hi", "baseline", "unit"}`` (SI, ``unit`` names it)
        and ``display``: ``{"unit", "value", "lo95", "hi95", "band_lo", "band_hi", "baseline"}`` in the display
        unit (SI x ``display_scale``)."""
        lo, hi = interval95(self.value, self.std)
        k = self.display_scale
        return {"value": self.value, "std": self.std, "lo95": lo, "hi95": hi, "band_lo": self.band_lo,
                "band_hi": self.band_hi, "baseline": self.baseline, "unit": self.unit,
                "display": {"unit": self.display_unit, "value": self.value * k, "lo95": lo * k, "hi95": hi * k,
                            "band_lo": _scaled(self.band_lo, k), "band_hi": _scaled(self.band_hi, k),
                            "baseline": _scaled(self.baseline, k)}}


@dataclass(frozen=True, slots=True)
class EstimateEvent(_FromJson):
    """The parameter estimates of one rig at one instant.

    :ivar rig: rig id.
    :ivar t_ns: ingest time [ns].
    :ivar t_s: time from the start of the record [s].
    :ivar params: parameter name -> :class:`ParamEstimate` (read-only mapping;
        plain ``{"value", "std", "unit"}`` dicts, with ``band_lo``, ``band_hi``, ``baseline`` if known, are
        accepted and converted; ``lo95``/``hi95`` and the ``display`` numbers in them are ignored: they follow
        from value, std and the display unit).
    :ivar nis: normalised innovation squared of the step, ``None`` before the first update.
    :ivar status: filter status (``ok``, ``gated``, ``repaired_covariance``, ``stale_input``, ...).
    """

    rig: str
    t_ns: int
    t_s: float
    params: Mapping[str, ParamEstimate]
    nis: float | None = None
    status: str = "ok"

    SCHEMA: ClassVar[dict[str, Any]] = _ESTIMATE_SCHEMA

    def __post_init__(self) -> None:
        if not isinstance(self.params, Mapping):
            raise DataError(f"EstimateEvent.params: {self.params!r} must be an object")
        converted: dict[str, ParamEstimate] = {}
        for name, item in self.params.items():
            if isinstance(item, ParamEstimate):
                converted[name] = item
            elif isinstance(item, Mapping):
                validate(item, _PARAM_ESTIMATE_SCHEMA, f"EstimateEvent.params.{name}")
                du, sc = _display_of_dict(name, item)
                converted[name] = ParamEstimate(item["value"], item["std"], item["unit"], item.get("band_lo"),
                                                item.get("band_hi"), item.get("baseline"), name, du, sc)
            else:
                raise DataError(f"EstimateEvent.params.{name}: {item!r} must be an object")
        object.__setattr__(self, "params", MappingProxyType(converted))
        _check("EstimateEvent", self.SCHEMA, self.to_dict())

    @classmethod
    def of_tracker(cls, rig: str, t_ns: int, t_s: float, names: tuple[str, ...], values, stds,
                   units: tuple[str, ...], nis: float | None, status: str, bands: Mapping | None = None,
                   displays: tuple[tuple[str, float], ...] | None = None) -> Self:
        """An estimate from the tracker's arrays, built without the schema walk when every number is finite.

        ``bands``: parameter name -> its healthy band (a Baseline, ``(lo, hi)`` or ``(lo, hi, baseline)``, SI).
        ``displays``: per parameter ``(display unit, scale)`` (the tracker's ``displays``; default
        :func:`display_of`).

        The service builds one per published estimate of every rig (20 per
        second per rig by default); the full validation of ``__init__`` is kept
        for anything unusual (a non-finite value, a negative std), which then
        raises as usual.
        """
        vals = [float(v) for v in values]
        sds = [float(v) for v in stds]
        bs = [_band((bands or {}).get(n)) for n in names]
        ds = tuple(displays) if displays is not None else tuple(display_of(n, u) for n, u in zip(names, units))
        if (not all(math.isfinite(v) for v in vals) or not all(math.isfinite(v) and v >= 0 for v in sds)
                or not 0 <= t_ns <= INT64_MAX or not math.isfinite(t_s)
                or (nis is not None and not (math.isfinite(nis) and nis >= 0))):
            plain: dict[str, Any] = {}
            for n, v, sd, u, b, d in zip(names, vals, sds, units, bs, ds):
                item = {"value": v, "std": sd, "unit": u, "band_lo": b[0], "band_hi": b[1], "baseline": b[2]}
                validate(item, _PARAM_ESTIMATE_SCHEMA, f"EstimateEvent.params.{n}")  # named as the event would
                plain[n] = ParamEstimate(v, sd, u, b[0], b[1], b[2], n, d[0], d[1])
            return cls(rig, t_ns, t_s, plain, nis, status)
        ev = object.__new__(cls)
        params = {}
        for n, v, sd, u, b, d in zip(names, vals, sds, units, bs, ds):
            p = object.__new__(ParamEstimate)
            for field_name, x in (("value", v), ("std", sd), ("unit", u), ("band_lo", b[0]), ("band_hi", b[1]),
                                  ("baseline", b[2]), ("name", n), ("display_unit", d[0]),
                                  ("display_scale", float(d[1]))):
                object.__setattr__(p, field_name, x)
            params[n] = p
        for name, value in (("rig", rig), ("t_ns", int(t_ns)), ("t_s", float(t_s)),
                            ("params", MappingProxyType(params)), ("nis", nis), ("status", status)):
            object.__setattr__(ev, name, value)
        return ev

    def to_dict(self) -> dict[str, Any]:
        """The event as a JSON-ready dict (the payload of ``fpdd/<rig>/estimate``)."""
        return {
            "rig": self.rig,
            "t_ns": self.t_ns,
            "t_s": self.t_s,
            "params": {name: p.to_dict() for name, p in self.params.items()},
            "nis": self.nis,
            "status": self.status,
        }

    def with_bands(self, bands: Mapping) -> Self:
        """A copy whose parameters without a band take theirs from ``bands`` (name -> Baseline or
        ``(lo, hi[, baseline])``, SI)."""
        params = {}
        for name, p in self.params.items():
            b = _band(bands.get(name)) if p.band_lo is None and p.band_hi is None else None
            params[name] = replace(p, band_lo=b[0], band_hi=b[1], baseline=b[2]) if b and b[0] is not None else p
        return replace(self, params=params)


def _display_of_dict(name: str, item: Mapping[str, Any]) -> tuple[str, float]:
    """``(display unit, scale)`` of a parameter's dict: its ``display.unit`` with the parameter's own scale for
    that unit (1 for the SI unit; else the ratio of the dict's display value to its value); the parameter's
    own (:func:`display_of`) when the dict has none."""
    own = display_of(name, item["unit"])
    d = item.get("display")
    if not isinstance(d, Mapping) or not isinstance(d.get("unit"), str) or not d["unit"]:
        return own
    unit = d["unit"]
    if unit == own[0]:
        return own
    if unit == item["unit"]:
        return unit, 1.0
    v, dv = item["value"], d.get("value")
    if isinstance(dv, (int, float)) and not isinstance(dv, bool) and math.isfinite(dv) and v != 0:
        return unit, float(dv) / float(v)
    return unit, 1.0


def _json_number(x: float | None) -> str:
    """A number as ``json.dumps`` of a finite float writes it; ``null`` for ``None`` or non-finite."""
    return "null" if x is None or not math.isfinite(x) else repr(float(x))


class EstimateEncoder:
    """The ``EstimateEvent`` payload of one rig's tracker written straight from its numbers: the very text of
    ``event_to_json(EstimateEvent.of_tracker(rig, ..., bands=bands))`` (sorted keys, compact, floats by
    ``repr``, intervals and bands included) without building the event, for the service's hot path."""

    def __init__(self, rig: str, names: tuple[str, ...], units: tuple[str, ...], bands: Mapping | None = None,
                 displays: tuple[tuple[str, float], ...] | None = None):
        """``displays``: per parameter ``(display unit, scale)`` as :meth:`EstimateEvent.of_tracker` takes them."""
        import json

        def text(v: str) -> str:  # a JSON string constant inside a %-format
            return json.dumps(v).replace("%", "%%")

        self.names = tuple(names)
        self._order = sorted(range(len(names)), key=lambda j: names[j])
        ds = tuple(displays) if displays is not None else tuple(display_of(n, u) for n, u in zip(names, units))
        self._scales = [float(ds[j][1]) for j in self._order]
        parts = []
        for j in self._order:
            lo, hi, base = _band((bands or {}).get(names[j]))
            k = float(ds[j][1])
            shown = (f'"display":{{"band_hi":{_json_number(_scaled(hi, k))},"band_lo":{_json_number(_scaled(lo, k))},'
                     f'"baseline":{_json_number(_scaled(base, k))},"hi95":%r,"lo95":%r,"unit":{text(ds[j][0])},'
                     '"value":%r}')
            parts.append(f'{text(names[j])}:{{"band_hi":{_json_number(hi)},"band_lo":{_json_number(lo)},'
                         f'"baseline":{_json_number(base)},{shown},"hi95":%r,"lo95":%r,"std":%r,'
                         f'"unit":{text(units[j])},"value":%r}}')
        self._fmt = ('{"nis":%s,"params":{' + ",".join(parts)
                     + f'}},"rig":{text(rig)},"status":"%s","t_ns":%d,"t_s":%r}}')

    def __call__(self, t_ns: int, t_s: float, values, stds, nis: float, status: str) -> str | None:
        """The payload; ``None`` for anything the schema checks would refuse (the event path then runs)."""
        vals = values.tolist() if hasattr(values, "tolist") else list(values)
        sds = stds.tolist() if hasattr(stds, "tolist") else list(stds)
        if not (all(map(math.isfinite, vals)) and all(math.isfinite(v) and v >= 0 for v in sds) and t_ns >= 0
                and math.isfinite(t_s) and not nis < 0):
            return None
        nums: list[Any] = ["null" if not math.isfinite(nis) else repr(nis)]
        for j, k in zip(self._order, self._scales):
            lo, hi = interval95(vals[j], sds[j])
            v = vals[j]
            shown = (hi * k, lo * k, v * k)
            if not (math.isfinite(lo) and math.isfinite(hi) and all(map(math.isfinite, shown))):
                return None
            nums += [*shown, hi, lo, sds[j], v]
        return self._fmt % (*nums, status, t_ns, t_s)


# --------------------------------------------------------------------------- status

#: what the tracker says of each measured signal
SENSOR_STATES = ("ok", "noisy", "stuck", "clipped", "offset", "wrong_unit", "missing")

_STATUS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "fpdd-twin/status-event.schema.json",
    "title": "StatusEvent",
    "description": "Health of the twin serving one rig (key fpdd/<rig>/status).",
    "type": "object",
    "required": ["rig", "t_ns", "state", "parameters", "counters", "message", "sensors", "consistency"],
    "properties": {
        "rig": {"type": "string", "pattern": RIG_PATTERN},
        "t_ns": {"type": "integer", "minimum": 0, "maximum": INT64_MAX, "description": "ingest time [ns]"},
        "state": {"type": "string", "enum": list(SERVICE_STATES)},
        "parameters": {
            "type": "object",
            "propertyNames": {"pattern": NAME_PATTERN},
            "additionalProperties": {"type": "string", "pattern": STATUS_PATTERN},
            "description": "parameter name -> status: ok, frozen (not excited), unresolved (not identifiable from recent data), warning, alarm",
        },
        "counters": {
            "type": "object",
            "propertyNames": {"pattern": NAME_PATTERN},
            "additionalProperties": {"type": "integer", "minimum": 0, "maximum": INT64_MAX},
            "description": "non-negative counters: samples, alarms, gated, repaired_covariance, bad_blocks, source_errors, ...; 'alarm_seq' is the last journaled alarm seq; gauges 'lag_ms' (how far behind real time) and 'stale_ms' (how long without input)",
        },
        "message": {"type": "string"},
        "sensors": {
            "type": "object",
            "propertyNames": {"pattern": NAME_PATTERN},
            "additionalProperties": {"type": "string", "enum": list(SENSOR_STATES)},
            "description": "measured signal -> sensor status: ok, noisy, stuck, clipped, offset, wrong_unit, "
                           "missing (a faulty signal is left out of the filter and parameter alarms are held)",
        },
        "consistency": {
            "type": "string",
            "description": "the filter's consistency with the data: 'consistent', or why not (the drift test "
                           "holds its evidence meanwhile)",
        },
    },
}


@dataclass(frozen=True, slots=True)
class StatusEvent(_FromJson):
    """Health of the twin serving one rig.

    :ivar rig: rig id.
    :ivar t_ns: ingest time [ns].
    :ivar state: one of :data:`SERVICE_STATES`.
    :ivar parameters: parameter name -> status word (``ok``, ``frozen``,
        ``unresolved``, ``warning``, ``alarm``), read-only.
    :ivar counters: counter name -> non-negative int, read-only. The key
        ``alarm_seq`` (last journaled alarm of the rig) is filled in by
        :meth:`twin.service.bus.TwinPublisher.publish_status`; subscribers use it to
        notice a lost last alarm.
    :ivar message: one human-readable line.
    :ivar sensors: measured signal -> sensor status (:data:`SENSOR_STATES`).
    :ivar consistency: ``consistent`` or why the filter is not consistent with the data.
    """

    rig: str
    t_ns: int
    state: str
    parameters: Mapping[str, str] = field(default_factory=dict)
    counters: Mapping[str, int] = field(default_factory=dict)
    message: str = ""
    sensors: Mapping[str, str] = field(default_factory=dict)
    consistency: str = "consistent"

    SCHEMA: ClassVar[dict[str, Any]] = _STATUS_SCHEMA

    def __post_init__(self) -> None:
        for name in ("parameters", "counters", "sensors"):
            value = getattr(self, name)
            if not isinstance(value, Mapping):
                raise DataError(f"StatusEvent.{name}: {value!r} must be an object")
            object.__setattr__(self, name, MappingProxyType(dict(value)))
        _check("StatusEvent", self.SCHEMA, self.to_dict())

    def to_dict(self) -> dict[str, Any]:
        """The event as a JSON-ready dict (the payload of ``fpdd/<rig>/status``)."""
        return {
            "rig": self.rig,
            "t_ns": self.t_ns,
            "state": self.state,
            "parameters": dict(self.parameters),
            "counters": dict(self.counters),
            "message": self.message,
            "sensors": dict(self.sensors),
            "consistency": self.consistency,
        }

