"""Every SQLite access of the service: alarms, checkpoints and bookkeeping of one database file.

One database per rig (``<journal_dir>/<rig>.db``) holds

* ``alarms``: every journaled :class:`~twin.online.events.AlarmEvent`, numbered per
  rig 1, 2, 3, ... (primary key ``(rig, seq)``) and unique by identity
  ``(rig, parameter, level, kind, t_ns)``: the same alarm is never stored
  twice, whatever re-processing raised it again. Each row carries the JSON
  payload and its CRC-32;
* ``checkpoints``: the last checkpoint of each rig (the pickled tracker and
  detector, the source position), replaced atomically;
* ``meta``: schema version and the record of a legacy journal imported.

Durability: WAL mode with ``synchronous=FULL``: a commit is on disk when it
returns (an alarm survives ``kill -9`` and a power cut once journaled).

Corruption is detected, reported and never repaired: the open runs
``PRAGMA quick_check`` and verifies every alarm's CRC and the sequence numbers;
any failure raises :class:`~twin.errors.LogFormatError` naming the file (and
the rig and seq of a damaged alarm) and leaves the file untouched, so that an
operator can restore it from a backup. Nothing committed is ever deleted.

One writer per file: a writer holds an exclusive ``flock`` on ``<file>.lock``
(a separate file: closing any descriptor of the database itself would drop
SQLite's own POSIX locks). Readers (the bus's history queryable in the
service's main process) open without the lock; WAL lets them read while the
writer writes.
"""

from __future__ import annotations

import dataclasses
import fcntl
import json
import logging
import os
import sqlite3
import threading
import time
import zlib
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import BinaryIO, Self

from twin.errors import DataError, LogFormatError, SourceError
from twin.online.events import AlarmEvent, AlarmIdentity, event_to_json

__all__ = ["Checkpoint", "Store"]

log = logging.getLogger(__name__)

SCHEMA_VERSION = "1"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS alarms (
    rig TEXT NOT NULL, seq INTEGER NOT NULL,
    parameter TEXT NOT NULL, level TEXT NOT NULL, kind TEXT NOT NULL, t_ns INTEGER NOT NULL,
    payload TEXT NOT NULL, crc INTEGER NOT NULL,
    PRIMARY KEY (rig, seq),
    UNIQUE (rig, parameter, level, kind, t_ns)
);
CREATE TABLE IF NOT EXISTS checkpoints (
    rig TEXT PRIMARY KEY, t_ns INTEGER NOT NULL, samples INTEGER NOT NULL,
    fingerprint TEXT NOT NULL, state BLOB NOT NULL, crc INTEGER NOT NULL, saved_at REAL NOT NULL
);
"""


def _crc(data: str | bytes) -> int:
    return zlib.crc32(data.encode("utf-8") if isinstance(data, str) else data)


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """A rig's saved state: its pickled objects and where in its input it was taken."""

    rig: str
    t_ns: int
    """Time of the last sample processed (resume after it)."""
    samples: int
    fingerprint: str
    """What the state was computed under (rig configuration); a mismatch invalidates it."""
    state: bytes
    saved_at: float
    """Wall-clock time of the save [s since the epoch]."""


