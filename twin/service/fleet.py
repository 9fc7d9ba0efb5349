"""Running rigs: one :class:`~twin.service.runner.RigRunner` per rig, in threads or spread over spawned worker
processes (:mod:`twin.service.workers`); the service's side of the bus (:class:`BusFront`) and the
:class:`Fleet` that runs them all.

A rig never stops silently:

* a **live** input (``can://``, ``zenoh://``) that goes quiet or is lost is a
  status (``stale_input``, counter ``stale_ms``: for how long) while the rig
  waits and re-opens its input; a message that breaks the source or a block
  the tracker cannot use is counted (``source_errors``, ``bad_blocks``,
  ``bad_samples``), logged and skipped;
* a live sample's time is judged before it is processed: one at or before the
  last processed (or not increasing) is dropped as ``time_backwards``; a run of
  samples that leaps more than ``TIME_JUMP_S`` past the rig's present (our clock
  now, less the best delivery delay seen; the host's UNIX time before the first
  sample) and past the last processed time is dropped as ``time_jump`` (a clock
  glitch of the sender, :mod:`twin.service.live_time`); neither moves the rig's time
  nor reaches a checkpoint, so the correct samples that follow are processed. A
  rig whose samples are stamped ahead, or behind the last processed, for
  ``CLOCK_STEP_SAMPLES`` in a row stepped its clock: that time is adopted (``clock_steps``,
  the filter restarts as after a gap, the events' record time runs on, the journal notes it);
* a **replayed log** is paced in blocks of ``block_s`` (:mod:`twin.service.pacing`)
  and ends normally (state ``finished``);
* an unrecoverable error (a log that cannot be read, a filter that diverged,
  a bug) is state ``failed`` with the cause, on the bus and on the console;
  the service then stops the other rigs (each checkpoints) and exits non-zero
  naming the rig, so systemd restarts it.

Resume, don't replay: every ``checkpoint_s`` (and when it stops) a runner
saves its twin's state (the tracker's and detector's numbers, plain data,
:func:`twin.service.checkpoint_file.write_checkpoints`) with the time of the last sample
processed, the journal's id and the rig's last alarm number, atomically beside
the rig's journal. A restart restores it: a log continues after that sample; a
live input keeps the detector's state, so an ongoing alarm is not raised again.
A checkpoint that cannot be restored (another version, damaged) or a journal
that disagrees with it is refused with one line, never started afresh silently
(:mod:`twin.service.checkpoints`).
Alarms raised between the last checkpoint and a crash are raised again by
the re-processing and recognised by their identity (not journaled or
published twice).

Real time: a runner measures its lag (how far the processing of the last
block is behind the moment its samples were due: the replay schedule for a
log, the best observed arrival for a live input) and publishes it in its
status (``lag_ms``; state ``degraded`` with a message above ``lag_warn_s``).
With ``workers`` > 0 the rigs whose input is not ``zenoh://`` run in spawned
worker processes, so the Python around the compiled filter of one process
does not hold up the others; a worker dies with the service (``PR_SET_PDEATHSIG``).
Events travel to the service's process through a queue (JSON payloads, one
batch per block) and are published there on the service's one Zenoh session.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import os
import queue
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable

from fpdd.errors import ConfigError, TwinError
from twin.online.events import AlarmEvent
from twin.service.checkpoints import commission_path, journal_path, legacy_journal_path
from twin.service.config import RigConfig, ServiceConfig
from twin.service.inputs import is_live
from twin.service.journal import AlarmJournal
from twin.service.outcome import RigSummary
from twin.service.runner import RigRunner
from twin.service.spawn import profiled
from twin.service.workers import worker_main

if TYPE_CHECKING:
    from multiprocessing.process import BaseProcess
    from multiprocessing.queues import Queue as MpQueue

log = logging.getLogger("twin.serve")


# --------------------------------------------------------------------------- the service's process


def _binding(rig: RigConfig):
    """What the rig's journal is bound to (:class:`twin.service.journal.Binding`)."""
    from twin.service.journal import Binding
    from twin.service.signing import load_signer

    key = load_signer(rig.signing_key, rig.name).fingerprint if rig.signing_key else ""
    return Binding(rig.name, key, rig.source)


