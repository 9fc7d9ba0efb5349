"""A live CAN bus (any python-can interface) as a sample source, and samples onto a bus: ``can://INTERFACE/CHANNEL``.

Frames are decoded and aligned exactly as a CAN log's (:mod:`replay.can.decode`); what the live sources share
(drop counting, rate-limited logging, staleness) is :class:`replay.live.watch.Live`."""

from __future__ import annotations

import difflib
import threading
import time
from collections.abc import Iterator, Sequence
from urllib.parse import urlparse

import can
import numpy as np

from replay.base import ReadReport, Samples, Sink, Source
from replay.can.codec import FrameCollector, Frames, VectorCodec
from replay.can.decode import BLOCK_FRAMES, CanStream, make_plan, probe_plan, split_block
from replay.can.encode import FrameScheduler, frames_to_messages
from fpdd.errors import DataError, SourceError, TwinError
from replay.live.payloads import MAX_FRAMES_PER_S
from replay.live.watch import Live
from replay.quality import require_signals


def parse_can_uri(uri: str) -> tuple[str, str]:
    """``can://INTERFACE/CHANNEL`` -> (interface, channel)."""
    u = urlparse(uri)
    chan = u.path.lstrip("/")
    if u.scheme != "can" or not u.netloc or not chan:
        raise SourceError(f"{uri}: expected a CAN URI of the form can://INTERFACE/CHANNEL, e.g. can://virtual/rig1")
    return u.netloc, chan


def check_can_uri(uri: str) -> tuple[str, str]:
    """``can://INTERFACE/CHANNEL`` with an INTERFACE python-can knows -> (interface, channel); SourceError naming
    the known interfaces otherwise (checked before anything waits on the bus)."""
    interface, channel = parse_can_uri(uri)
    known = sorted(can.interfaces.VALID_INTERFACES)
    if interface not in known:
        close = difflib.get_close_matches(interface, known, n=1)
        raise SourceError(f"{uri}: unknown CAN interface {interface!r}"
                          + (f" (did you mean {close[0]!r}?)" if close else "")
                          + f"; python-can knows {', '.join(known)}")
    return interface, channel


def open_bus(uri_or_bus: str | can.BusABC, **kwargs) -> tuple[can.BusABC, bool]:
    """A python-can bus from a URI (owned: shut down by the caller) or the bus itself (not owned)."""
    if isinstance(uri_or_bus, can.BusABC):
        return uri_or_bus, False
    interface, channel = check_can_uri(uri_or_bus)
    try:
        return can.Bus(interface=interface, channel=channel, **kwargs), True
    except Exception as e:  # CanError, OSError (no such device), ImportError, ValueError, ...
        hint = ""
        if interface == "socketcan":
            hint = (" (SocketCAN needs Linux with the CAN modules and the interface up, e.g. "
                    f"'ip link add dev {channel} type vcan && ip link set up {channel}')")
        raise SourceError(f"{uri_or_bus}: cannot open CAN bus: {type(e).__name__}: {e}{hint}") from e


