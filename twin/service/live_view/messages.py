"""The live view's channels: one JSON topic per kind of message, each with its schema, and the messages on them.

:class:`LiveView` serves the Foxglove WebSocket protocol (loopback ``127.0.0.1``
by default) under both subprotocol names: ``foxglove.websocket.v1`` (the
documented one, which Foxglove and most clients offer) and ``foxglove.sdk.v1``
(the name ``foxglove-sdk`` >= 0.30 servers answer to).  The SDK's server runs
on an internal loopback port; a small WebSocket front on the public port
accepts either name and relays the frames unchanged.  One JSON channel per
kind of message, each with its JSON schema:

* ``/rig/signals`` (``fpdd.live.Signals``): the rig's signals, decimated to
  ``signal_rate_hz``, as the rig's MCAP carries them: each signal in its SI unit
  under its own name (``x`` in m, ``pA`` in Pa: whatever the rig logs), the unit
  in ``units`` and in the channel's schema; the same numbers in the display unit
  people read under ``display`` (``display.x`` in mm, ``display.pA`` in MPa, the
  unit in ``display.units``), which the layout's plots read, as for the estimates.
* ``/twin/estimate`` (``EstimateEvent``): the very message the twin puts on
  Zenoh and in its MCAP (:class:`twin.online.events.EstimateEvent`, SI with the
  unit beside each parameter: ``value``, ``std``, ``lo95``/``hi95``, ``band_lo``/
  ``band_hi``, ``baseline``; the same in the display unit under ``display``, which the layout's
  plots read), plus the Foxglove ``timestamp``.
* ``/twin/status`` (``StatusEvent``): service state, per-parameter status words, counters, message, as on
  Zenoh and in the MCAP.
* ``/twin/forecast`` (``fpdd.Forecast``): when each parameter leaves its band, as on Zenoh
  (``fpdd/<rig>/forecast``) and in the MCAP: per parameter the median exit time and its 90 % interval (record
  seconds) and the remaining time (``remaining_s``, ``remaining_lo_s``, ``remaining_hi_s``), SI with ``units``.
* ``/twin/alarm`` (``AlarmEvent``): every alarm event as on Zenoh and in the MCAP (SI, unit beside, the
  record's ``t_ns`` and the wall-clock ``wall_ns``).
* ``/twin/alarm_log`` (``foxglove.Log``): the same alarms as the lines a person reads (display units, the
  wall-clock time first); the Log panel lists them.

Every message carries ``rig`` (several rigs share the topics; Foxglove filters
with ``/twin/estimate{rig=="hall1-a"}``) and ``timestamp`` as Foxglove
time ``{sec, nsec}``; its log time is the sample's ``t_ns``.  The layout
``deploy/foxglove-layout.json`` plots each parameter's trend with its band and
interval, the remaining time until each parameter leaves its band with its 90 % interval, the rig's
position and pressures, and lists the alarms (open it in
Foxglove: Layouts, Import from file; connect to ``ws://127.0.0.1:PORT``);
``twin serve --foxglove`` writes one whose variable ``rig`` is the first rig served.

Feeding it: :meth:`LiveView.signals` with sample blocks, :meth:`estimate`,
:meth:`status`, :meth:`alarm` with the events of :mod:`twin.online.events` (or their
dicts), :meth:`payload` with the JSON the service puts on Zenoh;
:meth:`tee` wraps a :class:`twin.service.rig.RigTwin` publisher so everything it
publishes is shown too; :meth:`follow` subscribes to a Zenoh session's
``fpdd/<rig>/{estimate,status,forecast,alarm,signals}`` (any process, any number of twins;
a service puts ``signals`` when its ``signals_hz`` is set, as ``twin serve
--foxglove`` does).
"""

from __future__ import annotations

from replay.mcapio import foxglove_time as mcap_time
from twin.models import DEFAULT_MODEL


SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
"""The subprotocol names the live view accepts: the documented one first, then foxglove-sdk's own."""
EXAMPLE_RIG = f"{DEFAULT_MODEL}-hall1-a"
"""The first rig of ``deploy/rigs.example.toml`` (a rig of the default model): the shipped layout's default
``rig``."""

_TIME = {"type": "object", "title": "time", "description": "Foxglove time: seconds and nanoseconds since the epoch "
         "(of the ingest clock: a replayed log's own time)",
         "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0,
                                                                          "maximum": 999999999}},
         "required": ["sec", "nsec"]}
_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}

def signals_schema(model: str = DEFAULT_MODEL) -> dict:
    """The schema of ``/rig/signals`` for ``model``'s records (:func:`twin.record.signal_specs`: each model
    declares its signals, a drive ``u`` may be a voltage or a force): every signal in its SI unit, named in
    ``units`` and in its description; under ``display`` the same numbers in the display unit
    (:func:`twin.reports.units.signal_unit`), named in ``display.units``."""
    from twin.models.records import signal_specs
    from twin.reports.units import signal_unit

    specs = signal_specs(model)
    si = {n: {**_NUM_OR_NULL, "description": f"{s.meaning}, {s.unit}"} for n, s in specs.items()}
    shown = {n: {**_NUM_OR_NULL, "description": f"{s.meaning}, {signal_unit(n, model)[0]}"}
             for n, s in specs.items()}
    units = {"type": "object", "additionalProperties": {"type": "string"}}
    return {
        "title": "fpdd.live.Signals", "type": "object",
        "description": "Rig signals, decimated for display: each in its SI unit (named in units), and the same "
                       "numbers in the display unit people read under display (named in display.units)",
        "properties": {"timestamp": _TIME, "rig": {"type": "string"},
                       "t_s": {**_NUM, "description": "time from the first sample shown, s"}, **si,
                       "units": {**units, "description": "signal -> its SI unit (m, V, Pa, ...)"},
                       "display": {"type": "object", "description": "the signals in display units (SI x the "
                                   "signal's display scale: x in mm, pressures in MPa); null stays null",
                                   "properties": {**shown, "units": {**units, "description": "signal -> its "
                                                                     "display unit (mm, V, MPa, ...)"}},
                                   "additionalProperties": _NUM_OR_NULL, "required": ["units"]}},
        "additionalProperties": _NUM_OR_NULL, "required": ["timestamp", "rig", "t_s", "units", "display"],
    }


