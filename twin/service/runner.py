"""One rig run from its source to its publisher until its log ends, it fails or it is stopped
(:class:`RigRunner`, made of the parts in :mod:`twin.service.runner_core`)."""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from pathlib import Path

import numpy as np

from replay.base import Samples
from fpdd.errors import TwinError
from twin.service.checkpoints import Checkpoints
from twin.service.commissioning import Commissioner
from twin.service.inputs import is_live, open_rig_source
from twin.service.live import LiveInput
from twin.service.live_time import LiveTime
from twin.service.outcome import RigFailure, RigSummary, Stopped
from twin.service.pacing import MAX_BLOCK_S, READ_CHUNK, Pacer, blocks_by_time
from twin.service.rig import make_twin

log = logging.getLogger("twin.serve")


class RigRunner(LiveInput, LiveTime, Commissioner, Checkpoints):
    """Runs one rig from its source to its publisher until its log ends, it fails or ``stop`` is set.

    :param rig: the rig's configuration.
    :param cfg: the service configuration (timing, estimate rate, MCAP directory).
    :param journal: the rig's open journal (alarms and checkpoints).
    :param out: where bus messages go (a ``queue.Queue`` or a multiprocessing queue).
    :param stop: ``threading.Event`` or multiprocessing event.
    :param session: the service's Zenoh session (for a ``zenoh://`` input).
    :param keep: a dict that receives the rig's :class:`RigTwin` (reports, tests).

    Its state and per-block work are :class:`~twin.service.runner_core.RunnerCore`'s; a live input
    (:class:`~twin.service.live.LiveInput`), its samples' time (:class:`~twin.service.live_time.LiveTime`),
    commissioning (:class:`~twin.service.commissioning.Commissioner`) and checkpoints
    (:class:`~twin.service.checkpoints.Checkpoints`) are the parts it is made of; here: its life and a
    replayed log.
    """

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
        fit may be done) and does the work when resumed; ``throw(Stopped())`` stops it the way ``stop``
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
        except Stopped:
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
            from twin.service.live_view.record import TwinRecording

            self.recorder = TwinRecording(_free_name(Path(self.cfg.out_dir), f"{self.rig.name}.twin", ".mcap"),
                                          self.rig.name, self.rig.model, parameters=self.rig.track)
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

    # ------------------------------------------------------------------ a replayed log

    def _log_steps(self):
        """The replayed log, paced: yields when the next block is due (see :meth:`run_steps`)."""
        twin = self.twin
        assert twin is not None  # made by _open
        position = twin.last_t_ns
        try:
            src = open_rig_source(self.rig, self.session, cfg=self.cfg)
        except (TwinError, OSError) as exc:
            raise RigFailure(f"cannot open its log: {exc}") from None
        pacer = Pacer(self.rig.speed)
        span = self.cfg.block_s * self.rig.speed if self.rig.speed > 0 else math.inf
        shift: int | None = None
        with src:
            from twin.models.records import check_signals

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
                        raise Stopped
                    self._process(block, live=False)
                    yield from self._commission_steps()
                    self._lag = pacer.lag(int(block.t_ns[-1]))
                    self._tick()
                if self.stop.is_set():
                    raise Stopped
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


def _free_name(directory: Path, stem: str, suffix: str) -> str:
    """``stem.suffix``, or ``stem.1.suffix``, ... : an earlier run's record is never overwritten."""
    path = directory / f"{stem}{suffix}"
    n = 0
    while path.exists():
        n += 1
        path = directory / f"{stem}.{n}{suffix}"
    return str(path)

