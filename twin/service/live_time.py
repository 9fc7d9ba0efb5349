"""A live sample's time judged before it is processed: one at or before the last processed (or not increasing)
is dropped as ``time_backwards``; a run of samples that leaps more than ``TIME_JUMP_S`` past the rig's present
is dropped as ``time_jump`` (a clock glitch of the sender); neither moves the rig's time nor reaches a
checkpoint. A rig whose every sample is stamped ahead, or behind the last processed, for ``CLOCK_STEP_S``
stepped its clock: that time is adopted (``clock_steps``, the filter restarts as after a gap)."""

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
#: A live input whose every sample is stamped ahead (``time_jump``) for this long stepped its clock: the new
#: time is adopted (counted ``clock_steps``) rather than blinding the rig for ever [s].
CLOCK_STEP_S = 30.0



class LiveTime(RunnerCore):
    """The live samples a runner cannot use, masked and counted (:meth:`_clean`)."""

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

