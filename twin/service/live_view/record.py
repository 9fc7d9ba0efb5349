"""The twin's MCAP as the live view shows it: the same topics, schemas and messages, so that Foxglove's layout
(:func:`twin.service.live_view.layout.foxglove_layout`) fills on a recorded file as on the live view.

:class:`TwinRecording` is the :class:`replay.mcapio.McapSink` of ``twin track`` and ``twin serve`` (the twin's
``RIG.twin.mcap``): besides ``/twin/estimate``, ``/twin/status``, ``/twin/forecast`` and ``/twin/alarm`` (which
the twin writes), it records each alarm's line on ``/twin/alarm_log`` (``foxglove.Log``) and the rig's signals
decimated to ``signals_hz`` on ``/rig/signals`` (the live view's message: SI under each signal's name with
``units``, the same numbers in display units under ``display``), every message with the rig's name.
"""

from __future__ import annotations

import json
import os
from typing import Any
from collections.abc import Mapping, Sequence

from replay.mcapio import McapSink
from twin.models import DEFAULT_MODEL
from twin.service.live_view.messages import LOG_SCHEMA, SignalFields, alarm_log_message, signals_schema
from twin.service.live_view.signals import SignalDecimator

SIGNALS_HZ = 50.0
"""Signal messages per second in a twin's MCAP (the live view's default display rate)."""


class TwinRecording(McapSink):
    """The twin's MCAP with the live view's topics (module docstring).

    ``rig``: the rig's name; ``model``: its model (units of its signals, parameters of the layout);
    ``signals_hz``: the signals' rate in the file (0: none); ``layout``: a path where :meth:`close` writes the
    Foxglove layout of this rig (its variable ``rig`` set, one plot per parameter of ``parameters``)."""

    def __init__(self, path: str | os.PathLike, rig: str, model: str = DEFAULT_MODEL, *,
                 signals_hz: float = SIGNALS_HZ, parameters: Sequence[str] | None = None,
                 layout: str | os.PathLike | None = None) -> None:
        super().__init__(path, rig=rig)
        self.model = model
        self._decimate = SignalDecimator(signals_hz) if signals_hz > 0 else None
        self._fields: SignalFields | None = None
        self._meta: dict[str, str] = {}
        self._schema: dict | None = None
        self._t0_ns: int | None = None
        self._parameters = tuple(parameters) if parameters is not None else None
        self._layout = os.fspath(layout) if layout is not None else None

    def signals(self, samples) -> int:
        """A block of the rig's samples (SI): its decimated samples on ``/rig/signals``; returns how many."""
        if self._decimate is None or len(samples) == 0:
            return 0
        if self._t0_ns is None:
            self._t0_ns = int(samples.t_ns[0])
        kept = self._decimate(samples)
        if kept is None:
            return 0
        if self._fields is None or self._fields.names != tuple(kept.signals):
            self._fields = SignalFields(kept.signals, self.model)
            self._meta = {"signals": ",".join(self._fields.names), "rig": self.rig,
                          "units": ",".join(self._fields.units[n] for n in self._fields.names)}
        f = self._fields
        if self._schema is None:
            self._schema = signals_schema(self.model)
        cols = [kept.signals[n].tolist() for n in f.names]
        for i, t in enumerate(kept.t_ns.tolist()):
            msg = f.message(self.rig, t, (t - self._t0_ns) * 1e-9, [c[i] for c in cols])
            self.write_message("/rig/signals", t, msg, schema=self._schema, metadata=self._meta)
        return len(kept)

    def write_message(self, topic: str, t_ns: int, payload: Mapping[str, Any], *,
                      schema: Mapping[str, Any] | None = None, metadata: Mapping[str, str] | None = None) -> None:
        """As :meth:`McapSink.write_message`; an alarm (``/twin/alarm``) also as its line on ``/twin/alarm_log``."""
        super().write_message(topic, t_ns, payload, schema=schema, metadata=metadata)
        if topic == "/twin/alarm":
            from twin.online.events import AlarmEvent

            ev = AlarmEvent.from_dict(dict(payload))
            super().write_message("/twin/alarm_log", t_ns, alarm_log_message(ev, self.model), schema=LOG_SCHEMA)

    def close(self) -> None:
        closed = self._closed
        super().close()
        if not closed and self._layout is not None:
            from twin.models import get_model
            from twin.service.live_view.layout import foxglove_layout

            params = self._parameters or tuple(get_model(self.model).PHENOMENOLOGICAL)
            with open(self._layout, "w", encoding="utf-8") as f:
                json.dump(foxglove_layout(params, model=self.model, rig=self.rig), f, indent=2, ensure_ascii=False)
                f.write("\n")
