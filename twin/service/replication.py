"""A rig's state kept on its standbys: the owner puts each checkpoint on the bus (:class:`ReplicaSource`), a
standby keeps the latest one and every alarm in its own journal (:class:`Replica`).

Key space::

    fpdd/<rig>/replica/checkpoint   put  the owner's checkpoint at each ``checkpoint_s`` and when the rig stops
                                    get  the latest one (a standby that starts late asks it first)

A replica message is the checkpoint as :mod:`twin.service.checkpoint_file` writes it (data only: numbers,
strings, raw little-endian arrays in base64; never executed), with the rig's state (``running``,
``finished``, ``stopped``, ``failed``), the owner's ``service_id``, the epoch of the owner's alarm numbering and
the SHA-256 of its body; a damaged or foreign message is refused (logged) and the previous checkpoint kept. A
standby keeps the checkpoint in the owner's epoch (its journal takes it), so a takeover numbers on in the
owner's numbering even when the checkpoint came before the owner's first alarm.

A standby journals the owner's alarms (``fpdd/<rig>/alarm``) under the owner's numbers; a gap is filled from
the owner's ``fpdd/<rig>/alarm/history`` before anything after it, so its journal always holds 1..n without a
hole. A checkpoint is kept only once every alarm it counts (``alarm_seq``) is journaled here: a takeover from it
raises again only alarms after those, which the journal recognises by identity or numbers next. The standby
also notes the record time of the owner's last estimate (``watched_until``): a live rig taken over says how
much input nobody watched.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import queue
import threading
from typing import Any

import zenoh

from fpdd.errors import DataError, TwinError
from twin.online.events import AlarmEvent
from twin.service.checkpoint_file import Checkpoint, decode_state, encode_state
from twin.service.config import RigConfig, ServiceConfig
from twin.service.journal import AlarmJournal

log = logging.getLogger("twin.serve")

REPLICA_FORMAT = "fpdd-twin replica checkpoint"
REPLICA_VERSION = 1
_JSON = zenoh.Encoding.APPLICATION_JSON
#: How long a standby waits for the owner's history or latest checkpoint [s].
FETCH_S = 3.0


def replica_key(rig: str) -> str:
    return f"fpdd/{rig}/replica/checkpoint"


def _canonical(body: Any) -> bytes:
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode("utf-8")


def encode_replica(cp: Checkpoint, rig_state: str, service_id: str) -> str:
    body = {"rig": cp.rig, "t_ns": cp.t_ns, "samples": cp.samples, "fingerprint": cp.fingerprint,
            "saved_at": cp.saved_at, "alarm_seq": cp.alarm_seq, "rig_state": rig_state, "service_id": service_id,
            "state": encode_state(cp.state, f"{cp.rig}.state")}
    if cp.epoch:  # the owner's numbering the checkpoint counts alarm_seq in (absent from earlier owners' messages)
        body["epoch"] = cp.epoch
    data = _canonical(body)
    return json.dumps({"format": REPLICA_FORMAT, "version": REPLICA_VERSION,
                       "sha256": hashlib.sha256(data).hexdigest(), "body": body}, separators=(",", ":"))


def decode_replica(payload: str, rig: str) -> tuple[Checkpoint, str, str]:
    """``(checkpoint, rig state, owner's service id)``; raises DataError naming what is wrong."""
    try:
        doc = json.loads(payload)
    except ValueError as exc:
        raise DataError(f"{replica_key(rig)}: not JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != REPLICA_FORMAT or doc.get("version") != REPLICA_VERSION:
        raise DataError(f"{replica_key(rig)}: not a replica checkpoint of version {REPLICA_VERSION}")
    body = doc.get("body")
    if not isinstance(body, dict) or hashlib.sha256(_canonical(body)).hexdigest() != doc.get("sha256"):
        raise DataError(f"{replica_key(rig)}: the SHA-256 does not match the body (damaged)")
    try:
        if body["rig"] != rig:
            raise ValueError(f"rig {body['rig']!r}")
        state = decode_state(body["state"], f"{rig}.state")
        if not isinstance(state, dict):
            raise ValueError("state is not a mapping")
        epoch = str(body.get("epoch", ""))
        if epoch and not all(c in "0123456789abcdef" for c in epoch):
            raise ValueError(f"epoch {epoch!r}")
        cp = Checkpoint(rig, int(body["t_ns"]), int(body["samples"]), str(body["fingerprint"]), state,
                        float(body["saved_at"]), int(body["alarm_seq"]), epoch=epoch)
        return cp, str(body["rig_state"]), str(body["service_id"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{replica_key(rig)}: not a valid replica checkpoint ({type(exc).__name__}: {exc})") \
            from None


class ReplicaSource:
    """The owner's side: puts each checkpoint of its rig and answers ``get`` with the latest one."""

    def __init__(self, session, rig: str, service_id: str) -> None:
        self.rig = rig
        self.service_id = service_id
        self._latest: str | None = None
        self._lock = threading.Lock()
        key = replica_key(rig)
        self._pub = session.declare_publisher(key, encoding=_JSON, congestion_control=zenoh.CongestionControl.BLOCK,
                                              reliability=zenoh.Reliability.RELIABLE)
        self._q = session.declare_queryable(key, self._on_query)

    def publish(self, cp: Checkpoint, rig_state: str) -> None:
        """Put ``cp``; ``rig_state``: the runner's (``finished``, ``stopped`` and ``failed`` are said as they
        are, anything else is ``running``)."""
        rig_state = rig_state if rig_state in ("finished", "stopped", "failed") else "running"
        payload = encode_replica(cp, rig_state, self.service_id)
        with self._lock:
            self._latest = payload
        try:
            self._pub.put(payload)
        except zenoh.ZError as exc:
            log.warning("rig %s: checkpoint not replicated: %s", self.rig, exc)

    def _on_query(self, query) -> None:
        with query:
            with self._lock:
                payload = self._latest
            if payload is not None:
                query.reply(replica_key(self.rig), payload, encoding=_JSON)

    def close(self) -> None:
        for ent in (self._q, self._pub):
            try:
                ent.undeclare()
            except zenoh.ZError as exc:
                log.debug("rig %s: undeclare: %s", self.rig, exc)


class Replica:
    """A standby's copy of one rig: its journal (this service's, the owner's alarm numbers) and the latest
    checkpoint, kept up to date from the bus by one thread (see the module docstring).

    :raises SourceError, LogFormatError: the rig's journal here cannot be opened (as ``twin serve`` would).
    """

    def __init__(self, session, cfg: ServiceConfig, rig: RigConfig) -> None:
        from twin.service.bus import RigKeys
        from twin.service.checkpoints import commission_path, journal_path

        self.rig = rig.name
        self._session = session
        self.keys = RigKeys(rig.name)
        from twin.service.journal import Binding

        self.journal = AlarmJournal(journal_path(cfg, rig.name), witnesses=[commission_path(cfg, rig.name)],
                                    bind=Binding(rig.name, source=rig.source))
        self.checkpoint: Checkpoint | None = self.journal.load_checkpoint(rig.name)
        """The latest checkpoint kept (its alarms all journaled here)."""
        self.owner = ""
        """The service that published it."""
        self.finished = False
        """The owner said the rig's log ended."""
        self.watched_until_ns: int | None = self.checkpoint.t_ns if self.checkpoint else None
        self.alarms_received = 0
        self._work: queue.Queue[tuple | None] = queue.Queue()
        self._subs: list[Any] = []
        self._thread = threading.Thread(target=self._loop, name=f"replica-{rig.name}", daemon=True)
        try:
            self._subs.append(session.declare_subscriber(self.keys.alarm, lambda s: self._put("alarm", s)))
            self._subs.append(session.declare_subscriber(replica_key(rig.name), lambda s: self._put("checkpoint", s)))
            self._subs.append(session.declare_subscriber(self.keys.estimate, self._on_estimate))
        except BaseException:
            self.close()
            raise
        self._work.put(("catch_up", None))
        self._thread.start()

    # ------------------------------------------------------------------ from Zenoh threads (never block)

    def _put(self, kind: str, sample) -> None:
        self._work.put((kind, sample.payload.to_string()))

    def _on_estimate(self, sample) -> None:
        try:
            t = int(json.loads(sample.payload.to_string())["t_ns"])
        except (ValueError, KeyError, TypeError):
            return
        if self.watched_until_ns is None or t > self.watched_until_ns:
            self.watched_until_ns = t

    # ------------------------------------------------------------------ the replica's thread

    def _loop(self) -> None:
        while (item := self._work.get()) is not None:
            kind, payload = item
            if self.journal.closed:  # closed while this thread was in a query: the rest is dropped, not queried
                continue
            try:
                if kind == "alarm":
                    self._alarm(self._event(payload))
                elif kind == "checkpoint":
                    self._checkpoint(payload)
                else:
                    self._catch_up()
                    for reply in self._session.get(replica_key(self.rig), timeout=FETCH_S):
                        if reply.ok is not None:
                            self._checkpoint(reply.ok.payload.to_string())
            except (TwinError, zenoh.ZError, ValueError) as exc:
                log.warning("rig %s: replica: %s", self.rig, exc)
            except Exception as exc:  # noqa: BLE001 - a bug: said, and the replica goes on with the next message
                log.error("rig %s: replica: unexpected %s: %s", self.rig, type(exc).__name__, exc)
                log.debug("rig %s: replica", self.rig, exc_info=True)

    @staticmethod
    def _event(payload: str) -> AlarmEvent:
        ev = AlarmEvent.from_dict(json.loads(payload))
        return dataclasses.replace(ev, signature="") if ev.signature else ev

    def _alarm(self, ev: AlarmEvent, fill: bool = True) -> None:
        if ev.rig != self.rig:
            return
        last = self.journal.last_seq(self.rig)
        if ev.seq <= last:
            return
        if ev.seq > last + 1 and fill:
            self._catch_up()
            last = self.journal.last_seq(self.rig)
        if ev.seq == last + 1:
            if self.journal.record(ev).new:
                self.alarms_received += 1

    def _catch_up(self) -> None:
        """The owner's alarms after the last one journaled here, in order."""
        since = self.journal.last_seq(self.rig) + 1
        events = []
        for reply in self._session.get(f"{self.keys.history}?since_seq={since}", timeout=FETCH_S,
                                       consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is not None:
                try:
                    events.append(self._event(reply.ok.payload.to_string()))
                except (DataError, ValueError) as exc:
                    log.warning("rig %s: replica: a history reply refused: %s", self.rig, exc)
        for ev in sorted(events, key=lambda e: e.seq):
            self._alarm(ev, fill=False)

    def _checkpoint(self, payload: str) -> None:
        cp, rig_state, owner = decode_replica(payload, self.rig)
        if self.checkpoint is not None and cp.t_ns < self.checkpoint.t_ns and owner == self.owner:
            return  # an older one (a get's answer after a put)
        if self.journal.last_seq(self.rig) < cp.alarm_seq:
            self._catch_up()
        have = self.journal.last_seq(self.rig)
        if have < cp.alarm_seq:
            log.warning("rig %s: replica: checkpoint at t_ns=%d not kept: it counts %d alarm(s), %d journaled here",
                        self.rig, cp.t_ns, cp.alarm_seq, have)
            return
        if cp.epoch and cp.epoch != self.journal.epoch(self.rig):  # the owner's numbering, whatever this journal
            # made before the owner's first alarm came (else a takeover from this checkpoint would number in it)
            self.journal.adopt_epoch(self.rig, cp.epoch, replica=True)
        self.checkpoint = self.journal.save_checkpoint(cp)
        self.owner = owner
        if self.watched_until_ns is None or cp.t_ns > self.watched_until_ns:
            self.watched_until_ns = cp.t_ns
        if rig_state == "finished":
            self.finished = True

    # ------------------------------------------------------------------ life

    def close(self) -> None:
        """Stop following the bus (what was queued is journaled first), close the journal and stop the thread
        (idempotent). The thread never outlives this call by more than one query of the bus: a thread inside a
        Zenoh call when the session closes and the interpreter exits aborts the process (SIGABRT)."""
        for s in self._subs:
            try:
                s.undeclare()
            except zenoh.ZError as exc:
                log.debug("rig %s: undeclare: %s", self.rig, exc)
        self._subs.clear()
        if self._thread.is_alive():
            self._work.put(None)
            self._thread.join(timeout=2 * FETCH_S + 1.0)
        if not self.journal.closed:  # the owner's alarms journaled here were put by the owner
            from twin.service.put_mark import PutMark, put_mark_path

            PutMark(put_mark_path(self.journal.path), self.rig).done(self.journal.last_seq(self.rig),
                                                                     self.journal.epoch(self.rig))
        self.journal.close()
        if self._thread.is_alive():  # still in a query of the bus: with the journal closed the rest fails at once;
            # never leave the thread inside a Zenoh call into the session's close and the interpreter's exit
            self._thread.join(timeout=FETCH_S + 1.0)
            if self._thread.is_alive():
                log.warning("rig %s: replica: its thread did not stop within %.0f s", self.rig, 3 * FETCH_S + 2)
            else:
                log.debug("rig %s: replica: its thread stopped once the journal was closed", self.rig)
