"""The Zenoh layer: the key space and publishing the twin's events (:class:`TwinPublisher`); querying the
latest values is :mod:`twin.service.queries`, subscribing to its alarms :mod:`twin.service.subscriber`.

Key space (one set of keys per rig; ``<rig>`` is one key chunk, see
:data:`twin.online.events.RIG_PATTERN`)::

    fpdd/<rig>/estimate        put    EstimateEvent JSON, every published tracker step
                               get    latest EstimateEvent (latest-value queryable)
    fpdd/<rig>/status          put    StatusEvent JSON, on change and periodically
                               get    latest StatusEvent (latest-value queryable)
    fpdd/<rig>/forecast        put    forecast JSON (``twin.online.events.forecast.FORECAST_SCHEMA``): when each
                                      parameter leaves its band, on change and every ``FORECAST_S``
                               get    latest forecast (latest-value queryable)
    fpdd/<rig>/maintenance     get    record a maintenance event (payload {"parameters": [...], "note"}):
                                      the reply is the event as recorded (:mod:`twin.service.maintenance`)
    fpdd/<rig>/alarm           put    AlarmEvent JSON, live alarms (reliable, blocking, high priority)
    fpdd/<rig>/alarm/history   get    every journaled AlarmEvent of the rig, one reply per alarm,
                                      in seq order; selector parameters (``;``-separated):
                                      ``since_seq=N`` (seq >= N), ``since_t_ns=T`` (t_ns >= T)
    fpdd/<rig>/alarm/handover  get    an owner that stood down after a split network hands over the alarms it
                                      raised in its term (payload {"rig", "term", "alarms": [...]}); the owner
                                      journals those it does not hold under its next numbers, marked, puts them
                                      and replies {"term", "epoch", "alarms": [{"seq", "now", "held"}]}
                                      (:meth:`TwinPublisher.adopt`, :mod:`twin.service.handover`)
    fpdd/<rig>/twin            liveliness token, present while the twin serves the rig

Payloads are UTF-8 JSON (encoding ``application/json``) following the schemas in
:mod:`twin.online.events` (``AlarmEvent.SCHEMA``, ``EstimateEvent.SCHEMA``,
``StatusEvent.SCHEMA``) and :data:`twin.online.events.forecast.FORECAST_SCHEMA`. Every alarm carries ``seq``, a per-rig number 1, 2,
3, ... without gaps, assigned by the durable journal (:mod:`twin.service.journal`).

Delivery guarantees and how they are obtained:

* An alarm is appended to the journal and ``fsync``-ed *before* it is put
  (:meth:`TwinPublisher.publish_alarm`), so whatever reached a subscriber is on
  disk, and whatever is on disk is served by ``fpdd/<rig>/alarm/history``.
* Alarms are put reliably, with ``CongestionControl.BLOCK`` (never dropped
  by a full queue) and ``Priority.INTERACTIVE_HIGH``, ``express``.
* Zenoh still loses what is published while a link or router is down, and a
  plain subscriber receives nothing published before it joined. The
  :class:`~twin.service.subscriber.AlarmSubscriber` therefore (1) subscribes first, then fetches the
  history, (2) de-duplicates by ``(rig, seq)``, (3) fills a gap in ``seq``
  from the history, (4) re-syncs from the history when a twin's liveliness
  token (re)appears (a twin or a router came back), and (5) catches a lost
  *last* alarm through the ``alarm_seq`` counter that every status carries.
* Who published it: with a per-rig key (:mod:`twin.service.signing`) every
  alarm put and every history reply carries an Ed25519 signature over all its
  fields; an :class:`~twin.service.subscriber.AlarmSubscriber` with a trust store refuses and reports a
  forged one before it can move a sequence number, and never merges history
  queryables that disagree. This holds on a plain peer bus with no router.
* Estimates, statuses and forecasts go through ``zenoh.ext`` advanced publishers with a
  one-sample cache (late ``zenoh.ext.AdvancedSubscriber`` with a
  ``HistoryConfig`` gets the current value), and the latest value is also
  served by a plain queryable on the same key, so a plain ``get`` (any Zenoh
  client, ``z_get``) works too. Measured with eclipse-zenoh 1.10.2: the
  advanced publisher's cache answers only advanced subscribers (a plain ``get``
  on the key returns nothing), and an advanced publisher with a cache needs
  either ``sample_miss_detection`` or ``timestamping`` enabled in the config
  (otherwise ``ZError: ... Sequencing::Timestamp``); we enable miss detection.
  History replies of many alarms on one key need ``ConsolidationMode.NONE``:
  the default consolidation keeps only the last reply per key.

Resources: every declaration is undeclared by ``close()``/``__exit__``; the
session itself belongs to the caller and must be closed too (a session with
callback subscribers or queryables left open hangs the interpreter at exit).
"""

