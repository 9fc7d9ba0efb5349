"""How far a rig's journaled alarms were put on the bus: ``<journal>.put.json`` beside the journal.

An alarm is journaled first and put after (:mod:`twin.service.bus`). A service killed between the two
(``kill -9``, a power cut) leaves an alarm that is in the journal, and so in the history a
:class:`~twin.service.subscriber.AlarmSubscriber` reads, but that no plain Zenoh subscriber ever got. The
put mark closes that window: the highest number put and settled is written (a temporary file, fsync,
rename), and when the service starts again the alarms after the mark are put, in order
(:meth:`twin.service.bus.TwinPublisher.put_unsent`).

A put that returned has only reached the session's transmit queue: killed a moment later, the process
takes it with it. So a put is *settled*, and written in the mark, only once the process has lived
``SETTLE_S`` after it (checked at the publisher's next put, estimate or status, and waited for at a clean
close); an alarm put in the last ``SETTLE_S`` before a kill is put again at the restart. Delivery is at
least once: a plain subscriber may get such an alarm twice, under the same epoch and number (and the same
signature), and keeps one; :class:`~twin.service.subscriber.AlarmSubscriber` delivers it once and says
``replayed: ... received live before``.

The mark names the rig and its journal's epoch (:mod:`twin.service.store`): a mark of another journal
says nothing of this one. A missing mark (the first start of this version, or a new journal) counts every
alarm journaled so far as put.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path

log = logging.getLogger("twin.serve")

SETTLE_S = 1.0
"""How long the process must live after a put before the put counts as having left it [s]: the transmit
queue of a session on a working link is drained in milliseconds; a second covers a loaded machine."""


def put_mark_path(journal: str | os.PathLike[str]) -> Path:
    """``<journal>.put.json`` beside the journal."""
    p = Path(journal)
    return p.with_name(p.name + ".put.json")


class PutMark:
    """The highest alarm number of ``rig`` put on the bus (see the module docstring)."""

    def __init__(self, path: str | os.PathLike[str], rig: str) -> None:
        self.path = Path(path)
        self.rig = rig
        self.epoch = ""
        self.seq: int | None = None
        """``None``: no mark (nothing known about what was put)."""
        self._pending: list[tuple[int, str, float]] = []  # (seq, epoch, monotonic time of the put), unsettled
        self._lock = threading.Lock()  # puts and settles may come from the bus's threads and the service's
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
            if isinstance(doc, dict) and doc.get("rig") == rig and isinstance(doc.get("seq"), int) \
                    and isinstance(doc.get("epoch"), str):
                self.seq, self.epoch = int(doc["seq"]), doc["epoch"]
            else:
                log.warning("%s: not the put mark of rig %s; every journaled alarm counts as put", self.path, rig)
        except FileNotFoundError:
            pass
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            log.warning("%s: unreadable put mark (%s); every journaled alarm counts as put", self.path, exc)

    def unsent(self, last_seq: int, epoch: str) -> int | None:
        """The first number journaled but not put, ``None`` when there is none (a mark of another epoch, or
        none, is set to ``last_seq`` now)."""
        if self.seq is None or (epoch and self.epoch and epoch != self.epoch):
            self.done(last_seq, epoch)
            return None
        return self.seq + 1 if last_seq > self.seq else None

    def put(self, seq: int, epoch: str = "", now: float | None = None) -> None:
        """Alarm ``seq`` was handed to the bus at ``now`` (monotonic): written in the mark once settled."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._pending.append((seq, epoch, now))
        self.settle(now)

    @property
    def pending(self) -> int:
        """Alarms put and not settled yet."""
        return len(self._pending)

    def settle(self, now: float | None = None) -> None:
        """Write the mark for the puts the process has outlived by ``SETTLE_S`` (cheap when there are none)."""
        if not self._pending:
            return
        now = time.monotonic() if now is None else now
        with self._lock:
            n = 0  # puts are kept in the order they were made: the settled ones are a prefix
            while n < len(self._pending) and now - self._pending[n][2] >= SETTLE_S:
                n += 1
            if n:
                seq, epoch, _ = self._pending[n - 1]
                del self._pending[:n]
                self.done(seq, epoch)

    def wait_settled(self, timeout: float = SETTLE_S) -> None:
        """At a clean close: wait (at most ``timeout``) until every put is settled, then write the mark."""
        with self._lock:
            last = self._pending[-1][2] if self._pending else None
        if last is not None:
            time.sleep(max(0.0, min(timeout, last + SETTLE_S - time.monotonic())))
            self.settle(last + SETTLE_S)

    def done(self, seq: int, epoch: str = "") -> None:
        """Alarm ``seq`` (and every one before it) was put: written durably (a failure is logged: the worst
        case is that alarm put again after a restart)."""
        if self.seq is not None and seq <= self.seq and (not epoch or epoch == self.epoch):
            return
        self.seq, self.epoch = seq, epoch or self.epoch
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(json.dumps({"rig": self.rig, "epoch": self.epoch, "seq": seq}) + "\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except OSError as exc:
            log.warning("%s: cannot write the put mark (%s); alarm seq %d may be put again after a restart",
                        self.path, exc.strerror or exc, seq)
