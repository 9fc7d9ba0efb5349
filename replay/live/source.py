"""Rig samples received on a Zenoh key expression (:class:`ZenohSource`), either payload, every one validated."""

from __future__ import annotations

import dataclasses
import queue
import time
from collections.abc import Iterator, Sequence

import numpy as np
import zenoh

from replay.base import ReadReport, Samples, Source
from replay.can.decode import CanStream, split_block, make_plan, probe_plan
from replay.can.codec import Frames, VectorCodec
from replay.quality import QualityGate, QualityOptions
from fpdd.errors import DataError, SourceError, TwinError
from replay.live.payloads import CAN_MAGIC, SAMPLES_FORMAT, PayloadError, json_to_samples, payload_to_frames
from replay.live.sinks import open_live_session, parse_zenoh_uri
from replay.live.payloads import MAX_BLOCK, MAX_PAYLOAD_BYTES, MAX_QUEUE
from replay.live.watch import Live


class ZenohSource(Live, Source):
    """Rig samples received on a Zenoh key expression (either payload of :mod:`replay.live.payloads`).

    The subscriber is declared in the constructor, so a publisher started afterwards
    is not missed (Zenoh does not replay what was published before a subscriber joined).
    The stream ends at the sender's end marker or on :meth:`close`; a quiet key only
    makes the source stale (:mod:`replay.live.watch`).  Every payload is validated; what
    cannot be used is dropped and counted per cause.

    :param key: key expression or ``zenoh://KEY``.
    :param dbc, grid_hz, window_s, max_age_s: for ``fpdd.can/1`` payloads, as for CAN logs.
    :param config: Zenoh config (see :func:`zenoh_config`); ignored if ``session`` is given.
    :param timeout_s: staleness threshold (s); ``poll_s``: heartbeat period while quiet (s).
    :param max_payload_bytes, max_block, max_queue: limits (``oversized``, ``flood``).
    :param quality: gate options for sample payloads (range and unit check, time order).
    """

    def __init__(self, key: str, dbc=None, config: zenoh.Config | None = None, *,
                 session: zenoh.Session | None = None, timeout_s: float | None = 5.0, poll_s: float | None = None,
                 signals: Sequence[str] | None = None, grid_hz: float | None = None,
                 window_s: float | None = None, max_age_s: float | None = None,
                 max_payload_bytes: int = MAX_PAYLOAD_BYTES, max_block: int = MAX_BLOCK, max_queue: int = MAX_QUEUE,
                 quality: QualityOptions | None = None) -> None:
        self.key = parse_zenoh_uri(key) if key.startswith("zenoh://") else key
        self.path = f"zenoh://{self.key}"
        self.report = ReadReport(self.path)
        self._live_init(timeout_s, poll_s)
        self._dbc = dbc
        self._codec: VectorCodec | None = None
        self._align = dict(grid_hz=grid_hz, window_s=window_s, max_age_s=max_age_s)
        self._signals = tuple(signals) if signals is not None else None
        self.max_payload_bytes = int(max_payload_bytes)
        self.max_block = int(max_block)
        self._queue: queue.Queue[tuple[int, bytes] | None] = queue.Queue(maxsize=max(1, int(max_queue)))
        self._shed = 0  # payloads shed unparsed by the callback under a burst (see _on_sample)
        self._shed_counted = 0
        self._first: list[tuple[str, object]] = []  # payloads received while finding `signals`
        self._kind: str | None = None
        self._stream: CanStream | None = None
        self._ended = False
        self._n = 0  # payloads received (numbers them in messages)
        self._gate = QualityGate(self.report, dataclasses.replace(quality or QualityOptions(), keep_nan=True,
                                                                  systematic="drop"))
        self._owned = session is None
        self.session = session if session is not None else open_live_session(config, self.path)
        try:
            self.subscriber = self.session.declare_subscriber(self.key, self._on_sample)
        except Exception as e:  # ZError: an invalid key expression
            if self._owned:
                self.session.close()
            raise SourceError(f"{self.path}: cannot subscribe: {e}") from e
        self._closed = False

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh's callback thread: size and flood checks only; never raises."""
        try:
            with self._lock:
                n = self._n
                self._n += 1
            size = len(sample.payload)
            if size > self.max_payload_bytes:
                self._drop("oversized", f"payload {n}", f"{size} bytes, at most {self.max_payload_bytes} accepted; "
                                                        "dropped unread")
                return
            data = sample.payload.to_bytes()
            if not _plausible(data) and self._queue.qsize() >= self._queue.maxsize // 2:
                # Under a burst, what is plainly not a payload is shed here, unparsed and uncounted but for one
                # integer (folded into the report by the consumer): it never takes the place of a good payload
                # in the queue, and costs the callback (which every key of the session shares) next to nothing.
                self._shed += 1
                return
            try:
                self._queue.put_nowait((n, data))
            except queue.Full:
                self._drop("flood", f"payload {n}", f"{self._queue.maxsize} payloads already waiting: the input "
                                                    "comes faster than it is consumed; dropped")
        except Exception as e:  # noqa: BLE001 - nothing may escape into zenoh's thread
            self._drop("bad_payload", "callback", f"{type(e).__name__}: {e}")

    @property
    def codec(self) -> VectorCodec:
        if self._codec is None:
            self._codec = self._dbc if isinstance(self._dbc, VectorCodec) else VectorCodec(self._dbc)
        return self._codec

    def _parse(self, n: int, payload: bytes) -> tuple[str, object] | None:
        """('samples', Samples) | ('can', Frames) | ('end', None); None if dropped."""
        where = f"payload {n}"
        try:
            if payload[:4] == CAN_MAGIC:
                fr = payload_to_frames(payload, where)
                item: tuple[str, object] = ("end", None) if len(fr) == 0 else ("can", fr)
            else:
                got = json_to_samples(payload, where, self.max_block)
                if got is None:
                    return ("end", None)
                s, bad = got
                if bad.any():
                    i = int(np.flatnonzero(bad)[0])
                    vals = {k: float(v[i]) for k, v in s.signals.items() if not np.isfinite(v[i])}
                    self._drop("non_finite", f"{where}, sample {i} (t_ns {int(s.t_ns[i])})",
                               f"values {vals} are not finite numbers (null is a missing value); "
                               f"{int(bad.sum())} sample(s) dropped", count=int(bad.sum()))
                    keep = np.flatnonzero(~bad)
                    s = Samples(s.t_ns[keep], {k: v[keep] for k, v in s.signals.items()})
                    if not len(s):
                        return None
                with self._lock:
                    self.report.records_read += 1
                item = ("samples", s)
        except PayloadError as e:
            self._drop(e.cause, where, str(e).split(": ", 1)[-1])
            return None
        except Exception as e:  # noqa: BLE001 - a payload must never break the source
            self._drop("bad_payload", where, f"{type(e).__name__}: {e}")
            return None
        if item[0] == "end":
            return item
        if self._kind is None:
            self._kind = item[0]
        elif item[0] != self._kind:
            self._drop("mixed_payload", where, f"{item[0]} payload on a stream of {self._kind} payloads; skipped")
            return None
        return item

    def _next_payload(self, wait_s: float | None) -> tuple[str, object] | None:
        """The next usable payload, waiting up to ``wait_s`` (None: at most poll_s); None when quiet."""
        deadline = time.monotonic() + (self.poll_s if wait_s is None else wait_s)
        while not self._closing.is_set():
            left = deadline - time.monotonic()
            try:
                got = self._queue.get(timeout=max(0.0, min(left, self.poll_s)))
            except queue.Empty:
                self._count_shed()
                if time.monotonic() >= deadline:
                    return None
                continue
            if got is None:  # close() wakes the consumer
                return None
            self._count_shed()
            item = self._parse(*got)
            if item is not None:
                return item
        return None

    def _count_shed(self) -> None:
        """Fold the payloads the callback shed into the report (one drop line per ``LOG_EVERY_S``)."""
        shed = self._shed
        if shed > self._shed_counted:
            n, self._shed_counted = shed - self._shed_counted, shed
            with self._lock:
                self.report.skipped["shed"] += n
            self._log_drop("shed", n, f"payloads that are neither {SAMPLES_FORMAT} JSON nor fpdd.can/1 frames, "
                                      "arriving faster than they were consumed: dropped unparsed")

    def _take_first(self, item: tuple[str, object]) -> None:
        """Keep a first payload for the stream and learn the signals from it (samples, or CAN frames)."""
        self._first.append(item)
        kind, obj = item
        if kind == "samples":
            assert isinstance(obj, Samples)
            self._signals = obj.names
        else:
            assert isinstance(obj, Frames)
            self._start_can(obj)

    def _start_can(self, frames: Frames) -> bool:
        """Alignment plan of a CAN payload stream: from ``signals`` or from the first frames."""
        try:
            if self._signals is not None:
                plan = make_plan(self.codec, None, self._signals, source=self.path, **self._align)
            else:
                plan = probe_plan(self.codec, frames, self.path, **self._align)
        except DataError as e:
            self._drop("no_rig_frames", f"{len(frames)} frames", str(e).split(": ", 1)[-1], count=len(frames))
            return False
        self._signals = plan.signals
        self._stream = CanStream(self.codec, plan, self.report)
        return True

    @property
    def signals(self) -> tuple[str, ...]:
        if self._signals is None:
            deadline = time.monotonic() + (self.timeout_s if self.timeout_s is not None else 3.0e7)
            while self._signals is None:
                left = deadline - time.monotonic()
                item = None if self._ended or left <= 0 else self._next_payload(left)
                if item is None or item[0] == "end":
                    if item is not None:
                        self._ended = True
                    raise SourceError(f"{self.path}: nothing received within {self.timeout_s} s; the signals are "
                                      "not known yet (the source keeps waiting)")
                self._take_first(item)
        return self._signals

    def _blocks(self, kind: str, obj, size: int) -> Iterator[Samples]:
        if kind == "samples":
            assert self._signals is not None  # known before any block is decoded
            missing = [s for s in self._signals if s not in obj.signals]
            if missing:
                self._drop("missing_signal", f"payload with {len(obj)} samples",
                           f"signals {', '.join(missing)} missing; expected {', '.join(self._signals)}",
                           count=len(obj))
                return
            blk = Samples(obj.t_ns, {s: obj.signals[s] for s in self._signals})
            with self._lock:
                before = dict(self.report.skipped)
                n_problems = len(self.report.problems)
                blk = self._gate.apply(blk, None, "sample")
                new = {k: v - before.get(k, 0) for k, v in self.report.skipped.items() if v > before.get(k, 0)}
                said = [str(p).split(": ", 1)[-1] for p in self.report.problems[n_problems:]]
            for cause, n in new.items():  # what the gate dropped (time order, range, unit) is logged too
                self._log_drop(cause, n, next((t for t in said if cause.split("_")[0] in t), said[0] if said
                                              else "dropped by the quality gate"))
        else:
            if self._stream is None and not self._start_can(obj):
                return
            assert self._stream is not None  # made by _start_can
            try:
                blk = self._stream.feed(obj)
            except (TwinError, ValueError, IndexError) as e:
                self._drop("bad_frames", f"{len(obj)} frames", f"{type(e).__name__}: {e}", count=len(obj))
                return
        if len(blk):
            self._fresh()
        yield from split_block(blk, size)

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Sample blocks as payloads arrive; an empty block every ``poll_s`` while quiet; ends at
        the end marker or on :meth:`close`."""
        while self._signals is None and not self._ended and not self._closing.is_set():
            item = self._next_payload(None)
            if item is None:
                self._quiet()
                yield Samples.empty()
                continue
            if item[0] == "end":
                self._ended = True
                break
            self._take_first(item)
        items, self._first = self._first, []
        for kind, obj in items:
            yield from self._blocks(kind, obj, size)
        while not self._ended and not self._closing.is_set():
            item = self._next_payload(None)
            if item is None:
                out = self._stream.release() if self._stream is not None else None
                if out is not None and len(out):
                    yield from split_block(out, size)
                    continue
                self._quiet()
                if not self._closing.is_set():
                    yield Samples.empty(self._signals or ())
            elif item[0] == "end":
                self._ended = True
            else:
                yield from self._blocks(item[0], item[1], size)
        if self._stream is not None:
            yield from split_block(self._stream.flush(), size)

    def close(self) -> None:
        """End the stream (from any thread: an iterating thread sees it within ``poll_s``) and release."""
        if self._closed:
            return
        self._closed = True
        self._closing.set()
        try:
            self._queue.put_nowait(None)
        except queue.Full:
            pass
        self.subscriber.undeclare()
        if self._owned:
            self.session.close()


_FORMAT_BYTES = SAMPLES_FORMAT.encode()


def _plausible(data: bytes) -> bool:
    """Whether a payload may be one (``fpdd.can/1`` frames, or a JSON object naming ``fpdd.samples/1``): a
    check of a few bytes and one substring search, no parse."""
    if data[:4] == CAN_MAGIC:
        return True
    return data.lstrip()[:1] == b"{" and _FORMAT_BYTES in data
