"""Running rigs: one :class:`RigRunner` per rig, in threads or spread over spawned worker processes.

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
  glitch of the sender, :meth:`RigRunner._future`); neither moves the rig's time
  nor reaches a checkpoint, so the correct samples that follow are processed. A
  rig whose every sample is stamped ahead, or behind the last processed, for
  ``CLOCK_STEP_S`` stepped its clock: that time is adopted (``clock_steps``, the
  filter restarts as after a gap, the events' record time runs on);
* a **replayed log** is paced in blocks of ``block_s`` and ends normally
  (state ``finished``);
* an unrecoverable error (a log that cannot be read, a filter that diverged,
  a bug) is state ``failed`` with the cause, on the bus and on the console;
  the service then stops the other rigs (each checkpoints) and exits non-zero
  naming the rig, so systemd restarts it.

Resume, don't replay: every ``checkpoint_s`` (and when it stops) a runner
saves its twin's state (the tracker's and detector's numbers, plain data,
:func:`twin.service.store.write_checkpoints`) with the time of the last sample
processed, the journal's id and the rig's last alarm number, atomically beside
the rig's journal. A restart restores it: a log continues after that sample; a
live input keeps the detector's state, so an ongoing alarm is not raised again.
A checkpoint that cannot be restored (another version, damaged) or a journal
that disagrees with it is refused with one line, never started afresh silently.
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

import ctypes
import dataclasses
import logging
import math
import multiprocessing as mp
import os
import queue
import signal
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any
from collections.abc import Callable

import numpy as np

from replay.base import Samples
from twin.service.config import RigConfig, ServiceConfig
from twin.errors import ConfigError, DataError, FilterError, SourceError, TwinError
from twin.online.events import AlarmEvent, StatusEvent, event_to_json
from twin.service.journal import AlarmJournal
from twin.service.rig import RigStats, RigTwin, fingerprint, make_twin
from twin.service.store import Checkpoint

if TYPE_CHECKING:
    from multiprocessing.process import BaseProcess
    from multiprocessing.queues import Queue as MpQueue

    from replay.mcapio import McapSink

log = logging.getLogger("twin.serve")

#: Samples read from a log per chunk before it is cut into paced blocks.
READ_CHUNK = 2000
#: A runner's bus messages are flushed at least this often [s] even without samples.
FLUSH_S = 0.25
#: A jump in sample time longer than this (or 20 sample periods) restarts the filter's model states [s].
GAP_S = 0.5
#: A rig behind real time filters every sample already due in one block, up to this much of them [s]
#: (fewer, larger blocks cost less Python per sample, so a rig that fell behind catches up).
MAX_BLOCK_S = 1.0
#: A filter that diverges again within this long of a restart is a failure of the rig [s].
RESET_WINDOW_S = 10.0
#: A live sample stamped more than this after the rig's present (our clock now, less the best delivery delay
#: seen) cannot have been measured yet: a clock glitch, dropped as ``time_jump`` [s]. Far beyond delivery
#: jitter and the corrections a synchronised clock makes (milliseconds); an accepted sample at most this far
#: ahead costs the correct samples of at most this long (they come before it).
TIME_JUMP_S = 5.0
#: A live input whose every sample is stamped ahead (``time_jump``) for this long stepped its clock: the new
#: time is adopted (counted ``clock_steps``) rather than blinding the rig for ever [s].
CLOCK_STEP_S = 30.0


def is_live(uri: str) -> bool:
    return uri.startswith(("can://", "zenoh://"))


def journal_path(cfg: ServiceConfig, rig: str) -> Path:
    """The rig's SQLite journal."""
    return Path(cfg.journal_dir) / f"{rig}.db"


def commission_path(cfg: ServiceConfig, rig: str) -> Path:
    """Where a rig's commissioning in service (``commission_s``) is saved, next to its journal."""
    return Path(cfg.journal_dir) / f"{rig}.commission.json"


def legacy_journal_path(cfg: ServiceConfig, rig: str) -> Path:
    """Where earlier versions kept the rig's JSON-lines journal (imported once)."""
    return Path(cfg.journal_dir) / f"{rig}.alarms.jsonl"


def open_rig_source(rig: RigConfig, session=None, timeout_s: float | None = None):
    """The rig's source; a ``zenoh://`` input rides on the service's own Zenoh session."""
    from replay.factory import open_source

    opts: dict[str, Any] = rig.source_options()
    if rig.source.startswith("zenoh://") and session is not None:
        opts["session"] = session
    if is_live(rig.source) and timeout_s is not None:
        opts["timeout_s"] = timeout_s
    if rig.source.startswith("zenoh://"):  # the runner orders blocks itself and judges a block from the future
        from replay.quality import QualityOptions

        opts["quality"] = QualityOptions(order_across_blocks=False)
    return open_source(rig.source, **opts)


# --------------------------------------------------------------------------- results


@dataclasses.dataclass
class RigSummary:
    """What one rig did in this run of the service."""

    rig: str
    state: str = "starting"
    message: str = ""
    samples: int = 0
    """Samples processed in this run."""
    alarms: int = 0
    """Alarms journaled and published in this run."""
    duplicates: int = 0
    resumed_samples: int | None = None
    """Samples already processed according to the checkpoint restored (None: fresh start)."""
    lag_max_s: float | None = None
    source_errors: int = 0
    bad_blocks: int = 0
    bad_samples: int = 0
    """Live samples without a finite drive (dropped)."""
    time_backwards: int = 0
    """Live samples at or before the last one processed, or not increasing (dropped)."""
    time_jump: int = 0
    """Live samples stamped far ahead of the rig's present (dropped, see ``TIME_JUMP_S``)."""
    clock_steps: int = 0
    """Times the live input's clock stepped ahead and its new time was adopted (``CLOCK_STEP_S``)."""
    input_gaps: int = 0
    filter_resets: int = 0
    input_dropped: int = 0
    """Messages or samples the live source dropped (its counts per cause are in the status)."""
    input_lost: str = ""
    """What the reader of a replayed log lost on the way (its loss line; "" when nothing): ``twin serve`` warns
    and exits 3."""
    busy_s: float = 0.0
    stats: RigStats = dataclasses.field(default_factory=RigStats)

    def line(self) -> str:
        parts = [f"{self.rig}: {self.state}", f"{self.samples} samples", f"{self.alarms} alarm(s)"]
        if self.resumed_samples is not None:
            parts.append(f"resumed after {self.resumed_samples} samples")
        if self.duplicates:
            parts.append(f"{self.duplicates} alarm(s) already journaled")
        if self.lag_max_s is not None:
            parts.append(f"lag max {self.lag_max_s:.3f} s")
        for name in _COUNTED + ("input_dropped",):
            if getattr(self, name):
                parts.append(f"{name} {getattr(self, name)}")
        text = ", ".join(parts)
        text = f"{text}: {self.message}" if self.message else text
        return f"{text}; input lost: {self.input_lost}" if self.input_lost and self.input_lost not in text else text


