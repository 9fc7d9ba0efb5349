"""Rigs in worker processes: a spawned worker runs its replayed logs on one thread, earliest due block first
(:func:`run_scheduled`), and each live input on a thread of its own (:func:`worker_main`); results and bus
messages go to the service's process through a queue."""

from __future__ import annotations

import math
import signal
import threading
import time
from typing import Any

from fpdd.errors import TwinError
from twin.service.checkpoints import commission_path, journal_path
from twin.service.config import RigConfig, ServiceConfig
from twin.service.inputs import is_live
from twin.service.journal import AlarmJournal
from twin.service.outcome import RigSummary, Stopped
from twin.service.runner import RigRunner
from twin.service.spawn import die_with_parent, profiled


def worker_main(rigs: list[RigConfig], cfg: ServiceConfig, out, stop_conn, log_level: int) -> None:
    """A spawned worker: its replayed logs on one thread (:func:`run_scheduled`), each live input on a
    thread of its own; results and bus messages go to ``out``.

    ``stop_conn``: the reading end of a pipe from the service; a message or
    its end (the service's process gone) stops the rigs. Not a
    ``multiprocessing.Event``: a process that exits while one of its threads
    waits on it leaves the event's condition blocked for whoever sets it, and
    many threads waiting on it serialise on its process-shared semaphores.
    """
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the service's process decides when to stop
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from twin.service.console import install

    console = install(log_level)  # a stuck console never stalls a rig
    local = threading.Event()

    def relay() -> None:
        try:
            stop_conn.recv()
        except (EOFError, OSError):
            pass
        local.set()

    threading.Thread(target=relay, name="stop-relay", daemon=True).start()
    threads = []
    logs = [rig for rig in rigs if not is_live(rig.source)]
    if logs:  # replayed logs: one thread, earliest due first (see run_scheduled)
        threads.append(threading.Thread(target=profiled(run_scheduled, "logs"), args=(logs, cfg, out, local),
                                        name="rig-logs", daemon=True))
    for rig in rigs:
        if is_live(rig.source):  # a live input blocks in its reads: a thread of its own
            threads.append(threading.Thread(target=profiled(_run_one, f"rig-{rig.name}"),
                                            args=(rig, cfg, out, local), name=f"rig-{rig.name}", daemon=True))
    for t in threads:
        t.start()
    from fpdd.process import TRIM_EVERY_S, trim_heap

    for t in threads:
        while t.is_alive():  # meanwhile the freed C heap goes back to the system (glibc would keep it)
            t.join(TRIM_EVERY_S)
            if t.is_alive():
                trim_heap()
    console.close()
    from fpdd.process import exit_process

    out.close()  # what the rigs put on the queue reaches the service first
    out.join_thread()
    exit_process(0)  # as the programs leave (Zenoh's threads at the interpreter's exit)


def run_scheduled(rigs: list[RigConfig], cfg: ServiceConfig, out, stop) -> None:
    """Rigs replaying logs, all on this thread: each rig's :meth:`RigRunner.run_steps` is resumed when its
    next block is due, the earliest first.

    Why not a thread per rig: the Python around each compiled filter call
    holds the GIL, and dozens of threads of one process handing it over cost
    more CPU than the work between the calls (with 50 rigs in one process,
    17 us per sample in threads against 13 one after another, filter
    included; ``python -m benchmarks.service fleet``). A worker process per
    core keeps the cores busy; a rig that falls behind catches up in larger
    blocks (:func:`blocks_by_time`), so every rig gets its turn. ``stop``
    stops each rig at its next turn (it checkpoints).
    """
    import heapq
    import inspect

    heap: list[tuple[float, int, Any, AlarmJournal]] = []
    for i, rig in enumerate(rigs):
        journal = _open_journal(rig, cfg, out)
        if journal is None:
            continue
        heap.append((-math.inf, i, RigRunner(rig, cfg, journal, out, stop).run_steps(), journal))
    heapq.heapify(heap)
    while heap:
        due, i, steps, journal = heap[0]
        delay = due - time.monotonic()
        if delay > 0 and not stop.is_set():
            stop.wait(delay)
            if not stop.is_set() and heap[0][0] > time.monotonic():
                continue
        heapq.heappop(heap)
        try:
            if stop.is_set() and inspect.getgeneratorstate(steps) != inspect.GEN_CREATED:
                nxt = steps.throw(Stopped())
            else:  # a rig not started yet opens, reports and stops at its first check
                nxt = next(steps)
        except StopIteration:
            journal.close()
            continue
        heapq.heappush(heap, (nxt, i, steps, journal))


def _open_journal(rig: RigConfig, cfg: ServiceConfig, out) -> AlarmJournal | None:
    """The rig's alarm journal, or None when it cannot be opened (the rig is then reported failed on ``out``)."""
    try:
        return AlarmJournal(journal_path(cfg, rig.name), lock_wait_s=10.0,
                            witnesses=[commission_path(cfg, rig.name)])
    except TwinError as exc:
        out.put(("done", rig.name, RigSummary(rig.name, "failed", str(exc))))
        return None


def _run_one(rig: RigConfig, cfg: ServiceConfig, out, stop) -> None:
    journal = _open_journal(rig, cfg, out)
    if journal is None:
        return
    with journal:
        RigRunner(rig, cfg, journal, out, stop).run()