class BusFront:
    """The service's side of the bus: a :class:`~twin.service.bus.TwinPublisher` per rig, fed by the runners."""

    def __init__(self, session, histories: dict[str, Any],
                 on_alarm: Callable[[AlarmEvent], None] | None = None, signing_keys: dict[str, str] | None = None,
                 terms: dict[str, int] | None = None) -> None:
        from twin.service.bus import TwinPublisher
        from twin.service.put_mark import put_mark_path
        from twin.service.signing import load_signer

        self._pubs: dict[str, TwinPublisher] = {}
        self._signal_pubs: dict[str, Any] = {}
        self._session = session
        self._histories = histories
        self.on_alarm = on_alarm
        self.replicate: Callable[[str, Any, str], None] | None = None
        self.state: dict[str, tuple[str, str]] = {}
        try:
            for rig, history in histories.items():
                key = (signing_keys or {}).get(rig)
                path = getattr(history, "path", None)
                self._pubs[rig] = TwinPublisher(session, rig, history=history,
                                                signer=load_signer(key, rig) if key else None,
                                                put_mark=put_mark_path(path) if path is not None else None,
                                                term=(terms or {}).get(rig, 0))
            for rig, pub in self._pubs.items():  # what a killed service journaled and never put, first
                try:
                    pub.put_unsent()
                except TwinError as exc:
                    log.warning("rig %s: %s", rig, exc)
        except BaseException:
            self.close()
            raise

    def handle(self, rig: str, batch: list[tuple]) -> None:
        pub = self._pubs[rig]
        for item in batch:
            kind = item[0]
            try:
                if kind == "estimate":
                    pub.put_payload("estimate", item[1])
                elif kind == "status":
                    pub.put_payload("status", item[1])
                    self.state[rig] = (item[2], item[3])
                elif kind == "forecast":
                    pub.publish_forecast(item[1])
                elif kind == "signals":
                    sp = self._signal_pubs.get(rig)
                    if sp is None:
                        from twin.service.live_view import signals_key

                        import zenoh

                        sp = self._signal_pubs[rig] = self._session.declare_publisher(  # its payload is JSON
                            signals_key(rig), encoding=zenoh.Encoding.APPLICATION_JSON)
                    sp.put(item[1])
                elif kind == "checkpoint":  # replicated to the standbys (twin.service.replication)
                    if self.replicate is not None:
                        self.replicate(rig, item[1], item[2])
                elif kind == "alarm":
                    event = item[1]
                    pub.put_alarm(event)
                    if self.on_alarm is not None:
                        self.on_alarm(event)
            except TwinError as exc:
                log.warning("rig %s: %s", rig, exc)

    def close(self) -> None:
        for pub in self._pubs.values():
            pub.close()
        self._pubs.clear()
        for sp in self._signal_pubs.values():
            sp.undeclare()
        self._signal_pubs.clear()


#: 1 kHz rigs one worker process is given under ``workers = "auto"`` (a log replayed at speed ``s`` counts ``s``
#: rigs, one replayed as fast as it can be a whole worker): the service's whole path costs 20-30 us of CPU a
#: sample (Results, speed), so 16 rigs take about half a core and leave the rest of it for their window re-fits
#: and bursts; a worker more is an interpreter, numba and the kernels again (about 130 MB of memory).
AUTO_RIGS_PER_WORKER = 16


