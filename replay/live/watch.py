"""What live sources share: drop counting per cause, rate-limited logging, staleness and closing.

Every live message is validated
===============================

Nothing a sender puts on the wire raises out of a live source.  A message that
cannot be used is dropped, **counted per cause** in ``source.report.skipped`` (the
first few named in ``report.problems``) and logged through :mod:`logging` (logger
``replay.live``, at most one line per cause every :data:`LOG_EVERY_S` seconds, with
the count since the last line):

==================  ==============================================================
cause               what
==================  ==============================================================
``oversized``       a payload larger than ``max_payload_bytes`` (default 8 MiB) or
                    with more than ``max_block`` samples; dropped unread
``flood``           more payloads queued than ``max_queue`` (the consumer cannot keep
                    up), or CAN frames beyond ``max_frames_per_s``: the excess dropped
``bad_json``        not UTF-8 JSON
``bad_schema``      JSON, but not ``fpdd.samples/1`` (e.g. ``{"t_ns":5,"signals":[1,2]}``):
                    wrong format tag, types or list lengths
``bad_time``        ``t_ns`` not integers within int64 (e.g. ``2**70``, ``1.5``, ``true``)
``non_finite``      a value ``NaN``/``Infinity``/``1e999`` (``null`` is a missing value,
                    kept as NaN): that sample is dropped
``wrong_unit``      a block whose values are systematically outside the signal's
                    physical range or look like another unit (pressures in bar): the
                    block is dropped, the message names the likely unit
``out_of_range``    an isolated value outside the physical range: that sample dropped
``time_backwards``, ``time_repeated``, ``time_jump``: as for files (:mod:`replay.quality`)
``bad_payload``     a malformed ``fpdd.can/1`` payload; ``mixed_payload``: the other
                    payload kind on a stream of one kind
``missing_signal``  a sample block without a signal the stream delivers
``bad_frames``      CAN frames the decoder could not use as a block (unknown ids,
                    wrong DLC etc. are counted under their own names, see canio)
==================  ==============================================================

Quiet inputs, staleness and closing
===================================

A quiet input does not end a live source: it waits until it is closed (or, for
Zenoh, until the sender's end marker).  ``timeout_s`` is the staleness threshold:
with no usable data for that long the source becomes *stale* (``source.stale`` is
True, one problem and one log line say so, ``stale_events`` counts it) and goes on
waiting; the next data clears it.  While quiet, :meth:`chunks` yields an **empty**
:class:`~replay.base.Samples` block every ``poll_s`` (default ``min(timeout_s,
0.25)`` s), so a consumer looping ``for block in src.chunks(): ...`` gets control
back to check its own stop flag (``twin.service.rig.run_rig`` does; an empty block is a
no-op for a :class:`~replay.base.Sink`).  A service polls :meth:`idle` (seconds
since the last usable data), ``stale`` and :meth:`health` (a dict: stale, idle_s,
stale_events, samples_out, dropped counts per cause).  :meth:`close` may be called
from another thread: the iterating thread sees it within ``poll_s`` and the
iteration ends.  ``signals`` of a source that was not told them waits up to
``timeout_s`` for the first data and raises :class:`~fpdd.errors.SourceError` if none
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter


from replay.base import Problem, ReadReport

log = logging.getLogger("replay.live")

#: Seconds between two log lines of the same drop cause.
LOG_EVERY_S = 10.0


class Live:
    """Drop counting (thread-safe), rate-limited logging and staleness of a live source."""

    path: str
    report: ReadReport
    timeout_s: float | None

    def _live_init(self, timeout_s: float | None, poll_s: float | None) -> None:
        self.timeout_s = timeout_s
        self.poll_s = float(poll_s if poll_s is not None else min(timeout_s or 0.25, 0.25))
        if not self.poll_s > 0:
            raise ValueError(f"poll_s (={poll_s}) must be > 0 s")
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._last_data = time.monotonic()
        self._stale = False
        self.stale_events = 0
        self._log_last: dict[str, float] = {}
        self._log_count: Counter = Counter()

    # -- drops ---------------------------------------------------------------------------------
    def _drop(self, cause: str, where: str, what: str, count: int = 1) -> None:
        """Count ``count`` dropped items under ``cause``; keep the message; log at most every LOG_EVERY_S."""
        with self._lock:
            self.report.skipped[cause] += count
            if len(self.report.problems) < self.report.max_problems:
                self.report.problems.append(Problem(self.path, where, what))
        self._log_drop(cause, count, f"{where}: {what}")

    def _log_drop(self, cause: str, count: int, text: str) -> None:
        """Log a drop already counted; one line per cause every LOG_EVERY_S with the count since."""
        with self._lock:
            self._log_count[cause] += count
            now = time.monotonic()
            last = self._log_last.get(cause)
            if last is not None and now - last < LOG_EVERY_S:
                return
            n = self._log_count.pop(cause)
            self._log_last[cause] = now
        log.warning("%s: dropped %d %s%s: %s", self.path, n, cause,
                    f" in the last {LOG_EVERY_S:g} s" if last is not None else "", text)

    # -- staleness --------------------------------------------------------------------------------
    def idle(self) -> float:
        """Seconds since the last usable data (or since the source was opened)."""
        return time.monotonic() - self._last_data

    @property
    def stale(self) -> bool:
        """True after ``timeout_s`` without usable data (the source keeps waiting)."""
        return self.timeout_s is not None and self.idle() >= self.timeout_s

    def _fresh(self) -> None:
        self._last_data = time.monotonic()
        if self._stale:
            self._stale = False
            log.info("%s: data again after a quiet spell", self.path)

    def _quiet(self) -> None:
        if not self._stale and self.stale:
            self._stale = True
            self.stale_events += 1
            with self._lock:
                if len(self.report.problems) < self.report.max_problems:
                    self.report.problems.append(Problem(self.path, "input stale",
                                                        f"no data for {self.timeout_s} s; still waiting"))
            log.warning("%s: no data for %s s: input stale, still waiting", self.path, self.timeout_s)

    def health(self) -> dict:
        """What a service polls: staleness, idle time, samples out, drops per cause."""
        with self._lock:
            skipped = dict(self.report.skipped)
        return {"source": self.path, "stale": self.stale, "idle_s": self.idle(), "stale_events": self.stale_events,
                "samples_out": self.report.samples_out, "dropped": skipped, "closed": self._closing.is_set()}

    @property
    def closed(self) -> bool:
        return self._closing.is_set()