SIGNALS_SCHEMA: dict = signals_schema()
"""The schema of ``/rig/signals`` for the default model's records."""


def _event_schema(kind: str) -> dict:
    """The schema of a twin event (``EstimateEvent``, ``StatusEvent``, ``AlarmEvent``) with the Foxglove
    ``timestamp``: as the twin's MCAP records it."""
    from replay.mcapio import with_time_schema
    from twin.online import events

    return dict(with_time_schema(getattr(events, kind).SCHEMA))


ESTIMATE_SCHEMA: dict = _event_schema("EstimateEvent")
STATUS_SCHEMA: dict = _event_schema("StatusEvent")
ALARM_SCHEMA: dict = _event_schema("AlarmEvent")


def _forecast_schema() -> dict:
    from replay.mcapio import with_time_schema
    from twin.online.events.forecast import FORECAST_SCHEMA

    return dict(with_time_schema(FORECAST_SCHEMA))


FORECAST_SCHEMA: dict = _forecast_schema()
LOG_SCHEMA: dict = {
    "title": "foxglove.Log", "type": "object",
    "description": "Foxglove's well-known log message (the Log panel lists them): one line per alarm event",
    "properties": {"timestamp": _TIME, "level": {"type": "integer", "minimum": 0, "maximum": 5,
                                                 "description": "2 info (returned), 3 warning, 4 error (alarm)"},
                   "message": {"type": "string"}, "name": {"type": "string", "description": "the rig"},
                   "file": {"type": "string"}, "line": {"type": "integer", "minimum": 0}},
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}


def topics(model: str = DEFAULT_MODEL) -> dict[str, tuple[str, dict]]:
    """kind -> (topic, schema) of the live view's channels for ``model``'s rigs (the signals' units are the
    model's)."""
    return {"signals": ("/rig/signals", SIGNALS_SCHEMA if model == DEFAULT_MODEL else signals_schema(model)),
            "estimate": ("/twin/estimate", ESTIMATE_SCHEMA), "status": ("/twin/status", STATUS_SCHEMA),
            "forecast": ("/twin/forecast", FORECAST_SCHEMA), "alarm": ("/twin/alarm", ALARM_SCHEMA),
            "alarm_log": ("/twin/alarm_log", LOG_SCHEMA)}


TOPICS = topics()
"""kind -> (topic, schema) of the live view's channels (the default model's)."""
LOG_LEVEL = {"ok": 2, "warning": 3, "alarm": 4, "early": 3}


def foxglove_time(t_ns: int) -> dict:
    """``{"sec", "nsec"}`` of integer nanoseconds as the MCAP files carry it (:func:`replay.mcapio.foxglove_time`),
    a time before 0 shown at 0 (the live view's time has no negative seconds)."""
    return mcap_time(max(0, int(t_ns)))


def estimate_message(ev) -> dict:
    """The message of an :class:`~twin.online.events.EstimateEvent` on ``/twin/estimate``, live and in the
    twin's MCAP alike: the event's dict (SI, unit beside each parameter, 95 % interval, band, and the same in the
    display unit under ``display``) and its Foxglove
    ``timestamp``."""
    return {**ev.to_dict(), "timestamp": foxglove_time(ev.t_ns)}


def alarm_log_message(ev, model: str = DEFAULT_MODEL) -> dict:
    """The ``/twin/alarm_log`` message (``foxglove.Log``, :data:`LOG_SCHEMA`) of an
    :class:`~twin.online.events.AlarmEvent`: the line a person reads (display units,
    :func:`twin.online.events.format_alarm`), live and in the twin's MCAP alike."""
    from twin.online.events import format_alarm

    return {"timestamp": foxglove_time(ev.t_ns), "level": LOG_LEVEL.get(ev.level, 2),
            "message": format_alarm(ev, model=model), "name": ev.rig, "file": "", "line": 0}


class SignalFields:
    """How one rig's signals become ``/rig/signals`` messages (:func:`signals_schema`): per signal its SI unit
    and its display unit and scale, for the signals of a block (``names``) of ``model``'s records."""

    def __init__(self, names, model: str = DEFAULT_MODEL) -> None:
        from twin.models.records import signal_specs
        from twin.reports.units import signal_unit

        specs = signal_specs(model)
        self.names = tuple(names)
        self.units = {n: specs[n].unit if n in specs else "" for n in self.names}
        shown = {n: signal_unit(n, model) for n in self.names}
        self.display_units = {n: u for n, (u, _) in shown.items()}
        self.scales = tuple(shown[n][1] for n in self.names)

    def message(self, rig: str, t_ns: int, t_s: float, values) -> dict:
        """The message of one sample: ``values`` in SI, in the order of :attr:`names` (a non-finite one is
        ``null``)."""
        si = [_finite(v) for v in values]
        shown = {n: None if v is None else v * k for n, v, k in zip(self.names, si, self.scales)}
        return {"timestamp": foxglove_time(t_ns), "rig": rig, "t_s": t_s, **dict(zip(self.names, si)),
                "units": dict(self.units), "display": {**shown, "units": dict(self.display_units)}}


def _finite(v) -> float | None:
    import math

    return float(v) if v is not None and math.isfinite(float(v)) else None
