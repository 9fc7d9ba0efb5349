"""How far a rig's journaled alarms were put on the bus: ``<journal>.put.json`` beside the journal.

An alarm is journaled first and put after (:mod:`twin.service.bus`). A service killed between the two
(``kill -9``, a power cut) leaves an alarm that is in the journal, and so in the history a
:class:`~twin.service.subscriber.AlarmSubscriber` reads, but that no plain Zenoh subscriber ever got. The
put mark closes that window: after each put the highest number put is written (a temporary file, fsync,
rename), and when the service starts again the alarms after the mark are put, in order
(:meth:`twin.service.bus.TwinPublisher.put_unsent`). An alarm is put twice only when the service died
after the put and before the mark was written (a subscriber counts such a copy as a replay).

The mark names the rig and its journal's epoch (:mod:`twin.service.store`): a mark of another journal
says nothing of this one. A missing mark (the first start of this version, or a new journal) counts every
alarm journaled so far as put.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

log = logging.getLogger("twin.serve")


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