from __future__ import annotations

import json
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, Self

import zenoh
from zenoh import ext as zext

from fpdd.zenohconf import (zenoh_text)
from fpdd.errors import ConfigError, DataError, SourceError
from twin.online.events import (
    RIG_PATTERN,
    AlarmEvent,
    EstimateEvent,
    StatusEvent,
    event_to_json,
    format_alarm,
)
from twin.service.journal import AlarmJournal
from twin.service.publisher import Publisher
from twin.service.signing import Signer

__all__ = [
    "KEY_PREFIX",
    "ForecastGate",
    "RigKeys",
    "TwinPublisher",
    "format_alarm",
]

log = logging.getLogger(__name__)

KEY_PREFIX = "fpdd"
"""First chunk of every key of the service."""

_JSON = zenoh.Encoding.APPLICATION_JSON
_RIG_RE = re.compile(RIG_PATTERN)
#: A rig's forecast is put when it changes (:class:`ForecastGate`) and at least this often while it is made [s].
FORECAST_S = 3.0
#: Another owner's status seen within this long: the rig is run twice (a split network), said in ours: three
#: status periods (statuses come at least once a second) [s].
SPLIT_S = 3.0


def _check_rig(rig: str, *, wildcard: bool) -> str:
    if wildcard and rig == "*":
        return rig
    if not isinstance(rig, str) or _RIG_RE.match(rig) is None:
        allowed = f"'*' or {RIG_PATTERN}" if wildcard else RIG_PATTERN
        raise ConfigError(f"rig: {rig!r} is not a valid rig id (must match {allowed})")
    return rig


class RigKeys:
    """The key expressions of one rig (or of all rigs with ``rig="*"``).

    :ivar estimate: ``fpdd/<rig>/estimate``
    :ivar status: ``fpdd/<rig>/status``
    :ivar forecast: ``fpdd/<rig>/forecast``
    :ivar alarm: ``fpdd/<rig>/alarm``
    :ivar history: ``fpdd/<rig>/alarm/history``
    :ivar handover: ``fpdd/<rig>/alarm/handover`` (an owner that stood down hands its alarms over)
    :ivar twin: ``fpdd/<rig>/twin`` (liveliness)
    """

    __slots__ = ("rig", "estimate", "status", "forecast", "alarm", "history", "handover", "twin")

    def __init__(self, rig: str) -> None:
        self.rig = _check_rig(rig, wildcard=True)
        base = f"{KEY_PREFIX}/{rig}"
        self.estimate = f"{base}/estimate"
        self.status = f"{base}/status"
        self.forecast = f"{base}/forecast"
        self.alarm = f"{base}/alarm"
        self.history = f"{base}/alarm/history"
        self.handover = f"{base}/alarm/handover"
        self.twin = f"{base}/twin"

    @staticmethod
    def rig_of(key_expr: str | zenoh.KeyExpr) -> str:
        """The rig chunk of a concrete key ``fpdd/<rig>/...``.

        :raises DataError: the key is not in the service's key space.
        """
        parts = str(key_expr).split("/")
        if len(parts) < 3 or parts[0] != KEY_PREFIX:
            raise DataError(f"key {str(key_expr)!r} is not of the form {KEY_PREFIX}/<rig>/...")
        return parts[1]


def _open_error(exc: zenoh.ZError, what: str) -> SourceError:
    return SourceError(f"{what}: {zenoh_text(exc)}")


# --------------------------------------------------------------------------- history


class History(Protocol):
    """What the history queryable answers from: an :class:`AlarmJournal` or a :class:`StoreHistory`."""

    def read(self, since_seq: int | None = None, since_t_ns: int | None = None,
             rig: str | None = None) -> list[AlarmEvent]: ...

    def last_seq(self, rig: str) -> int: ...