#: Counters of a :class:`RigSummary` that go into the rig's status when not zero.
_COUNTED = ("source_errors", "bad_blocks", "bad_samples", "time_backwards", "time_jump", "clock_steps", "input_gaps",
            "filter_resets")


class RigFailure(TwinError):
    """An unrecoverable error of one rig (named in the message)."""


class _Stopped(Exception):
    pass


# --------------------------------------------------------------------------- the runner's publisher


class Outbox:
    """A runner's publisher for its :class:`RigTwin`: journals alarms, batches bus messages.

    Messages (put on ``out`` as ``("batch", rig, [...])`` after each block):
    ``("alarm", AlarmEvent, durable)``, ``("estimate", json)``,
    ``("status", json, state, message)``, ``("forecast", dict)``.
    """

    def __init__(self, rig: str, journal: AlarmJournal, out, signals_hz: float = 0.0) -> None:
        self.rig = rig
        self.journal = journal
        self.out = out
        self._decimate = None
        if signals_hz > 0:  # the rig's signals for live views, ("signals", json) on fpdd/<rig>/signals
            from twin.service.live_view import SignalDecimator

            self._decimate = SignalDecimator(signals_hz)
        self._batch: list[tuple] = []
        self._last_flush = time.monotonic()
        self._seq = journal.last_seq(rig)

    def publish_alarm(self, event: AlarmEvent) -> AlarmEvent | None:
        recorded = self.journal.record(event)
        if not recorded.new:
            return None
        if recorded.durable:  # an alarm goes on the bus once it is in the journal's main file, and at once
            self._seq = max(self._seq, recorded.event.seq)
            self._batch.append(("alarm", recorded.event, True))
            self.flush()
        return recorded.event  # one the journal holds (write failed) goes out when written (flush)

    def publish_estimate(self, event) -> None:
        self._batch.append(("estimate", event_to_json(event)))

    def publish_estimate_json(self, payload: str) -> None:
        """An estimate already written as its JSON payload (:meth:`twin.service.rig.RigTwin._estimate_json`)."""
        self._batch.append(("estimate", payload))

    def publish_forecast(self, msg: dict) -> None:
        """A forecast message (:func:`twin.online.forecast.forecast_message`): relayed to the service's
        :meth:`twin.service.bus.TwinPublisher.publish_forecast` (which decides when it goes on the bus)."""
        self._batch.append(("forecast", msg))

    def publish_signals(self, samples: Samples) -> None:
        """The rig's samples, decimated to ``signals_hz`` (nothing when it is 0)."""
        if self._decimate is not None:
            kept = self._decimate(samples)
            if kept is not None:
                from twin.service.live_view import signals_to_json

                self._batch.append(("signals", signals_to_json(self.rig, kept)))

    def status_counters(self) -> dict[str, int]:
        """``alarm_seq``: the last number the journal gave an alarm of this rig (this runner is its one writer)."""
        return {"alarm_seq": self._seq}

    def publish_status(self, event: StatusEvent) -> StatusEvent:
        if "alarm_seq" not in event.counters:
            event = dataclasses.replace(event, counters={**event.counters, **self.status_counters()})
        self._batch.append(("status", event_to_json(event), event.state, event.message))
        return event

    def flush(self, force: bool = True) -> None:
        if self.journal.pending:
            self.journal.retry()
        written = self.journal.take_written()
        for ev in written:
            self._seq = max(self._seq, ev.seq)
            self._batch.append(("alarm", ev, True))
        if self._batch and (force or written or time.monotonic() - self._last_flush >= FLUSH_S):
            batch, self._batch = self._batch, []
            self.out.put(("batch", self.rig, batch))
            self._last_flush = time.monotonic()


# --------------------------------------------------------------------------- timing


class Pacer:
    """When each sample of a replayed log is due: ``wall0 + (t_ns - t_first) / speed`` (0: never waits)."""

    def __init__(self, speed: float) -> None:
        self.speed = speed
        self._t0: int | None = None
        self._w0 = 0.0

    def due(self, t_ns: int) -> float:
        if self.speed <= 0:
            return -math.inf
        if self._t0 is None:
            self._t0, self._w0 = int(t_ns), time.monotonic()
        return self._w0 + (int(t_ns) - self._t0) * 1e-9 / self.speed

    def lag(self, t_ns: int) -> float | None:
        if self.speed <= 0:
            return None
        return max(0.0, time.monotonic() - self.due(t_ns))

    def due_now(self) -> float:
        """The sample time [ns] due now (``inf`` before the first sample or without pacing)."""
        if self.speed <= 0 or self._t0 is None:
            return math.inf
        return self._t0 + (time.monotonic() - self._w0) * self.speed * 1e9


class LiveLag:
    """Lag of a live input: the arrival delay of the latest sample beyond the smallest one seen.

    The rig's clock and ours need not agree: ``now - t`` is their offset plus
    the delay; its minimum since the last :meth:`rebase` is the offset plus the
    best delay. Our clock is the monotonic one (a step of the host's wall clock
    is neither lag nor a sample from the future). After a hold of the input the
    runner re-bases: the samples that follow define the offset again (a rig that
    waited for its input was not behind it).
    """

    def __init__(self) -> None:
        self._best: float | None = None

    def lag(self, t_ns: int) -> float:
        d = time.monotonic() - int(t_ns) * 1e-9
        self._best = d if self._best is None else min(self._best, d)
        return d - self._best

    def rebase(self) -> None:
        """Forget the offset: the next sample's delay is the new best."""
        self._best = None

    def now_ns(self) -> float | None:
        """The rig's present as our clock sees it [ns of the rig's clock] (``None`` before the first sample):
        a sample measured by now has at most this time (plus the best delivery delay)."""
        return None if self._best is None else (time.monotonic() - self._best) * 1e9


