"""Every SQLite access of the service: alarms, checkpoints and bookkeeping of one database file.

One database per rig (``<journal_dir>/<rig>.db``) holds

* ``alarms``: every journaled :class:`~twin.online.events.AlarmEvent`, numbered per
  rig 1, 2, 3, ... (primary key ``(rig, seq)``) and unique by identity
  ``(rig, parameter, level, kind, t_ns)``: the same alarm is never stored
  twice, whatever re-processing raised it again. Each row carries the JSON
  payload and its CRC-32;
* ``notes``: what happened to a rig's input that its alarms depend on (a clock step adopted, ...), one
  line each with the wall-clock time;
* ``meta``: schema version, the journal's id (random, made with the journal),
  each rig's *epoch* (``epoch:<rig>``) and the record of a legacy journal imported.

Epochs: a rig's alarm numbers count within its epoch, a random identity made
with the rig's first use of the journal (:func:`new_epoch`: its creation time
first, so a later epoch sorts after an earlier one). Every alarm carries it
(:attr:`~twin.online.events.AlarmEvent.epoch`, covered by the signature), the
owner announces it in its status, and a subscriber refuses an alarm of an earlier
epoch (a replay of another campaign's alarms). A journal that starts numbering
again from 1 (a new journal) has a new epoch; a standby's journal adopts the
owner's epoch with its first alarm (it continues the owner's numbering).

Durability: WAL mode with ``synchronous=FULL``, and every alarm commit is
folded into the main database file at once (``PRAGMA wal_checkpoint(TRUNCATE)``):
when :meth:`Store.insert_alarm` returns, the alarm is in the main file and the
WAL is empty, so a lost, cut or damaged WAL cannot take a journaled alarm with
it (an alarm survives ``kill -9`` and a power cut once journaled).

Continuity: the files beside a journal (its checkpoint, a commissioning) say
that a rig ran before, under which journal id and with how many alarms
(:class:`Continuity`). A journal that is missing, empty, replaced (another id)
or whose alarms end before those numbers is refused with one line naming the
file: alarm numbering never restarts silently.

Checkpoints are data only, in a file beside the journal
(:mod:`twin.service.checkpoint_file`).

High-water marks: the journal keeps, in the same transaction as each alarm, the rig's last number in
``meta`` (``last_seq:<rig>``) and the count of all its alarms in the SQLite file header (``PRAGMA
user_version``). A journal alone (its checkpoint gone) whose last rows were deleted, whose alarms table was
dropped or whose rows were lost otherwise is refused on open, naming the numbers missing.

Corruption is detected, reported and never repaired: the open runs
``PRAGMA quick_check`` and verifies every alarm's CRC and the sequence numbers;
any failure raises :class:`~fpdd.errors.LogFormatError` naming the file (and
the rig and seq of a damaged alarm) and leaves the file untouched, so that an
operator can restore it from a backup. Nothing committed is ever deleted.

One writer per file: a writer holds an exclusive ``flock`` on ``<file>.lock``
(a separate file: closing any descriptor of the database itself would drop
SQLite's own POSIX locks). Readers (the bus's history queryable in the
service's main process) open without the lock; WAL lets them read while the
writer writes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import logging
import os
import secrets
import sqlite3
import threading
import time
import uuid
import zlib
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from types import TracebackType
from typing import BinaryIO, Self


from fpdd.errors import DataError, LogFormatError, SourceError
from twin.online.events import AlarmEvent, AlarmIdentity, event_to_json

__all__ = ["Continuity", "NotFolded", "Store", "new_epoch"]

log = logging.getLogger(__name__)

SCHEMA_VERSION = "2"
#: Schema versions this program opens: 1 (checkpoints inside the database, pickled; opened only without any) and 2.
KNOWN_SCHEMAS = ("1", "2")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS alarms (
    rig TEXT NOT NULL, seq INTEGER NOT NULL,
    parameter TEXT NOT NULL, level TEXT NOT NULL, kind TEXT NOT NULL, t_ns INTEGER NOT NULL,
    payload TEXT NOT NULL, crc INTEGER NOT NULL,
    PRIMARY KEY (rig, seq),
    UNIQUE (rig, parameter, level, kind, t_ns)
);
CREATE TABLE IF NOT EXISTS notes (rig TEXT NOT NULL, wall_ns INTEGER NOT NULL, kind TEXT NOT NULL, text TEXT NOT NULL);
"""


