"""The Zenoh layer: publishing the twin's events and subscribing to its alarms.

Key space (one set of keys per rig; ``<rig>`` is one key chunk, see
:data:`twin.online.events.RIG_PATTERN`)::

    fpdd/<rig>/estimate        put    EstimateEvent JSON, every published tracker step
                               get    latest EstimateEvent (latest-value queryable)
    fpdd/<rig>/status          put    StatusEvent JSON, on change and periodically
                               get    latest StatusEvent (latest-value queryable)
    fpdd/<rig>/forecast        put    forecast JSON (``twin.online.forecast.FORECAST_SCHEMA``): when each
                                      parameter leaves its band, on change and every ``FORECAST_S``
                               get    latest forecast (latest-value queryable)
    fpdd/<rig>/alarm           put    AlarmEvent JSON, live alarms (reliable, blocking, high priority)
    fpdd/<rig>/alarm/history   get    every journaled AlarmEvent of the rig, one reply per alarm,
                                      in seq order; selector parameters (``;``-separated):
                                      ``since_seq=N`` (seq >= N), ``since_t_ns=T`` (t_ns >= T)
    fpdd/<rig>/twin            liveliness token, present while the twin serves the rig

Payloads are UTF-8 JSON (encoding ``application/json``) following the schemas in
:mod:`twin.online.events` (``AlarmEvent.SCHEMA``, ``EstimateEvent.SCHEMA``,
``StatusEvent.SCHEMA``) and :data:`twin.online.forecast.FORECAST_SCHEMA`. Every alarm carries ``seq``, a per-rig number 1, 2,
3, ... without gaps, assigned by the durable journal (:mod:`twin.service.journal`).

Delivery guarantees and how they are obtained:

* An alarm is appended to the journal and ``fsync``-ed *before* it is put
  (:meth:`TwinPublisher.publish_alarm`), so whatever reached a subscriber is on
  disk, and whatever is on disk is served by ``fpdd/<rig>/alarm/history``.
* Alarms are put reliably, with ``CongestionControl.BLOCK`` (never dropped
  by a full queue) and ``Priority.INTERACTIVE_HIGH``, ``express``.
* Zenoh still loses what is published while a link or router is down, and a
  plain subscriber receives nothing published before it joined. The
  :class:`AlarmSubscriber` therefore (1) subscribes first, then fetches the
  history, (2) de-duplicates by ``(rig, seq)``, (3) fills a gap in ``seq``
  from the history, (4) re-syncs from the history when a twin's liveliness
  token (re)appears (a twin or a router came back), and (5) catches a lost
  *last* alarm through the ``alarm_seq`` counter that every status carries.
* Who published it: with a per-rig key (:mod:`twin.service.signing`) every
  alarm put and every history reply carries an Ed25519 signature over all its
  fields; an :class:`AlarmSubscriber` with a trust store refuses and reports a
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
import queue
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, Self

import zenoh
from zenoh import ext as zext

from replay.zenohconf import (zenoh_text)
from twin.errors import ConfigError, DataError, SourceError
from twin.online.events import (
    RIG_PATTERN,
    validate,
    AlarmEvent,
    EstimateEvent,
    StatusEvent,
    event_to_json,
    format_alarm,
)
from twin.service.journal import AlarmJournal
from twin.service.signing import FORGED, UNVERIFIED, VERIFIED, Signer, TrustStore, Verdict

__all__ = [
    "KEY_PREFIX",
    "AlarmSubscriber",
    "ForecastGate",
    "RigKeys",
    "TwinPublisher",
    "fetch_forecasts",
    "fetch_latest",
    "format_alarm",
    "live_twins",
]

log = logging.getLogger(__name__)

KEY_PREFIX = "fpdd"
"""First chunk of every key of the service."""

_JSON = zenoh.Encoding.APPLICATION_JSON
_KEEP_DELIVERED = 100_000
"""Delivered alarms an :class:`AlarmSubscriber` remembers (to tell a conflicting duplicate from a plain one)."""
_RIG_RE = re.compile(RIG_PATTERN)
#: A rig's forecast is put when it changes (:class:`ForecastGate`) and at least this often while it is made [s].
FORECAST_S = 3.0


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
    :ivar twin: ``fpdd/<rig>/twin`` (liveliness)
    """

    __slots__ = ("rig", "estimate", "status", "forecast", "alarm", "history", "twin")

    def __init__(self, rig: str) -> None:
        self.rig = _check_rig(rig, wildcard=True)
        base = f"{KEY_PREFIX}/{rig}"
        self.estimate = f"{base}/estimate"
        self.status = f"{base}/status"
        self.forecast = f"{base}/forecast"
        self.alarm = f"{base}/alarm"
        self.history = f"{base}/alarm/history"
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
    """A rig's journal read from another process (no writer lock), plus alarms its writer could not write.

    The service's main process answers history queries with it while the
    rig's worker process owns the journal. ``add_pending`` keeps an alarm the
    worker published without a durable write, until the file has it.
    """

    def __init__(self, path: str | Path) -> None:
        from twin.service.store import Store

        self._store = Store(path, writer=False)
        self._pending: dict[tuple[str, int], AlarmEvent] = {}
        self._lock = threading.Lock()

    def add_pending(self, event: AlarmEvent) -> None:
        with self._lock:
            self._pending[(event.rig, event.seq)] = event

    def read(self, since_seq: int | None = None, since_t_ns: int | None = None,
             rig: str | None = None) -> list[AlarmEvent]:
        events = self._store.alarms(rig, since_seq, since_t_ns)
        have = {(e.rig, e.seq) for e in events}
        with self._lock:
            for key in [k for k in self._pending if k in have]:
                del self._pending[key]
            extra = [e for e in self._pending.values() if (rig in (None, "*") or e.rig == rig)
                     and (since_seq is None or e.seq >= since_seq) and (since_t_ns is None or e.t_ns >= since_t_ns)]
        return sorted(events + extra, key=lambda e: (e.rig, e.seq))

    def last_seq(self, rig: str) -> int:
        with self._lock:
            mine = [seq for (r, seq) in self._pending if r == rig]
        return max([self._store.last_seq(rig), *mine])

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


