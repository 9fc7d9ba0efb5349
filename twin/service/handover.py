"""After a split network: the owner that stands down hands the alarms it raised over to the owner that stays,
then takes that owner's numbering.

While the network was split, two services ran one rig (:mod:`twin.service.ownership`), each numbering its alarms
after the last one they shared: the same numbers, different alarms. When they see each other again the one the
rule ranks after stands down (:mod:`twin.service.failover`) and, before it stands by, :func:`hand_over`:

1. sends the alarms it raised in its term (its journal's alarms carrying that term) to the owner that stays, on
   ``fpdd/<rig>/alarm/handover`` (signed with the rig's key when it has one: the owner refuses any that does not
   verify);
2. that owner (:meth:`twin.service.bus.TwinPublisher.adopt`) journals every one it does not hold (by identity:
   the same alarm raised on both sides is kept once, as the owner raised it) under its own next numbers, marked
   in the message ``split: raised by term T as seq N at <time> ...; renumbered by term W``, keeping its term T and
   raise time, and puts it on ``fpdd/<rig>/alarm`` like any alarm: every subscriber, a plain one included,
   receives it under a number of its own;
3. the service that stood down reads the owner's history from the first number it had given (from 1 when it
   numbered in another epoch than the owner's) and replaces its own alarms from there by the owner's (:meth:`twin.service.journal.AlarmJournal.supersede`; the replaced ones
   are kept whole in its journal's notes, kind ``superseded``): its journal then holds the owner's alarm under
   every number, and its replica follows the owner from there.

An :class:`~twin.service.subscriber.AlarmSubscriber` (``twin alarms``) that receives a marked alarm reports
in one line that the alarm of number N was the losing side's, and, when it had delivered that side's alarm under
N, delivers the owner's alarm of N from the history. So no number ends up meaning two different alarms, and no
alarm raised on either side is lost.
"""

from __future__ import annotations

import dataclasses
import json
import logging

import zenoh

from fpdd.errors import DataError, SourceError
from twin.online.events import AlarmEvent
from twin.service.bus import RigKeys, _ranges, signed_by
from twin.service.journal import AlarmJournal
from twin.service.signing import Signer

log = logging.getLogger("twin.serve")

#: How long the service that stands down waits for the owner's answer and history [s].
HANDOVER_S = 5.0


@dataclasses.dataclass(frozen=True)
class Handover:
    """What :func:`hand_over` did."""

    raised: int
    """Alarms this service raised in its term."""
    adopted: int = 0
    """Of those, journaled by the owner under its numbers (it did not hold them)."""
    replaced: int = 0
    """Alarms of this journal replaced by the owner's of the same numbers."""
    note: str = ""
    """One line: what was done, or why nothing was."""


def hand_over(session: zenoh.Session, journal: AlarmJournal, rig: str, term: int, signer: Signer | None = None,
              timeout: float = HANDOVER_S) -> Handover:
    """Hand the alarms ``journal`` holds of ``rig`` raised in ``term`` over to the rig's owner and take its
    numbering (see the module docstring). Never raises for the bus: a failure is said in :attr:`Handover.note`
    (and logged), the journal then left as it was."""
    keys = RigKeys(rig)
    mine = [e for e in journal.read(rig=rig) if term and e.term == term]
    if not mine:
        return Handover(0, note=f"rig {rig}: no alarm raised in term {term}; nothing to hand over")
    alarms = [json.loads(signer.payload(e)) if signer is not None else e.to_dict() for e in mine]
    body = json.dumps({"rig": rig, "term": term, "alarms": alarms})
    answer = None
    errors = []
    try:
        for reply in session.get(keys.handover, payload=body, timeout=timeout):
            if reply.ok is not None and answer is None:
                answer = json.loads(reply.ok.payload.to_string())
            elif reply.err is not None:
                errors.append(reply.err.payload.to_string())
    except (zenoh.ZError, ValueError) as exc:
        errors.append(str(exc))
    first = mine[0].seq
    seqs = _ranges([e.seq for e in mine])
    if not isinstance(answer, dict) or not isinstance(answer.get("alarms"), list):
        note = (f"rig {rig}: alarm(s) seq {seqs} raised in term {term} not handed over (no owner answered on "
                f"{keys.handover}{': ' + '; '.join(errors) if errors else ''}); they stay in this journal only")
        log.warning("%s", note)
        return Handover(len(mine), note=note)
    adopted = sum(1 for a in answer["alarms"] if isinstance(a, dict) and not a.get("held"))
    if answer.get("epoch") and answer["epoch"] != journal.epoch(rig):
        first = 1  # this journal numbered in another epoch than the owner's: its whole numbering is the owner's
    theirs = _history(session, keys, first, timeout, signer)
    try:
        replaced = journal.supersede(rig, first, theirs)
    except (DataError, SourceError) as exc:
        note = (f"rig {rig}: alarm(s) seq {seqs} of term {term} handed over ({adopted} journaled by the owner), "
                f"but this journal keeps its own numbers from seq {first}: {exc}")
        log.warning("%s", note)
        return Handover(len(mine), adopted, note=note)
    note = (f"rig {rig}: alarm(s) seq {seqs} raised in term {term} handed over to term {answer.get('term')} "
            f"({adopted} journaled there under new numbers, {len(mine) - adopted} held already); this journal "
            f"follows its numbering from seq {first} ({replaced} alarm(s) replaced, kept in its notes)")
    log.warning("%s", note)
    return Handover(len(mine), adopted, replaced, note)


def _history(session: zenoh.Session, keys: RigKeys, since_seq: int, timeout: float,
             signer: Signer | None) -> list[AlarmEvent]:
    """The owner's journaled alarms from ``since_seq`` (its history queryable: the only one once this service
    stood down), one per number; with the rig's key, only those signed with it."""
    got: dict[int, AlarmEvent] = {}
    for reply in session.get(f"{keys.history}?since_seq={since_seq}", timeout=timeout,
                             consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is None:
            continue
        try:
            data = json.loads(reply.ok.payload.to_string())
            if signer is not None and not signed_by(signer, data):
                raise DataError(f"does not verify with the key of rig {keys.rig!r}")
            ev = AlarmEvent.from_dict(data)
        except (DataError, ValueError) as exc:
            log.warning("%s: a history reply refused: %s", keys.history, exc)
            continue
        if ev.rig == keys.rig:
            got.setdefault(ev.seq, ev)
    return [got[s] for s in sorted(got)]
