"""A live sample's time judged before it is processed: one at or before the last processed (or not increasing)
is dropped as ``time_backwards``; a run of samples that leaps more than ``TIME_JUMP_S`` past the rig's present
is dropped as ``time_jump`` (a clock glitch of the sender); neither moves the rig's time nor reaches a
checkpoint.

A clock *step* is told from a glitch by the samples themselves, not by the wall clock: once
``CLOCK_STEP_SAMPLES`` samples in a row, in order among themselves, lie all behind the last processed one (or
all beyond the rig's present), the input's clock stepped and its new time is adopted (:meth:`LiveTime._step`):
the rig's clock is re-based there, the filter restarts as after a gap, the events' record time ``t_s`` runs
on, ``clock_steps`` is counted, the status says so and the journal keeps a note of it. A step, back or forward,
of any size costs about ``CLOCK_STEP_SAMPLES`` samples (at most those and the rest of a block that holds both
clocks: the step is adopted with the first block wholly on the new one); a glitch shorter than that costs only
its own."""

from __future__ import annotations

import logging
import time

import numpy as np

from replay.base import Samples
from twin.service.runner_core import GAP_S, RunnerCore

log = logging.getLogger("twin.serve")

#: A live sample stamped more than this after the rig's present (our clock now, less the best delivery delay
#: seen) cannot have been measured yet: a clock glitch, dropped as ``time_jump`` [s]. Far beyond delivery
#: jitter and the corrections a synchronised clock makes (milliseconds); an accepted sample at most this far
#: ahead costs the correct samples of at most this long (they come before it).
TIME_JUMP_S = 5.0
#: Samples in a row, in order among themselves, all behind the last processed one or all beyond the rig's
#: present: the input's clock stepped, its time is adopted (0.5 s at the rigs' 1 kHz; a burst of mis-stamped
#: samples shorter than this is a glitch and costs only itself) [samples].
CLOCK_STEP_SAMPLES = 500


class LiveTime(RunnerCore):
    """The live samples a runner cannot use, masked and counted (:meth:`_clean`); a clock step adopted."""

    def _clean(self, block: Samples) -> Samples | None:
        """A live block without the samples it cannot use, each counted: stamped far in the future
        (``time_jump``, :meth:`_future`), at or before the last one processed or not increasing
        (``time_backwards``), without a finite drive (``bad_samples``); a persisting step adopted (:meth:`_step`)."""
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
        self._step(t, jump, back, last)
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

    def _step(self, t: np.ndarray, jump: np.ndarray, back: np.ndarray, last: int | None) -> None:
        """Count the samples in a row on another clock (the block's trailing run of rejected samples, all one
        way and in order, continuing the previous block's run); at ``CLOCK_STEP_SAMPLES`` adopt the new time
        (the masks of that run's samples in this block are cleared: they are processed)."""
        n = len(t)
        rejected = jump | back
        if not n or not rejected[-1]:
            self._step_run = 0
            return
        kept = np.flatnonzero(~rejected)
        first = int(kept[-1]) + 1 if kept.size else 0
        seg = t[first:]
        way = "ahead" if jump[first:].all() else "back" if back[first:].all() else ""
        if not way or (len(seg) > 1 and not bool(np.all(np.diff(seg) > 0))):
            self._step_run = 0
            return
        continues = (first == 0 and self._step_way == way and self._step_last is not None
                     and int(seg[0]) > self._step_last)
        if not continues:
            self._step_run, self._step_first = 0, int(seg[0])
        self._step_run += len(seg)
        self._step_way, self._step_last = way, int(seg[-1])
        if self._step_run < CLOCK_STEP_SAMPLES or first > 0:
            return  # adopted with a block wholly on the new clock: the samples before the run are processed first
        twin = self.twin
        assert twin is not None  # made by _open
        lost = self._step_run - len(seg)
        size_s = (self._step_first - int(last)) * 1e-9 if last is not None else 0.0
        line = (f"the input's clock stepped {'back' if way == 'back' else 'forward'} {abs(size_s):.1f} s at "
                f"t_ns={self._step_first} ({self._step_run} samples in a row on the new clock; the first {lost} "
                "dropped); its time is adopted")
        if way == "back":
            twin.step_clock(int(seg[0]))
            self._restart_filter(line)
        else:
            self._notes = line
            log.warning("rig %s: %s", self.rig.name, line)
        if self._live_lag is not None:
            self._live_lag.rebase()
        jump[first:] = False
        back[first:] = False
        self._step_run, self._step_way, self._step_last = 0, "", None
        self.summary.clock_steps += 1
        self._step_note = f"clock step #{self.summary.clock_steps}: {line}"
        self.journal.note(self.rig.name, "clock_step", line)

    def _future(self, t: np.ndarray, last: int | None) -> np.ndarray:
        """Mask of live samples stamped more than ``TIME_JUMP_S`` after the rig's present (as the best delay
        seen places it on our clock) and after the last processed time plus the time passed since it was
        processed: they cannot have been measured yet. What leaps is judged, not what runs on: a run of
        samples without a gap (``GAP_S`` or 20 sample periods) is dropped when its first sample is beyond that
        bound, kept when it started within it (a sender faster than real time). Before this run processed a
        sample (no offset learnt yet) the rig's present is the host's UNIX time (a rig stamping UNIX time,
        as a live input should; other clocks are far behind it and never judged so). A run that stays ahead is
        a clock step (:meth:`_step`)."""
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
        if jump.any():
            self._lead_s = (float(t[jump].max()) - present) * 1e-9
        return jump
