"""Events the twin publishes (alarms, estimates and service status): what they share, their vocabulary,
the schema validation and the JSON writer.

Each event is a frozen dataclass with ``to_dict()`` / ``from_dict()`` and a
JSON schema (draft 2020-12, a plain ``dict``) in its ``SCHEMA`` class
attribute. The same schema drives validation: ``from_dict`` checks a decoded
payload against it and raises :class:`~fpdd.errors.DataError` with a message
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

import math
import re
from collections.abc import Mapping
from typing import Any, ClassVar, Self

from fpdd import jsonio
from fpdd.errors import DataError

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

#: what the tracker says of each measured signal
SENSOR_STATES = ("ok", "noisy", "stuck", "clipped", "offset", "wrong_unit", "missing")


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


def check(cls_name: str, schema: Mapping[str, Any], data: Mapping[str, Any]) -> None:
    validate(data, schema, cls_name)


def as_mapping(data: Any, cls_name: str) -> Mapping[str, Any]:
    if not isinstance(data, Mapping):
        raise DataError(f"{cls_name}: expected a JSON object, got {type(data).__name__}")
    return data


class FromJson:
    """``from_dict`` shared by the event classes: validate against ``SCHEMA``, then build."""

    __slots__ = ()
    SCHEMA: ClassVar[dict[str, Any]]

    @classmethod
    def from_dict(cls, data: Any) -> Self:
        """Build and validate an event from a decoded JSON payload.

        :raises DataError: naming the field that does not validate.
        """
        data = as_mapping(data, cls.__name__)
        check(cls.__name__, cls.SCHEMA, data)
        import dataclasses

        optional = {f.name for f in dataclasses.fields(cls)} - set(cls.SCHEMA["required"])  # type: ignore[arg-type]
        return cls(**{name: data[name] for name in cls.SCHEMA["required"]},
                   **{name: data[name] for name in optional if name in data})

    def to_dict(self) -> dict[str, Any]:
        """The event as a JSON-ready dict (its payload)."""
        raise NotImplementedError


def event_to_json(event: FromJson) -> str:
    """Serialise an event to compact JSON (sorted keys, no NaN/inf)."""
    return jsonio.dumps(event.to_dict(), indent=None, sort_keys=True)


def num(description: str, **extra: Any) -> dict[str, Any]:
    return {"type": "number", "description": description, **extra}