def blocks_by_time(block: Samples, span_s: float, pacer: Pacer | None = None, max_span_s: float = MAX_BLOCK_S):
    """``block`` cut into consecutive pieces spanning at most ``span_s`` of sample time; with a ``pacer``,
    a piece whose samples are all due already (the rig is behind) takes every sample due now, up to
    ``max_span_s`` (larger blocks where the latency is there anyway)."""
    t = block.t_ns
    i, n = 0, len(block)
    while i < n:
        j = int(np.searchsorted(t, t[i] + int(span_s * 1e9), side="left"))
        j = max(j, i + 1)
        if pacer is not None and j < n and t[j - 1] <= pacer.due_now():
            late = min(pacer.due_now(), t[i] + max_span_s * 1e9)
            j = max(j, int(np.searchsorted(t, late, side="right")))
        yield block if (i == 0 and j >= n) else block.slice(i, j)
        i = j


# --------------------------------------------------------------------------- commissioning


def _fit_job(conn, samples: Samples, tracked: tuple[str, ...], params: dict, timing, rig: str) -> None:
    """A spawned process: the commissioning fit of one rig's window, its outcome sent on ``conn``."""
    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from twin.online.commission import fit_window

    try:
        out = fit_window(samples, tracked, params, timing, rig)
    except Exception as exc:  # noqa: BLE001 - a bug of the fit is a failed commissioning, not a dead rig
        out = (None, f"internal error of the fit {type(exc).__name__}: {exc}")
    conn.send(out)
    conn.close()


class FitJob:
    """A rig's commissioning fit in its own spawned process (the other rigs go on meanwhile)."""

    def __init__(self, rig: RigConfig, samples: Samples) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=False)
        timing = rig.timing
        self.proc = ctx.Process(target=_fit_job, args=(child, samples, tuple(rig.track), dict(rig.params), timing,
                                                       rig.name), name=f"twin-commission-{rig.name}")
        self.proc.start()
        child.close()

    def done(self) -> bool:
        return self._conn.poll() or not self.proc.is_alive()

    def result(self) -> tuple[dict | None, str]:
        try:
            if self._conn.poll(1.0):
                return self._conn.recv()
        except (EOFError, OSError):
            pass
        finally:
            self.proc.join(5.0)
        return None, f"the fit's process ended without a result (exit code {self.proc.exitcode})"

    def cancel(self) -> None:
        if self.proc.is_alive():
            self.proc.terminate()
        self.proc.join(5.0)
        self._conn.close()


# --------------------------------------------------------------------------- one rig


