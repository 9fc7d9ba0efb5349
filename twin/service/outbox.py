"""A rig runner's publisher: the :class:`Outbox` journals a rig's alarms and batches its bus messages for the
service's process, which puts them on Zenoh (:class:`twin.service.fleet.BusFront`)."""

from __future__ import annotations

import dataclasses
import time

from replay.base import Samples
from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent, event_to_json
from twin.service.journal import AlarmJournal
from twin.service.publisher import Publisher

#: A runner's bus messages are flushed at least this often [s] even without samples.
FLUSH_S = 0.25


class Outbox(Publisher):
    """A runner's publisher for its :class:`RigTwin`: journals alarms, batches bus messages.

    Messages (put on ``out`` as ``("batch", rig, [...])`` after each block):
    ``("alarm", AlarmEvent)`` (only once it is in the journal's main file), ``("estimate", json)``,
    ``("status", json, state, message)``, ``("forecast", dict)``.
    """

    def __init__(self, rig: str, journal: AlarmJournal, out, signals_hz: float = 0.0) -> None:
        self.rig = rig
        self.journal = journal
        self.out = out
        self._decimate = None
        if signals_hz > 0:  # the rig's signals for live views, ("signals", json) on fpdd/<rig>/signals
            from twin.service.live_view import SignalDecimator

            self._decimate = SignalDecimator(signals_hz)
        self._batch: list[tuple] = []
        self._last_flush = time.monotonic()
        self._seq = journal.last_seq(rig)
        journal.epoch(rig)  # made now if the rig has none: its first status announces it
        self.term = journal.term(rig)  # the ownership term this run publishes in (twin.service.ownership)

    def publish_alarm(self, event: AlarmEvent) -> AlarmEvent | None:
        recorded = self.journal.record(event)
        if not recorded.new:
            return None
        if recorded.durable:  # an alarm goes on the bus once it is in the journal's main file, and at once
            self._seq = max(self._seq, recorded.event.seq)
            self._batch.append(("alarm", recorded.event))
            self.flush()
        return recorded.event  # one the journal holds (write failed) goes out when written (flush)

    def publish_estimate(self, event: EstimateEvent) -> None:
        self._batch.append(("estimate", event_to_json(event)))

    def publish_estimate_json(self, payload: str) -> bool:
        """An estimate already written as its JSON payload (:meth:`twin.service.rig.RigTwin._estimate_json`)."""
        self._batch.append(("estimate", payload))
        return True

    def publish_forecast(self, message: dict) -> None:
        """A forecast message (:func:`twin.online.events.forecast.forecast_message`): relayed to the service's
        :meth:`twin.service.bus.TwinPublisher.publish_forecast` (which decides when it goes on the bus)."""
        self._batch.append(("forecast", message))

    def publish_checkpoint(self, cp, rig_state: str) -> None:
        """A checkpoint just saved, for the standbys (``("checkpoint", Checkpoint, state)``, see
        :mod:`twin.service.replication`)."""
        self._batch.append(("checkpoint", cp, rig_state))

    def publish_signals(self, samples: Samples) -> None:
        """The rig's samples, decimated to ``signals_hz`` (nothing when it is 0)."""
        if self._decimate is not None:
            kept = self._decimate(samples)
            if kept is not None:
                from twin.service.live_view import signals_to_json

                self._batch.append(("signals", signals_to_json(self.rig, kept)))

    def status_counters(self) -> dict[str, int]:
        """``alarm_seq``: the last number the journal gave an alarm of this rig (this runner is its one writer)."""
        return {"alarm_seq": self._seq}

    def publish_status(self, event: StatusEvent) -> StatusEvent:
        if "alarm_seq" not in event.counters:
            event = dataclasses.replace(event, counters={**event.counters, **self.status_counters()})
        if not event.epoch:  # the numbering the alarms count in, announced (and signed by the bus front)
            event = dataclasses.replace(event, epoch=self.journal.epoch(self.rig))
        if self.term and not event.term:
            event = dataclasses.replace(event, term=self.term)
        self._batch.append(("status", event_to_json(event), event.state, event.message))
        return event

    def flush(self, force: bool = True) -> None:
        if self.journal.pending:
            self.journal.retry()
        written = self.journal.take_written()
        for ev in written:
            self._seq = max(self._seq, ev.seq)
            self._batch.append(("alarm", ev))
        if self._batch and (force or written or time.monotonic() - self._last_flush >= FLUSH_S):
            batch, self._batch = self._batch, []
            self.out.put(("batch", self.rig, batch))
            self._last_flush = time.monotonic()

