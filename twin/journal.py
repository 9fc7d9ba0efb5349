"""Durable, append-only journal of alarms (JSON lines on disk).

Every alarm the twin publishes is first written here, flushed and
``fsync``-ed, and only then put on the bus (:meth:`twin.bus.TwinPublisher.publish_alarm`).
The journal is therefore the source of truth: the bus's history queryable
answers from it, and a subscriber that missed a live alarm fills the gap from it.

File format: one :meth:`AlarmEvent.to_dict` JSON object per line, UTF-8,
``\\n``-terminated, sorted keys. One journal may hold several rigs; sequence
numbers are per rig and run 1, 2, 3, ... without gaps.

Crash safety:

* a write is ``write() + flush() + fsync()`` of one whole line, so after a
  crash only the *last* line can be incomplete. On reopen a torn last line
  (no terminating newline, or not valid JSON) is reported (``logging``
  warning, :attr:`AlarmJournal.torn_bytes`) and truncated away; the journal
  then resumes at the last complete sequence number + 1;
* a bad line anywhere *else* is not a crash artefact but corruption and
  raises :class:`~twin.errors.LogFormatError` naming the file and line;
* the file is held under an exclusive ``flock`` while open, so two services
  cannot interleave writes into the same journal (:class:`~twin.errors.SourceError`).
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import threading
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Self

from twin.errors import DataError, LogFormatError, SourceError
from twin.events import AlarmEvent, event_to_json

__all__ = ["AlarmJournal"]

log = logging.getLogger(__name__)


class AlarmJournal:
    """Append-only JSON-lines alarm journal with per-rig sequence numbers.

    Open it with ``with AlarmJournal(path) as journal:`` (or call :meth:`close`).
    Thread-safe: the bus's history queryable reads while the service appends.

    :param path: the journal file; created (with its parent directories) if missing.
    :param fsync: ``True`` (default) makes every append durable before it
        returns. Only tests of throughput should ever turn it off.
    :raises SourceError: the file cannot be opened or is locked by another process.
    :raises LogFormatError: a line other than the last one is corrupt, or
        sequence numbers in the file are not 1, 2, 3, ... per rig.
    """

    def __init__(self, path: str | os.PathLike[str], *, fsync: bool = True) -> None:
        self.path = Path(path)
        self._fsync = fsync
        self._lock = threading.Lock()
        self._events: list[AlarmEvent] = []
        self._last_seq: dict[str, int] = {}
        self.torn_bytes = 0
        """Bytes of a torn last line truncated away when the journal was opened (0 if none)."""
        try:
            created = not self.path.exists()
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "a+b")  # noqa: SIM115 - held open until close()
        except OSError as exc:
            raise SourceError(f"{self.path}: cannot open alarm journal: {exc.strerror or exc}") from exc
        try:
            fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            self._file.close()
            raise SourceError(
                f"{self.path}: alarm journal is locked by another process (one writer per journal)"
            ) from exc
        try:
            self._load()
            if created:
                self._sync_dir()
        except BaseException:
            self._file.close()
            raise

    # ------------------------------------------------------------------ life cycle

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
        """Release the lock and close the file (idempotent)."""
        with self._lock:
            if not self._file.closed:
                self._file.close()

    @property
    def closed(self) -> bool:
        """``True`` once :meth:`close` has been called."""
        return self._file.closed

    # ------------------------------------------------------------------ loading

    def _load(self) -> None:
        self._file.seek(0)
        data = self._file.read()
        good_end = 0
        lines = data.split(b"\n")
        # split() leaves the bytes after the last newline (b"" when the file ends cleanly).
        tail = lines.pop()
        for number, raw in enumerate(lines, start=1):
            is_last = number == len(lines) and not tail
            try:
                event = AlarmEvent.from_dict(json.loads(raw))
            except (ValueError, UnicodeDecodeError) as exc:
                if is_last:
                    # A complete but unreadable last line: also a crash artefact
                    # (a line is written in one write(); treat it like a torn one).
                    tail = raw + b"\n"
                    break
                raise LogFormatError(f"{self.path}:{number}: corrupt journal line: {exc}") from exc
            expected = self._last_seq.get(event.rig, 0) + 1
            if event.seq != expected:
                raise LogFormatError(
                    f"{self.path}:{number}: rig {event.rig!r} seq {event.seq} where {expected} was expected"
                )
            self._append_memory(event)
            good_end += len(raw) + 1
        if tail:
            self.torn_bytes = len(data) - good_end
            log.warning(
                "%s: torn last line (%d bytes) from an interrupted write truncated away; "
                "journal resumes after %d complete alarm(s)",
                self.path, self.torn_bytes, len(self._events),
            )
            self._file.truncate(good_end)
            self._file.flush()
            os.fsync(self._file.fileno())
        self._file.seek(0, os.SEEK_END)

    def _append_memory(self, event: AlarmEvent) -> None:
        self._events.append(event)
        self._last_seq[event.rig] = event.seq

    def _sync_dir(self) -> None:
        """Make the directory entry of a new journal durable too."""
        if not self._fsync:
            return
        fd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    # ------------------------------------------------------------------ writing

    def last_seq(self, rig: str) -> int:
        """The last journaled sequence number of ``rig`` (0 if none yet)."""
        with self._lock:
            return self._last_seq.get(rig, 0)

    def append(self, event: AlarmEvent) -> AlarmEvent:
        """Write one alarm durably and return it with its sequence number.

        An event with ``seq=0`` gets the rig's next number; an event that
        already carries one must carry exactly the next number.

        :returns: the journaled event (a copy with ``seq`` set).
        :raises DataError: ``event.seq`` is not 0 and not the rig's next number.
        :raises SourceError: the write or the ``fsync`` failed (disk full, I/O error)
            or the journal is closed.
        """
        with self._lock:
            if self._file.closed:
                raise SourceError(f"{self.path}: alarm journal is closed")
            expected = self._last_seq.get(event.rig, 0) + 1
            if event.seq == 0:
                event = event.with_seq(expected)
            elif event.seq != expected:
                raise DataError(
                    f"AlarmEvent.seq: {event.seq} for rig {event.rig!r} where {expected} "
                    f"(the next journal number) or 0 (assign) was expected"
                )
            line = (event_to_json(event) + "\n").encode("utf-8")
            start = self._file.tell()
            try:
                self._file.write(line)
                self._file.flush()
                if self._fsync:
                    os.fsync(self._file.fileno())
            except OSError as exc:
                # Do not leave half a line behind for the next append to extend.
                self._file.truncate(start)
                raise SourceError(f"{self.path}: cannot write alarm journal: {exc}") from exc
            self._append_memory(event)
            return event

    # ------------------------------------------------------------------ reading

    def read(
        self,
        since_seq: int | None = None,
        since_t_ns: int | None = None,
        rig: str | None = None,
    ) -> list[AlarmEvent]:
        """Journaled alarms in journal order, filtered.

        :param since_seq: keep ``seq >= since_seq`` (inclusive).
        :param since_t_ns: keep ``t_ns >= since_t_ns`` (inclusive).
        :param rig: keep only this rig (``None`` or ``"*"``: all rigs).
        """
        with self._lock:
            events = list(self._events)
        return [
            e
            for e in events
            if (rig is None or rig == "*" or e.rig == rig)
            and (since_seq is None or e.seq >= since_seq)
            and (since_t_ns is None or e.t_ns >= since_t_ns)
        ]

    def __iter__(self) -> Iterator[AlarmEvent]:
        return iter(self.read())

    def __len__(self) -> int:
        with self._lock:
            return len(self._events)

    def rigs(self) -> list[str]:
        """The rigs that have at least one journaled alarm, sorted."""
        with self._lock:
            return sorted(self._last_seq)
