"""Timing of a rig's blocks: when a replayed log's samples are due (:class:`Pacer`), how far a live input lags
(:class:`LiveLag`), and blocks cut by sample time (:func:`blocks_by_time`)."""

from __future__ import annotations

import math
import time

import numpy as np

from replay.base import Samples

#: Samples read from a log per chunk before it is cut into paced blocks.
READ_CHUNK = 2000
#: A rig behind real time filters every sample already due in one block, up to this much of them [s]
#: (fewer, larger blocks cost less Python per sample, so a rig that fell behind catches up).
MAX_BLOCK_S = 1.0


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