def new_epoch() -> str:
    """A new epoch: 16 hex digits of the wall-clock time [ns] then 16 random ones (sorts by creation time)."""
    return f"{time.time_ns():016x}{secrets.token_hex(8)}"


def _crc(data: str | bytes) -> int:
    return zlib.crc32(data.encode("utf-8") if isinstance(data, str) else data)


@contextlib.contextmanager
def _immediate(db: sqlite3.Connection, undo=None):
    """One write transaction (``BEGIN IMMEDIATE`` ... ``COMMIT``), rolled back on any exception, ``undo`` then
    called (what the transaction made in memory is not on disk); a body that rolls back itself and returns
    leaves nothing to commit."""
    db.execute("BEGIN IMMEDIATE")
    try:
        yield db
        if db.in_transaction:
            db.execute("COMMIT")
    except BaseException:
        if db.in_transaction:
            db.execute("ROLLBACK")
        if undo is not None:
            undo()
        raise


@dataclasses.dataclass(frozen=True)
class Continuity:
    """What the files beside a journal say about it; a journal that disagrees is refused (:class:`Store`)."""

    evidence: str
    """The file that says the rig ran before (named in the refusal)."""
    journal_id: str | None = None
    """The journal's id as that file knows it (``None``: unknown)."""
    last_seqs: Mapping[str, int] = dataclasses.field(default_factory=dict)
    """Per rig: alarms that were journaled when that file was written."""


