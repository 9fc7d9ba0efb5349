"""The durable alarm journal of a twin: an SQLite database (:mod:`twin.service.store`) and its rigs' checkpoints.

Every alarm the twin publishes is journaled first: committed with
``synchronous=FULL`` and folded into the main database file
(:meth:`twin.service.store.Store.insert_alarm`), so the bus's history
queryable (which answers from the journal) has every alarm that was ever
published, whatever happens to the WAL. The journal numbers the alarms of
each rig 1, 2, 3, ... and keeps one alarm per identity
(:attr:`twin.online.events.AlarmEvent.identity`): re-processing the same data after a
restart raises the same alarms, which are recognised and neither journaled
nor published again.

When a write fails (disk full, file system remounted read-only, I/O error)
the alarm gets the next number and stays in memory as *pending*: it is not
published (:attr:`Recorded.durable` is False) until it is on disk; every later
:meth:`AlarmJournal.record` (and :meth:`AlarmJournal.retry`) writes the pending
alarms again, in order, and :meth:`AlarmJournal.take_written` hands over those
now journaled, to be published then. :attr:`AlarmJournal.write_error` names the
file and the cause while writes fail; the service reports it (and the alarms
held) in the rig's status. No checkpoint is saved while an alarm is pending, so
a restart re-processes its data, raises it again and publishes it once: an
alarm is never published twice, with or without a restart in between.

Checkpoints live beside the journal (``<stem>.checkpoint.json``,
:func:`twin.service.checkpoint_file.read_checkpoints`: data only, versioned). Each
records the journal's id and the rig's last alarm number; on open, a journal
that is missing, empty, replaced or whose alarms end before the checkpoint's
(or, without a checkpoint, one missing or empty where a ``witnesses`` file such
as a commissioning says the rig ran before) is refused with one line.

Binding: the service opens a rig's journal with the rig it belongs to (:class:`Binding`: the rig's name,
its signing key's fingerprint, its source). The first open records them in the journal; a journal that holds
another rig's alarms or was recorded for another rig or under another key is refused with one line (a
journal copied from another rig, with or without its checkpoint, is never continued). The checkpoint beside
it is sealed under the journal's own key and names the rig's epoch and source
(:mod:`twin.service.checkpoint_file`).

Migration: the journal of earlier versions was a JSON-lines file
(``<rig>.alarms.jsonl``). Given ``legacy=PATH``, an existing file is imported
once, in one transaction, and renamed ``PATH.imported``; a file that is not a
clean journal (a bad line other than a torn last one, or sequence numbers
that jump) is refused with the file and line, and nothing is imported.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Self

from fpdd.errors import DataError, LogFormatError, SourceError
from twin.online.events import AlarmEvent
from twin.service.checkpoint_file import Checkpoint, checkpoint_path, read_checkpoints, write_checkpoints
from twin.service.store import Continuity, NotFolded, Store

__all__ = ["AlarmJournal", "Binding", "Recorded", "read_legacy_journal"]

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Recorded:
    """What :meth:`AlarmJournal.record` did with an alarm."""

    event: AlarmEvent
    """The alarm with its sequence number (for a duplicate: the one journaled before)."""
    new: bool
    """False: an alarm of the same identity was journaled before (do not publish it again)."""
    durable: bool
    """False: the write failed; the alarm is pending in memory, retried, and must not be published until
    :meth:`AlarmJournal.take_written` hands it over."""


@dataclasses.dataclass(frozen=True)
class Binding:
    """The rig a journal belongs to (see the module docstring)."""

    rig: str
    key: str = ""
    """The fingerprint of the rig's signing key (``""``: unsigned)."""
    source: str = ""
    """The rig's source URI (recorded, not enforced: a rig's next campaign may read another log)."""