class RigRunner:
    """Runs one rig from its source to its publisher until its log ends, it fails or ``stop`` is set.

    :param rig: the rig's configuration.
    :param cfg: the service configuration (timing, estimate rate, MCAP directory).
    :param journal: the rig's open journal (alarms and checkpoints).
    :param out: where bus messages go (a ``queue.Queue`` or a multiprocessing queue).
    :param stop: ``threading.Event`` or multiprocessing event.
    :param session: the service's Zenoh session (for a ``zenoh://`` input).
    :param keep: a dict that receives the rig's :class:`RigTwin` (reports, tests).
    """

    def __init__(self, rig: RigConfig, cfg: ServiceConfig, journal: AlarmJournal, out, stop, *,
                 session=None, keep: dict | None = None) -> None:
        self.rig = rig
        self.cfg = cfg
        self.journal = journal
        self.out = out
        self.stop = stop
        self.session = session
        self.keep = keep
        self.summary = RigSummary(rig.name)
        self.outbox = Outbox(rig.name, journal, out, cfg.signals_hz)
        self.twin: RigTwin | None = None
        self.recorder: McapSink | None = None
        self._fp = fingerprint(rig, cfg.estimate_every)
        self._last_cp = time.monotonic()
        self._cp_error: str | None = None
        self._lag: float | None = None
        self._stale_since: float | None = None
        self._notes: str = ""
        self._start_samples = 0
        self._last_data = time.monotonic()
        self._last_reset: float | None = None
        self._last_quiet_status = 0.0
        self._dropped: dict[str, int] = {}
        self._dropped_base: dict[str, int] = {}
        self._fit: FitJob | None = None
        self._live_lag: LiveLag | None = None
        self._held = False  # the live input paused: the lag is re-based on the next samples processed
        self._accepted_at: float | None = None  # monotonic time the last live samples were processed
        self._jump_since: float | None = None  # monotonic time of the first time_jump since samples were processed
        self._lead_s = 0.0  # how far the last time_jump was ahead of the rig's present [s]
        self._jump_blocks = 0  # blocks with a time_jump (the first few and every 100th are logged)
        self._back_since: float | None = None  # monotonic time of the first block all time_backwards since then

    # ------------------------------------------------------------------ life

    def run(self) -> RigSummary:
        """Never raises: the outcome is in the summary, on the bus and in the log."""
        for due in self.run_steps():
            delay = due - time.monotonic()
            if delay > 0:
                self.stop.wait(delay)
        return self.summary

    def run_steps(self):
        """:meth:`run` as a generator for a scheduler that runs many rigs on one thread: it yields the
        ``time.monotonic()`` at which it wants to go on (a replayed log's next block is due, a commissioning
        fit may be done) and does the work when resumed; ``throw(_Stopped())`` stops it the way ``stop``
        does. Never raises: the outcome is in the summary, on the bus and in the log. A live input blocks in
        its reads, so it runs to its end in one step (its own thread)."""
        try:
            self._open()
            yield -math.inf  # opened: a scheduler opens every rig before the first one's log is paced
            if is_live(self.rig.source):
                self._run_live()
            else:
                yield from self._log_steps()
            if is_live(self.rig.source):
                self._set_state("stopped")
            else:  # what the log's reader lost stays the rig's last word
                self._set_state("finished", self.summary.input_lost)
        except _Stopped:
            self._set_state("stopped")
        except RigFailure as exc:
            self._fail(str(exc))
        except TwinError as exc:
            self._fail(str(exc))
        except Exception as exc:  # a bug: one line on the console, the traceback in the debug log
            log.debug("rig %s: unexpected error", self.rig.name, exc_info=True)
            self._fail(f"internal error {type(exc).__name__}: {exc}")
        finally:
            self._close()

    def _open(self) -> None:
        if self.cfg.out_dir:
            from replay.mcapio import McapSink

            self.recorder = McapSink(_free_name(Path(self.cfg.out_dir), f"{self.rig.name}.twin", ".mcap"))
        saved = self._saved_commission()
        self.twin = make_twin(self.rig, self.outbox, self.recorder, self.cfg.estimate_every)
        if self.keep is not None:
            self.keep[self.rig.name] = self.twin
        self._resume()
        self.twin.status_after_write = False  # _tick publishes after each block, the rig's health included
        if self.rig.commission_s and saved is None and self.summary.resumed_samples is None:
            from twin.service.rig import Commissioning

            self.twin.commissioning = Commissioning(self.rig.commission_s)
            log.info("rig %s: commissioning on its first %g s (no alarms before it ends)", self.rig.name,
                     self.rig.commission_s)
        self._start_samples = self.twin.stats.samples
        self.twin.health.state = "starting"
        self.twin.health.message = self._notes
        self.twin.publish_status(force=True)
        self.outbox.flush()

    def _saved_commission(self):
        """A commissioning saved by an earlier run (``commission_s``): it wins over commissioning again."""
        if not self.rig.commission_s:
            return None
        path = commission_path(self.cfg, self.rig.name)
        if not path.exists():
            return None
        from twin.online.commission import apply_commission, describe, load_fit

        try:
            com = load_fit(str(path))
            self.rig = apply_commission(self.rig, com)
        except TwinError as exc:
            log.warning("rig %s: its saved commissioning cannot be used (%s); commissioning again", self.rig.name,
                        exc)
            return None
        self._fp = fingerprint(self.rig, self.cfg.estimate_every)
        self._notes = f"commissioned by an earlier run ({path.name}): {describe(com, self.rig.track)}"
        log.info("rig %s: %s", self.rig.name, self._notes)
        return com

    def _commission(self, wait: bool) -> None:
        """Start the commissioning fit once the window is gathered; finish the commissioning once it is done
        (``wait``: until then, the rig's status going on; a replayed log waits, a live input does not)."""
        twin = self.twin
        assert twin is not None  # made by _open
        c = twin.commissioning
        if c is None or not c.window.full:
            return
        if self._fit is None:
            try:
                self._fit = FitJob(self.rig, c.window.samples())
            except (OSError, RuntimeError, ValueError) as exc:  # no process for the fit: the rig goes on all the same
                self._end_commission(None, f"the fit's process cannot start ({type(exc).__name__}: {exc})")
                return
            c.fitting = True
            log.info("rig %s: %s", self.rig.name, c.note())
            twin.publish_status(force=True)
            self.outbox.flush()
        while not self._fit.done():
            if not wait:
                return
            if self.stop.wait(0.5):
                raise _Stopped
            twin.publish_status()
            self.outbox.flush(force=False)
        self._finish_fit()

    def _commission_steps(self):
        """:meth:`_commission` for a replayed log, which waits for the fit: yields while it runs."""
        self._commission(wait=False)
        while self._fit is not None and not self._fit.done():
            yield time.monotonic() + 0.5
            if self.stop.is_set():
                raise _Stopped
            assert self.twin is not None  # made by _open
            self.twin.publish_status()
            self.outbox.flush(force=False)
        if self._fit is not None:
            self._finish_fit()

    def _finish_fit(self) -> None:
        assert self._fit is not None
        doc, problem = self._fit.result()
        self._fit = None
        self._end_commission(doc, problem)

    def _end_commission(self, doc: dict | None, problem: str) -> None:
        twin = self.twin
        assert twin is not None  # made by _open
        com = None
        if doc is not None:
            com = self._save_commission(doc)
        try:
            line = twin.finish_commissioning(com, problem)
        except FilterError as exc:
            raise RigFailure(f"{exc} (right after its commissioning)") from None
        self.rig = twin.rig
        self._fp = fingerprint(self.rig, self.cfg.estimate_every)
        self._notes = line
        (log.info if com is not None else log.warning)("rig %s: %s", self.rig.name, line)
        self._checkpoint()
        self.outbox.flush()

    def _save_commission(self, doc: dict):
        """Save a commissioning next to the journal (atomically) and read it back; unsaved, it is used all the same."""
        import json

        from twin.online.commission import from_dict, load_fit

        path = commission_path(self.cfg, self.rig.name)
        tmp = path.with_name(path.name + ".tmp")
        try:
            tmp.write_text(json.dumps(doc, indent=2, allow_nan=False))
            os.replace(tmp, path)
            return load_fit(str(path))
        except (OSError, ValueError, TwinError) as exc:
            log.error("rig %s: its commissioning cannot be saved to %s (%s); it is used but a restart "
                      "commissions again", self.rig.name, path, exc)
            return from_dict(doc, f"commissioning of {self.rig.name} (not saved)")

    def _resume(self) -> None:
        cp = self.journal.load_checkpoint(self.rig.name)
        if cp is None:
            return
        if cp.fingerprint != self._fp:
            log.warning("rig %s: its configuration changed since the checkpoint of %s; starting afresh "
                        "(alarms journaled before are not raised twice)", self.rig.name,
                        time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(cp.saved_at)))
            return
        assert self.twin is not None  # made by _open
        try:
            self.twin.restore(cp.state)
        except (TwinError, ValueError, KeyError, TypeError, AttributeError) as exc:  # another version's state
            raise RigFailure(f"its checkpoint in {self.journal.checkpoint_path} cannot be restored "
                             f"({type(exc).__name__}: {exc}); refused: move it aside to start the rig afresh "
                             "from its journal") from None
        self.summary.resumed_samples = cp.samples
        log.info("rig %s: resumed from its checkpoint after %d samples (t_ns=%d)", self.rig.name, cp.samples,
                 cp.t_ns)

    def _close(self) -> None:
        if self._fit is not None:
            self._fit.cancel()
            self._fit = None
        twin = self.twin
        if twin is not None:
            if self.summary.state != "failed":
                self._checkpoint()
            twin.health.state = self.summary.state
            twin.health.message = self.summary.message
            try:
                twin.publish_status(force=True)
            except TwinError as exc:
                log.debug("rig %s: last status: %s", self.rig.name, exc)
            s = twin.stats
            self.summary.samples = s.samples - self._start_samples
            self.summary.alarms = s.alarms
            self.summary.duplicates = s.duplicates
            self.summary.busy_s = s.busy_s
            self.summary.input_dropped = sum(self._dropped.values())
            self.summary.stats = dataclasses.replace(s)
        if self.recorder is not None:
            try:
                self.recorder.close()
            except Exception as exc:  # noqa: BLE001 - reported, the rig's outcome stands
                log.error("rig %s: closing its MCAP record: %s", self.rig.name, exc)
        self.outbox.flush()
        self.out.put(("done", self.rig.name, self.summary))

    def _set_state(self, state: str, message: str = "") -> None:
        self.summary.state = state
        self.summary.message = message

    def _fail(self, message: str) -> None:
        self._set_state("failed", message)
        log.error("rig %s failed: %s", self.rig.name, message)

    # ------------------------------------------------------------------ a replayed log

    def _log_steps(self):
        """The replayed log, paced: yields when the next block is due (see :meth:`run_steps`)."""
        twin = self.twin
        assert twin is not None  # made by _open
        position = twin.last_t_ns
        try:
            src = open_rig_source(self.rig, self.session)
        except (TwinError, OSError) as exc:
            raise RigFailure(f"cannot open its log: {exc}") from None
        pacer = Pacer(self.rig.speed)
        span = self.cfg.block_s * self.rig.speed if self.rig.speed > 0 else math.inf
        shift: int | None = None
        with src:
            from twin.record import check_signals

            try:
                check_signals(self.rig.source, src.signals, self.rig.model)
            except TwinError as exc:
                raise RigFailure(str(exc)) from None
            chunks = src.chunks(READ_CHUNK)
            while True:
                try:
                    chunk = next(chunks)
                except StopIteration:
                    break
                except (TwinError, OSError, ValueError) as exc:
                    raise RigFailure(f"{self.rig.source}: cannot read on: {exc}") from None
                if shift is None and len(chunk):  # a pre-trigger record (times from -t0) runs from 0
                    shift = -int(chunk.t_ns[0]) if int(chunk.t_ns[0]) < 0 else 0
                if shift:
                    chunk = Samples(chunk.t_ns + shift, chunk.signals)
                if position is not None:
                    k = int(np.searchsorted(chunk.t_ns, position, side="right"))
                    if k >= len(chunk):
                        continue
                    if k:
                        chunk = chunk.slice(k, len(chunk))
                for block in (blocks_by_time(chunk, span, pacer, max(span, MAX_BLOCK_S))
                              if math.isfinite(span) else (chunk,)):
                    due = pacer.due(int(block.t_ns[-1]))
                    if due > time.monotonic():
                        yield due
                    if self.stop.is_set():
                        raise _Stopped
                    self._process(block, live=False)
                    yield from self._commission_steps()
                    self._lag = pacer.lag(int(block.t_ns[-1]))
                    self._tick()
                if self.stop.is_set():
                    raise _Stopped
        if twin.commissioning is not None:  # the log ended before the window did: fit what it gave
            twin.commissioning.window.full = True
            yield from self._commission_steps()
        report = getattr(src, "report", None)
        if twin.stats.samples == 0:
            raise RigFailure(f"{self.rig.source}: no usable samples"
                             + (f" ({report.summary()})" if report is not None else ""))
        if report is not None and report.lossy:
            self.summary.input_lost = self._notes = report.loss_line()
            log.warning("rig %s: %s", self.rig.name, self._notes)

    # ------------------------------------------------------------------ a live input

    def _run_live(self) -> None:
        """Until ``stop``: open the input (again when it ends or keeps breaking), process what comes.

        Works with sources that end when quiet (a fresh subscription is then
        opened) and with sources that stay open and yield empty blocks while
        quiet (their ``idle()`` says for how long).
        """
        stale_s = self.cfg.stale_s
        self._last_data = time.monotonic()
        lag = self._live_lag = LiveLag()
        backoff = 0.0
        while not self.stop.is_set():
            try:
                src = open_rig_source(self.rig, self.session, timeout_s=stale_s)
            except (TwinError, OSError, ValueError) as exc:
                self._quiet(None, f"cannot open {self.rig.source}: {exc}")
                backoff = min(5.0, max(stale_s, backoff * 2))
                self.stop.wait(backoff)
                continue
            backoff = 0.0
            try:
                with src:
                    errors_in_row = 0
                    while not self.stop.is_set():
                        outcome = self._consume(src, lag)
                        if outcome == "ended":
                            break  # the sender's end marker, or a source that ends when quiet: subscribe afresh
                        if outcome == "error":
                            errors_in_row += 1
                            if errors_in_row >= 20:  # the source keeps breaking: open it afresh
                                break
                        else:
                            errors_in_row = 0
                        if outcome == "quiet":
                            self._quiet(src, self._notes)
                    self._input_counters(src)
                    self._dropped_base = dict(self._dropped)
            except (_Stopped, RigFailure):
                raise
            except (TwinError, OSError) as exc:
                self._notes = f"input: {exc}"
            if not self.stop.is_set():
                self._quiet(None, self._notes)

    def _consume(self, src, lag: LiveLag) -> str:
        """Process what ``src.chunks()`` yields; ``"ended"``, ``"quiet"``, ``"error"`` or ``"stopped"``."""
        it = src.chunks(READ_CHUNK)
        pending: list[Samples] = []
        first_wall = 0.0
        try:
            while not self.stop.is_set():
                try:
                    block = next(it)
                except StopIteration:
                    return "ended"
                except SourceError as exc:  # e.g. nothing received yet to learn the signals from
                    self._notes = str(exc)
                    return "quiet"
                except Exception as exc:  # a message that broke the source: count it, go on
                    self.summary.source_errors += 1
                    self._notes = f"{self.summary.source_errors} input error(s), the last: {type(exc).__name__}: {exc}"
                    if self.summary.source_errors <= 3 or self.summary.source_errors % 100 == 0:
                        log.warning("rig %s: %s", self.rig.name, self._notes)
                    return "error"
                if len(block) == 0:  # a quiet source's heartbeat
                    if pending:
                        self._live_block(pending, lag)
                        pending = []
                    if self._idle(src) >= self.cfg.stale_s:
                        self._quiet(src, "")
                    continue
                now = time.monotonic()
                if now - self._last_data >= min(self.cfg.stale_s, self.cfg.lag_warn_s):
                    self._held = True  # the input paused: the delays after it are not the rig's backlog
                self._last_data = now
                if not pending:
                    first_wall = self._last_data
                pending.append(block)
                span = (int(block.t_ns[-1]) - int(pending[0].t_ns[0])) * 1e-9
                # behind real time: larger blocks (up to MAX_BLOCK_S), the latency is there anyway
                want = self.cfg.block_s if not self._lag or self._lag <= self.cfg.block_s else \
                    min(MAX_BLOCK_S, self._lag)
                if span >= want or self._last_data - first_wall >= self.cfg.block_s:
                    self._live_block(pending, lag)
                    self._input_counters(src)
                    pending = []
            return "stopped"
        finally:
            if pending:
                self._live_block(pending, lag)

    def _idle(self, src) -> float:
        idle = getattr(src, "idle", None)
        mine = time.monotonic() - self._last_data
        return min(mine, idle()) if callable(idle) else mine

    def _input_counters(self, src) -> None:
        """What the source dropped, per cause, into the status counters (``dropped_<cause>``)."""
        report = getattr(src, "report", None)
        if report is None:
            return
        for cause, n in list(report.skipped.items()):
            name = "dropped_" + "".join(c if c.isalnum() else "_" for c in str(cause))
            self._dropped[name] = self._dropped_base.get(name, 0) + int(n)
        assert self.twin is not None  # made by _open
        self.twin.health.counters.update(self._dropped)

    def _live_block(self, blocks: list[Samples], lag: LiveLag) -> None:
        block = blocks[0] if len(blocks) == 1 else _concat(blocks)
        if block is None:
            self.summary.bad_blocks += 1
            return
        self._stale_since = None
        assert self.twin is not None  # made by _open
        before = self.twin.last_t_ns
        self._process(block, live=True)
        self._commission(wait=False)
        if self.twin.last_t_ns is not None and self.twin.last_t_ns != before:  # samples were processed
            self._accepted_at = time.monotonic()
            self._jump_since = self._back_since = None
            if self._held:
                lag.rebase()
                self._held = False
            self._lag = lag.lag(self.twin.last_t_ns)
        self._tick()

    def _quiet(self, src, why: str) -> None:
        """Status ``stale_input`` (for how long, and why) while the rig waits for its input (at most 1/s)."""
        now = time.monotonic()
        quiet = self._idle(src) if src is not None else now - self._last_data
        if self._stale_since is None:
            self._stale_since = now
            log.warning("rig %s: no input from %s for %.1f s; waiting for it%s", self.rig.name, self.rig.source,
                        quiet, f" ({why})" if why else "")
        elif now - self._last_quiet_status < 1.0:
            return
        self._last_quiet_status = now
        if src is not None:
            self._input_counters(src)
        twin = self.twin
        assert twin is not None  # made by _open
        twin.health.state = "stale_input"
        twin.health.counters["stale_ms"] = int(quiet * 1000)
        twin.health.message = f"no input from {self.rig.source} for {quiet:.1f} s" + (f" ({why})" if why else "")
        twin.publish_status(force=True)
        self.outbox.flush()
        self._commission(wait=False)
        if now - self._last_cp >= self.cfg.checkpoint_s:
            self._checkpoint()

    # ------------------------------------------------------------------ per block

    def _process(self, block: Samples, live: bool) -> None:
        twin = self.twin
        assert twin is not None  # made by _open
        if live:
            cleaned = self._clean(block)
            if cleaned is None:
                return
            block = cleaned
        last = twin.last_t_ns
        dt = twin.tracker.dt
        if last is not None and dt and (int(block.t_ns[0]) - last) * 1e-9 > max(GAP_S, 20 * dt):
            gap = (int(block.t_ns[0]) - last) * 1e-9
            self.summary.input_gaps += 1
            self._restart_filter(f"{gap:.1f} s without samples before t_ns={int(block.t_ns[0])}")
        self.outbox.publish_signals(block)
        try:
            twin.write(block)
        except FilterError as exc:
            good = twin.last_estimate()  # after the last block the filter finished (not this failed one)
            now = time.monotonic()
            if self._last_reset is not None and now - self._last_reset < RESET_WINDOW_S:
                raise RigFailure(f"{exc}; it diverged again {now - self._last_reset:.1f} s after a restart") from None
            self.summary.filter_resets += 1
            self._restart_filter(str(exc), good)
            self._last_reset = now
            try:
                twin.write(block)
            except FilterError as again:
                raise RigFailure(f"{again} (also right after a restart of the filter)") from None
        except DataError as exc:
            if not live:
                raise RigFailure(f"{self.rig.source}: {exc}") from None
            self.summary.bad_blocks += 1
            self._notes = f"block of {len(block)} samples not usable: {exc}"
            if self.summary.bad_blocks <= 3 or self.summary.bad_blocks % 100 == 0:
                log.warning("rig %s: %s (%d so far)", self.rig.name, self._notes, self.summary.bad_blocks)

    def _restart_filter(self, why: str, good: dict | None = None) -> None:
        twin = self.twin
        assert twin is not None  # made by _open
        est = good if good is not None else twin.tracker.estimate()
        start = {n: v for n, (v, _) in est.items() if math.isfinite(v) and v > 0}
        twin.restart_filter(start)
        self._notes = f"filter restarted from the last estimates: {why}"
        log.warning("rig %s: %s", self.rig.name, self._notes)

    def _clean(self, block: Samples) -> Samples | None:
        """A live block without the samples it cannot use, each counted: stamped far in the future
        (``time_jump``, :meth:`_future`), at or before the last one processed or not increasing
        (``time_backwards``), without a finite drive (``bad_samples``)."""
        t = block.t_ns
        assert self.twin is not None  # made by _open
        last = self.twin.last_t_ns
        jump = self._future(t, last)
        ok = np.flatnonzero(~jump)
        back = np.zeros(len(t), dtype=bool)
        if ok.size:
            start = np.iinfo(np.int64).min if last is None else int(last)
            tk = t[ok]
            back[ok] = tk <= np.maximum.accumulate(np.concatenate((np.array([start], dtype=np.int64), tk[:-1])))
        if len(t) and back.all() and self._stepped_back(t, last):
            back[:] = False
        keep = ~(jump | back)
        drive = [block.signals[k] for k in ("u", "x_ref") if k in block.signals]
        no_drive = keep & ~np.any(np.isfinite(np.stack(drive)), axis=0) if drive else np.zeros(len(t), dtype=bool)
        keep &= ~no_drive
        counts = {"time_jump": int(jump.sum()), "time_backwards": int(back.sum()), "bad_samples": int(no_drive.sum())}
        if any(counts.values()):
            for name, n in counts.items():
                setattr(self.summary, name, getattr(self.summary, name) + n)
            said = [f"{name} {getattr(self.summary, name)}" for name in counts if getattr(self.summary, name)]
            self._notes = "live samples dropped: " + ", ".join(said)
            if self.summary.time_jump:
                self._notes += (f" (the last stamped {self._lead_s:.1f} s after the rig's present: a clock glitch, "
                                "not processed, not checkpointed)")
            self._jump_blocks += bool(counts["time_jump"])
            if counts["time_jump"] and (self._jump_blocks <= 3 or self._jump_blocks % 100 == 0):
                log.warning("rig %s: %d sample(s) from t_ns=%d stamped %.1f s after the rig's present: dropped "
                            "(time_jump)", self.rig.name, counts["time_jump"], int(t[jump][0]), self._lead_s)
            block = Samples(t[keep], {k: v[keep] for k, v in block.signals.items()})
        return block if len(block) else None

    def _stepped_back(self, t: np.ndarray, last: int | None) -> bool:
        """A block all before the last processed sample: after ``CLOCK_STEP_S`` of nothing else (and the block in
        order), the input's clock stepped back (a rig controller restarted, say): its time is adopted (the
        filter restarts, the record time runs on, ``clock_steps`` counted) and ``True`` returned."""
        now = time.monotonic()
        if self._back_since is None:
            self._back_since = now
            return False
        if now - self._back_since < CLOCK_STEP_S or last is None or not bool(np.all(np.diff(t) > 0)):
            return False
        twin = self.twin
        assert twin is not None  # made by _open
        back_s = (int(last) - int(t[0])) * 1e-9
        twin.step_clock(int(t[0]))
        self._restart_filter(f"the input's clock stepped back {back_s:.1f} s (every sample for {CLOCK_STEP_S:.0f} s "
                             "was before the last one processed); its time is adopted")
        if self._live_lag is not None:
            self._live_lag.rebase()
        self._back_since = None
        self.summary.clock_steps += 1
        return True

    def _future(self, t: np.ndarray, last: int | None) -> np.ndarray:
        """Mask of live samples stamped more than ``TIME_JUMP_S`` after the rig's present (as the best delay
        seen places it on our clock) and after the last processed time plus the time passed since it was
        processed: they cannot have been measured yet. What leaps is judged, not what runs on: a run of
        samples without a gap (``GAP_S`` or 20 sample periods) is dropped when its first sample is beyond that
        bound, kept when it started within it (a sender faster than real time). Before this run processed a
        sample (no offset learnt yet) the rig's present is the host's UNIX time (a rig stamping UNIX time,
        as a live input should; other clocks are far behind it and never judged so). A rig whose every sample
        is ahead for ``CLOCK_STEP_S`` stepped its clock (or disagrees with ours): its time is adopted
        (nothing is masked, the lag re-based, ``clock_steps`` counted)."""
        none = np.zeros(len(t), dtype=bool)
        if not len(t):
            return none
        lag = self._live_lag
        present = lag.now_ns() if lag is not None else None
        if present is None:
            present = float(time.time_ns())
        now = time.monotonic()
        since = 0.0 if self._accepted_at is None else now - self._accepted_at
        tol = TIME_JUMP_S * 1e9
        limit = present + tol if last is None else max(present + tol, int(last) + since * 1e9 + tol)
        beyond = t > limit
        if not beyond.any():
            return none
        dt = self.twin.tracker.dt if self.twin is not None else None
        base = int(last) if last is not None else int(t[0])  # no sample before: the first one begins a run
        step = np.diff(np.concatenate((np.array([base], dtype=np.int64), t)))
        starts = (step <= 0) | (step > max(GAP_S, 20 * (dt or 0.0)) * 1e9)  # each run of samples begins at one
        run = np.cumsum(starts)  # the run of each sample (0: the one continuing the last processed sample)
        first = np.flatnonzero(starts)
        leaped = np.zeros(run[-1] + 1, dtype=bool)
        leaped[run[first]] = beyond[first]
        jump = leaped[run]
        if not jump.any():
            return none
        self._lead_s = (float(t[jump].max()) - present) * 1e-9
        if self._jump_since is None:
            self._jump_since = now
        elif now - self._jump_since >= CLOCK_STEP_S and not (~jump).any():
            if lag is not None:
                lag.rebase()
            self._jump_since = None
            self.summary.clock_steps += 1
            log.warning("rig %s: every sample for %.0f s is stamped ahead (the last %.1f s): its clock stepped; "
                        "that time is adopted", self.rig.name, CLOCK_STEP_S, self._lead_s)
            return none
        return jump

    def _tick(self) -> None:
        """After each block: health into the status, a checkpoint when due, the batch to the bus."""
        twin = self.twin
        assert twin is not None  # made by _open
        h = twin.health
        warn = []
        if self._lag is not None:
            h.counters["lag_ms"] = int(self._lag * 1000)
            self.summary.lag_max_s = max(self.summary.lag_max_s or 0.0, self._lag)
            if self._lag > self.cfg.lag_warn_s:
                warn.append(f"{self._lag:.1f} s behind real time (warning above {self.cfg.lag_warn_s:g} s)")
        h.counters.pop("stale_ms", None)
        for name in _COUNTED:
            if getattr(self.summary, name):
                h.counters[name] = getattr(self.summary, name)
        pending = self.journal.pending
        if pending:
            h.counters["journal_pending"] = pending
            held = ", ".join(f"#{a.seq} {a.parameter} {a.level}" for a in self.journal.pending_alarms()[:3])
            warn.append(f"{pending} alarm(s) held, published once journaled ({held}): {self.journal.write_error}")
        else:
            h.counters.pop("journal_pending", None)
        if self._cp_error:
            warn.append(f"checkpoint failed: {self._cp_error}")
        state = "degraded" if warn else "running"
        if state != h.state and state == "degraded":
            log.warning("rig %s: %s", self.rig.name, "; ".join(warn))
        h.state = state
        h.message = "; ".join(warn) or self._notes
        twin.publish_status()
        if time.monotonic() - self._last_cp >= self.cfg.checkpoint_s:
            self._checkpoint()
        self.outbox.flush(force=False)

    def _checkpoint(self) -> None:
        self._last_cp = time.monotonic()
        twin = self.twin
        self.journal.retry()
        if twin is None or twin.last_t_ns is None or twin.commissioning is not None:
            return  # nothing tracked yet (a restart during the commissioning gathers its window again)
        try:
            self.journal.save_checkpoint(Checkpoint(self.rig.name, twin.last_t_ns, twin.stats.samples, self._fp,
                                                    twin.state(), time.time()))
            if self._cp_error:
                log.warning("rig %s: checkpoints are written again", self.rig.name)
            self._cp_error = None
        except SourceError as exc:
            if self._cp_error is None:
                log.error("rig %s: %s", self.rig.name, exc)
            self._cp_error = str(exc)