class StoreHistory:
    """A rig's journal read from another process (no writer lock).

    The service's main process answers history queries with it while the
    rig's worker process owns the journal (an alarm reaches the bus only once it is
    in the journal's main file, so the file holds every alarm published).
    """

    def __init__(self, path: str | Path) -> None:
        from twin.service.store import Store

        self._store = Store(path, writer=False)

    def read(self, since_seq: int | None = None, since_t_ns: int | None = None,
             rig: str | None = None) -> list[AlarmEvent]:
        return sorted(self._store.alarms(rig, since_seq, since_t_ns), key=lambda e: (e.rig, e.seq))

    def last_seq(self, rig: str) -> int:
        return self._store.last_seq(rig)

    def epoch(self, rig: str) -> str:
        return self._store.epoch(rig)

    @property
    def path(self) -> Path:
        return self._store.path

    def close(self) -> None:
        self._store.close()


# --------------------------------------------------------------------------- publisher


class _Declarations:
    """Zenoh entities declared by one object, undeclared in reverse order on close (idempotent)."""

    _declared: list[Any]

    def _keep(self, entity: Any) -> Any:
        self._declared.append(entity)
        return entity

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything, the last declared (the liveliness token) first."""
        while self._declared:
            entity = self._declared.pop()
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                # Undeclaring on a session already closed is harmless; say so and go on.
                log.debug("%s: undeclare %r: %s", type(self).__name__, entity, exc)


class TwinPublisher(_Declarations, Publisher):
    """Everything one rig's twin declares on the bus.

    Declares, for ``rig``: the alarm publisher (reliable,
    ``CongestionControl.BLOCK``, ``Priority.INTERACTIVE_HIGH``, express), the
    estimate publisher (``CongestionControl.DROP``: at high rate a newer estimate
    replaces a dropped one) and the status publisher (``BLOCK``), both
    ``zenoh.ext`` advanced publishers with a one-sample cache; latest-value
    queryables on the estimate and status keys; the alarm-history queryable
    answering from ``history`` (default: ``journal``); and the liveliness
    token ``fpdd/<rig>/twin``.

    ``journal`` is needed by :meth:`publish_alarm` (journal, then put). The
    service's main process, whose rigs journal in their worker, passes only a
    ``history`` (:class:`StoreHistory`) and puts already journaled alarms with
    :meth:`put_alarm`.

    Use as a context manager (or call :meth:`close`); the session stays open.
    Several publishers (one per rig) may share one session and one journal.

    :param session: an open Zenoh session.
    :param rig: the rig id.
    :param journal: the durable journal alarms are written to before publishing.
    :param heartbeat_s: period of the advanced publishers' sporadic heartbeat [s]
        (lets advanced subscribers notice a missed last estimate/status).
    :param signer: the rig's private key (:func:`twin.service.signing.load_signer`): every alarm put and
        every history reply carries its signature. ``None``: alarms go out unsigned.
    :param term: this service's ownership term of the rig (:mod:`twin.service.ownership`): stamped on every
        estimate and status it puts (0: none); a status of the rig under another term seen on the bus (another
        owner: a split network) is said in this one's statuses for ``SPLIT_S``.
    :param put_mark: the file that records how far the journal's alarms were put
        (:mod:`twin.service.put_mark`; :meth:`put_unsent` puts those after it). ``None``: not recorded.
    :raises ConfigError: ``rig`` is not a valid rig id.
    :raises SourceError: a declaration failed (session closed, access denied).
    """

    def __init__(
        self,
        session: zenoh.Session,
        rig: str,
        journal: AlarmJournal | None = None,
        *,
        history: History | None = None,
        heartbeat_s: float = 1.0,
        signer: Signer | None = None,
        put_mark: str | Path | None = None,
        term: int = 0,
    ) -> None:
        from twin.service.put_mark import PutMark

        self.term = int(term)
        self._rival: tuple[int, float] | None = None  # another owner's term and when its status was seen
        self.rig = _check_rig(rig, wildcard=False)
        self._mark = PutMark(put_mark, rig) if put_mark is not None else None
        self.keys = RigKeys(rig)
        self._session = session
        self._journal = journal
        if signer is not None and signer.rig != rig:
            raise ConfigError(f"{signer.path}: the signing key of rig {signer.rig!r} given to the twin of rig {rig!r}")
        self._signer = signer
        if history is None and journal is None:
            raise ConfigError(f"rig {rig!r}: a twin publisher needs a journal or a history to answer from")
        self._history: History = history if history is not None else journal  # type: ignore[assignment]
        if self._mark is not None and self._mark.seq is None:  # no mark yet: what is journaled now counts as put,
            # and the mark exists before the first put (a put not settled at a kill is then put again)
            self._mark.done(self._history.last_seq(rig), getattr(self._history, "epoch", lambda _rig: "")(rig))
        self._latest: dict[str, str] = {}
        self._latest_lock = threading.Lock()
        self._declared: list[Any] = []
        try:
            self._alarm_pub = self._keep(
                session.declare_publisher(
                    self.keys.alarm,
                    encoding=_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.INTERACTIVE_HIGH,
                    express=True,
                    reliability=zenoh.Reliability.RELIABLE,
                )
            )
            miss = zext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=heartbeat_s)

            def latest_value_publisher(key: str, congestion: zenoh.CongestionControl, priority: zenoh.Priority):
                """An advanced publisher whose one-sample cache serves late advanced subscribers."""
                return self._keep(zext.declare_advanced_publisher(
                    session, key, encoding=_JSON, congestion_control=congestion, priority=priority,
                    cache=zext.CacheConfig(1), sample_miss_detection=miss, publisher_detection=True))

            self._estimate_pub = latest_value_publisher(
                self.keys.estimate, zenoh.CongestionControl.DROP, zenoh.Priority.DATA)
            self._status_pub = latest_value_publisher(
                self.keys.status, zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA_HIGH)
            self._forecast_pub = latest_value_publisher(
                self.keys.forecast, zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA)
            self._forecast_gate = ForecastGate()
            self._keep(session.declare_queryable(self.keys.history, self._on_history))
            self._keep(
                session.declare_queryable(self.keys.estimate, lambda q: self._on_latest(q, "estimate"))
            )
            self._keep(
                session.declare_queryable(self.keys.status, lambda q: self._on_latest(q, "status"))
            )
            self._keep(
                session.declare_queryable(self.keys.forecast, lambda q: self._on_latest(q, "forecast"))
            )
            if self.term:  # another owner's statuses of this rig: a split network (said in ours)
                self._keep(session.declare_subscriber(self.keys.status, self._on_rival_status))
                if self._adopter() is not None:  # the alarms an owner that stood down raised meanwhile
                    self._keep(session.declare_queryable(self.keys.handover, self._on_handover))
            # The token last: a subscriber seeing the twin alive can query its history at once.
            self._keep(session.liveliness().declare_token(self.keys.twin))
        except zenoh.ZError as exc:
            self.close()
            raise _open_error(exc, f"rig {rig!r}: cannot declare the twin on the bus") from exc

    def close(self) -> None:
        """Undeclare everything, once the alarms put in the last moments have left (their put mark settled:
        :mod:`twin.service.put_mark`, at most ``SETTLE_S`` of waiting)."""
        if self._mark is not None:
            self._mark.wait_settled()
        super().close()

    def wait_for_alarm_subscribers(self, timeout: float) -> bool:
        """Wait until at least one subscriber matches ``fpdd/<rig>/alarm``.

        Not needed for correctness (late subscribers read the history); useful
        for a demo or a test that wants to see alarms arrive live.

        :returns: ``True`` if a subscriber matched within ``timeout`` seconds.
        """
        matched = threading.Event()
        listener = self._alarm_pub.declare_matching_listener(
            lambda status: matched.set() if status.matching else None
        )
        try:
            # In eclipse-zenoh 1.10.2 the property is a MatchingStatus (always
            # truthy), not the bool its stub announces: read .matching.
            return self._alarm_pub.matching_status.matching or matched.wait(timeout)
        finally:
            listener.undeclare()

    # ------------------------------------------------------------------ publishing

    def _check_event_rig(self, event: AlarmEvent | EstimateEvent | StatusEvent) -> None:
        if event.rig != self.rig:
            raise DataError(
                f"{type(event).__name__}.rig: {event.rig!r} published through the twin of rig {self.rig!r}"
            )

    def publish_alarm(self, event: AlarmEvent) -> AlarmEvent:
        """Journal the alarm durably, then put it on ``fpdd/<rig>/alarm``.

        :param event: the alarm; ``seq=0`` lets the journal number it.
        :returns: the journaled event with its ``seq``.
        :raises DataError: wrong rig or wrong ``seq``.
        :raises SourceError: the journal write failed (nothing was published),
            or the put failed (the alarm is journaled and subscribers get it
            from the history).
        """
        self._check_event_rig(event)
        if self._journal is None:
            raise ConfigError(f"rig {self.rig!r}: this publisher has no journal; use put_alarm for journaled alarms")
        recorded = self._journal.record(event)
        if recorded.new:  # the same alarm raised again (re-processed data) is not published twice
            self.put_alarm(recorded.event)
        return recorded.event

    def put_alarm(self, event: AlarmEvent) -> None:
        """Put an alarm that is already journaled (it has its ``seq``) on ``fpdd/<rig>/alarm``.

        :raises SourceError: the put failed; the alarm is journaled and
            subscribers get it from the history.
        """
        self._check_event_rig(event)
        try:
            self._alarm_pub.put(self._payload(event))
        except zenoh.ZError as exc:
            raise SourceError(
                f"rig {self.rig!r}: alarm seq {event.seq} journaled but not published ({zenoh_text(exc)}); "
                f"subscribers will get it from {self.keys.history}"
            ) from exc
        if self._mark is not None:  # in the mark once the process has outlived the put (settled)
            self._mark.put(event.seq, event.epoch)

    def put_unsent(self, wait_s: float = 2.0) -> int:
        """Put the alarms journaled after the put mark (the service died between journal and put), in order,
        once a subscriber matches the alarm key (waiting up to ``wait_s``: a restarted session learns the
        subscribers' declarations after it opens). Returns how many were put."""
        if self._mark is None:
            return 0
        epoch = getattr(self._history, "epoch", lambda _rig: "")(self.rig)
        first = self._mark.unsent(self._history.last_seq(self.rig), epoch)
        if first is None:
            return 0
        events = self._history.read(since_seq=first, rig=self.rig)
        if not events:
            return 0
        self.wait_for_alarm_subscribers(wait_s)
        for event in events:
            self.put_alarm(event)
        log.warning("rig %s: alarm(s) seq %s were journaled but not put when the service stopped; put now",
                    self.rig, _ranges([e.seq for e in events]))
        return len(events)

    def _payload(self, event: AlarmEvent) -> str:
        """The alarm's JSON payload, signed when the rig has a key."""
        return event_to_json(event) if self._signer is None else self._signer.payload(event)

    def put_payload(self, what: str, payload: str) -> None:
        """Put an estimate or status already serialised (by a rig's worker) and keep it as the latest value; a
        status is signed when the rig has a key (it announces the rig's epoch)."""
        pub = {"estimate": self._estimate_pub, "status": self._status_pub}[what]
        if what == "status":
            payload = self._stamp_status(payload)
        elif self.term and payload.endswith("}") and '"term":' not in payload[-40:]:
            payload = f'{payload[:-1]},"term":{self.term}}}'  # an estimate: its term appended, the text as written
        with self._latest_lock:
            self._latest[what] = payload
        if self._mark is not None:
            self._mark.settle()
        try:
            pub.put(payload)
        except zenoh.ZError as exc:
            raise SourceError(f"rig {self.rig!r}: cannot publish {what}: {zenoh_text(exc)}") from exc

    def publish_estimate(self, event: EstimateEvent) -> None:
        """Put an estimate on ``fpdd/<rig>/estimate`` (may be dropped under congestion)."""
        self._check_event_rig(event)
        payload = event_to_json(event)
        with self._latest_lock:
            self._latest["estimate"] = payload
        if self._mark is not None:
            self._mark.settle()
        try:
            self._estimate_pub.put(payload)
        except zenoh.ZError as exc:
            raise SourceError(f"rig {self.rig!r}: cannot publish estimate: {exc}") from exc

    def publish_estimate_json(self, payload: str) -> bool:
        """Put an estimate given as its JSON payload on ``fpdd/<rig>/estimate`` (:meth:`put_payload`)."""
        self.put_payload("estimate", payload)
        return True

    def publish_forecast(self, message: dict) -> None:
        """A rig's forecast message (:func:`twin.online.events.forecast.forecast_message`): :meth:`put_forecast`."""
        self.put_forecast(message)

    def put_forecast(self, msg: dict[str, Any]) -> bool:
        """A rig's forecast message (:func:`twin.online.events.forecast.forecast_message`, one per second of record):
        kept as the latest value (``get``), put on ``fpdd/<rig>/forecast`` when :class:`ForecastGate` says so
        (on change, else every :data:`FORECAST_S`).

        :returns: whether it was put.
        :raises DataError: another rig's message.
        """
        if msg.get("rig") != self.rig:
            raise DataError(f"forecast.rig: {msg.get('rig')!r} published through the twin of rig {self.rig!r}")
        from fpdd import jsonio

        payload = jsonio.dumps(msg, indent=None)
        with self._latest_lock:
            self._latest["forecast"] = payload
        if not self._forecast_gate(msg):
            return False
        try:
            self._forecast_pub.put(payload)
        except zenoh.ZError as exc:
            raise SourceError(f"rig {self.rig!r}: cannot publish forecast: {zenoh_text(exc)}") from exc
        return True

    def publish_status(self, event: StatusEvent) -> StatusEvent:
        """Put a status on ``fpdd/<rig>/status`` with ``counters["alarm_seq"]`` filled in.

        ``alarm_seq`` is the last journaled alarm of the rig; a subscriber that
        sees it ahead of what it received fetches the missing alarms.

        :returns: the event as published.
        """
        self._check_event_rig(event)
        counters = dict(event.counters)
        if "alarm_seq" not in counters:  # a rig's worker fills it in from its own journal
            counters["alarm_seq"] = self._history.last_seq(self.rig)
        epoch = event.epoch or getattr(self._history, "epoch", lambda _rig: "")(self.rig)
        event = replace(event, counters=counters, epoch=epoch)
        payload = self._stamp_status(event_to_json(event))
        with self._latest_lock:
            self._latest["status"] = payload
        try:
            self._status_pub.put(payload)
        except zenoh.ZError as exc:
            raise SourceError(f"rig {self.rig!r}: cannot publish status: {exc}") from exc
        return event

    def _on_rival_status(self, sample: zenoh.Sample) -> None:
        """A status of this rig on the bus: another term than ours is another owner (a split network)."""
        try:
            term = json.loads(sample.payload.to_string()).get("term")
        except (ValueError, AttributeError):
            return
        if isinstance(term, int) and term and term != self.term:
            if self._rival is None or self._rival[0] != term:
                log.warning("rig %s: another service runs it too (term %d; this one: term %d): the network was split",
                            self.rig, term, self.term)
            self._rival = (term, time.monotonic())

    def split_note(self) -> str:
        """One line while another owner's status was seen within ``SPLIT_S`` (``""`` otherwise)."""
        rival = self._rival
        if rival is None or time.monotonic() - rival[1] > SPLIT_S:
            return ""
        return (f"split: rig {self.rig} is run by two owners at once (terms {min(rival[0], self.term)} and "
                f"{max(rival[0], self.term)}; this one: term {self.term}): the network was split")

    def _stamp_status(self, payload: str) -> str:
        """A status payload with this service's term and split note, signed when the rig has a key."""
        if self.term:
            data = json.loads(payload)
            data["term"] = self.term
            note = self.split_note()
            if note and not str(data.get("message", "")).startswith("split: "):
                data["message"] = "; ".join(m for m in (note, data.get("message", "")) if m)
                data.setdefault("counters", {})["split"] = 1
            from fpdd import jsonio

            payload = jsonio.dumps(data, indent=None, sort_keys=True)
        return self._signer.sign_status(payload) if self._signer is not None else payload

    # ------------------------------------------------------------------ a split network's alarms

    def adopt(self, events: list[AlarmEvent], term: int) -> list[dict[str, Any]]:
        """Journal and put, under this owner's next numbers, the alarms another owner of the rig raised in its
        ``term`` while the network was split and this journal does not hold (by identity); each is marked in its
        message (:func:`split_mark`: the term and number it had, when it was raised) and keeps its term and raise
        time. Returns, per alarm in the other owner's order, ``{"seq": its number there, "now": its number here,
        "held": whether this journal held it already}``."""
        journal = self._adopter()
        if journal is None:
            raise ConfigError(f"rig {self.rig!r}: this publisher has no journal to adopt alarms into")
        out: list[dict[str, Any]] = []
        for ev in sorted(events, key=lambda e: e.seq):
            self._check_event_rig(ev)
            raised_in = ev.term or term
            marked = replace(ev, seq=0, epoch="", signature="", term=raised_in,
                             message="; ".join(m for m in (split_mark(raised_in, ev.seq, ev.wall_ns, self.term),
                                                           ev.message) if m))
            recorded = journal.record(marked)
            if recorded.new and recorded.durable:
                self.put_alarm(recorded.event)
            out.append({"seq": ev.seq, "now": recorded.event.seq, "held": not recorded.new})
        adopted = [f"{o['seq']}->{o['now']}" for o in out if not o["held"]]
        log.warning("rig %s: %d alarm(s) of term %d (the other side of a split network) handed over: %s journaled "
                    "under this term's numbers, %d held already", self.rig, len(out), term,
                    ", ".join(adopted) or "none", len(out) - len(adopted))
        return out

    def _adopter(self) -> AlarmJournal | None:
        """The journal alarms handed over are journaled in: this publisher's, or the history it answers from when
        that is the rig's journal in this process (a service's rigs in threads, as under ``[failover]``)."""
        if self._journal is not None:
            return self._journal
        return self._history if isinstance(self._history, AlarmJournal) else None

    def _on_handover(self, query: zenoh.Query) -> None:
        with query:
            try:
                doc = json.loads(query.payload.to_string()) if query.payload is not None else None
                if not isinstance(doc, dict) or doc.get("rig") != self.rig or not isinstance(doc.get("alarms"), list) \
                        or not isinstance(doc.get("term"), int) or doc["term"] <= 0:
                    raise DataError(f'expected {{"rig": "{self.rig}", "term": <int>, "alarms": [...]}}')
                if doc["term"] == self.term:
                    raise DataError(f"term {doc['term']} is this owner's own")
                events = []
                for data in doc["alarms"]:
                    if self._signer is not None and not signed_by(self._signer, data):
                        raise DataError(f"an alarm handed over does not verify with the key of rig {self.rig!r}")
                    events.append(AlarmEvent.from_dict(data))
                moved = self.adopt(events, doc["term"])
            except (DataError, ValueError, TypeError, AttributeError) as exc:
                log.warning("rig %s: alarms handed over on %s refused: %s", self.rig, self.keys.handover, exc)
                query.reply_err(json.dumps({"error": f"{self.keys.handover}: {exc}"}), encoding=_JSON)
                return
            except (SourceError, ConfigError) as exc:
                query.reply_err(json.dumps({"error": str(exc)}), encoding=_JSON)
                return
            epoch = getattr(self._history, "epoch", lambda _rig: "")(self.rig)
            query.reply(self.keys.handover, json.dumps({"term": self.term, "epoch": epoch, "alarms": moved}),
                        encoding=_JSON)

    # ------------------------------------------------------------------ queryables

    def _on_latest(self, query: zenoh.Query, what: str) -> None:
        with query:
            with self._latest_lock:
                payload = self._latest.get(what)
            if payload is not None:
                key = {"estimate": self.keys.estimate, "status": self.keys.status,
                       "forecast": self.keys.forecast}[what]
                query.reply(key, payload, encoding=_JSON)

    def _on_history(self, query: zenoh.Query) -> None:
        with query:
            try:
                since_seq = _int_parameter(query.parameters, "since_seq")
                since_t_ns = _int_parameter(query.parameters, "since_t_ns")
            except DataError as exc:
                query.reply_err(json.dumps({"error": str(exc)}), encoding=_JSON)
                return
            try:
                events = self._history.read(since_seq=since_seq, since_t_ns=since_t_ns, rig=self.rig)
            except (SourceError, DataError) as exc:
                log.error("rig %s: history query failed: %s", self.rig, exc)
                query.reply_err(json.dumps({"error": str(exc)}), encoding=_JSON)
                return
            for event in events:
                query.reply(self.keys.history, self._payload(event), encoding=_JSON)


class ForecastGate:
    """Whether a rig's forecast message goes on the bus now: the first, one that changed, or ``period_s`` (wall
    clock) after the last one put.

    Changed: a parameter's forecast appeared or ended (a message with none left is put too), a quantile of its
    exit time became or stopped being ``null``, its median exit time (record seconds, which a steady trend
    keeps) left the 90 % interval of the message put last - a change the forecast itself calls significant -, or
    that interval's width halved or doubled (the forecast became much surer or much less sure).
    """

    def __init__(self, period_s: float = FORECAST_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s = float(period_s)
        self._clock = clock
        self._last: dict[str, Any] | None = None
        self._last_wall = -math.inf

    @staticmethod
    def changed(old: dict[str, Any], new: dict[str, Any]) -> bool:
        """Whether ``new`` says something ``old`` did not (see the class)."""
        a, b = old.get("forecasts") or {}, new.get("forecasts") or {}
        if set(a) != set(b) or old.get("maintenance") != new.get("maintenance"):  # or a maintenance recorded
            return True
        for name, f in b.items():
            g = a[name]
            if any((f.get(k) is None) != (g.get(k) is None) for k in ("t_exit", "t_exit_lo", "t_exit_hi")):
                return True
            t, lo, hi = f.get("t_exit"), g.get("t_exit_lo"), g.get("t_exit_hi")
            if t is not None and not ((-math.inf if lo is None else lo) <= t <= (math.inf if hi is None else hi)):
                return True
            if lo is not None and hi is not None and f.get("t_exit_lo") is not None and f.get("t_exit_hi") is not None:
                w_old, w_new = hi - lo, f["t_exit_hi"] - f["t_exit_lo"]
                if w_new < 0.5 * w_old or w_new > 2.0 * w_old:
                    return True
        return False

    def __call__(self, msg: dict[str, Any]) -> bool:
        now = self._clock()
        put = self._last is None or now - self._last_wall >= self.period_s or self.changed(self._last, msg)
        if put:
            self._last, self._last_wall = msg, now
        return put


#: How an alarm raised by another owner during a split network and journaled again by the owner that stayed
#: begins its message: the term that raised it, the number it had there (:func:`split_mark`).
SPLIT_MARK = re.compile(r"^split: raised by term (\d+) as seq (\d+) .*?; renumbered by term (\d+)")


def split_mark(term: int, seq: int, wall_ns: int | None, by: int) -> str:
    """The mark of an alarm handed over after a split network (:data:`SPLIT_MARK` reads it back)."""
    from datetime import UTC, datetime

    when = "at an unknown time" if wall_ns is None else "at " + datetime.fromtimestamp(
        wall_ns / 1e9, tz=UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    return (f"split: raised by term {term} as seq {seq} {when} while the network was split (the owner that stood "
            f"down); renumbered by term {by}")


def signed_by(signer: Signer, data: Any) -> bool:
    """Whether an alarm payload (decoded) carries a valid signature of ``signer``'s key."""
    import base64

    from cryptography.exceptions import InvalidSignature

    from twin.service.signing import SIGNATURE_FIELD, canonical

    if not isinstance(data, dict) or not isinstance(data.get(SIGNATURE_FIELD), str):
        return False
    try:
        signer._key.public_key().verify(base64.b64decode(data[SIGNATURE_FIELD], validate=True), canonical(data))
    except (InvalidSignature, ValueError, TypeError):
        return False
    return True


def _ranges(numbers: list[int]) -> str:
    """``1..5, 8`` for [1, 2, 3, 4, 5, 8]."""
    runs: list[list[int]] = []
    for n in sorted(set(numbers)):
        if runs and n == runs[-1][1] + 1:
            runs[-1][1] = n
        else:
            runs.append([n, n])
    return ", ".join(str(lo) if lo == hi else f"{lo}..{hi}" for lo, hi in runs)


def _int_parameter(parameters: zenoh.Parameters, name: str) -> int | None:
    text = parameters.get(name)
    if text is None or text == "":
        return None
    try:
        value = int(text)
    except ValueError:
        raise DataError(f"selector parameter {name}: {text!r} must be an integer") from None
    if value < 0:
        raise DataError(f"selector parameter {name}: {value} must be >= 0")
    return value