class CanBusSource(Live, Source):
    """Rig samples decoded live from a python-can bus.

    :param bus: ``can://INTERFACE/CHANNEL`` or an open :class:`can.BusABC` (then not shut down here).
    :param dbc: DBC path, database or :class:`~replay.can.codec.VectorCodec` (default: MSP25).
    :param grid_hz, window_s, max_age_s: alignment, as for :class:`~replay.can.logs.CanLogSource`.
    :param signals: rig signals to deliver; default: those of the messages seen in the
        first ``probe_s`` of traffic (frame timestamps; the DBC's slowest period x 2.5).
    :param timeout_s: staleness threshold in s (``None``: never stale); a quiet bus does
        not end the stream (module docstring).  Frame timestamps are the bus's receive times.
    :param poll_s: while quiet, an empty block is yielded this often (s).
    :param max_frames_per_s: frames beyond this rate (token bucket over 1 s) are dropped
        as ``flood``.
    :param required: signals that must be delivered (DataError naming them if not).
    :param bus_kwargs: passed to ``can.Bus``.
    """

    def __init__(self, bus: str | can.BusABC, dbc=None, grid_hz: float | None = None, *,
                 signals: Sequence[str] | None = None, timeout_s: float | None = 1.0, poll_s: float | None = None,
                 window_s: float | None = None, max_age_s: float | None = None, probe_s: float | None = None,
                 required: Sequence[str] = (), max_frames_per_s: float = MAX_FRAMES_PER_S, **bus_kwargs) -> None:
        self.codec = dbc if isinstance(dbc, VectorCodec) else VectorCodec(dbc)
        self._live_init(timeout_s, poll_s)
        self.bus, self._owned = open_bus(bus, **bus_kwargs)
        self.path = bus if isinstance(bus, str) else f"can://{type(self.bus).__name__}/{self.bus.channel_info}"
        self.report = ReadReport(self.path)
        self._align = dict(grid_hz=grid_hz, window_s=window_s, max_age_s=max_age_s)
        self._required = tuple(required)
        self._pending = Frames.empty()
        self._io = threading.Lock()  # held while a thread waits in bus.recv (close() waits for it)
        self._rate = float(max_frames_per_s)
        self._tokens = self._rate
        self._tokens_t = time.monotonic()
        periods = [m.period_s for m in self.codec.messages.values() if m.period_s and m.rig_signals]
        self.probe_s = probe_s if probe_s is not None else max(0.05, 2.5 * max(periods, default=0.02))
        self.plan = None
        if signals is not None:
            try:
                self.plan = make_plan(self.codec, None, signals, source=self.path, **self._align)
                require_signals(self.path, self.plan.signals, self._required)
            except DataError:
                self.close()
                raise

    def _recv_block(self, max_frames: int, timeout: float) -> Frames | None:
        """Frames available now (at least one, waiting up to ``timeout``); None when quiet or closed."""
        if self._closing.is_set():
            return None
        coll = FrameCollector()
        with self._io:
            if self._closing.is_set():
                return None
            try:
                msg = self.bus.recv(timeout=timeout)
                while msg is not None:
                    try:
                        coll.add(msg)
                    except Exception as e:  # a message python-can built but FrameCollector cannot hold
                        self._drop("bad_frames", "bus", f"{type(e).__name__}: {e}")
                    if len(coll) >= max_frames:
                        break
                    msg = self.bus.recv(timeout=0.0)
            except (can.CanError, OSError, ValueError) as e:
                self._drop("bus_error", "bus", f"receive failed: {type(e).__name__}: {e}")
                time.sleep(min(timeout, 0.05))  # a bus in error: do not spin
        if not len(coll):
            return None
        return self._limit(coll.take())

    def _limit(self, fr: Frames) -> Frames:
        """Token bucket: at most ``max_frames_per_s`` frames per second of wall time (burst: 1 s)."""
        now = time.monotonic()
        self._tokens = min(self._rate, self._tokens + (now - self._tokens_t) * self._rate)
        self._tokens_t = now
        n = len(fr)
        if n <= self._tokens:
            self._tokens -= n
            return fr
        keep = int(self._tokens)
        self._tokens -= keep
        self._drop("flood", f"{n} frames at t={fr.t_ns[0] / 1e9:.6f} s",
                   f"more than {self._rate:g} frames/s: {n - keep} frame(s) dropped", count=n - keep)
        return fr.take(np.arange(keep))

    def _probe(self, timeout_s: float | None) -> bool:
        """Collect frames until ``probe_s`` of traffic (or ``timeout_s`` of quiet); make the plan."""
        t_wait = time.monotonic()
        blocks = [self._pending] if len(self._pending) else []
        while self.plan is None and not self._closing.is_set():
            fr = self._recv_block(4096, self.poll_s)
            if fr is None:
                if timeout_s is not None and time.monotonic() - t_wait >= timeout_s:
                    self._pending = Frames.concat(blocks) if blocks else Frames.empty()
                    return False
                continue
            t_wait = time.monotonic()
            blocks.append(fr)
            got = Frames.concat(blocks)
            if int(got.t_ns.max()) - int(got.t_ns[0]) >= self.probe_s * 1e9:
                self._pending = got
                self._plan_from(got)
                blocks = [self._pending] if len(self._pending) else []
        return self.plan is not None

    def _plan_from(self, frames: Frames) -> None:
        try:
            self.plan = probe_plan(self.codec, frames, self.path, **self._align)
        except DataError as e:  # no rig message among these frames: drop them, keep probing
            self._drop("no_rig_frames", f"{len(frames)} frames", str(e).split(": ", 1)[-1])
            self._pending = Frames.empty()
            return
        require_signals(self.path, self.plan.signals, self._required)

    @property
    def signals(self) -> tuple[str, ...]:
        if self.plan is None and not self._probe(self.timeout_s):
            raise SourceError(f"{self.path}: no CAN frame of a rig message within {self.timeout_s} s; "
                              "the signals are not known yet (the source keeps waiting)")
        assert self.plan is not None  # made by _probe
        return self.plan.signals

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Sample blocks as frames arrive; an empty block every ``poll_s`` while quiet; ends on close()."""
        stream: CanStream | None = None
        if True:
            while not self._closing.is_set():
                if self.plan is None:
                    if not self._probe(0.0 if self.poll_s else None) and not self._closing.is_set():
                        self._quiet()
                        yield Samples.empty()
                    continue
                if stream is None:
                    stream = CanStream(self.codec, self.plan, self.report)
                fr: Frames | None
                if len(self._pending):
                    fr, self._pending = self._pending, Frames.empty()
                else:
                    fr = self._recv_block(min(size, BLOCK_FRAMES), self.poll_s)
                if fr is None:
                    out = stream.release()  # the window of the last cycle has passed
                    if len(out):
                        yield from split_block(out, size)
                        continue
                    self._quiet()
                    if not self._closing.is_set():
                        yield Samples.empty(self.plan.signals)
                    continue
                try:
                    out = stream.feed(fr)
                except (TwinError, ValueError, IndexError) as e:
                    self._drop("bad_frames", f"{len(fr)} frames at t={fr.t_ns[0] / 1e9:.6f} s",
                               f"{type(e).__name__}: {e}", count=len(fr))
                    continue
                if len(out):
                    self._fresh()
                yield from split_block(out, size)
            if stream is not None:
                yield from split_block(stream.flush(), size)

    def _shutdown(self) -> None:
        if self._owned and self.bus is not None:
            with self._io:
                if self._owned:
                    self._owned = False
                    self.bus.shutdown()

    def close(self) -> None:
        """End the stream (from any thread: an iterating thread sees it within ``poll_s``) and release the bus."""
        self._closing.set()
        self._shutdown()


class CanBusSink(Sink):
    """Samples sent as the rig's CAN frames on a python-can bus (encoded with the DBC).

    Frames of one block are sent back to back; pacing is the caller's (see :mod:`replay.play`).
    """

    def __init__(self, bus: str | can.BusABC, dbc=None, *, decimate: bool = True, **bus_kwargs) -> None:
        self.codec = dbc if isinstance(dbc, VectorCodec) else VectorCodec(dbc)
        self.bus, self._owned = open_bus(bus, **bus_kwargs)
        self.scheduler = FrameScheduler(self.codec, decimate, str(bus))

    def write(self, samples: Samples) -> None:
        self.write_frames(self.scheduler.frames(samples))

    def write_frames(self, frames: Frames) -> None:
        for msg in frames_to_messages(frames):
            try:
                self.bus.send(msg)
            except can.CanError as e:
                raise SourceError(f"CAN bus {self.bus.channel_info}: send failed at t={msg.timestamp:.6f} s, "
                                  f"id 0x{msg.arbitration_id:X}: {e}") from e

    def close(self) -> None:
        if self._owned:
            self.bus.shutdown()
            self._owned = False