class Fleet:
    """Every rig of a configuration, run until their logs end, one fails, or ``stop`` is set.

    :param keep: a dict that receives each rig's :class:`RigTwin`; forces threads (objects stay here).
    """

    def __init__(self, cfg: ServiceConfig, session, stop: threading.Event, *,
                 on_alarm: Callable[[AlarmEvent], None] | None = None, keep: dict | None = None,
                 replicate: Callable[[str, Any, str], None] | None = None, takeover: dict | None = None) -> None:
        self.cfg = cfg
        self.replicate = replicate  # each checkpoint to the standbys (twin.service.failover)
        self.takeover = takeover or {}  # rig -> what a takeover tells its runner (twin.service.failover)
        self.session = session
        self.stop = stop
        self.on_alarm = on_alarm
        self.keep = keep
        self.summaries: dict[str, RigSummary] = {}
        self.local, self.remote = self._place()

    def _place(self) -> tuple[list[RigConfig], list[list[RigConfig]]]:
        """Rigs run here (threads) or in worker processes: ``(local, [rigs of worker 1, ...])``."""
        rigs = list(self.cfg.rigs)
        local = [r for r in rigs if r.source.startswith("zenoh://")]  # they ride on this process's session
        others = [r for r in rigs if not r.source.startswith("zenoh://")]
        n = self.cfg.workers
        if n is None:  # auto: processes once there are more rigs than a few threads handle well, as many as
            # their samples need (each process is an interpreter, numba and its kernels: about 130 MB)
            load = sum(r.speed if r.speed > 0 else AUTO_RIGS_PER_WORKER for r in others)
            n = 0 if len(others) <= 4 else min(os.cpu_count() or 1, max(1, math.ceil(load / AUTO_RIGS_PER_WORKER)))
        if self.keep is not None or n == 0 or not others:
            return local + others, []
        n = min(n, len(others))
        groups = [others[i::n] for i in range(n)]
        return local, groups

    @property
    def worker_count(self) -> int:
        return len(self.remote)

    def run(self) -> dict[str, RigSummary]:
        from twin.service.bus import StoreHistory

        cfg = self.cfg
        from twin.service.ownership import new_term

        journals: dict[str, AlarmJournal] = {}
        terms: dict[str, int] = {}
        histories: dict[str, Any] = {}
        front = None
        procs: list[tuple[BaseProcess, list[str]]] = []
        ctx = mp.get_context("spawn")
        # One queue from every runner to the bus; a process-safe one once there are workers.
        inbox: MpQueue[Any] | queue.Queue[Any] = ctx.Queue() if self.remote else queue.Queue()
        stop_pipes: list = []
        threads: list[threading.Thread] = []
        maint: list = []
        try:
            # Every journal is opened here first: integrity, migration and locks are checked before any rig runs.
            for rig in cfg.rigs:
                journals[rig.name] = AlarmJournal(journal_path(cfg, rig.name), legacy=legacy_journal_path(cfg, rig.name),
                                                  witnesses=[commission_path(cfg, rig.name)], bind=_binding(rig))
                terms[rig.name] = new_term()  # this run of the rig: an ownership term (twin.service.ownership)
                journals[rig.name].begin_term(rig.name, terms[rig.name])
            for group in self.remote:
                for rig in group:
                    journals.pop(rig.name).close()
                    histories[rig.name] = StoreHistory(journal_path(cfg, rig.name))
            histories.update(journals)
            front = BusFront(self.session, histories, self.on_alarm,
                             {r.name: r.signing_key for r in cfg.rigs if r.signing_key}, terms)
            front.replicate = self.replicate
            if self.session is not None:  # fpdd/<rig>/maintenance: recorded here, applied by each rig's runner
                from twin.service.maintenance import maintenance_queryables

                maint = maintenance_queryables(self.session, cfg.rigs, cfg.journal_dir)
            for rig in self.local:
                runner = RigRunner(rig, cfg, journals[rig.name], inbox, self.stop, session=self.session,
                                   keep=self.keep)
                runner.takeover = self.takeover.get(rig.name)
                threads.append(threading.Thread(target=runner.run, name=f"rig-{rig.name}", daemon=True))
            for i, group in enumerate(self.remote):
                reader, writer = ctx.Pipe(duplex=False)
                stop_pipes.append((reader, writer))
                p = ctx.Process(target=worker_main, args=(group, cfg, inbox, reader,
                                                          logging.getLogger().getEffectiveLevel()),
                                name=f"twin-worker-{i}", daemon=False)  # may start a fit's process
                procs.append((p, [r.name for r in group]))
            for t in threads:
                t.start()
            for proc, _ in procs:
                proc.start()
            profiled(self._loop, "service")(front, inbox, procs)
        finally:
            self.stop.set()
            for _reader, writer in stop_pipes:
                try:
                    writer.send("stop")
                except OSError:  # that worker is gone already
                    pass
            self._drain_until_done(front, inbox, procs, threads)
            for reader, writer in stop_pipes:
                reader.close()
                writer.close()
            for q in maint:
                q.undeclare()
            if front is not None:
                front.close()
            for h in histories.values():
                if isinstance(h, StoreHistory):
                    h.close()
            for j in journals.values():
                j.close()
            if self.remote and not isinstance(inbox, queue.Queue):  # the process-safe one
                inbox.close()
                inbox.join_thread()
        return self.summaries

    def _receive(self, front, inbox, timeout: float) -> bool:
        """Handle the messages waiting (up to ``timeout`` for the first); ``True`` if any."""
        got = False
        wait = timeout
        while True:
            try:
                msg = inbox.get(timeout=wait) if wait > 0 else inbox.get_nowait()
            except queue.Empty:
                return got
            wait = 0.0
            got = True
            kind, rig = msg[0], msg[1]
            if kind == "batch":
                if front is not None:
                    front.handle(rig, msg[2])
            elif kind == "done":
                self.summaries[rig] = msg[2]
                if msg[2].state == "failed":
                    self.stop.set()

    def _loop(self, front, inbox, procs) -> None:
        from fpdd.process import TRIM_EVERY_S, trim_heap

        names = {r.name for r in self.cfg.rigs}
        trimmed = time.monotonic()
        while True:
            self._receive(front, inbox, 0.1)
            if time.monotonic() - trimmed >= TRIM_EVERY_S:  # the rigs run here too when there are no workers
                trim_heap()
                trimmed = time.monotonic()
            if names <= set(self.summaries) or self.stop.is_set():
                return
            for p, rigs in procs:
                if p.exitcode is not None and not set(rigs) <= set(self.summaries):
                    self._receive(front, inbox, 0.5)  # its last messages may still be in the pipe
                    for rig in rigs:
                        if rig not in self.summaries:
                            self.summaries[rig] = RigSummary(rig, "failed",
                                                             f"its worker process died (exit code {p.exitcode})")
                    self.stop.set()

    def _drain_until_done(self, front, inbox, procs, threads, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        names = {r.name for r in self.cfg.rigs}
        while time.monotonic() < deadline:
            self._receive(front, inbox, 0.05)
            alive = any(t.is_alive() for t in threads) or any(p.is_alive() for p, _ in procs)
            if not alive and (names <= set(self.summaries) or not self._receive(front, inbox, 0.2)):
                break
        for p, rigs in procs:
            p.join(timeout=max(0.1, deadline - time.monotonic()))
            if p.is_alive():
                log.error("worker process of %s did not stop; terminating it", ", ".join(rigs))
                p.terminate()
                p.join(5.0)
        for rig in names - set(self.summaries):
            self.summaries[rig] = RigSummary(rig, "failed", "did not report before the service stopped")


def check_journal_dir(cfg: ServiceConfig) -> None:
    """``journal_dir`` (and ``out_dir``) exist or can be made, are directories and writable; else ConfigError."""
    for key, value in (("journal_dir", cfg.journal_dir), ("out_dir", cfg.out_dir)):
        if not value:
            continue
        where = f"{cfg.path}: service.{key}"
        p = Path(value)
        for parent in [p, *p.parents]:
            if parent.exists():
                if not parent.is_dir():
                    raise ConfigError(f"{where}: {value!r} cannot be a directory: {str(parent)!r} is a file")
                break
        try:
            p.mkdir(parents=True, exist_ok=True)
            probe = p / f".write-test-{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise ConfigError(f"{where}: {value!r} is not a writable directory ({exc.strerror or exc})") from None


def check_sources(cfg: ServiceConfig) -> None:
    """Every log source exists (a missing log is a configuration error, before anything starts)."""
    for rig in cfg.rigs:
        if not is_live(rig.source):
            p = Path(rig.source)
            if not p.is_file():
                what = "is a directory" if p.is_dir() else "does not exist"
                raise ConfigError(f"{cfg.path}: rig {rig.name!r}.source: {rig.source!r} {what}")
