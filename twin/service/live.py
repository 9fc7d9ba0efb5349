"""A rig's live input (``can://``, ``zenoh://``): a rig never stops silently. An input that goes quiet or is
lost is a status (``stale_input``, counter ``stale_ms``) while the rig waits and re-opens its input; a message
that breaks the source or a block the tracker cannot use is counted (``source_errors``, ``bad_blocks``,
``bad_samples``), logged and skipped. Samples are gathered into blocks of ``block_s`` (larger, up to
``MAX_BLOCK_S``, while the rig is behind); their lag is measured against the best delivery seen."""

from __future__ import annotations

import logging
import time

from replay.base import Samples
from fpdd.errors import SourceError, TwinError
from twin.service.inputs import open_rig_source
from twin.service.outcome import RigFailure, Stopped
from twin.service.pacing import MAX_BLOCK_S, READ_CHUNK, LiveLag
from twin.service.runner_core import RunnerCore

log = logging.getLogger("twin.serve")


class LiveInput(RunnerCore):
    """A runner's live path: :meth:`_run_live` until ``stop``."""

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
                src = open_rig_source(self.rig, self.session, timeout_s=stale_s, cfg=self.cfg)
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
            except (Stopped, RigFailure):
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
        if self._step_note:  # said for the rest of the run
            twin.health.message = f"{self._step_note}; {twin.health.message}"
        twin.publish_status(force=True)
        self.outbox.flush()
        self._commission(wait=False)
        if now - self._last_cp >= self.cfg.checkpoint_s:
            self._checkpoint()


def _concat(blocks: list[Samples]) -> Samples | None:
    names = blocks[0].names
    if any(b.names != names for b in blocks):  # the signals changed between payloads: keep the last set
        blocks = [b for b in blocks if b.names == blocks[-1].names]
    return Samples.concat(blocks) if blocks else None