class TwinPublisher(_Declarations):
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
    ) -> None:
        self.rig = _check_rig(rig, wildcard=False)
        self.keys = RigKeys(rig)
        self._session = session
        self._journal = journal
        if signer is not None and signer.rig != rig:
            raise ConfigError(f"{signer.path}: the signing key of rig {signer.rig!r} given to the twin of rig {rig!r}")
        self._signer = signer
        if history is None and journal is None:
            raise ConfigError(f"rig {rig!r}: a twin publisher needs a journal or a history to answer from")
        self._history: History = history if history is not None else journal  # type: ignore[assignment]
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
            # The token last: a subscriber seeing the twin alive can query its history at once.
            self._keep(session.liveliness().declare_token(self.keys.twin))
        except zenoh.ZError as exc:
            self.close()
            raise _open_error(exc, f"rig {rig!r}: cannot declare the twin on the bus") from exc

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

    def _payload(self, event: AlarmEvent) -> str:
        """The alarm's JSON payload, signed when the rig has a key."""
        return event_to_json(event) if self._signer is None else self._signer.payload(event)

    def put_payload(self, what: str, payload: str) -> None:
        """Put an estimate or status already serialised (by a rig's worker) and keep it as the latest value."""
        pub = {"estimate": self._estimate_pub, "status": self._status_pub}[what]
        with self._latest_lock:
            self._latest[what] = payload
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
        try:
            self._estimate_pub.put(payload)
        except zenoh.ZError as exc:
            raise SourceError(f"rig {self.rig!r}: cannot publish estimate: {exc}") from exc

    def publish_forecast(self, msg: dict[str, Any]) -> bool:
        """A rig's forecast message (:func:`twin.online.forecast.forecast_message`, one per second of record):
        kept as the latest value (``get``), put on ``fpdd/<rig>/forecast`` when :class:`ForecastGate` says so
        (on change, else every :data:`FORECAST_S`).

        :returns: whether it was put.
        :raises DataError: another rig's message.
        """
        if msg.get("rig") != self.rig:
            raise DataError(f"forecast.rig: {msg.get('rig')!r} published through the twin of rig {self.rig!r}")
        from replay import jsonio

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
        event = replace(event, counters=counters)
        payload = event_to_json(event)
        with self._latest_lock:
            self._latest["status"] = payload
        try:
            self._status_pub.put(payload)
        except zenoh.ZError as exc:
            raise SourceError(f"rig {self.rig!r}: cannot publish status: {exc}") from exc
        return event

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
        if set(a) != set(b):
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


