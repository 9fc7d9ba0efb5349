"""Drift alarms (:class:`AlarmEvent`, its identity, its one console line)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, ClassVar, Self

from twin.models import DEFAULT_MODEL
from fpdd.errors import DataError
from datetime import UTC
from twin.online.events.schema import (ALARM_KINDS, EVENT_LEVELS, INT64_MAX, NAME_PATTERN, RIG_PATTERN, FromJson,
                                       as_mapping, check, num)
from twin.units import known_units


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
        "t_s": num("time from the start of the record [s]"),
        "estimate": num("parameter estimate, SI unit of the parameter"),
        "std": num("the filter's standard deviation of the estimate under its drift model (the scale the drift "
                    "test standardises by), same unit", minimum=0),
        "baseline": num("healthy baseline value, same unit"),
        "band_lo": num("lower edge of the healthy band, same unit"),
        "band_hi": num("upper edge of the healthy band, same unit"),
        "seq": {"type": "integer", "minimum": 1, "description": "per-rig sequence number, 1, 2, 3, ... without gaps"},
        "statistic": num("value of the sequential test (CUSUM/GLR) at this event"),
        "message": {"type": "string", "description": "one human-readable line"},
        "unit": {"type": "string", "description": "SI unit of estimate, std, baseline and band, e.g. 'N', "
                                                  "'m^2', 'rad/s', '1'"},
        "signature": {"type": "string", "description": "optional: base64 Ed25519 signature of the rig's key "
                      "over the canonical JSON of every other field (twin.service.signing)"},
        "wall_ns": {"type": ["integer", "null"], "minimum": 0, "maximum": INT64_MAX,
                    "description": "wall-clock time the twin journaled the alarm [ns since the Unix epoch] (beside "
                    "t_ns, the record's time: a replayed log's alarms are raised now about then); null: unknown"},
        "epoch": {"type": "string", "pattern": "^[0-9a-f]{1,64}$",
                  "description": "optional: the epoch of the rig's alarm numbering (a random identity made with its "
                  "journal, its creation time first: a later epoch sorts after an earlier one); seq counts within it"},
        "term": {"type": "integer", "minimum": 1, "maximum": INT64_MAX,
                 "description": "optional: the ownership term of the service that published it (fencing: a "
                                "later owner has a larger term; two terms at once: a split network)"},
    },
}


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
class AlarmEvent(FromJson):
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
    :ivar epoch: the epoch of the rig's numbering (set by the journal, :mod:`twin.service.store`); ``""``: unknown
        (the field is then left out of the payload).
    :ivar term: the ownership term that raised it (:mod:`twin.service.ownership`); 0: none (left out).
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
    epoch: str = ""
    term: int = 0

    SCHEMA: ClassVar[dict[str, Any]] = _ALARM_SCHEMA

    def __post_init__(self) -> None:
        if not self.unit:  # the SI unit of the parameter, named beside every value on the wire
            object.__setattr__(self, "unit", known_units().get(self.parameter, "1"))
        data = self.to_dict()
        # seq 0 (not journaled yet) is legal in memory, never on the wire.
        check("AlarmEvent", self.SCHEMA, {**data, "seq": self.seq or 1})
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
        if self.epoch:  # likewise an alarm of a journal without epochs
            data["epoch"] = self.epoch
        if self.term:  # and one raised outside an ownership term
            data["term"] = self.term
        return data

    @classmethod
    def from_dict(cls, data: Any) -> Self:
        """As :meth:`FromJson.from_dict`; an alarm journaled before units were named gets its parameter's, one
        journaled before wall-clock times were kept ``wall_ns=None``."""
        data = as_mapping(data, cls.__name__)
        if "unit" not in data and isinstance(data.get("parameter"), str):
            data = {**data, "unit": known_units().get(data["parameter"], "1")}
        if "wall_ns" not in data:  # journaled before wall-clock times were kept: unknown
            data = {**data, "wall_ns": None}
        # slots dataclass: no zero-argument super
        return FromJson.from_dict.__func__(cls, data)  # type: ignore[attr-defined]

    def with_seq(self, seq: int) -> Self:
        """A copy carrying sequence number ``seq``."""
        return replace(self, seq=seq)

    @property
    def identity(self) -> AlarmIdentity:
        """(rig, parameter, level, kind, t_ns): equal for the same alarm raised twice."""
        return AlarmIdentity(self.rig, self.parameter, self.level, self.kind, self.t_ns)


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