class Store:
    """One SQLite database of the service (see the module docstring).

    :param path: the database file; created with its schema when missing.
    :param writer: take the single-writer lock (default). Readers pass ``False``.
    :param lock_wait_s: how long a writer waits for the lock (a killed
        predecessor's process may still be exiting) before giving up.
    :raises SourceError: the file or its directory cannot be opened, or another
        process holds the writer lock.
    :raises LogFormatError: the file is not an intact journal (quick_check, a CRC
        or the sequence numbers fail), has a schema version this program does not
        know, holds a checkpoint of an earlier version (pickled: never loaded), or
        disagrees with ``expect``; the file is left as it is.
    :param expect: what the files beside the journal say (a writer checks it before writing anything), or a
        function that reads them, called once the writer's lock is held.
    """

    def __init__(self, path: str | os.PathLike[str], *, writer: bool = True, lock_wait_s: float = 5.0,
                 expect: Continuity | Callable[[], Continuity | None] | None = None) -> None:
        self.path = Path(path)
        self._lock = threading.RLock()
        self._lockfile: BinaryIO | None = None
        self._db: sqlite3.Connection | None = None
        self.journal_id: str | None = None
        """The journal's random id (made with the journal; ``None`` for a reader of a file without one)."""
        self._writer = writer
        self._epochs: dict[str, str] = {}
        self.new_secret = False
        """The checkpoint key (:attr:`secret`) was made by this open: the journal is new or of an earlier version."""
        try:
            if writer:
                self._take_lock(lock_wait_s)
            if callable(expect):
                expect = expect()
            if expect is not None and (not self.path.exists() or self.path.stat().st_size == 0):
                raise LogFormatError(self._refusal(expect, "is missing" if not self.path.exists()
                                                   else "is empty (0 bytes)"))
            self._db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None, check_same_thread=False)
            self._db.execute("PRAGMA busy_timeout = 30000")
            self._check_integrity()
            version = self._schema_version()
            if expect is not None:
                self._check_continuity(expect, version)
            self._verify_alarms()  # all checks before anything is written
            self._check_marks()
            mode = self._db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if mode.lower() != "wal":
                raise SourceError(f"{self.path}: cannot switch the journal to WAL mode (got {mode!r})")
            self._db.execute("PRAGMA synchronous = FULL")
            if writer:
                db = self._db
                with _immediate(db):  # the schema, the id and the version together, or none of them
                    for statement in _SCHEMA.split(";"):
                        if statement.strip():
                            db.execute(statement)
                    db.execute("INSERT OR IGNORE INTO meta VALUES ('journal_id', ?)", (uuid.uuid4().hex,))
                    had_secret = db.execute("SELECT 1 FROM meta WHERE key='checkpoint_key'").fetchone()
                    self.new_secret = had_secret is None  # made by this open (a journal of an earlier version)
                    db.execute("INSERT OR IGNORE INTO meta VALUES ('checkpoint_key', ?)", (secrets.token_hex(32),))
                    if version != SCHEMA_VERSION:
                        db.execute("INSERT OR REPLACE INTO meta VALUES ('schema_version', ?)", (SCHEMA_VERSION,))
                    if not self._marks(db):  # a journal of an earlier version: its marks from what it holds now
                        for rig, last in db.execute("SELECT rig, MAX(seq) FROM alarms GROUP BY rig").fetchall():
                            db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (f"last_seq:{rig}", str(last)))
                        count = db.execute("SELECT COUNT(*) FROM alarms").fetchone()[0]
                        db.execute(f"PRAGMA user_version = {int(count)}")
                self._fold()  # a WAL left by a killed writer goes into the main file now
            self.journal_id = self.meta("journal_id")
        except sqlite3.DatabaseError as exc:
            self.close()
            raise self._error(exc, "cannot open") from exc
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ life cycle

    def _take_lock(self, wait_s: float) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lockfile = open(f"{self.path}.lock", "a+b")  # noqa: SIM115 - held until close()
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(self._lockfile.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except OSError:
                if time.monotonic() >= deadline:
                    raise SourceError(f"{self.path}: journal is locked by another process "
                                      f"(one writer per journal; another twin serve on this journal?)") from None
                time.sleep(0.05)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Close the database and release the lock (idempotent)."""
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None
            if self._lockfile is not None:
                self._lockfile.close()
                self._lockfile = None

    @property
    def closed(self) -> bool:
        return self._db is None

    def _conn(self) -> sqlite3.Connection:
        if self._db is None:
            raise SourceError(f"{self.path}: journal is closed")
        return self._db

    def fold(self) -> None:
        """Move every committed transaction from the WAL into the main file and empty the WAL.

        :raises SourceError: naming the file, when it cannot be done (disk full, I/O error, readers holding
            the WAL for longer than the busy timeout).
        """
        with self._lock:
            try:
                self._fold()
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot fold the WAL into") from exc

    def _fold(self) -> None:
        busy, _, _ = self._conn().execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
        if busy:
            raise sqlite3.OperationalError("readers kept the WAL busy; committed alarms are in the WAL only")

    def _error(self, exc: sqlite3.Error, what: str) -> SourceError | LogFormatError:
        text = str(exc)
        if isinstance(exc, sqlite3.DatabaseError) and ("not a database" in text or "malformed" in text):
            return LogFormatError(f"{self.path}: the journal is corrupt ({text}); left untouched: "
                                  "restore it from a backup or move it aside")
        return SourceError(f"{self.path}: {what} the journal: {text}")

    # ------------------------------------------------------------------ integrity

    def _schema_version(self) -> str | None:
        """The file's schema version (``None``: no journal in it yet); refuses unknown ones and pickled checkpoints."""
        db = self._conn()
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'").fetchall()}
        if "meta" not in tables:
            if "alarms" in tables:
                raise LogFormatError(f"{self.path}: an alarms table without a schema version; not a journal of "
                                     "this program: left untouched")
            return None
        row = db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        version = None if row is None else str(row[0])
        if version not in KNOWN_SCHEMAS:
            raise LogFormatError(f"{self.path}: schema_version {version!r} is not one this program reads "
                                 f"({', '.join(KNOWN_SCHEMAS)}); left untouched: open it with the program "
                                 "that wrote it")
        if "checkpoints" in tables and db.execute("SELECT COUNT(*) FROM checkpoints").fetchone()[0]:
            raise LogFormatError(f"{self.path}: holds checkpoints of an earlier version (pickled objects, never "
                                 "loaded: they could run code); to start its rigs afresh from their journaled "
                                 f"alarms, delete them: sqlite3 {self.path} 'DELETE FROM checkpoints'")
        return version

    def _refusal(self, expect: Continuity, what: str) -> str:
        return (f"{self.path}: the journal {what}, but {expect.evidence} says the rig ran before; refused "
                "(alarm numbers never restart): put the rig's own journal back (a backup taken after that file), or "
                "move that file aside to go on from this journal (numbers then follow its last alarm)")

    def _check_continuity(self, expect: Continuity, version: str | None) -> None:
        db = self._conn()
        if version is None:
            raise LogFormatError(self._refusal(expect, "holds no alarm journal (an empty or replaced database)"))
        row = db.execute("SELECT value FROM meta WHERE key='journal_id'").fetchone()
        have = None if row is None else str(row[0])
        if expect.journal_id is not None and have != expect.journal_id:
            raise LogFormatError(
                f"{self.path}: the journal was replaced: its id is {have or 'missing'}, {expect.evidence} was "
                f"written with journal {expect.journal_id}; refused "
                "(alarm numbers never restart): put the rig's own journal back (a backup taken after that file), or "
                "move that file aside to go on from this journal (numbers then follow its last alarm)")
        for rig, n in sorted(expect.last_seqs.items()):
            last = self._last_seq(db, rig)
            if last < n:
                raise LogFormatError(
                    f"{self.path}: the alarms of rig {rig!r} end at seq {last}, but {expect.evidence} says {n} "
                    "were journaled (alarms were lost from the file); refused "
                    "(alarm numbers never restart): put the rig's own journal back (a backup taken after that file), or "
                    "move that file aside to go on from this journal (numbers then follow its last alarm)")

    def _check_integrity(self) -> None:
        rows = self._conn().execute("PRAGMA quick_check").fetchall()
        if [r[0] for r in rows] != ["ok"]:
            detail = "; ".join(" ".join(str(r[0]).split()) for r in rows[:3])  # one line
            raise LogFormatError(f"{self.path}: the journal is corrupt (quick_check: {detail}); left untouched: "
                                 "restore it from a backup or move it aside")

    @staticmethod
    def _marks(db: sqlite3.Connection) -> dict[str, int]:
        """Per rig, the last number journaled as the journal's own meta says (empty: none kept)."""
        try:
            rows = db.execute("SELECT key, value FROM meta WHERE key LIKE 'last_seq:%'").fetchall()
        except sqlite3.OperationalError:
            return {}
        return {k.split(":", 1)[1]: int(v) for k, v in rows}

    def _check_marks(self) -> None:
        """Refuse a journal whose alarms end before its own high-water marks (module docstring), naming the
        numbers missing."""
        db = self._conn()
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'").fetchall()}
        if "meta" not in tables:
            return  # not a journal (yet): an empty file, or another program's database (refused elsewhere)
        fix = "left untouched: restore it from a backup or move it aside"
        marks = self._marks(db)
        have = ({r: self._last_seq(db, r) for r in marks} if "alarms" in tables else {r: 0 for r in marks})
        for rig, mark in sorted(marks.items()):
            if have[rig] < mark:
                lost = f"seq {have[rig] + 1}..{mark}" if have[rig] + 1 < mark else f"seq {mark}"
                what = "its alarms table is missing" if "alarms" not in tables else \
                    f"the alarms of rig {rig!r} end at seq {have[rig]}"
                raise LogFormatError(f"{self.path}: {what}, but the journal's own high-water mark says rig {rig!r} "
                                     f"journaled {mark}: {lost} of rig {rig!r} missing (rows deleted or the file "
                                     f"damaged); {fix}")
        counted = int(db.execute("PRAGMA user_version").fetchone()[0])
        there = db.execute("SELECT COUNT(*) FROM alarms").fetchone()[0] if "alarms" in tables else 0
        if counted > there:
            raise LogFormatError(f"{self.path}: the journal's header counts {counted} alarms, {there} are there: "
                                 f"{counted - there} missing (rows or marks deleted, or the file damaged); {fix}")

    def _verify_alarms(self) -> None:
        """Every alarm's CRC, payload and number; raises LogFormatError naming the first bad one."""
        last: dict[str, int] = {}
        try:
            rows = self._conn().execute("SELECT rig, seq, payload, crc FROM alarms ORDER BY rig, seq").fetchall()
        except sqlite3.OperationalError as exc:
            if "no such table" in str(exc):  # a reader on a file no writer has initialised yet
                return
            raise
        for rig, seq, payload, crc in rows:
            where = f"{self.path}: alarm {rig!r} seq {seq}"
            if _crc(payload) != crc:
                raise LogFormatError(f"{where}: stored CRC does not match its content (the file is damaged); "
                                     "left untouched: restore the journal from a backup")
            try:
                ev = AlarmEvent.from_dict(json.loads(payload))
            except (ValueError, DataError) as exc:
                raise LogFormatError(f"{where}: unreadable payload ({exc})") from None
            if ev.rig != rig or ev.seq != seq:
                raise LogFormatError(f"{where}: payload says rig {ev.rig!r} seq {ev.seq}")
            expected = last.get(rig, 0) + 1
            if seq != expected:
                raise LogFormatError(f"{where}: sequence numbers jump from {expected - 1} to {seq}")
            last[rig] = seq

    # ------------------------------------------------------------------ alarms

    def insert_alarm(self, event: AlarmEvent) -> tuple[AlarmEvent, bool]:
        """Journal ``event`` durably unless an alarm of the same identity is there already.

        ``seq=0`` takes the rig's next number; an explicit ``seq`` must be exactly it.

        On return the alarm is in the main database file (the WAL folded into it).

        :returns: ``(journaled event, True)``, or ``(the stored one, False)`` for a duplicate.
        :raises DataError: an explicit ``seq`` that is not the next number.
        :raises NotFolded: committed (numbered, in the WAL) but not yet in the main file; :meth:`fold` later.
        :raises SourceError: the write failed (disk full, read-only, I/O error), naming the file.
        """
        ident = event.identity
        with self._lock:
            db = self._conn()
            try:
                # an epoch made in the transaction is not on disk: forgotten when it rolls back
                with _immediate(db, undo=lambda: self._epochs.pop(event.rig, None)):
                    found = self._find(db, ident)
                    if found is not None:
                        db.execute("ROLLBACK")
                        return found, False
                    nxt = self._last_seq(db, event.rig) + 1
                    if event.seq == 0:
                        event = event.with_seq(nxt)
                    elif event.seq != nxt:
                        raise DataError(f"AlarmEvent.seq: {event.seq} for rig {event.rig!r} where {nxt} "
                                        f"(the next journal number) or 0 (assign) was expected")
                    event = dataclasses.replace(event, epoch=self._stamp_epoch(db, event, nxt == 1),
                                                term=event.term or self.term(event.rig))
                    payload = event_to_json(event)
                    db.execute("INSERT INTO alarms VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                               (event.rig, event.seq, event.parameter, event.level, event.kind, event.t_ns,
                                payload, _crc(payload)))
                    self._mark(db, {event.rig: event.seq}, 1)
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot write to") from exc
            try:
                self._fold()
            except sqlite3.Error as exc:
                err = self._error(exc, "cannot fold the WAL into")
                raise NotFolded(event, str(err)) from exc
            return event, True

    def insert_many(self, events: Iterable[AlarmEvent], meta: dict[str, str]) -> int:
        """Import numbered alarms and set ``meta`` in one transaction (all or nothing).

        :returns: how many alarms were new (duplicates by identity are skipped).
        """
        n = 0
        with self._lock:
            db = self._conn()
            try:
                with _immediate(db):
                    lasts: dict[str, int] = {}
                    for ev in events:
                        if self._find(db, ev.identity) is not None:
                            continue
                        payload = event_to_json(ev)
                        db.execute("INSERT INTO alarms VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                                   (ev.rig, ev.seq, ev.parameter, ev.level, ev.kind, ev.t_ns, payload,
                                    _crc(payload)))
                        lasts[ev.rig] = max(lasts.get(ev.rig, 0), ev.seq)
                        n += 1
                    self._mark(db, lasts, n)
                    db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", list(meta.items()))
                self._fold()
            except sqlite3.IntegrityError as exc:
                raise LogFormatError(f"{self.path}: import refused, the alarms collide with those "
                                     f"already journaled ({exc})") from exc
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot write to") from exc
        return n

    def supersede(self, rig: str, since_seq: int, events: list[AlarmEvent], kind: str = "superseded") -> int:
        """Replace ``rig``'s alarms from ``since_seq`` on by ``events`` (another journal's numbers ``since_seq``,
        ``since_seq + 1``, ... without a gap, at least as many as are replaced), in one transaction; each alarm
        replaced by another one is kept whole in the notes (``kind``, its JSON payload). An owner that stood down after a split
        network takes the numbering of the owner that stayed this way, once that owner holds its alarms
        (:mod:`twin.service.handover`). Returns how many alarms were replaced by another one.

        :raises DataError: ``events`` are not numbered ``since_seq, since_seq + 1, ...``, are another rig's, end
            before this journal's alarms, or carry another epoch than the alarms kept before ``since_seq``.
        :raises SourceError: the write failed (naming the file); nothing changed.
        """
        events = sorted(events, key=lambda e: e.seq)
        if [e.seq for e in events] != list(range(since_seq, since_seq + len(events))) or \
                any(e.rig != rig for e in events):
            raise DataError(f"{self.path}: the alarms to number rig {rig!r} from seq {since_seq} are not that rig's "
                            f"{since_seq}, {since_seq + 1}, ... without a gap")
        with self._lock:
            db = self._conn()
            try:
                with _immediate(db):
                    last = self._last_seq(db, rig)
                    if events and events[-1].seq < last:
                        raise DataError(f"{self.path}: rig {rig!r}'s alarms end at seq {last}, the numbering given "
                                        f"ends at {events[-1].seq}")
                    epoch = self._read_epoch(db, rig)
                    theirs = {e.epoch for e in events if e.epoch}
                    if len(theirs) > 1 or (theirs and since_seq > 1 and epoch and theirs != {epoch}):
                        raise DataError(f"{self.path}: the alarms to number rig {rig!r} from seq {since_seq} are of "
                                        f"epoch(s) {', '.join(sorted(theirs))}, the journal's is {epoch}")
                    rows = db.execute("SELECT seq, payload FROM alarms WHERE rig=? AND seq>=? ORDER BY seq",
                                      (rig, since_seq)).fetchall()
                    payloads = {ev.seq: event_to_json(ev) for ev in events}
                    old = [(q, p) for q, p in rows if payloads.get(q) != p]  # the same alarm under its number: kept
                    now = time.time_ns()
                    db.executemany("INSERT INTO notes VALUES (?, ?, ?, ?)", [(rig, now, kind, p) for _, p in old])
                    db.execute("DELETE FROM alarms WHERE rig=? AND seq>=?", (rig, since_seq))
                    for ev in events:
                        payload = payloads[ev.seq]
                        db.execute("INSERT INTO alarms VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                                   (ev.rig, ev.seq, ev.parameter, ev.level, ev.kind, ev.t_ns, payload, _crc(payload)))
                    if theirs and (theirs != {epoch}):
                        db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (f"epoch:{rig}", theirs.pop()))
                        self._epochs.pop(rig, None)
                    self._mark(db, {rig: events[-1].seq} if events else {}, len(events) - len(rows))
                self._fold()
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot write to") from exc
        return len(old)

    @staticmethod
    def _mark(db: sqlite3.Connection, lasts: Mapping[str, int], added: int) -> None:
        """Raise the high-water marks (inside the caller's transaction)."""
        for rig, seq in lasts.items():
            db.execute("INSERT INTO meta VALUES (?, ?) ON CONFLICT(key) DO UPDATE SET value=excluded.value "
                       "WHERE CAST(value AS INTEGER) < CAST(excluded.value AS INTEGER)", (f"last_seq:{rig}", str(seq)))
        if added:
            count = int(db.execute("PRAGMA user_version").fetchone()[0])
            db.execute(f"PRAGMA user_version = {count + added}")

    def _find(self, db: sqlite3.Connection, ident: AlarmIdentity) -> AlarmEvent | None:
        row = db.execute("SELECT payload FROM alarms WHERE rig=? AND parameter=? AND level=? AND kind=? AND t_ns=?",
                         (ident.rig, ident.parameter, ident.level, ident.kind, ident.t_ns)).fetchone()
        return self._event(db, row[0]) if row else None

    def _event(self, db: sqlite3.Connection, payload: str) -> AlarmEvent:
        """A stored alarm; one journaled before epochs existed carries its rig's epoch now (the numbering it is in)."""
        ev = AlarmEvent.from_dict(json.loads(payload))
        if not ev.epoch:
            epoch = self._epochs.get(ev.rig) or self._read_epoch(db, ev.rig)
            if epoch:
                ev = dataclasses.replace(ev, epoch=epoch)
        return ev

    def _read_epoch(self, db: sqlite3.Connection, rig: str) -> str:
        try:
            row = db.execute("SELECT value FROM meta WHERE key=?", (f"epoch:{rig}",)).fetchone()
        except sqlite3.OperationalError:  # a reader on a file no writer has initialised yet
            return ""
        if row:
            self._epochs[rig] = str(row[0])
        return str(row[0]) if row else ""

    def _stamp_epoch(self, db: sqlite3.Connection, event: AlarmEvent, first: bool) -> str:
        """The epoch an alarm is journaled under, inside the insert's transaction: the rig's; made now if it has
        none; the alarm's own (a standby continuing the owner's numbering) when it is the rig's first alarm here.

        :raises DataError: the alarm carries another epoch than the rig's alarms journaled here.
        """
        have = self._read_epoch(db, event.rig)
        want = event.epoch or have or new_epoch()
        if want != have:
            if have and not first:
                raise DataError(f"AlarmEvent.epoch: {event.epoch} for rig {event.rig!r} seq {event.seq}, where this "
                                f"journal numbers the rig's alarms in epoch {have}")
            db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (f"epoch:{event.rig}", want))
            self._epochs.pop(event.rig, None)
        self._epochs[event.rig] = want
        return want

    def term(self, rig: str) -> int:
        """The ownership term the rig runs in (:func:`twin.service.ownership.new_term`, set by :meth:`set_meta`
        ``term:<rig>`` when a service starts running it); 0: none."""
        text = self.meta(f"term:{rig}")
        return int(text) if text and text.isdigit() else 0

    def epoch(self, rig: str) -> str:
        """The rig's epoch (a writer makes it when the rig has none yet; a reader returns ``""`` then).

        :raises SourceError: a writer cannot write it (naming the file).
        """
        with self._lock:
            if rig in self._epochs:
                return self._epochs[rig]
            have = self._read(lambda db: self._read_epoch(db, rig))
            if have or not self._writer:
                return have
            db = self._conn()
            try:
                with _immediate(db):
                    have = self._read_epoch(db, rig) or new_epoch()
                    db.execute("INSERT OR IGNORE INTO meta VALUES (?, ?)", (f"epoch:{rig}", have))
                self._fold()
            except sqlite3.Error as exc:
                self._epochs.pop(rig, None)
                raise self._error(exc, "cannot write to") from exc
            self._epochs[rig] = have
            return have

    @staticmethod
    def _last_seq(db: sqlite3.Connection, rig: str) -> int:
        return int(db.execute("SELECT COALESCE(MAX(seq), 0) FROM alarms WHERE rig=?", (rig,)).fetchone()[0])

    def find(self, ident: AlarmIdentity) -> AlarmEvent | None:
        """The journaled alarm of this identity, if any."""
        with self._lock:
            return self._read(lambda db: self._find(db, ident))

    def last_seq(self, rig: str) -> int:
        """The rig's last journaled number (0 if none)."""
        with self._lock:
            return self._read(lambda db: self._last_seq(db, rig))

    def alarms(self, rig: str | None = None, since_seq: int | None = None,
               since_t_ns: int | None = None) -> list[AlarmEvent]:
        """Journaled alarms (``rig`` None or ``"*"``: all), by rig then seq; ``since_*`` inclusive."""
        sql = "SELECT payload FROM alarms WHERE 1=1"
        args: list[str | int] = []
        if rig not in (None, "*"):
            sql += " AND rig=?"
            args.append(rig)
        if since_seq is not None:
            sql += " AND seq>=?"
            args.append(since_seq)
        if since_t_ns is not None:
            sql += " AND t_ns>=?"
            args.append(since_t_ns)
        sql += " ORDER BY rig, seq"
        with self._lock:
            rows = self._read(lambda db: db.execute(sql, args).fetchall())
            return self._read(lambda db: [self._event(db, r[0]) for r in rows])

    def rigs(self) -> list[str]:
        with self._lock:
            return [r[0] for r in self._read(lambda db: db.execute(
                "SELECT DISTINCT rig FROM alarms ORDER BY rig").fetchall())]

    def _read(self, fn):
        try:
            return fn(self._conn())
        except sqlite3.OperationalError as exc:
            if "no such table" in str(exc):
                return fn(_EMPTY)
            raise self._error(exc, "cannot read") from exc
        except sqlite3.Error as exc:
            raise self._error(exc, "cannot read") from exc

    # ------------------------------------------------------------------ meta

    def meta(self, key: str) -> str | None:
        with self._lock:
            row = self._read(lambda db: db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone())
        return row[0] if row else None

    def add_note(self, rig: str, kind: str, text: str) -> None:
        """Keep one line about the rig (``kind``: e.g. ``clock_step``), committed and folded.

        :raises SourceError: the write failed (naming the file).
        """
        with self._lock:
            db = self._conn()
            try:
                db.execute("INSERT INTO notes VALUES (?, ?, ?, ?)", (rig, time.time_ns(), kind, text))
                self._fold()
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot write to") from exc

    def notes(self, rig: str) -> list[tuple[int, str, str]]:
        """The rig's notes, oldest first: ``(wall_ns, kind, text)``."""
        with self._lock:
            return [tuple(r) for r in self._read(lambda db: db.execute(
                "SELECT wall_ns, kind, text FROM notes WHERE rig=? ORDER BY rowid", (rig,)).fetchall())]

    @property
    def secret(self) -> bytes:
        """The journal's random checkpoint key (made with it, never leaves the file): a checkpoint beside the
        journal carries an HMAC under it (:mod:`twin.service.checkpoint_file`); empty for a reader of a file
        without one."""
        text = self.meta("checkpoint_key")
        return bytes.fromhex(text) if text else b""

    def adopt_epoch(self, rig: str, epoch: str) -> None:
        """Number ``rig``'s alarms in ``epoch`` from now on (the caller makes sure none is journaled here yet).

        :raises SourceError: the write failed (naming the file).
        """
        self.set_meta({f"epoch:{rig}": epoch})
        with self._lock:
            self._epochs[rig] = epoch

    def set_meta(self, values: Mapping[str, str]) -> None:
        """Set ``values`` in the meta table in one transaction, folded into the main file.

        :raises SourceError: the write failed (naming the file).
        """
        with self._lock:
            db = self._conn()
            try:
                with _immediate(db):
                    db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", list(values.items()))
                self._fold()
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot write to") from exc


class NotFolded(SourceError):
    """An alarm committed to the WAL (numbered, journaled) that could not be folded into the main file yet."""

    def __init__(self, event: AlarmEvent, message: str) -> None:
        super().__init__(message)
        self.event = event


_EMPTY = sqlite3.connect(":memory:", check_same_thread=False)
_EMPTY.executescript(_SCHEMA)
