"""Service status (:class:`StatusEvent`): the life-cycle state of the twin serving one rig, its parameters', sensors'
and filter's health."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar

from fpdd.errors import DataError
from twin.online.events.schema import (INT64_MAX, NAME_PATTERN, RIG_PATTERN, SENSOR_STATES, SERVICE_STATES,
                                       STATUS_PATTERN, FromJson, check)


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
            "description": "parameter name -> status: ok, frozen (not excited), unresolved (not identifiable from recent data), warning, alarm; with confirmed alarms: not_testable (the last window re-fit could not test it), untested (no window yet)",
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
        "epoch": {"type": "string", "pattern": "^[0-9a-f]{1,64}$",
                  "description": "optional: the epoch of the rig's alarm numbering in the owner's journal "
                  "(AlarmEvent.epoch): announced so that a subscriber refuses alarms of an earlier epoch"},
        "term": {"type": "integer", "minimum": 1, "maximum": INT64_MAX,
                 "description": "optional: the ownership term of the service that published it (fencing: a "
                                "later owner has a larger term; two terms at once: a split network)"},
        "signature": {"type": "string", "description": "optional: base64 Ed25519 signature of the rig's key over "
                      "the canonical JSON of every other field (twin.service.signing, domain fpdd-status-v1)"},
        "tested": {
            "type": "object",
            "propertyNames": {"pattern": NAME_PATTERN},
            "additionalProperties": {"type": "number", "minimum": 0},
            "description": "optional: parameter -> record time [s] of the last window re-fit that tested it "
                           "(twin.online.confirm; a parameter not yet tested is absent)",
        },
    },
}


@dataclass(frozen=True, slots=True)
class StatusEvent(FromJson):
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
    :ivar epoch: the epoch of the rig's alarm numbering (``""``: not announced; left out of the payload).
    :ivar signature: the rig key's signature (:mod:`twin.service.signing`; ``""``: unsigned, left out).
    :ivar term: the ownership term of the service that published it (0: none, left out).
    :ivar tested: parameter -> record time [s] of the last window re-fit that tested it (confirmed alarms,
        :mod:`twin.online.confirm`; empty: left out of the payload).
    """

    rig: str
    t_ns: int
    state: str
    parameters: Mapping[str, str] = field(default_factory=dict)
    counters: Mapping[str, int] = field(default_factory=dict)
    message: str = ""
    sensors: Mapping[str, str] = field(default_factory=dict)
    consistency: str = "consistent"
    epoch: str = ""
    signature: str = ""
    term: int = 0
    tested: Mapping[str, float] = field(default_factory=dict)

    SCHEMA: ClassVar[dict[str, Any]] = _STATUS_SCHEMA

    def __post_init__(self) -> None:
        for name in ("parameters", "counters", "sensors", "tested"):
            value = getattr(self, name)
            if not isinstance(value, Mapping):
                raise DataError(f"StatusEvent.{name}: {value!r} must be an object")
            object.__setattr__(self, name, MappingProxyType(dict(value)))
        check("StatusEvent", self.SCHEMA, self.to_dict())

    def to_dict(self) -> dict[str, Any]:
        """The event as a JSON-ready dict (the payload of ``fpdd/<rig>/status``)."""
        data: dict[str, Any] = {
            "rig": self.rig,
            "t_ns": self.t_ns,
            "state": self.state,
            "parameters": dict(self.parameters),
            "counters": dict(self.counters),
            "message": self.message,
            "sensors": dict(self.sensors),
            "consistency": self.consistency,
        }
        for name in ("epoch", "signature", "term"):  # optional: a payload without them is as before they existed
            if getattr(self, name):
                data[name] = getattr(self, name)
        if self.tested:
            data["tested"] = dict(self.tested)
        return data