def _concat(blocks: list[Samples]) -> Samples | None:
    names = blocks[0].names
    if any(b.names != names for b in blocks):  # the signals changed between payloads: keep the last set
        blocks = [b for b in blocks if b.names == blocks[-1].names]
    return Samples.concat(blocks) if blocks else None


def _free_name(directory: Path, stem: str, suffix: str) -> str:
    """``stem.suffix``, or ``stem.1.suffix``, ... : an earlier run's record is never overwritten."""
    path = directory / f"{stem}{suffix}"
    n = 0
    while path.exists():
        n += 1
        path = directory / f"{stem}.{n}{suffix}"
    return str(path)


# --------------------------------------------------------------------------- worker processes


def _die_with_parent() -> None:
    """Linux: the kernel kills this worker when the service's process dies (even by SIGKILL)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    parent = mp.parent_process()
    if parent is not None and not parent.is_alive():
        os._exit(1)


def worker_main(rigs: list[RigConfig], cfg: ServiceConfig, out, stop_conn, log_level: int) -> None:
    """A spawned worker: its replayed logs on one thread (:func:`run_scheduled`), each live input on a
    thread of its own; results and bus messages go to ``out``.

    ``stop_conn``: the reading end of a pipe from the service; a message or
    its end (the service's process gone) stops the rigs. Not a
    ``multiprocessing.Event``: a process that exits while one of its threads
    waits on it leaves the event's condition blocked for whoever sets it, and
    many threads waiting on it serialise on its process-shared semaphores.
    """
    _die_with_parent()
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
        threads.append(threading.Thread(target=_profiled(run_scheduled, "logs"), args=(logs, cfg, out, local),
                                        name="rig-logs", daemon=True))
    for rig in rigs:
        if is_live(rig.source):  # a live input blocks in its reads: a thread of its own
            threads.append(threading.Thread(target=_profiled(_run_one, f"rig-{rig.name}"),
                                            args=(rig, cfg, out, local), name=f"rig-{rig.name}", daemon=True))
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    console.close()


def _profiled(target: Callable[..., Any], name: str) -> Callable[..., Any]:
    """``target`` under cProfile (CPU time of its thread) when ``FPDD_PROFILE_DIR`` is set: the statistics go
    to ``FPDD_PROFILE_DIR/<name>.prof`` (``python -m benchmarks.service fleet --profile DIR`` reads them)."""
    directory = os.environ.get("FPDD_PROFILE_DIR")
    if not directory:
        return target

    def run(*args: Any) -> Any:
        import cProfile

        prof = cProfile.Profile(time.thread_time)
        try:
            return prof.runcall(target, *args)
        finally:
            prof.dump_stats(os.path.join(directory, f"{name}.{os.getpid()}.prof"))

    return run


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
        try:
            journal = AlarmJournal(journal_path(cfg, rig.name), lock_wait_s=10.0,
                                   witnesses=[commission_path(cfg, rig.name)])
        except TwinError as exc:
            out.put(("done", rig.name, RigSummary(rig.name, "failed", str(exc))))
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
                nxt = steps.throw(_Stopped())
            else:  # a rig not started yet opens, reports and stops at its first check
                nxt = next(steps)
        except StopIteration:
            journal.close()
            continue
        heapq.heappush(heap, (nxt, i, steps, journal))


def _run_one(rig: RigConfig, cfg: ServiceConfig, out, stop) -> None:
    try:
        journal = AlarmJournal(journal_path(cfg, rig.name), lock_wait_s=10.0,
                               witnesses=[commission_path(cfg, rig.name)])
    except TwinError as exc:
        out.put(("done", rig.name, RigSummary(rig.name, "failed", str(exc))))
        return
    with journal:
        RigRunner(rig, cfg, journal, out, stop).run()


# --------------------------------------------------------------------------- the service's process


class BusFront:
    """The service's side of the bus: a :class:`~twin.service.bus.TwinPublisher` per rig, fed by the runners."""

    def __init__(self, session, histories: dict[str, Any],
                 on_alarm: Callable[[AlarmEvent], None] | None = None, signing_keys: dict[str, str] | None = None) -> None:
        from twin.service.bus import StoreHistory, TwinPublisher
        from twin.service.signing import load_signer

        self._pubs: dict[str, TwinPublisher] = {}
        self._signal_pubs: dict[str, Any] = {}
        self._session = session
        self._histories = histories
        self._store_history = StoreHistory
        self.on_alarm = on_alarm
        self.state: dict[str, tuple[str, str]] = {}
        try:
            for rig, history in histories.items():
                key = (signing_keys or {}).get(rig)
                self._pubs[rig] = TwinPublisher(session, rig, history=history,
                                                signer=load_signer(key, rig) if key else None)
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

                        sp = self._signal_pubs[rig] = self._session.declare_publisher(signals_key(rig))
                    sp.put(item[1])
                elif kind == "alarm":
                    event, durable = item[1], item[2]
                    history = self._histories[rig]
                    if not durable and isinstance(history, self._store_history):
                        history.add_pending(event)
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


class Fleet:
    """Every rig of a configuration, run until their logs end, one fails, or ``stop`` is set.

    :param keep: a dict that receives each rig's :class:`RigTwin`; forces threads (objects stay here).
    """

    def __init__(self, cfg: ServiceConfig, session, stop: threading.Event, *,
                 on_alarm: Callable[[AlarmEvent], None] | None = None, keep: dict | None = None) -> None:
        self.cfg = cfg
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
        if n is None:  # auto: processes once there are more rigs than a few threads handle well
            n = 0 if len(others) <= 4 else min(os.cpu_count() or 1, len(others))
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
        journals: dict[str, AlarmJournal] = {}
        histories: dict[str, Any] = {}
        front = None
        procs: list[tuple[BaseProcess, list[str]]] = []
        ctx = mp.get_context("spawn")
        # One queue from every runner to the bus; a process-safe one once there are workers.
        inbox: MpQueue[Any] | queue.Queue[Any] = ctx.Queue() if self.remote else queue.Queue()
        stop_pipes: list = []
        threads: list[threading.Thread] = []
        try:
            # Every journal is opened here first: integrity, migration and locks are checked before any rig runs.
            for rig in cfg.rigs:
                journals[rig.name] = AlarmJournal(journal_path(cfg, rig.name), legacy=legacy_journal_path(cfg, rig.name),
                                                  witnesses=[commission_path(cfg, rig.name)])
            for group in self.remote:
                for rig in group:
                    journals.pop(rig.name).close()
                    histories[rig.name] = StoreHistory(journal_path(cfg, rig.name))
            histories.update(journals)
            front = BusFront(self.session, histories, self.on_alarm,
                             {r.name: r.signing_key for r in cfg.rigs if r.signing_key})
            for rig in self.local:
                runner = RigRunner(rig, cfg, journals[rig.name], inbox, self.stop, session=self.session,
                                   keep=self.keep)
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
            _profiled(self._loop, "service")(front, inbox, procs)
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
        names = {r.name for r in self.cfg.rigs}
        while True:
            self._receive(front, inbox, 0.1)
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