class AlarmJournal:
    """Alarms and checkpoints of one or more rigs in one SQLite file (one writer).

    :param path: the database file (created with its directory if missing).
    :param legacy: an old JSON-lines journal to import once if it exists.
    :param witnesses: files whose existence says the journal's rigs ran before (a saved commissioning).
    :param bind: the rig the journal belongs to (refused when it is another's; see the module docstring).
    :raises SourceError: the file cannot be opened or is locked by another writer.
    :raises LogFormatError: the file (or the legacy journal, or the checkpoint) is corrupt, or the journal
        disagrees with its checkpoint or witnesses (module docstring); nothing is changed.
    """

    def __init__(self, path: str | os.PathLike[str], *, legacy: str | os.PathLike[str] | None = None,
                 lock_wait_s: float = 5.0, witnesses: Iterable[str | os.PathLike[str]] = (),
                 bind: Binding | None = None) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SourceError(f"{self.path.parent}: cannot create the journal directory "
                              f"({exc.strerror or exc})") from None
        self.checkpoint_path = checkpoint_path(self.path)
        self._checkpoints: dict[str, Checkpoint] = {}
        seen = [Path(w) for w in witnesses]

        def expect() -> Continuity | None:  # read once the writer's lock is held: no writer changes it meanwhile
            saved = read_checkpoints(self.checkpoint_path)
            if saved is not None:
                self._checkpoints = saved[1]
                when = max((cp.saved_at for cp in self._checkpoints.values()), default=None)
                stamp = f" of {time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(when))}" if when is not None else ""
                return Continuity(f"its checkpoint {self.checkpoint_path.name}{stamp}", saved[0],
                                  {rig: cp.alarm_seq for rig, cp in self._checkpoints.items()})
            there = [w for w in seen if w.exists()]
            return Continuity(str(there[0])) if there else None

        self.store = Store(self.path, lock_wait_s=lock_wait_s, expect=expect)
        self._lock = threading.Lock()
        self._pending: list[AlarmEvent] = []
        self._written: list[AlarmEvent] = []
        self.write_error: str | None = None
        """While writes fail: one line naming the file and the cause; ``None`` when all is on disk."""
        self.imported = 0
        """Alarms imported from the legacy journal by this open."""
        try:
            saved = read_checkpoints(self.checkpoint_path, self.store.secret, legacy=self.store.new_secret)
            self._checkpoints = saved[1] if saved is not None else {}  # sealed under this journal's key
            if bind is not None:
                self._bind(bind)
            if legacy is not None:
                self._import(Path(legacy))
        except BaseException:
            self.store.close()
            raise

    def _bind(self, bind: Binding) -> None:
        """Refuse a journal of another rig or key; record the binding at the first open."""
        store, rig = self.store, bind.rig
        fix = (f"refused: put rig {rig}'s own journal back, or move this one (and its checkpoint) aside to start "
               "a new journal (a new epoch)")
        owner = store.meta("rig")
        others = [r for r in store.rigs() if r != rig]
        if (owner is not None and owner != rig) or others:
            who = owner if owner is not None and owner != rig else others[0]
            raise LogFormatError(f"{self.path}: the journal of rig {who!r}, not of rig {rig!r} (copied from another "
                                 f"rig?); {fix}")
        key = store.meta(f"key:{rig}")
        if bind.key and key and key != bind.key:
            raise LogFormatError(f"{self.path}: the journal of rig {rig!r} under signing key {key}, the rig's key is "
                                 f"{bind.key} now (another rig's journal, or a new key: a new key starts a new "
                                 f"journal); {fix}")
        values = {"rig": rig, f"source:{rig}": bind.source}
        if bind.key:
            values[f"key:{rig}"] = bind.key
        if any(store.meta(k) != v for k, v in values.items()):
            store.set_meta(values)

    # ------------------------------------------------------------------ life cycle

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Try the pending alarms one last time, then close (idempotent)."""
        if not self.store.closed:
            self.retry()
            if self._pending:
                log.error("%s: closing with %d alarm(s) not written (%s); they were not published, and no "
                          "checkpoint was saved after them: a restart goes back to before them (a log is "
                          "processed again and raises them; a live rig's detector resumes from there)", self.path,
                          len(self._pending), self.write_error)
        self.store.close()

    @property
    def closed(self) -> bool:
        return self.store.closed

    # ------------------------------------------------------------------ writing

    def record(self, event: AlarmEvent) -> Recorded:
        """Journal ``event`` (see the module docstring); on a write failure it is pending (not durable: do
        not publish it before :meth:`take_written` returns it).

        :raises DataError: ``event.seq`` is not 0 and not the rig's next number.
        :raises SourceError: the journal is closed.
        """
        if event.wall_ns is None:  # the wall-clock time beside the record's: when it was raised
            event = dataclasses.replace(event, wall_ns=time.time_ns())
        with self._lock:
            if self.store.closed:
                raise SourceError(f"{self.path}: alarm journal is closed")
            self._retry_locked()
            for p in self._pending:
                if p.identity == event.identity:
                    return Recorded(p, False, False)
            if not self._pending:
                try:
                    ev, new = self.store.insert_alarm(event)
                    return Recorded(ev, new, True)
                except NotFolded as exc:  # numbered and committed, not yet in the main file
                    self._failed(exc)
                    self._pending.append(exc.event)
                    log.error("rig %s: alarm seq %d is in the WAL only, not published until it is in the main "
                              "file: %s", exc.event.rig, exc.event.seq, self.write_error)
                    return Recorded(exc.event, True, False)
                except SourceError as exc:
                    self._failed(exc)
            try:
                found = self.store.find(event.identity)
            except SourceError:
                found = None
            if found is not None:
                return Recorded(found, False, True)
            nxt = self._last_seq_locked(event.rig) + 1
            if event.seq not in (0, nxt):
                raise DataError(f"AlarmEvent.seq: {event.seq} for rig {event.rig!r} where {nxt} "
                                f"(the next journal number) or 0 (assign) was expected")
            event = event.with_seq(nxt)
            if not event.epoch and event.rig in self.store._epochs:  # known: the pending alarm carries it already
                event = dataclasses.replace(event, epoch=self.store._epochs[event.rig])
            self._pending.append(event)
            log.error("rig %s: alarm seq %d kept in memory, not on disk and not published yet: %s; retrying "
                      "with every alarm and every block", event.rig, event.seq, self.write_error)
            return Recorded(event, True, False)

    def append(self, event: AlarmEvent) -> AlarmEvent:
        """:meth:`record` returning just the journaled event (with its ``seq``)."""
        return self.record(event).event

    def retry(self) -> bool:
        """Write the pending alarms; ``True`` when nothing is pending any more."""
        with self._lock:
            return self._retry_locked()

    def _retry_locked(self) -> bool:
        while self._pending:
            try:
                done, _ = self.store.insert_alarm(self._pending[0])  # a duplicate when committed, not folded
                self.store.fold()
            except SourceError as exc:
                self._failed(exc)
                return False
            self._pending.pop(0)
            self._written.append(done)
            log.warning("rig %s: pending alarm seq %d is now on disk in %s", done.rig, done.seq, self.path)
        if self.write_error is not None:
            log.warning("%s: journal writes work again", self.path)
        self.write_error = None
        return True

    def _failed(self, exc: SourceError) -> None:
        self.write_error = str(exc)

    def take_written(self) -> list[AlarmEvent]:
        """Alarms that were pending and are journaled now (each handed over once): publish them."""
        with self._lock:
            done, self._written = self._written, []
            return done

    @property
    def pending(self) -> int:
        """Alarms kept in memory because their write failed."""
        with self._lock:
            return len(self._pending)

    def pending_alarms(self) -> list[AlarmEvent]:
        """The alarms kept in memory (not journaled, not published), oldest first."""
        with self._lock:
            return list(self._pending)

    # ------------------------------------------------------------------ checkpoints

    def save_checkpoint(self, cp: Checkpoint) -> Checkpoint:
        """Save a rig's checkpoint with the journal's id and the rig's last journaled alarm number.

        :returns: the checkpoint as saved.
        :raises SourceError: alarms of the rig are pending (a checkpoint after them would keep a restart
            from raising them again), or the file cannot be written (naming it).
        :raises TypeError: the state holds something that is not plain data.
        """
        with self._lock:
            held = [p.seq for p in self._pending if p.rig == cp.rig]
            if held:
                raise SourceError(f"{self.checkpoint_path}: checkpoint held while {len(held)} alarm(s) of rig "
                                  f"{cp.rig} are not journaled ({self.write_error})")
            if self.store.journal_id is None:
                raise SourceError(f"{self.path}: the journal has no id")
            cp = dataclasses.replace(cp, alarm_seq=self.store.last_seq(cp.rig), journal_id=self.store.journal_id,
                                     epoch=self.store.epoch(cp.rig))
            write_checkpoints(self.checkpoint_path, self.store.journal_id, {**self._checkpoints, cp.rig: cp},
                              self.store.secret)
            self._checkpoints[cp.rig] = cp
            return cp

    def load_checkpoint(self, rig: str) -> Checkpoint | None:
        """The rig's checkpoint read at open (checked against the journal), ``None`` if it has none."""
        with self._lock:
            return self._checkpoints.get(rig)

    # ------------------------------------------------------------------ reading

    def begin_term(self, rig: str, term: int) -> None:
        """This service runs ``rig`` from now in ownership ``term``: its alarms carry it (:mod:`twin.service.ownership`).

        :raises SourceError: it cannot be written (naming the file).
        """
        self.store.set_meta({f"term:{rig}": str(int(term))})

    def term(self, rig: str) -> int:
        """The ownership term the rig runs in here (0: none)."""
        return self.store.term(rig)

    def note(self, rig: str, kind: str, text: str) -> None:
        """Keep one line about the rig in the journal (a failed write is logged: a note is no alarm)."""
        try:
            self.store.add_note(rig, kind, text)
        except SourceError as exc:
            log.warning("rig %s: note not journaled (%s): %s", rig, exc, text)

    def notes(self, rig: str) -> list[tuple[int, str, str]]:
        """The rig's notes, oldest first: ``(wall_ns, kind, text)``."""
        return self.store.notes(rig)

    def epoch(self, rig: str) -> str:
        """The epoch of ``rig``'s alarm numbering in this journal (made when the rig has none yet;
        :mod:`twin.service.store`); ``""`` while it cannot be written."""
        try:
            return self.store.epoch(rig)
        except SourceError as exc:
            self._failed(exc)
            return ""

    def adopt_epoch(self, rig: str, epoch: str, *, replica: bool = False) -> bool:
        """Take ``epoch`` as the numbering of ``rig``'s alarms here while none is journaled or pending, or, with
        ``replica``, in any case (a standby that resumes the owner's replicated checkpoint continues the owner's
        numbering, whatever its replica journaled before); False (nothing changed) otherwise."""
        with self._lock:
            if self._last_seq_locked(rig) and not replica:
                return False
            self.store.adopt_epoch(rig, epoch)
            return True

    def supersede(self, rig: str, since_seq: int, events: list[AlarmEvent]) -> int:
        """Take another journal's numbering of ``rig`` from ``since_seq`` on (:meth:`twin.service.store.Store.supersede`:
        the alarms replaced are kept in the notes, kind ``superseded``); refused while alarms are pending."""
        with self._lock:
            if any(p.rig == rig for p in self._pending):
                raise SourceError(f"{self.path}: alarms of rig {rig} are not journaled yet ({self.write_error})")
            return self.store.supersede(rig, since_seq, [dataclasses.replace(e, signature="") for e in events])

    def _last_seq_locked(self, rig: str) -> int:
        mine = [p.seq for p in self._pending if p.rig == rig]
        return max(mine) if mine else self.store.last_seq(rig)

    def last_seq(self, rig: str) -> int:
        """The last number given to an alarm of ``rig`` (journaled or pending; 0 if none)."""
        with self._lock:
            return self._last_seq_locked(rig)

    def read(self, since_seq: int | None = None, since_t_ns: int | None = None,
             rig: str | None = None) -> list[AlarmEvent]:
        """Journaled alarms (not the pending ones: they are not published yet), by rig then seq, filtered
        (``since_*`` inclusive)."""
        with self._lock:
            held = {(p.rig, p.seq) for p in self._pending}
        events = self.store.alarms(rig, since_seq, since_t_ns)
        return [e for e in events if (e.rig, e.seq) not in held]  # committed to the WAL, not folded yet

    def __iter__(self) -> Iterator[AlarmEvent]:
        return iter(self.read())

    def __len__(self) -> int:
        return len(self.read())

    def rigs(self) -> list[str]:
        """The rigs that have at least one alarm, sorted."""
        return sorted({e.rig for e in self.read()})

    # ------------------------------------------------------------------ migration

    def _import(self, legacy: Path) -> None:
        if not legacy.exists():
            return
        data = legacy.read_bytes()
        digest = hashlib.sha256(data).hexdigest()
        if self.store.meta(f"imported:{legacy.name}") == digest:
            log.warning("%s: already imported into %s; rename or remove it", legacy, self.path)
            return
        events, torn = read_legacy_journal(legacy, data)
        n = self.store.insert_many(events, {f"imported:{legacy.name}": digest})
        self.imported = n
        target = legacy.with_name(legacy.name + ".imported")
        os.replace(legacy, target)
        log.warning("%s: imported %d alarm(s) of the old JSON-lines journal%s; the old file is now %s",
                    self.path, n, f" (a torn last line of {torn} bytes was left out)" if torn else "", target)


