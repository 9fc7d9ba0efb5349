"""What a rig's twin (:class:`twin.service.rig.RigTwin`) hands its events to: the :class:`Publisher` protocol.

Its implementations: the Zenoh publisher of a rig (:class:`twin.service.bus.TwinPublisher`), a runner's
outbox that journals alarms and batches the rest for the service's process
(:class:`twin.service.outbox.Outbox`), the live view's tee (:meth:`twin.service.live_view.LiveView.tee`) and
the offline track's alarm numbering (:class:`twin.service.track.SequenceNumbers`). Each subclasses
:class:`Publisher` explicitly, so the type checker holds its methods to these signatures; a method a
publisher has nothing to do for keeps the default here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent


class Publisher(Protocol):
    """Where a rig's twin publishes its alarms, estimates and statuses."""

    def publish_alarm(self, event: AlarmEvent) -> AlarmEvent | None:
        """Publish an alarm (journaled first where there is a journal); returns the event as published (with
        its ``seq``), or ``None`` for an alarm published before (the twin counts it as a duplicate)."""
        ...

    def publish_estimate(self, event: EstimateEvent) -> None:
        """Publish an estimate."""
        ...

    def publish_estimate_json(self, payload: str) -> bool:
        """Publish an estimate given as its JSON payload (written by
        :class:`twin.online.events.EstimateEncoder`, the very text of the event's JSON): ``True`` when taken;
        ``False`` (the default) when this publisher wants the event (:meth:`publish_estimate`) instead."""
        return False

    def publish_status(self, event: StatusEvent) -> StatusEvent:
        """Publish a status; returns it as published (counters filled in)."""
        ...

    def publish_forecast(self, message: dict) -> None:
        """Publish one forecast message (:func:`twin.online.events.forecast.forecast_message`; default: not published)."""
        return None

    def status_counters(self) -> dict[str, int]:
        """Counters of the publisher's own that go into the rig's status (default: none)."""
        return {}