# --------------------------------------------------------------------------- queries


def fetch_forecasts(session: zenoh.Session, rig: str = "*", *, timeout: float = 5.0) -> list[dict[str, Any]]:
    """The latest forecast message of each matching running twin (a plain ``get`` on ``fpdd/<rig>/forecast``),
    sorted by rig; a reply that does not follow :data:`twin.online.forecast.FORECAST_SCHEMA` is left out (logged).
    """
    from twin.online.forecast import FORECAST_SCHEMA

    out = []
    for reply in session.get(RigKeys(rig).forecast, target=zenoh.QueryTarget.ALL, timeout=timeout):
        if reply.ok is None:
            continue
        try:
            d = json.loads(reply.ok.payload.to_string())
            validate(d, FORECAST_SCHEMA, "forecast")
        except (DataError, ValueError) as exc:
            log.warning("%s: rejected forecast reply: %s", reply.ok.key_expr, exc)
            continue
        out.append(d)
    return sorted(out, key=lambda d: d["rig"])


def fetch_latest(
    session: zenoh.Session,
    what: str,
    rig: str = "*",
    *,
    timeout: float = 5.0,
) -> list[EstimateEvent | StatusEvent]:
    """The latest estimate or status of each matching running twin (a plain ``get``).

    :param what: ``"estimate"`` or ``"status"``.
    :param rig: a rig id or ``"*"``.
    :param timeout: how long to wait for replies [s].
    :returns: one event per twin that has published one, sorted by rig.
    """
    keys = RigKeys(rig)
    parse: Callable[[Any], EstimateEvent | StatusEvent]
    if what == "estimate":
        key, parse = keys.estimate, EstimateEvent.from_dict
    elif what == "status":
        key, parse = keys.status, StatusEvent.from_dict
    else:
        raise ConfigError(f"what: {what!r} is not one of ['estimate', 'status']")
    events = []
    for reply in session.get(key, target=zenoh.QueryTarget.ALL, timeout=timeout):
        if reply.ok is not None:
            events.append(parse(json.loads(reply.ok.payload.to_string())))
    return sorted(events, key=lambda e: e.rig)


def live_twins(session: zenoh.Session, rig: str = "*", *, timeout: float = 5.0) -> list[str]:
    """The rigs whose twin is currently alive (liveliness tokens ``fpdd/<rig>/twin``), sorted."""
    rigs = set()
    for reply in session.liveliness().get(RigKeys(rig).twin, timeout=timeout):
        if reply.ok is not None:
            rigs.add(RigKeys.rig_of(reply.ok.key_expr))
    return sorted(rigs)


# --------------------------------------------------------------------------- subscriber


