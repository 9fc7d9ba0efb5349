"""The receiving side of the Zenoh layer (:mod:`twin.service.bus`): :class:`AlarmSubscriber`, every alarm of
one rig or all rigs, history first, then live; de-duplicated by ``(rig, seq)``, gaps filled from the twin's
history, re-synced when a twin's liveliness token (re)appears, a lost last alarm caught through the status's
``alarm_seq``, and with a trust store nothing forged (:mod:`twin.service.signing`)."""

from __future__ import annotations

import json
import logging
import queue
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import zenoh

from fpdd.zenohconf import zenoh_text
from fpdd.errors import DataError
from twin.online.events import AlarmEvent, StatusEvent
from twin.service.bus import SPLIT_MARK, SPLIT_S, RigKeys, _Declarations, _open_error, _ranges
from twin.service.signing import FORGED, STATUS_DOMAIN, UNVERIFIED, VERIFIED, TrustStore, Verdict

log = logging.getLogger("twin.service.bus")

_KEEP_DELIVERED = 100_000
"""Delivered alarms an :class:`AlarmSubscriber` remembers (to tell a conflicting duplicate from a plain one)."""


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

    Epochs (:mod:`twin.service.store`): a rig's numbers count within its epoch,
    which every alarm carries (signed) and the rig's owner announces in its signed
    status. The subscriber keeps per rig the epoch (:attr:`epochs`: from a verified
    status or alarm, or, for a rig without a key, from the alarms it delivers) and
    refuses, reported as ``replayed: ...``, an alarm of an earlier epoch (one
    recorded off the bus in another campaign and put again) and a live alarm whose
    number was received live before. A verified alarm or status of a later epoch
    (a new journal) starts the rig's numbering afresh: its alarms 1, 2, ... are
    delivered.

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
        """Every report line (``forged: ...``, ``conflict: ...``, ``unverified: ...``, ``replayed: ...``,
        ``epoch: ...``, ``split: ...``, ``superseded: ...``), in order."""
        self.epochs: dict[str, str] = {}
        """Per rig: the epoch its alarms are delivered in (see the class docstring)."""
        self.replayed = 0
        """Alarms refused as replays: of an earlier epoch, or a number received live before."""
        self._live: set[tuple[str, int]] = set()
        self.splits = 0
        """Times two ownership terms of one rig were seen publishing at once (a split network), each reported."""
        self.superseded = 0
        """Alarms delivered that an owner which stood down after a split network handed over (:mod:`twin.service.handover`):
        each reported in one line (``superseded: ...``) with the number it had on the losing side; when this
        subscriber had delivered the losing side's alarm under that number, the owner's alarm of the number is
        delivered from the history (:attr:`recovered` counts it; it is the one :meth:`last_seq` and a later
        duplicate are judged by from then on)."""
        self._refetch: set[tuple[str, int]] = set()
        self._terms: dict[str, dict[int, tuple[float, float]]] = {}  # rig -> term -> (first, last seen)
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
            self._ask_status(rig)  # the owners' announced epochs first: a replayed history reply is told by them
            for event, status in sorted(self._query(rig, since_seq, since_t_ns), key=lambda p: (p[0].rig, p[0].seq)):
                self._accept(event, status)
            self._redeliver()

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

    def _status_of(self, payload: str, key_expr: Any) -> tuple[StatusEvent, str] | None:
        """A status payload and its verdict (signed with the rig's key: ``verified``); ``None``: not a status or
        a forged one (logged)."""
        try:
            data = json.loads(payload)
            status = StatusEvent.from_dict(data)
        except (DataError, ValueError) as exc:
            log.warning("%s: rejected status payload: %s", key_expr, exc)
            return None
        verdict = self._trust.check(data, STATUS_DOMAIN)
        if verdict.status == FORGED:
            log.warning("%s: status not accepted: %s", key_expr, verdict.reason)
            return None
        return status, verdict.status

    def _on_status(self, sample: zenoh.Sample) -> None:
        got = self._status_of(sample.payload.to_string(), sample.key_expr)
        if got is not None:
            status, verdict = got
            self._inbox.put(("status", (status.rig, status.counters.get("alarm_seq"), status.epoch, verdict,
                                        status.term)))

    def _ask_status(self, rig: str) -> None:
        """Learn the epochs the rigs' owners announce (their latest status) before the history is judged."""
        try:
            replies = list(self._session.get(RigKeys(rig).status, timeout=min(self._query_timeout, 1.0)))
        except zenoh.ZError:
            return
        for reply in replies:
            if reply.ok is not None:
                got = self._status_of(reply.ok.payload.to_string(), reply.ok.key_expr)
                if got is not None and got[1] == VERIFIED and got[0].epoch:
                    self._learn_epoch(got[0].rig, got[0].epoch, f"the status of rig {got[0].rig}")

    def _on_twin(self, sample: zenoh.Sample) -> None:
        try:
            rig = RigKeys.rig_of(sample.key_expr)
        except DataError as exc:
            log.warning("liveliness: %s", exc)
            return
        self._inbox.put(("twin" if sample.kind == zenoh.SampleKind.PUT else "twin-gone", rig))

    # ------------------------------------------------------------------ epochs

    def _learn_epoch(self, rig: str, epoch: str, where: str) -> bool:
        """Take ``epoch`` (from a trusted source) as the rig's when none is known or it is later; ``True``
        when it is the rig's epoch now. A later epoch starts the rig's numbering afresh."""
        known = self.epochs.get(rig)
        if known is not None and epoch <= known:
            return epoch == known
        self.epochs[rig] = epoch
        if known is not None:
            self._report("epoch", f"rig {rig} numbers its alarms in a new epoch {epoch} (was {known or 'none'}), "
                         f"announced by {where}; its alarms from 1 are delivered")
            if rig in self._last:
                self._last[rig] = 0
            self._gaps.pop(rig, None)
            self._status_seq.pop(rig, None)
            for key in [k for k in self._delivered if k[0] == rig]:
                del self._delivered[key]
            self._live = {k for k in self._live if k[0] != rig}
        return True

    def _stale(self, event: AlarmEvent, where: str) -> bool:
        """An alarm of an earlier epoch than the rig's (reported, counted): ``True``, refuse it."""
        known = self.epochs.get(event.rig)
        if known is None or event.epoch >= known:
            return False
        self.rejected += 1
        self.replayed += 1
        self._report("replayed", f"rig {event.rig} seq {event.seq} on {where}: of epoch {event.epoch or 'none'}, "
                     f"earlier than the rig's epoch {known}; not accepted")
        return True

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
                self._live.discard(key)
        mark = SPLIT_MARK.match(event.message)
        if mark is not None:  # handed over by an owner that stood down after a split network
            term, old, by = (int(g) for g in mark.groups())
            self.superseded += 1
            self._report("superseded", f"rig {event.rig} seq {old} of term {term} was the losing side's of a split "
                         f"network (two owners at once): that alarm is seq {event.seq} now, in term {by}'s "
                         "numbering", once=True)
            had = self._delivered.get((event.rig, old))
            if had is not None and had.term == term and old != event.seq and not SPLIT_MARK.match(had.message):
                self._refetch.add((event.rig, old))  # the owner's alarm of that number: delivered from its history
        self._delivered[(event.rig, event.seq)] = event
        self.verification[(event.rig, event.seq)] = status
        if event.epoch and event.rig not in self.epochs:
            self.epochs[event.rig] = event.epoch
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
        if kind == "split":
            self.splits += 1
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
        replayed: dict[tuple[str, str, str], list[int]] = {}  # (replier, rig, epoch) -> seqs
        newest: dict[str, str] = {}  # the latest epoch trusted replies carry, per rig
        for _, event, verdict in answers:  # rigs without a key: repliers that disagree are never merged anyway
            if verdict.status == VERIFIED and event.epoch > newest.get(event.rig, ""):
                newest[event.rig] = event.epoch
        for rig, epoch in newest.items():
            self._learn_epoch(rig, epoch, f"the replies on {RigKeys(rig).history}")
        for replier, event, verdict in answers:
            rig = event.rig
            per_rig.setdefault(rig, {}).setdefault(replier, {})
            if verdict.status == FORGED or (verdict.status == UNVERIFIED and self._require_signed):
                key = ("forged" if verdict.status == FORGED else "unverified", replier, rig)
                forged.setdefault(key, []).append(event.seq)
                reasons[key] = verdict.reason
                continue
            if self._trust.has_key(rig) and rig in self.epochs and event.epoch < self.epochs[rig]:
                replayed.setdefault((replier, rig, event.epoch), []).append(event.seq)
                continue
            per_rig[rig][replier][event.seq] = event
            status.setdefault((rig, event.seq), {})[event] = verdict.status
        where = {r: RigKeys(r).history for r in per_rig}
        for (kind, replier, rig), seqs in forged.items():
            self.rejected += len(seqs)
            self._report(kind, f"rig {rig} seq {_ranges(seqs)} in replies of {replier} on {where[rig]}: "
                         f"{reasons[(kind, replier, rig)]}; not accepted", len(seqs), once=True)
        for (replier, rig, epoch), seqs in replayed.items():
            self.rejected += len(seqs)
            self.replayed += len(seqs)
            self._report("replayed", f"rig {rig} seq {_ranges(seqs)} in replies of {replier} on {where[rig]}: of "
                         f"epoch {epoch or 'none'}, earlier than the rig's epoch {self.epochs[rig]}; not accepted",
                         once=True)
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
        before = self.epochs.get(rig)
        answered = self._query(rig, since_seq, since_t_ns)
        if before is not None and self.epochs.get(rig) != before:  # a new epoch: its numbers from the start
            answered = self._query(rig, self.since_seq, None)
        found = sorted((p for p in answered if p[0].rig == rig), key=lambda p: p[0].seq)
        for event, status in found:
            self._accept(event, status)
        return [event for event, _ in found]

    def _twin_alive(self, rig: str, fresh: bool = False) -> bool:
        """Whether the rig's twin holds its liveliness token (asked again when not known alive, or ``fresh``:
        a twin killed a moment ago is still alive in the order of this subscriber's messages, its token's removal
        queued behind its last alarms, while a query finds nobody to answer it)."""
        if rig in self._alive and not fresh:
            return True
        try:
            replies = list(self._session.liveliness().get(RigKeys(rig).twin, timeout=min(self._query_timeout, 1.0)))
        except zenoh.ZError:
            return False
        if any(r.ok is not None for r in replies):
            self._alive.add(rig)
        elif fresh:
            self._alive.discard(rig)
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
        if event.epoch and event.epoch > self.epochs.get(rig, event.epoch) and not self._later_epoch(event, verdict):
            return
        if (verdict.status == VERIFIED or rig not in self._alive) and self._stale(event, RigKeys(rig).alarm):
            return  # an earlier epoch's alarm put again: moves nothing (an unverified one: the live twin's
            # history tells it below)
        last = self._last.get(rig)
        if last is not None and seq <= last and not self._in_gap(rig, seq):
            if (rig, seq) in self._live and self._delivered.get((rig, seq)) == event:
                self.replayed += 1  # the very alarm again: not a payload to reject, a number not to deliver twice
                self._report("replayed", f"rig {rig} seq {seq} on {RigKeys(rig).alarm}: received live before "
                             f"(epoch {event.epoch or 'none'}); not delivered again")
                return
            self._live.add((rig, seq))
            self._check_duplicate(event)
            return  # a duplicate (live after history, or twice)
        self._live.add((rig, seq))
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
        if verdict.status != VERIFIED and rig not in self._conflicted and self._twin_alive(rig, fresh=True):
            self.rejected += 1
            self._report("forged", f"rig {rig} seq {seq} on {RigKeys(rig).alarm}: not in the history of the rig's "
                         "live twin (not journaled by it); not accepted")
            return
        expected = self._expected(rig)
        if rig not in self._last and expected is not None and seq > expected:
            self._record_missed(rig, expected, seq - 1)
            self._last[rig] = seq - 1
        self._accept(event, verdict.status)  # signed by the rig, or unverifiable: never drop what may be real

    def _later_epoch(self, event: AlarmEvent, verdict: Verdict) -> bool:
        """A live alarm of a later epoch than the rig's: a verified one (or, without a key, one the rig's live
        twin's history holds, or any when no twin answers) starts the new epoch; else it is refused."""
        rig = event.rig
        if verdict.status != VERIFIED and self._twin_alive(rig):
            held = [e for e, _ in self._query(rig, event.seq, None) if e.seq == event.seq]
            if not any(replace(e, signature="") == replace(event, signature="") for e in held) and \
                    self._twin_alive(rig, fresh=True):
                self.rejected += 1
                self._report("forged", f"rig {rig} seq {event.seq} on {RigKeys(rig).alarm}: epoch {event.epoch} is "
                             "not the live twin's (not journaled by it); not accepted")
                return False
        self._learn_epoch(rig, event.epoch, f"alarm seq {event.seq} on {RigKeys(rig).alarm}")
        return True

    def _on_term(self, rig: str, term: int) -> None:
        """Two owners at once: a lower term's status seen after a higher term began publishing (within
        ``SPLIT_S``); reported once per pair of terms."""
        now = time.monotonic()
        seen = self._terms.setdefault(rig, {})
        first = seen.get(term, (now, now))[0]
        seen[term] = (first, now)
        for t in [t for t, (_, last) in seen.items() if now - last > SPLIT_S]:
            del seen[t]
        newer = [t for t in seen if t > term]
        if newer or any(t < term and seen[t][1] >= first for t in seen):
            pair = (min(seen), max(seen))
            self._report("split", f"rig {rig} is published by two owners at once (terms {pair[0]} and {pair[1]}): "
                         "the network was split; alarms of both are shown, a number claimed by both is a conflict",
                         once=True)

    def _on_alarm_seq(self, rig: str, alarm_seq: int | None, epoch: str = "", status: str = UNVERIFIED,
                      term: int = 0) -> None:
        if term:
            self._on_term(rig, term)
        if epoch:
            known = self.epochs.get(rig)
            if known is not None and epoch < known:
                return  # an earlier epoch's status (replayed): says nothing of the numbers now
            if status == VERIFIED:
                self._learn_epoch(rig, epoch, f"the status of rig {rig}")
            elif known is not None and epoch != known:
                return  # an unverifiable status of another epoch moves nothing
        if alarm_seq is None:
            return
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
            self._redeliver()
        return self._ready.popleft()

    def _redeliver(self) -> None:
        """Deliver from the history the owner's alarm of each number whose losing-side alarm (a split network)
        was delivered here (see :attr:`superseded`)."""
        while self._refetch:
            rig, seq = min(self._refetch)
            self._refetch.discard((rig, seq))
            had = self._delivered.get((rig, seq))
            for event, status in self._query(rig, seq, None):
                if event.rig == rig and event.seq == seq and had is not None and \
                        replace(event, signature="") != replace(had, signature=""):
                    self.recovered += 1
                    self._hand_over(event, status)

    def events(self, timeout: float | None = None) -> Iterator[AlarmEvent]:
        """Iterate over alarms; stops when none arrives within ``timeout`` seconds."""
        while True:
            try:
                yield self.recv(timeout)
            except TimeoutError:
                return

    def __iter__(self) -> Iterator[AlarmEvent]:
        return self.events(None)