class Store:
    """One SQLite database of the service (see the module docstring).

    :param path: the database file; created with its schema when missing.
    :param writer: take the single-writer lock (default). Readers pass ``False``.
    :param lock_wait_s: how long a writer waits for the lock (a killed
        predecessor's process may still be exiting) before giving up.
    :raises SourceError: the file or its directory cannot be opened, or another
        process holds the writer lock.
    :raises LogFormatError: the file is not an intact journal (quick_check, a CRC
        or the sequence numbers fail); the file is left as it is.
    """

    def __init__(self, path: str | os.PathLike[str], *, writer: bool = True, lock_wait_s: float = 5.0) -> None:
        self.path = Path(path)
        self._lock = threading.RLock()
        self._lockfile: BinaryIO | None = None
        self._db: sqlite3.Connection | None = None
        try:
            if writer:
                self._take_lock(lock_wait_s)
            self._db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None, check_same_thread=False)
            self._db.execute("PRAGMA busy_timeout = 30000")
            mode = self._db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if mode.lower() != "wal":
                raise SourceError(f"{self.path}: cannot switch the journal to WAL mode (got {mode!r})")
            self._db.execute("PRAGMA synchronous = FULL")
            self._check_integrity()
            if writer:
                self._db.executescript(_SCHEMA)
                self._db.execute("INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (SCHEMA_VERSION,))
            self._verify_alarms()
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

    def _error(self, exc: sqlite3.Error, what: str) -> SourceError | LogFormatError:
        text = str(exc)
        if isinstance(exc, sqlite3.DatabaseError) and ("not a database" in text or "malformed" in text):
            return LogFormatError(f"{self.path}: the journal is corrupt ({text}); left untouched: "
                                  "restore it from a backup or move it aside")
        return SourceError(f"{self.path}: {what} the journal: {text}")

    # ------------------------------------------------------------------ integrity

    def _check_integrity(self) -> None:
        rows = self._conn().execute("PRAGMA quick_check").fetchall()
        if [r[0] for r in rows] != ["ok"]:
            detail = "; ".join(str(r[0]) for r in rows[:3])
            raise LogFormatError(f"{self.path}: the journal is corrupt (quick_check: {detail}); left untouched: "
                                 "restore it from a backup or move it aside")

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

        :returns: ``(journaled event, True)``, or ``(the stored one, False)`` for a duplicate.
        :raises DataError: an explicit ``seq`` that is not the next number.
        :raises SourceError: the write failed (disk full, read-only, I/O error), naming the file.
        """
        ident = event.identity
        with self._lock:
            db = self._conn()
            try:
                db.execute("BEGIN IMMEDIATE")
                try:
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
                    payload = event_to_json(event)
                    db.execute("INSERT INTO alarms VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                               (event.rig, event.seq, event.parameter, event.level, event.kind, event.t_ns,
                                payload, _crc(payload)))
                    db.execute("COMMIT")
                except BaseException:
                    if db.in_transaction:
                        db.execute("ROLLBACK")
                    raise
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot write to") from exc
            return event, True

    def insert_many(self, events: Iterable[AlarmEvent], meta: dict[str, str]) -> int:
        """Import numbered alarms and set ``meta`` in one transaction (all or nothing).

        :returns: how many alarms were new (duplicates by identity are skipped).
        """
        n = 0
        with self._lock:
            db = self._conn()
            try:
                db.execute("BEGIN IMMEDIATE")
                try:
                    for ev in events:
                        if self._find(db, ev.identity) is not None:
                            continue
                        payload = event_to_json(ev)
                        db.execute("INSERT INTO alarms VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                                   (ev.rig, ev.seq, ev.parameter, ev.level, ev.kind, ev.t_ns, payload,
                                    _crc(payload)))
                        n += 1
                    db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", list(meta.items()))
                    db.execute("COMMIT")
                except BaseException:
                    if db.in_transaction:
                        db.execute("ROLLBACK")
                    raise
            except sqlite3.IntegrityError as exc:
                raise LogFormatError(f"{self.path}: import refused, the alarms collide with those "
                                     f"already journaled ({exc})") from exc
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot write to") from exc
        return n

    @staticmethod
    def _find(db: sqlite3.Connection, ident: AlarmIdentity) -> AlarmEvent | None:
        row = db.execute("SELECT payload FROM alarms WHERE rig=? AND parameter=? AND level=? AND kind=? AND t_ns=?",
                         (ident.rig, ident.parameter, ident.level, ident.kind, ident.t_ns)).fetchone()
        return AlarmEvent.from_dict(json.loads(row[0])) if row else None

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
        return [AlarmEvent.from_dict(json.loads(r[0])) for r in rows]

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

    # ------------------------------------------------------------------ checkpoints

    def save_checkpoint(self, cp: Checkpoint) -> None:
        """Replace the rig's checkpoint (one transaction: the old one or the new one, never half)."""
        with self._lock:
            try:
                self._conn().execute("INSERT OR REPLACE INTO checkpoints VALUES (?, ?, ?, ?, ?, ?, ?)",
                                     (cp.rig, cp.t_ns, cp.samples, cp.fingerprint, cp.state, _crc(cp.state),
                                      cp.saved_at))
            except sqlite3.Error as exc:
                raise self._error(exc, "cannot write a checkpoint to") from exc

    def load_checkpoint(self, rig: str) -> Checkpoint | None:
        """The rig's checkpoint, ``None`` if there is none or it is damaged (logged)."""
        with self._lock:
            row = self._read(lambda db: db.execute(
                "SELECT t_ns, samples, fingerprint, state, crc, saved_at FROM checkpoints WHERE rig=?",
                (rig,)).fetchone())
        if row is None:
            return None
        t_ns, samples, fingerprint, state, crc, saved_at = row
        if _crc(state) != crc:
            log.error("%s: the checkpoint of rig %s is damaged (CRC mismatch); starting that rig afresh "
                      "(journaled alarms are kept and not raised twice)", self.path, rig)
            return None
        return Checkpoint(rig, int(t_ns), int(samples), fingerprint, bytes(state), float(saved_at))

    # ------------------------------------------------------------------ meta

    def meta(self, key: str) -> str | None:
        with self._lock:
            row = self._read(lambda db: db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone())
        return row[0] if row else None


_EMPTY = sqlite3.connect(":memory:", check_same_thread=False)
_EMPTY.executescript(_SCHEMA)
