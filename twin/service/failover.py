"""``twin serve`` with ``[failover]``: rigs shared by several services, each run by one of them at a time, the
others standing by with a replica of its state (:mod:`twin.service.ownership` for who runs what,
:mod:`twin.service.replication` for the replica).

Each rig is a slot that goes through::

    standby --(no owner, first standby by the rule)--> claiming --(claim_s, no better owner)--> owner
    owner --(its log ended)--> done          owner --(a better owner or a better 'prefer' standby)--> standby

An owner runs its rig as a service of one rig would (:class:`twin.service.fleet.Fleet`, threads of this
process), resuming from the replica's checkpoint: a replayed log from that checkpoint's position (the data
after it is processed again and raises its alarms again, which the journal recognises by identity or numbers
next, never publishing one twice); a live input from now. Its status says so for the rest of the run
(``took over from <id>``, counters ``took_over_ms``: from the last owner's token gone to the rig running,
``unwatched_ms``: record time no service watched, live inputs only) and the console logs it. Each service
appends to ``<journal_dir>/<rig>.owners.jsonl`` when it starts and stops running a rig (:meth:`FailoverService._record`):
the files of the services sharing a rig say together who watched it when. An owner that stands down because
another one ran the rig at the same time (a split network joined again) hands the alarms of its term over to
that owner and takes its numbering before it stands by (:mod:`twin.service.handover`; ``handed_over`` in its
owners file).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable

from fpdd.errors import TwinError
from twin.online.events import AlarmEvent
from twin.service.config import RigConfig, ServiceConfig
from twin.service.inputs import is_live
from twin.service.outcome import RigSummary
from twin.service.ownership import FailoverConfig, Ownership
from twin.service.replication import Replica, ReplicaSource

log = logging.getLogger("twin.serve")

#: The main loop looks at the tokens at least this often [s] (and at once when one comes or goes).
TICK_S = 0.05


@dataclasses.dataclass
class Slot:
    """One rig's place in this service."""

    rig: RigConfig
    state: str = "standby"
    replica: Replica | None = None
    source: ReplicaSource | None = None
    thread: threading.Thread | None = None
    stop: threading.Event = dataclasses.field(default_factory=threading.Event)
    claim_at: float = 0.0
    owner: str = ""
    """The last owner seen (another service)."""
    owner_gone_at: float | None = None
    """``time.monotonic()`` when no owner was seen any more."""
    standing_down: bool = False
    summary: RigSummary | None = None


