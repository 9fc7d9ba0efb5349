"""What every part of a rig's runner shares: its state, the work on each block (the filter fed, restarted
after a gap or a divergence) and what follows each block (health into the status, a checkpoint when due, the
batch to the bus). The parts are mixins of :class:`RunnerCore`: a live input (:mod:`twin.service.live`), its
time judged (:mod:`twin.service.live_time`), commissioning (:mod:`twin.service.commissioning`) and
checkpoints (:mod:`twin.service.checkpoints`), put together as :class:`twin.service.runner.RigRunner`."""

from __future__ import annotations

import abc
import logging
import math
import time
from typing import TYPE_CHECKING

from replay.base import Samples
from fpdd.errors import DataError, FilterError
from twin.service.config import RigConfig, ServiceConfig
from twin.service.journal import AlarmJournal
from twin.service.outbox import Outbox
from twin.service.outcome import COUNTED, RigFailure, RigSummary
from twin.service.pacing import LiveLag
from twin.service.rig import RigTwin, fingerprint
from twin.service.spawn import FitJob

if TYPE_CHECKING:
    from replay.mcapio import McapSink
    from twin.service.maintenance import MaintenanceLog

log = logging.getLogger("twin.serve")

#: A jump in sample time longer than this (or 20 sample periods) restarts the filter's model states [s].
GAP_S = 0.5
#: A filter that diverges again within this long of a restart is a failure of the rig [s].
RESET_WINDOW_S = 10.0


class RunnerCore(abc.ABC):
    """A rig runner's state and the work every path of it does per block (see :class:`twin.service.runner.RigRunner`)."""

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
        self._step_run = 0  # samples in a row on another clock (twin.service.live_time: a clock step)
        self._step_way = ""  # "back" or "ahead"
        self._step_last: int | None = None  # the last sample of that run
        self._step_first = 0  # and its first
        self._step_note = ""  # the last clock step adopted, said in every status after it
        self.takeover: dict | None = None  # set when this run took the rig over (twin.service.failover)
        self._maintenance_log: MaintenanceLog | None = None  # the rig's maintenance log, opened on first use

    def _set_state(self, state: str, message: str = "") -> None:
        self.summary.state = state
        self.summary.message = message

    def _fail(self, message: str) -> None:
        self._set_state("failed", message)
        log.error("rig %s failed: %s", self.rig.name, message)

    # ------------------------------------------------------------------ per block

    def _process(self, block: Samples, live: bool) -> None:
        twin = self.twin
        assert twin is not None  # made by _open
        if live:
            cleaned = self._clean(block)
            if cleaned is None:
                return
            block = cleaned
        if self.takeover is not None and self.takeover.get("watched_until_ns") is not None:  # first live block
            gap = max(0, int(block.t_ns[0]) - self.takeover.pop("watched_until_ns"))
            self.takeover["counters"]["unwatched_ms"] = gap // 1_000_000
            self.takeover["note"] += f"; {gap * 1e-9:.2f} s of input not watched"
            log.warning("rig %s: %.2f s of input not watched", self.rig.name, gap * 1e-9)
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

    def _tick(self) -> None:
        """After each block: health into the status, a checkpoint when due, the batch to the bus."""
        twin = self.twin
        assert twin is not None  # made by _open
        self._maintenance()
        h = twin.health
        warn = []
        if self._lag is not None:
            h.counters["lag_ms"] = int(self._lag * 1000)
            self.summary.lag_max_s = max(self.summary.lag_max_s or 0.0, self._lag)
            if self._lag > self.cfg.lag_warn_s:
                warn.append(f"{self._lag:.1f} s behind real time (warning above {self.cfg.lag_warn_s:g} s)")
        h.counters.pop("stale_ms", None)
        for name in COUNTED:
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
        if self._step_note and self._step_note not in h.message:  # said for the rest of the run
            h.message = "; ".join(m for m in (self._step_note, h.message) if m)
        if self.takeover is not None:  # said for the rest of the run
            h.counters.update(self.takeover["counters"])
            h.message = "; ".join(m for m in (self.takeover["note"], h.message) if m)
        twin.publish_status()
        if time.monotonic() - self._last_cp >= self.cfg.checkpoint_s:
            self._checkpoint()
        self.outbox.flush(force=False)

    def _maintenance(self) -> None:
        """Apply the recorded maintenance events the twin has not applied yet (a ``stat`` when none is new)."""
        from twin.service.maintenance import MaintenanceLog, maintenance_path

        twin = self.twin
        assert twin is not None  # made by _open
        if self._maintenance_log is None:
            self._maintenance_log = MaintenanceLog(maintenance_path(self.cfg.journal_dir, self.rig.name),
                                                   self.rig.name)
        for ev in self._maintenance_log.since(twin.forecast.maintenance_seq):
            params = [p for p in ev.get("parameters", []) if p in twin.forecast.params]
            note = ev.get("note") or ""
            twin.maintenance(params, why=f"maintenance #{ev['seq']}" + (f": {note}" if note else ""), record=ev)
            self._notes = (f"maintenance #{ev['seq']} recorded: {', '.join(params)}" + (f" ({note})" if note else "")
                           + ": forecast started afresh")
            log.info("rig %s: %s", self.rig.name, self._notes)

    # ------------------------------------------------------------------ the parts' own

    @abc.abstractmethod
    def _checkpoint(self) -> None:
        """Save the twin's state now (:class:`twin.service.checkpoints.Checkpoints`)."""

    @abc.abstractmethod
    def _commission(self, wait: bool) -> None:
        """Go on with a commissioning (:class:`twin.service.commissioning.Commissioner`)."""

    @abc.abstractmethod
    def _clean(self, block: Samples) -> Samples | None:
        """A live block without the samples it cannot use (:class:`twin.service.live_time.LiveTime`)."""