class AlarmSubscriber(_Declarations):
    """Every alarm of one rig (or all rigs), history first, then live; nothing forged, nothing dropped.

    On construction it subscribes to ``fpdd/<rig>/alarm``, to the status key
    (for ``alarm_seq``) and to the twins' liveliness, and only then fetches
    the history, so nothing published in between is lost. Each ``(rig, seq)``
    is handed out once, in ``seq`` order per rig as far as the history allows.

    The twin's journal (its history queryable) is the authority on what a
    sequence number holds:

    * a live alarm whose ``seq`` jumps ahead triggers a history query for the
      numbers in between *before* anything is declared lost; the history's
      version of an alarm wins over a live payload claiming the same number;
    * while the rig's twin is alive (its liveliness token is present), a live
      alarm or a status ``alarm_seq`` that its history does not hold is
      rejected (:attr:`rejected`, logged): it was not journaled by the twin,
      so it is forged or corrupt, and it moves no sequence number; an alarm
      no key vouches for is checked so even when it carries the number owed
      (the twin journals before it puts, so the history holds the real one);
    * with no twin alive nothing can be checked: the alarm is delivered (a
      real alarm is never dropped) and the numbers in between are recorded in
      :attr:`missed`; when a twin appears (liveliness), the history is
      fetched again from the first missed number, and every alarm found
      there is delivered, even below numbers already seen
      (:attr:`recovered` counts them).

    :param session: an open Zenoh session (stays open after :meth:`close`).
    :param rig: a rig id or ``"*"`` for all rigs.
    :param since_seq: deliver only ``seq >= since_seq`` (per rig).
    :param since_t_ns: deliver only alarms with ``t_ns >= since_t_ns`` from the history.
    Signatures (:mod:`twin.service.signing`): with a ``trust`` store, every live
    alarm and every history reply of a rig that has a key there is verified
    before anything else looks at it. One that does not verify (or is unsigned)
    is *forged*: reported (:attr:`reports`, ``on_report``), counted in
    :attr:`rejected`, and it moves no sequence number, so the real alarm of that
    number is still delivered when it comes. A validly signed alarm is real:
    it is delivered even when the history does not (yet) hold it. Alarms of a
    rig without a key are delivered as ``unverified`` (rejected with
    ``require_signed``). :attr:`verification` says, per delivered ``(rig, seq)``,
    ``verified`` or ``unverified``.

    Several history queryables (``QueryTarget.ALL``) are never merged: their
    replies are grouped by replier; when two repliers disagree on a rig
    (different alarms under one number, or numbers only one of them has), that
    is a *conflict*, reported once per query, and only verified alarms are taken
    from that query (with no keys: nothing, the bus cannot tell which replier
    is the twin). A different alarm arriving live under a number already
    delivered is reported as a conflict too (it is not delivered).

    :param history: fetch the history first (default). With ``False`` only live
        alarms are delivered; gaps between them are still filled.
    :param query_timeout: timeout of each history query [s].
    :param trust: the public keys to verify with (``None``: nothing is verified).
    :param require_signed: reject alarms of rigs without a key in ``trust`` too.
    :param on_report: called with ``(kind, line)`` for every ``forged``, ``conflict`` or
        ``unverified`` (rejected under ``require_signed``) report, on the consumer's thread.
    :raises ConfigError: ``rig`` is not a rig id or ``"*"``.
    :raises SourceError: the subscription failed (session closed, access denied).
    """

    def __init__(
        self,
        session: zenoh.Session,
        rig: str = "*",
        since_seq: int | None = None,
        since_t_ns: int | None = None,
        *,
        history: bool = True,
        query_timeout: float = 5.0,
        trust: TrustStore | None = None,
        require_signed: bool = False,
        on_report: Callable[[str, str], None] | None = None,
    ) -> None:
        self.keys = RigKeys(rig)
        self.rig = rig
        self._trust = trust if trust is not None else TrustStore()
        self._require_signed = require_signed
        self._on_report = on_report
        self._delivered: dict[tuple[str, int], AlarmEvent] = {}
        self._conflicted: set[str] = set()
        self._reported: set[str] = set()
        self.verification: dict[tuple[str, int], str] = {}
        """Per delivered ``(rig, seq)``: ``verified`` or ``unverified``."""
        self.reports: list[str] = []
        """Every report line (``forged: ...``, ``conflict: ...``, ``unverified: ...``), in order."""
        self.forged = 0
        """Alarms (live, or history replies the first time they are seen) that did not verify with their rig's key."""
        self.conflicts = 0
        """Disagreements of history repliers (each reported once), plus live alarms different from the one
        delivered under their number."""
        self.since_seq = since_seq
        self.since_t_ns = since_t_ns
        self._session = session
        self._history = history
        self._query_timeout = query_timeout
        self._inbox: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._ready: deque[AlarmEvent] = deque()
        self._last: dict[str, int] = {}
        self._gaps: dict[str, list[list[int]]] = {}
        self._alive: set[str] = set()
        self._status_seq: dict[str, int] = {}
        self._declared: list[Any] = []
        self.missed: list[tuple[str, int, int]] = []
        """Alarm numbers not recoverable when noticed: ``(rig, first_seq, last_seq)``."""
        self.recovered = 0
        """Alarms of a range recorded in :attr:`missed` that the history delivered later."""
        self.rejected = 0
        """Payloads rejected: not a valid alarm, or a number the live twin's history does not hold."""
        self.history_queries = 0
        """History queries sent (initial fetch, gap fills, re-syncs, checks)."""
        try:
            # Declarations reach a remote twin in this order: once a live alarm
            # arrives, the status and liveliness subscriptions are in place too.
            self._keep(session.declare_subscriber(self.keys.status, self._on_status))
            self._keep(session.liveliness().declare_subscriber(self.keys.twin, self._on_twin, history=True))
            self._keep(session.declare_subscriber(self.keys.alarm, self._on_alarm))
        except zenoh.ZError as exc:
            self.close()
            raise _open_error(exc, f"cannot subscribe to {self.keys.alarm}") from exc
        if history:
            for event, status in sorted(self._query(rig, since_seq, since_t_ns), key=lambda p: (p[0].rig, p[0].seq)):
                self._accept(event, status)

    # ------------------------------------------------------------------ life cycle

    def close(self) -> None:
        """Undeclare the subscriptions (idempotent); received events stay readable."""
        super().close()

    def last_seq(self, rig: str) -> int | None:
        """The highest ``seq`` of ``rig`` up to which every number was handed over or recorded missed."""
        return self._last.get(rig)

    # ------------------------------------------------------------------ zenoh callbacks
    # They run on Zenoh threads: parse, then hand over to the consumer's thread.

    def _on_alarm(self, sample: zenoh.Sample) -> None:
        try:
            data = json.loads(sample.payload.to_string())
            event = AlarmEvent.from_dict(data)
            if event.rig != RigKeys.rig_of(sample.key_expr):
                raise DataError(f"AlarmEvent.rig: {event.rig!r} published on {sample.key_expr}")
        except (DataError, ValueError) as exc:
            self._inbox.put(("rejected", f"{sample.key_expr}: rejected alarm payload: {exc}"))
            return
        self._inbox.put(("alarm", (event, self._trust.check(data))))

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = StatusEvent.from_dict(json.loads(sample.payload.to_string()))
        except (DataError, ValueError) as exc:
            log.warning("%s: rejected status payload: %s", sample.key_expr, exc)
            return
        if "alarm_seq" in status.counters:
            self._inbox.put(("status", (status.rig, status.counters["alarm_seq"])))

    def _on_twin(self, sample: zenoh.Sample) -> None:
        try:
            rig = RigKeys.rig_of(sample.key_expr)
        except DataError as exc:
            log.warning("liveliness: %s", exc)
            return
        self._inbox.put(("twin" if sample.kind == zenoh.SampleKind.PUT else "twin-gone", rig))

    # ------------------------------------------------------------------ ordering logic

    def _expected(self, rig: str) -> int | None:
        """The next ``seq`` owed for ``rig``, ``None`` when any number is acceptable."""
        if rig in self._last:
            return self._last[rig] + 1
        if not self._history:
            return None
        if self.since_seq is not None:
            return self.since_seq
        return 1 if self.since_t_ns is None else None

    def _in_gap(self, rig: str, seq: int) -> bool:
        return any(lo <= seq <= hi for lo, hi in self._gaps.get(rig, ()))

    def _close_gap(self, rig: str, seq: int) -> None:
        out = []
        for lo, hi in self._gaps.get(rig, ()):
            if lo <= seq <= hi:
                out += [r for r in ([lo, seq - 1], [seq + 1, hi]) if r[0] <= r[1]]
            else:
                out.append([lo, hi])
        self._gaps[rig] = out

    def _accept(self, event: AlarmEvent, status: str = UNVERIFIED) -> bool:
        """Hand ``event`` over unless its number was handed over already."""
        rig, seq = event.rig, event.seq
        if self.since_seq is not None and seq < self.since_seq:
            return False
        last = self._last.get(rig)
        if last is not None and seq <= last:
            if not self._in_gap(rig, seq):
                self._check_duplicate(event)
                return False
            self._close_gap(rig, seq)  # a number recorded missed, found in the history after all
            self.recovered += 1
            self._hand_over(event, status)
            return True
        if last is not None and seq > last + 1:
            self._record_missed(rig, last + 1, seq - 1)
        self._last[rig] = seq
        self._hand_over(event, status)
        return True

    def _hand_over(self, event: AlarmEvent, status: str) -> None:
        if len(self._delivered) >= _KEEP_DELIVERED:  # a subscriber that runs for years: forget the oldest half
            for key in list(self._delivered)[: _KEEP_DELIVERED // 2]:
                del self._delivered[key]
                self.verification.pop(key, None)
        self._delivered[(event.rig, event.seq)] = event
        self.verification[(event.rig, event.seq)] = status
        self._ready.append(event)

    def _check_duplicate(self, event: AlarmEvent) -> None:
        """A number seen again: the same alarm is a harmless duplicate, a different one a conflict."""
        first = self._delivered.get((event.rig, event.seq))
        if first is not None and replace(first, signature="") != replace(event, signature=""):
            self._report("conflict", f"rig {event.rig} seq {event.seq}: a different alarm under a number already "
                         f"delivered ({first.parameter} {first.level} {first.kind} delivered, "
                         f"{event.parameter} {event.level} {event.kind} now); not delivered")

    def _report(self, kind: str, text: str, count: int = 1, once: bool = False) -> None:
        """Report one line; ``once``: not again when the same line was reported (a history asked again)."""
        line = f"{kind}: {text}"
        if once and line in self._reported:
            return
        self._reported.add(line)
        if kind == "forged":
            self.forged += count
        elif kind == "conflict":
            self.conflicts += count
        self.reports.append(line)
        log.warning("%s", line)
        if self._on_report is not None:
            self._on_report(kind, line)

    def _admit(self, event: AlarmEvent, verdict: Verdict, where: str) -> bool:
        """Whether a payload may be looked at further; a forged one is reported, counted and dropped."""
        if verdict.status == FORGED:
            self.rejected += 1
            self._report("forged", f"rig {event.rig} seq {event.seq} on {where}: {verdict.reason}; not accepted")
            return False
        if verdict.status == UNVERIFIED and self._require_signed:
            self.rejected += 1
            self._report("unverified", f"rig {event.rig} seq {event.seq} on {where}: {verdict.reason}; "
                         "not accepted (signatures required)")
            return False
        return True

    def _query(self, rig: str, since_seq: int | None, since_t_ns: int | None) -> list[tuple[AlarmEvent, str]]:
        """The history's alarms that may be delivered, with their verification status (see :meth:`_judge`)."""
        parameters = {}
        if since_seq is not None:
            parameters["since_seq"] = str(since_seq)
        if since_t_ns is not None:
            parameters["since_t_ns"] = str(since_t_ns)
        selector = zenoh.Selector(RigKeys(rig).history, parameters)
        self.history_queries += 1
        answers: list[tuple[str, AlarmEvent, Verdict]] = []
        try:
            replies = self._session.get(
                selector,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=self._query_timeout,
            )
            for reply in replies:
                if reply.ok is None:
                    assert reply.err is not None  # a reply is either ok or an error
                    log.warning("%s: history error: %s", selector, reply.err.payload.to_string())
                    continue
                who = reply.replier_id  # a session and an entity in it: two queryables are two repliers
                replier = "queryable " + (f"{who.zid}:{who.eid}" if who is not None else "(unknown)")
                try:
                    data = json.loads(reply.ok.payload.to_string())
                    event = AlarmEvent.from_dict(data)
                    if event.rig != RigKeys.rig_of(reply.ok.key_expr):
                        raise DataError(f"AlarmEvent.rig: {event.rig!r} in a reply on {reply.ok.key_expr}")
                    answers.append((replier, event, self._trust.check(data)))
                except (DataError, ValueError) as exc:
                    self.rejected += 1
                    log.warning("%s: rejected history reply from %s: %s", selector, replier, exc)
        except zenoh.ZError as exc:
            log.warning("%s: history query failed: %s", selector, zenoh_text(exc))
        return self._judge(answers)

    def _judge(self, answers: list[tuple[str, AlarmEvent, Verdict]]) -> list[tuple[AlarmEvent, str]]:
        """What may be delivered from the replies of one query, never merging disagreeing repliers.

        Forged replies are dropped (one report per replier and rig). A verified
        alarm is taken unless another verified one claims its number. An
        unverified alarm is taken only when every replier that answered for its
        rig gave exactly it. Repliers that disagree are reported once.
        """
        forged: dict[tuple[str, str, str], list[int]] = {}  # (kind, replier, rig) -> seqs
        reasons: dict[tuple[str, str, str], str] = {}
        per_rig: dict[str, dict[str, dict[int, AlarmEvent]]] = {}
        status: dict[tuple[str, int], dict[AlarmEvent, str]] = {}
        for replier, event, verdict in answers:
            rig = event.rig
            per_rig.setdefault(rig, {}).setdefault(replier, {})
            if verdict.status == FORGED or (verdict.status == UNVERIFIED and self._require_signed):
                key = ("forged" if verdict.status == FORGED else "unverified", replier, rig)
                forged.setdefault(key, []).append(event.seq)
                reasons[key] = verdict.reason
                continue
            per_rig[rig][replier][event.seq] = event
            status.setdefault((rig, event.seq), {})[event] = verdict.status
        where = {r: RigKeys(r).history for r in per_rig}
        for (kind, replier, rig), seqs in forged.items():
            self.rejected += len(seqs)
            self._report(kind, f"rig {rig} seq {_ranges(seqs)} in replies of {replier} on {where[rig]}: "
                         f"{reasons[(kind, replier, rig)]}; not accepted", len(seqs), once=True)
        out: list[tuple[AlarmEvent, str]] = []
        for rig, by_replier in per_rig.items():
            views = {replier: frozenset(alarms.items()) for replier, alarms in by_replier.items()}
            agree = len(set(views.values())) <= 1
            if not agree:
                self._conflicted.add(rig)
                names = sorted(views)
                numbers = sorted(set().union(*(set(a) for a in by_replier.values())))
                self._report("conflict", f"rig {rig}: the history on {where[rig]} is answered differently by "
                             f"{len(names)} repliers ({', '.join(names)}; seq {_ranges(numbers)}); not merged: "
                             "only alarms that verify with the rig's key are taken", once=True)
            else:
                self._conflicted.discard(rig)
            seqs = sorted(set().union(*(set(a) for a in by_replier.values())))
            for seq in seqs:
                versions = status.get((rig, seq), {})
                verified = [e for e, st in versions.items() if st == VERIFIED]
                if len(verified) == 1:
                    out.append((verified[0], VERIFIED))
                elif len(verified) > 1:
                    self._report("conflict", f"rig {rig} seq {seq}: {len(verified)} different alarms that all "
                                 "verify with the rig's key; none delivered", once=True)
                elif agree and len(versions) == 1:
                    out.append((next(iter(versions)), UNVERIFIED))
        return out

    def _fill(self, rig: str) -> list[AlarmEvent]:
        """Fetch what the history holds for ``rig`` from the first number not yet handed over."""
        gaps = self._gaps.get(rig)
        since_seq: int | None
        if gaps:
            since_seq, since_t_ns = min(lo for lo, _ in gaps), None
        elif rig in self._last:
            since_seq, since_t_ns = self._last[rig] + 1, None
        else:
            since_seq, since_t_ns = self.since_seq, self.since_t_ns
        found = sorted((p for p in self._query(rig, since_seq, since_t_ns) if p[0].rig == rig),
                       key=lambda p: p[0].seq)
        for event, status in found:
            self._accept(event, status)
        return [event for event, _ in found]

    def _twin_alive(self, rig: str) -> bool:
        """Whether the rig's twin holds its liveliness token (asked again when not known alive)."""
        if rig in self._alive:
            return True
        try:
            replies = list(self._session.liveliness().get(RigKeys(rig).twin, timeout=min(self._query_timeout, 1.0)))
        except zenoh.ZError:
            return False
        if any(r.ok is not None for r in replies):
            self._alive.add(rig)
        return rig in self._alive

    def _record_missed(self, rig: str, first: int, last: int) -> None:
        self.missed.append((rig, first, last))
        self._gaps.setdefault(rig, []).append([first, last])
        log.warning(
            "rig %s: alarms seq %d..%d were lost in transit and the twin's history could not supply them "
            "(no twin reachable); they are fetched when the twin is back",
            rig, first, last,
        )

    def _reject(self, message: str) -> None:
        self.rejected += 1
        log.warning("%s", message)

    def _on_live(self, event: AlarmEvent, verdict: Verdict) -> None:
        rig, seq = event.rig, event.seq
        if not self._admit(event, verdict, RigKeys(rig).alarm):
            return  # forged: moves nothing, the real alarm of this number is still awaited
        last = self._last.get(rig)
        if last is not None and seq <= last and not self._in_gap(rig, seq):
            self._check_duplicate(event)
            return  # a duplicate (live after history, or twice)
        expected = self._expected(rig)
        if expected is not None and seq < expected and last is None:
            return  # below --since-seq
        # An alarm that no key vouches for, with the number owed, while the rig's twin is alive: the twin
        # journals before it puts, so its history holds the real alarm of that number; ask it first.
        check = verdict.status != VERIFIED and expected is not None and rig in self._alive
        if expected is None or (seq == expected and not check):
            self._accept(event, verdict.status)
            return
        # A jump, a number inside a recorded gap, or an unverified number: ask the history before believing it.
        found = {e.seq: e for e in self._fill(rig)}
        if seq in found:
            if replace(found[seq], signature="") != replace(event, signature=""):
                self.rejected += 1
                self._report("forged", f"rig {rig} seq {seq} on {RigKeys(rig).alarm}: differs from the alarm the "
                             "twin journaled under that number (that one was delivered); not accepted")
            return
        if verdict.status != VERIFIED and rig not in self._conflicted and self._twin_alive(rig):
            self.rejected += 1
            self._report("forged", f"rig {rig} seq {seq} on {RigKeys(rig).alarm}: not in the history of the rig's "
                         "live twin (not journaled by it); not accepted")
            return
        expected = self._expected(rig)
        if rig not in self._last and expected is not None and seq > expected:
            self._record_missed(rig, expected, seq - 1)
            self._last[rig] = seq - 1
        self._accept(event, verdict.status)  # signed by the rig, or unverifiable: never drop what may be real

    def _on_alarm_seq(self, rig: str, alarm_seq: int) -> None:
        if self._status_seq.get(rig) == alarm_seq:
            return
        self._status_seq[rig] = alarm_seq
        last = self._last.get(rig)
        if last is not None and alarm_seq <= last and not self._gaps.get(rig):
            return
        if last is None and not self._history:
            return
        expected = self._expected(rig)
        if expected is not None and alarm_seq < expected and not self._gaps.get(rig):
            return
        self._fill(rig)
        expected = self._expected(rig)
        if expected is None or alarm_seq < expected:
            return
        if rig not in self._conflicted and self._twin_alive(rig):
            self._reject(f"rig {rig}: a status claims alarm seq {alarm_seq}, the twin's history ends at "
                         f"{expected - 1}; claim ignored")
            return
        self._record_missed(rig, expected, alarm_seq)
        self._last[rig] = alarm_seq

    def _process(self, kind: str, value: Any) -> None:
        if kind == "alarm":
            self._on_live(*value)
        elif kind == "status":
            self._on_alarm_seq(*value)
        elif kind == "rejected":
            self._reject(value)
        elif kind == "twin-gone":
            self._alive.discard(value)
        elif kind == "twin":
            self._alive.add(value)
            if self._history or value in self._last:
                self._fill(value)

    # ------------------------------------------------------------------ consuming

    def recv(self, timeout: float | None = None) -> AlarmEvent:
        """The next alarm, blocking up to ``timeout`` seconds (``None``: forever).

        :raises TimeoutError: no alarm within ``timeout``.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._ready:
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise TimeoutError(f"no alarm on {self.keys.alarm} within {timeout} s")
            try:
                kind, value = self._inbox.get(timeout=remaining)
            except queue.Empty:
                raise TimeoutError(f"no alarm on {self.keys.alarm} within {timeout} s") from None
            self._process(kind, value)
        return self._ready.popleft()

    def events(self, timeout: float | None = None) -> Iterator[AlarmEvent]:
        """Iterate over alarms; stops when none arrives within ``timeout`` seconds."""
        while True:
            try:
                yield self.recv(timeout)
            except TimeoutError:
                return

    def __iter__(self) -> Iterator[AlarmEvent]:
        return self.events(None)


# --------------------------------------------------------------------------- CLI