class FailoverService:
    """Every rig of ``cfg`` shared with the other services of ``cfg.failover`` (see the module docstring)."""

    def __init__(self, cfg: ServiceConfig, session, stop: threading.Event,
                 on_alarm: Callable[[AlarmEvent], None] | None = None) -> None:
        assert cfg.failover is not None
        self.cfg = cfg
        self.me: FailoverConfig = cfg.failover
        self.session = session
        self.stop = stop
        self.on_alarm = on_alarm
        self.slots = {r.name: Slot(r) for r in cfg.rigs}
        self._wake = threading.Event()
        self.summaries: dict[str, RigSummary] = {}
        self._replicas: list[Replica] = []  # every one made: each closed (its thread stopped) before run returns

    def run(self) -> dict[str, RigSummary]:
        own = Ownership(self.session, list(self.slots), self.me, self._wake.set)
        self.ownership = own
        started = time.monotonic()
        warm = threading.Thread(target=self._warm_up, name="failover-warm-up", daemon=True)
        warm.start()
        try:
            for slot in self.slots.values():
                self._stand_by(slot)
            while not self.stop.is_set():
                self._wake.wait(TICK_S)
                self._wake.clear()
                settled = time.monotonic() - started >= self.me.claim_s  # tokens already there have come in
                for slot in self.slots.values():
                    self._step(slot, settled)
                if all(s.state == "done" for s in self.slots.values()):
                    break
        finally:
            self.stop.set()
            for slot in self.slots.values():
                slot.stop.set()
            for slot in self.slots.values():
                self._end(slot)
            own.close()
            warm.join()
            for replica in self._replicas:  # no replica thread left in a Zenoh call when the session closes: a
                replica.close()  # thread inside Zenoh at the interpreter's exit aborts the process (SIGABRT)
        return self.summaries

    def _warm_up(self) -> None:
        """Load each model's compiled filter now (about 2 s from the disk cache), not when a rig is taken over."""
        from twin.service.rig import make_twin

        for rig in {r.model: r for r in self.cfg.rigs}.values():
            try:
                make_twin(rig)
            except Exception as exc:  # noqa: BLE001 - the takeover will say what is wrong
                log.debug("rig %s: warm-up: %s", rig.name, exc)

    # ------------------------------------------------------------------ transitions

    def _stand_by(self, slot: Slot) -> None:
        slot.replica = Replica(self.session, self.cfg, slot.rig)
        self._replicas.append(slot.replica)
        slot.state = "standby"
        slot.standing_down = False
        self.ownership.hold(slot.rig.name, "standby", True)
        if self.me.prefer:
            self.ownership.hold(slot.rig.name, "prefer", True)

    def _step(self, slot: Slot, settled: bool) -> None:
        name, me = slot.rig.name, self.ownership.my_rank
        view = self.ownership.view(name)
        others = sorted((p, s) for s, p in view.roles["owner"].items() if s != self.me.service_id)
        now = time.monotonic()
        if others:
            slot.owner, slot.owner_gone_at = others[0][1], None
        elif slot.owner_gone_at is None:
            slot.owner_gone_at = now
        if slot.state == "standby":
            assert slot.replica is not None
            if slot.replica.finished:
                self._done(slot, RigSummary(name, "finished", f"its log was run to its end by {slot.replica.owner}"))
            elif not others and settled and view.ranked("standby")[:1] == [me]:
                log.info("rig %s: no owner; claiming it (first of %d standby service(s))", name,
                         len(view.roles["standby"]))
                self.ownership.hold(name, "owner", True)
                slot.state, slot.claim_at = "claiming", now
        elif slot.state == "claiming":
            assert slot.replica is not None
            if any(o < me for o in others) or slot.replica.finished:
                log.info("rig %s: claim withdrawn (%s)", name,
                         "its log has ended" if slot.replica.finished else f"{others[0][1]} runs it")
                self.ownership.hold(name, "owner", False)
                slot.state = "standby"
            elif now - slot.claim_at >= self.me.claim_s:
                self._run(slot)
        elif slot.state == "owner":
            assert slot.thread is not None
            if not slot.thread.is_alive():
                self._ended(slot)
                return
            prefer = [p for p in view.ranked("prefer") if p[1] != self.me.service_id and p < me]
            better = [o for o in others if o < me]
            if (better or prefer) and not slot.standing_down:
                who = (better or prefer)[0][1]
                log.warning("rig %s: standing down for %s (%s)", name, who,
                            "it runs the rig too: the network was split" if better else "it asks for the rig back")
                slot.standing_down = True
                slot.stop.set()

    def _run(self, slot: Slot) -> None:
        from twin.service.fleet import Fleet

        name = slot.rig.name
        replica = slot.replica
        assert replica is not None
        gone = slot.owner_gone_at
        cp, watched, previous = replica.checkpoint, replica.watched_until_ns, replica.owner or slot.owner
        replica.close()
        slot.replica = None
        self.ownership.hold(name, "standby", False)
        self.ownership.hold(name, "prefer", False)
        takeover = None
        took_ms = None
        if previous:
            took_ms = int(max(0.0, time.monotonic() - gone) * 1000) if gone is not None else 0
            if is_live(slot.rig.source):
                where = "from now"
            elif cp is not None:
                again = max(0, (watched or cp.t_ns) - cp.t_ns) * 1e-9
                where = f"from its checkpoint at t={cp.t_ns * 1e-9:.3f} s of the log ({again:.2f} s processed again)"
            else:
                where = "from the start of its log (no checkpoint replicated)"
            note = f"took over from {previous} {took_ms / 1000:.2f} s after its token went, {where}"
            takeover = {"note": note, "counters": {"took_over_ms": took_ms},
                        "watched_until_ns": watched if is_live(slot.rig.source) else None}
            log.warning("rig %s: %s", name, note)
        source = ReplicaSource(self.session, name, self.me.service_id)
        slot.source = source
        slot.stop = threading.Event()
        cfg = dataclasses.replace(self.cfg, rigs=(slot.rig,), workers=0)
        fleet = Fleet(cfg, self.session, slot.stop, on_alarm=self.on_alarm,
                      replicate=lambda _rig, cp_, state: source.publish(cp_, state),
                      takeover={name: takeover} if takeover else None)

        def run() -> None:
            try:
                slot.summary = fleet.run().get(name)
            except TwinError as exc:
                slot.summary = RigSummary(name, "failed", str(exc))
            except Exception as exc:  # a bug: the rig's outcome, the traceback in the debug log
                log.debug("rig %s: unexpected error", name, exc_info=True)
                slot.summary = RigSummary(name, "failed", f"internal error {type(exc).__name__}: {exc}")

        slot.thread = threading.Thread(target=run, name=f"owner-{name}", daemon=True)
        slot.state = "owner"
        self._record(name, "runs", previous=previous or None,
                     took_over_ms=took_ms,
                     resumed_t_ns=cp.t_ns if cp is not None else None)
        slot.thread.start()

    def _ended(self, slot: Slot) -> None:
        """The rig's run ended: done (its log ended, it failed, the service stops) or stand by (stood down)."""
        name = slot.rig.name
        summary = slot.summary or RigSummary(name, "failed", "its run ended without a summary")
        if slot.source is not None:
            slot.source.close()
            slot.source = None
        self.ownership.hold(name, "owner", False)
        slot.thread = None
        self._record(name, "stood_down" if slot.standing_down and summary.state == "stopped" else summary.state,
                     message=summary.message or None)
        if slot.standing_down and not self.stop.is_set() and summary.state == "stopped":
            log.info("rig %s: stood down; standing by", name)
            self._hand_over(slot)
            self._stand_by(slot)
            return
        self._done(slot, summary)
        if summary.state == "failed":
            self.stop.set()  # as a service of its own: the others stop, the process exits non-zero

    def _hand_over(self, slot: Slot) -> None:
        """Stood down (a split network joined again): the alarms raised in this service's term go to the owner
        that stays, and the journal takes its numbering (:mod:`twin.service.handover`)."""
        from twin.service.checkpoints import commission_path, journal_path
        from twin.service.fleet import _binding
        from twin.service.handover import hand_over
        from twin.service.journal import AlarmJournal
        from twin.service.signing import load_signer

        rig = slot.rig
        try:
            signer = load_signer(rig.signing_key, rig.name) if rig.signing_key else None
            with AlarmJournal(journal_path(self.cfg, rig.name), witnesses=[commission_path(self.cfg, rig.name)],
                              bind=_binding(rig)) as journal:
                done = hand_over(self.session, journal, rig.name, journal.term(rig.name), signer)
        except TwinError as exc:
            log.warning("rig %s: the alarms of its term were not handed over: %s", rig.name, exc)
            return
        if done.raised:
            self._record(rig.name, "handed_over", message=done.note, raised=done.raised, adopted=done.adopted,
                         replaced=done.replaced)

    def _record(self, rig: str, event: str, **info) -> None:
        """Who watched the rig when: a line appended to ``<journal_dir>/<rig>.owners.jsonl`` when this service
        starts (``runs``) and stops running it (``finished``, ``stopped``, ``failed``, ``stood_down``)."""
        import json
        from pathlib import Path

        line = json.dumps({"wall_ns": time.time_ns(), "service_id": self.me.service_id, "rig": rig, "event": event,
                           **{k: v for k, v in info.items() if v is not None}})
        try:
            with open(Path(self.cfg.journal_dir) / f"{rig}.owners.jsonl", "a", encoding="utf-8") as f:
                f.write(line + "\n")
        except OSError as exc:
            log.warning("rig %s: cannot record who runs it: %s", rig, exc)

    def _done(self, slot: Slot, summary: RigSummary) -> None:
        if slot.replica is not None:
            slot.replica.close()
            slot.replica = None
        for role in ("standby", "prefer", "owner"):
            self.ownership.hold(slot.rig.name, role, False)
        slot.state = "done"
        self.summaries[slot.rig.name] = summary

    def _end(self, slot: Slot) -> None:
        if slot.thread is not None:
            slot.thread.join()
            self._ended(slot)
        if slot.state != "done":
            who = slot.owner or "no service"
            self._done(slot, RigSummary(slot.rig.name, "stopped", f"stood by (owner: {who})"))


def serve_failover(cfg: ServiceConfig, session, stop: threading.Event,
                   on_alarm: Callable[[AlarmEvent], None] | None = None) -> dict[str, RigSummary]:
    """Run ``cfg``'s rigs shared with the other services of its ``[failover]`` until their logs end (here or on
    another service) or ``stop`` is set; per-rig summaries."""
    return FailoverService(cfg, session, stop, on_alarm).run()