def read_legacy_journal(path: Path, data: bytes | None = None) -> tuple[list[AlarmEvent], int]:
    """Alarms of an old JSON-lines journal, and the bytes of a torn last line left out.

    Only an *incomplete* last line (no newline: a write interrupted by a crash)
    is left out. Any complete line that does not parse, or a jump in a rig's
    numbers, raises :class:`LogFormatError` naming the file and line: it is
    damage, not a crash artefact, and a damaged journal is not imported.
    """
    data = path.read_bytes() if data is None else data
    lines = data.split(b"\n")
    tail = lines.pop()
    events: list[AlarmEvent] = []
    last: dict[str, int] = {}
    for number, raw in enumerate(lines, start=1):
        try:
            ev = AlarmEvent.from_dict(json.loads(raw))
        except (ValueError, UnicodeDecodeError) as exc:
            raise LogFormatError(f"{path}:{number}: corrupt journal line ({exc}); not imported: fix or move "
                                 "the file aside") from None
        expected = last.get(ev.rig, 0) + 1
        if ev.seq != expected:
            raise LogFormatError(f"{path}:{number}: rig {ev.rig!r} seq {ev.seq} where {expected} was expected; "
                                 "not imported")
        last[ev.rig] = ev.seq
        events.append(ev)
    return events, len(tail)
