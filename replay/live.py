"""Live sources and sinks: a CAN bus through python-can, and Zenoh.

URIs
====

* ``can://INTERFACE/CHANNEL`` — any python-can interface, opened with
  ``can.Bus(interface=INTERFACE, channel=CHANNEL)``; e.g. ``can://virtual/rig1``,
  ``can://socketcan/can0``, ``can://pcan/PCAN_USBBUS1``.
* ``zenoh://KEYEXPR`` — e.g. ``zenoh://fpdd/msp25/samples``.

Zenoh payloads
==============

Two payloads travel on a key expression; a :class:`ZenohSource` accepts either
(it tells them apart by their first bytes) and keeps to the kind it saw first.

``fpdd.samples/1`` — JSON, one object per block of samples, encoding
``application/json``::

    {"format": "fpdd.samples/1", "t_ns": [1700000000000000000, ...],
     "signals": {"x": [0.0012, ...], "u": [...], ...}}

SI units (``replay.base.SIGNALS``), every list as long as ``t_ns``, ``null`` for a
NaN.  A single sample is a block of one.  The end of a stream is
``{"format": "fpdd.samples/1", "end": true}``.

``fpdd.can/1`` — raw CAN frames, binary, encoding ``application/octet-stream``:
an 8-byte header ``b"FCAN"``, uint16 version (1), uint16 record size (24), then
little-endian records ``int64 t_ns, uint32 id (bit 31 set for 29-bit ids),
uint8 dlc, uint8 kind (0 data, 1 remote, 2 error), 2 pad bytes, 8 data bytes``.  A
header with no records ends the stream.  By convention the key is
``fpdd/<rig>/can``.  This is how CAN frames cross processes here (the ``virtual``
bus of python-can is in-process only); the receiving side decodes them with the DBC
exactly as a CAN log (:mod:`replay.canio`).

Zenoh sessions are opened from :func:`zenoh_config` (explicit endpoints, multicast
scouting optional) and closed on ``close()``; sources and sinks are context managers.
"""

from __future__ import annotations

import abc
import json
import queue
import threading
from pathlib import Path
from typing import Iterator, Sequence
from urllib.parse import urlparse

import can
import numpy as np
import zenoh

from replay.base import Problem, ReadReport, Samples, Sink, Source
from replay.canio import (BLOCK_FRAMES, CanStream, FrameScheduler, _split, frames_to_messages, make_plan,
                          probe_plan)
from replay.dbc import FrameCollector, Frames, VectorCodec
from replay.quality import require_signals
from twin.errors import DataError, LogFormatError, SourceError

SAMPLES_FORMAT = "fpdd.samples/1"
CAN_MAGIC = b"FCAN"
CAN_VERSION = 1
#: One raw CAN frame on Zenoh (``fpdd.can/1``).
CAN_RECORD = np.dtype([("t_ns", "<i8"), ("key", "<u4"), ("dlc", "u1"), ("kind", "u1"),
                       ("pad", "u1", (2,)), ("data", "u1", (8,))])
assert CAN_RECORD.itemsize == 24


# --- URIs and configuration --------------------------------------------------------------

def parse_can_uri(uri: str) -> tuple[str, str]:
    """``can://INTERFACE/CHANNEL`` -> (interface, channel)."""
    u = urlparse(uri)
    chan = u.path.lstrip("/")
    if u.scheme != "can" or not u.netloc or not chan:
        raise SourceError(f"{uri}: expected a CAN URI of the form can://INTERFACE/CHANNEL, e.g. can://virtual/rig1")
    return u.netloc, chan


def parse_zenoh_uri(uri: str) -> str:
    """``zenoh://KEYEXPR`` -> key expression."""
    if not uri.startswith("zenoh://") or len(uri) <= len("zenoh://"):
        raise SourceError(f"{uri}: expected a Zenoh URI of the form zenoh://KEY/EXPR, e.g. zenoh://fpdd/msp25/samples")
    return uri[len("zenoh://"):]


def open_bus(uri_or_bus: str | can.BusABC, **kwargs) -> tuple[can.BusABC, bool]:
    """A python-can bus from a URI (owned: shut down by the caller) or the bus itself (not owned)."""
    if isinstance(uri_or_bus, can.BusABC):
        return uri_or_bus, False
    interface, channel = parse_can_uri(uri_or_bus)
    try:
        return can.Bus(interface=interface, channel=channel, **kwargs), True
    except (can.CanError, OSError, ValueError, ImportError) as e:
        raise SourceError(f"{uri_or_bus}: cannot open CAN bus: {type(e).__name__}: {e}") from e


def zenoh_config(listen: Sequence[str] = (), connect: Sequence[str] = (), *, multicast_scouting: bool = False,
                 config_file: str | Path | None = None) -> zenoh.Config:
    """A Zenoh config: optional json5 file, explicit endpoints (e.g. ``tcp/127.0.0.1:7447``), scouting."""
    try:
        conf = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    except Exception as e:  # zenoh raises ZError for a bad file
        raise SourceError(f"{config_file}: cannot load Zenoh config: {e}") from e
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "true" if multicast_scouting else "false")
    return conf


def _open_session(conf: zenoh.Config | None, what: str) -> zenoh.Session:
    try:
        return zenoh.open(conf if conf is not None else zenoh_config(multicast_scouting=True))
    except Exception as e:  # ZError: endpoint in use, unreachable
        raise SourceError(f"{what}: cannot open Zenoh session: {e}") from e


# --- payloads ------------------------------------------------------------------------------------

def samples_to_json(samples: Samples) -> bytes:
    """``fpdd.samples/1`` payload of a block (NaN -> null)."""
    sig = {}
    for k, v in samples.signals.items():
        lst = v.tolist()
        if not np.isfinite(v).all():
            lst = [x if np.isfinite(x) else None for x in lst]
        sig[k] = lst
    return json.dumps({"format": SAMPLES_FORMAT, "t_ns": samples.t_ns.tolist(), "signals": sig},
                      separators=(",", ":")).encode()


def json_to_samples(payload: bytes, where: str) -> Samples | None:
    """Samples of an ``fpdd.samples/1`` payload; None for the end marker; LogFormatError if malformed."""
    try:
        obj = json.loads(payload)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise LogFormatError(f"{where}: payload is not JSON ({e}); expected {SAMPLES_FORMAT}") from e
    if not isinstance(obj, dict) or obj.get("format") != SAMPLES_FORMAT:
        raise LogFormatError(f"{where}: JSON without \"format\": \"{SAMPLES_FORMAT}\"")
    if obj.get("end"):
        return None
    t = obj.get("t_ns")
    sig = obj.get("signals")
    if isinstance(t, int):  # a single sample: scalars
        t = [t]
        sig = {k: [v] for k, v in (sig or {}).items()}
    if not isinstance(t, list) or not isinstance(sig, dict):
        raise LogFormatError(f"{where}: expected \"t_ns\" (list of int ns) and \"signals\" (object of lists)")
    try:
        cols = {k: np.array([np.nan if x is None else x for x in v], dtype=np.float64) for k, v in sig.items()}
        return Samples(np.array(t, dtype=np.int64), cols)
    except (TypeError, ValueError) as e:
        raise LogFormatError(f"{where}: {e}; expected every signal list as long as t_ns, numbers or null") from e


def frames_to_payload(frames: Frames) -> bytes:
    """``fpdd.can/1`` payload of a frame block (an empty block is the end marker)."""
    rec = np.zeros(len(frames), CAN_RECORD)
    rec["t_ns"] = frames.t_ns
    rec["key"] = frames.key
    rec["dlc"] = frames.dlc
    rec["kind"] = frames.kind
    rec["data"] = frames.data
    head = CAN_MAGIC + np.array([CAN_VERSION, CAN_RECORD.itemsize], "<u2").tobytes()
    return head + rec.tobytes()


def payload_to_frames(payload: bytes, where: str) -> Frames:
    """Frames of an ``fpdd.can/1`` payload; LogFormatError if malformed."""
    if len(payload) < 8 or payload[:4] != CAN_MAGIC:
        raise LogFormatError(f"{where}: not an fpdd.can payload (expected header {CAN_MAGIC!r})")
    ver, size = np.frombuffer(payload[4:8], "<u2")
    if ver != CAN_VERSION or size != CAN_RECORD.itemsize or (len(payload) - 8) % size:
        raise LogFormatError(f"{where}: fpdd.can version {ver}, record size {size}, {len(payload) - 8} bytes of "
                             f"records; expected version {CAN_VERSION}, records of {CAN_RECORD.itemsize} bytes")
    rec = np.frombuffer(payload[8:], CAN_RECORD)
    return Frames(rec["t_ns"], rec["key"], rec["dlc"], rec["data"], rec["kind"])


# --- live CAN bus ------------------------------------------------------------------------------

class CanBusSource(Source):
    """Rig samples decoded live from a python-can bus.

    :param bus: ``can://INTERFACE/CHANNEL`` or an open :class:`can.BusABC` (then not shut down here).
    :param dbc: DBC path, database or :class:`~replay.dbc.VectorCodec` (default: MSP25).
    :param grid_hz, window_s, max_age_s: alignment, as for :class:`~replay.canio.CanLogSource`.
    :param signals: rig signals to deliver; default: those of the messages seen in the
        first ``probe_s`` of traffic (frame timestamps; the DBC's slowest period x 2.5).
    :param timeout_s: receive timeout in s: with no frame for that long the stream ends
        (``None``: wait for ever).  Frame timestamps are the bus's receive times.
    :param required: signals that must be delivered (DataError naming them if not).
    :param bus_kwargs: passed to ``can.Bus``.
    """

    def __init__(self, bus: str | can.BusABC, dbc=None, grid_hz: float | None = None, *,
                 signals: Sequence[str] | None = None, timeout_s: float | None = 1.0,
                 window_s: float | None = None, max_age_s: float | None = None, probe_s: float | None = None,
                 required: Sequence[str] = (), **bus_kwargs) -> None:
        self.codec = dbc if isinstance(dbc, VectorCodec) else VectorCodec(dbc)
        self.bus, self._owned = open_bus(bus, **bus_kwargs)
        self.path = bus if isinstance(bus, str) else f"can://{type(self.bus).__name__}/{self.bus.channel_info}"
        self.report = ReadReport(self.path)
        self.timeout_s = timeout_s
        self._align = dict(grid_hz=grid_hz, window_s=window_s, max_age_s=max_age_s)
        self._pending = Frames.empty()
        self._ended = False
        if signals is not None:
            self.plan = make_plan(self.codec, None, signals, source=self.path, **self._align)
        else:
            periods = [m.period_s for m in self.codec.messages.values() if m.period_s and m.rig_signals]
            self.probe_s = probe_s if probe_s is not None else max(0.05, 2.5 * max(periods, default=0.02))
            self._pending = self._probe()
            if len(self._pending) == 0:
                self.close()
                raise SourceError(f"{self.path}: no CAN frame within {timeout_s} s")
            self.plan = probe_plan(self.codec, self._pending, self.path, **self._align)
        try:
            require_signals(self.path, self.plan.signals, required)
        except DataError:
            self.close()
            raise

    def _recv_block(self, max_frames: int) -> Frames | None:
        """Frames available now (at least one, waiting up to the timeout); None at timeout."""
        coll = FrameCollector()
        msg = self.bus.recv(timeout=self.timeout_s)
        if msg is None:
            return None
        coll.add(msg)
        while len(coll) < max_frames:
            msg = self.bus.recv(timeout=0.0)
            if msg is None:
                break
            coll.add(msg)
        return coll.take()

    def _probe(self) -> Frames:
        blocks: list[Frames] = []
        t0 = None
        while True:
            fr = self._recv_block(4096)
            if fr is None:
                self._ended = True
                break
            blocks.append(fr)
            t0 = int(fr.t_ns[0]) if t0 is None else t0
            if int(fr.t_ns[-1]) - t0 >= self.probe_s * 1e9:
                break
        return Frames.concat(blocks)

    @property
    def signals(self) -> tuple[str, ...]:
        return self.plan.signals

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Sample blocks as frames arrive (each block what could be aligned so far)."""
        stream = CanStream(self.codec, self.plan, self.report)
        if len(self._pending):
            yield from _split(stream.feed(self._pending), size)
            self._pending = Frames.empty()
        while not self._ended:
            fr = self._recv_block(min(size, BLOCK_FRAMES))
            if fr is None:
                self._ended = True
                self.report.problems.append(Problem(self.path, "end of stream",
                                                    f"no CAN frame for {self.timeout_s} s; stream ended"))
                break
            yield from _split(stream.feed(fr), size)
        yield from _split(stream.flush(), size)

    def close(self) -> None:
        if self._owned and self.bus is not None:
            self.bus.shutdown()
            self._owned = False


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


# --- Zenoh -------------------------------------------------------------------------------------

class _ZenohPublisher(Sink):
    def __init__(self, key: str, config: zenoh.Config | None, encoding: zenoh.Encoding,
                 session: zenoh.Session | None) -> None:
        self.key = parse_zenoh_uri(key) if key.startswith("zenoh://") else key
        self._owned = session is None
        self.session = session if session is not None else _open_session(config, f"zenoh://{self.key}")
        self.publisher = self.session.declare_publisher(self.key, encoding=encoding)
        self._matched = threading.Event()
        self._listener = self.publisher.declare_matching_listener(self._on_matching)
        if self.publisher.matching_status.matching:
            self._matched.set()
        self._closed = False

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        if status.matching:
            self._matched.set()
        else:
            self._matched.clear()

    def wait_for_subscriber(self, timeout_s: float = 5.0) -> bool:
        """Block until a subscriber matches the key (True) or the timeout passes (False)."""
        return self._matched.wait(timeout_s)

    def _put(self, payload: bytes) -> None:
        self.publisher.put(payload)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._send_end()
        self._listener.undeclare()
        self.publisher.undeclare()
        if self._owned:
            self.session.close()

    @abc.abstractmethod
    def _send_end(self) -> None:
        """Publish the end-of-stream marker of the payload format."""


class ZenohSampleSink(_ZenohPublisher):
    """Publishes sample blocks as ``fpdd.samples/1`` JSON on a key (``replay play --to zenoh``).

    :param key: key expression or ``zenoh://KEY``.
    :param config: Zenoh config (see :func:`zenoh_config`); ignored if ``session`` is given.
    :param max_block: samples per payload at most (larger blocks are split).
    :param end_marker: publish the end marker on close.
    """

    def __init__(self, key: str, config: zenoh.Config | None = None, *, session: zenoh.Session | None = None,
                 max_block: int = 1000, end_marker: bool = True) -> None:
        super().__init__(key, config, zenoh.Encoding.APPLICATION_JSON, session)
        self.max_block = max_block
        self.end_marker = end_marker

    def write(self, samples: Samples) -> None:
        for part in _split(samples, self.max_block):
            self._put(samples_to_json(part))

    def _send_end(self) -> None:
        if self.end_marker:
            self._put(json.dumps({"format": SAMPLES_FORMAT, "end": True}).encode())


class ZenohCanSink(_ZenohPublisher):
    """Publishes raw CAN frames (``fpdd.can/1``) on a key, e.g. ``fpdd/msp25/can``.

    ``write(samples)`` encodes samples into the rig's frames with the DBC (like
    :class:`~replay.canio.CanLogSink`); ``write_frames(frames)`` forwards frames as they
    are (a bus or a log bridged to Zenoh); ``write_messages`` takes python-can messages.
    """

    def __init__(self, key: str, dbc=None, config: zenoh.Config | None = None, *,
                 session: zenoh.Session | None = None, decimate: bool = True, end_marker: bool = True) -> None:
        super().__init__(key, config, zenoh.Encoding.APPLICATION_OCTET_STREAM, session)
        self.codec = dbc if isinstance(dbc, VectorCodec) else VectorCodec(dbc)
        self.scheduler = FrameScheduler(self.codec, decimate, f"zenoh://{self.key}")
        self.end_marker = end_marker

    def write(self, samples: Samples) -> None:
        self.write_frames(self.scheduler.frames(samples))

    def write_frames(self, frames: Frames) -> None:
        if len(frames):
            self._put(frames_to_payload(frames))

    def write_messages(self, messages) -> None:
        coll = FrameCollector()
        for m in messages:
            coll.add(m)
        self.write_frames(coll.take())

    def _send_end(self) -> None:
        if self.end_marker:
            self._put(frames_to_payload(Frames.empty()))


class ZenohSource(Source):
    """Rig samples received on a Zenoh key expression (either payload of the module docstring).

    The subscriber is declared in the constructor, so a publisher started afterwards
    is not missed (Zenoh does not replay what was published before a subscriber joined).
    The stream ends at an end marker or after ``timeout_s`` without data.
    ``signals`` waits (up to ``timeout_s``) for the first payload unless given.

    :param key: key expression or ``zenoh://KEY``.
    :param dbc, grid_hz, window_s, max_age_s: for ``fpdd.can/1`` payloads, as for CAN logs.
    :param config: Zenoh config (see :func:`zenoh_config`); ignored if ``session`` is given.
    """

    def __init__(self, key: str, dbc=None, config: zenoh.Config | None = None, *,
                 session: zenoh.Session | None = None, timeout_s: float | None = 5.0,
                 signals: Sequence[str] | None = None, grid_hz: float | None = None,
                 window_s: float | None = None, max_age_s: float | None = None) -> None:
        self.key = parse_zenoh_uri(key) if key.startswith("zenoh://") else key
        self.path = f"zenoh://{self.key}"
        self.report = ReadReport(self.path)
        self.timeout_s = timeout_s
        self._dbc = dbc
        self._codec: VectorCodec | None = None
        self._align = dict(grid_hz=grid_hz, window_s=window_s, max_age_s=max_age_s)
        self._signals = tuple(signals) if signals is not None else None
        self._queue: queue.Queue[bytes] = queue.Queue()
        self._first: list[tuple[str, object]] = []  # payloads received while finding `signals`
        self._kind: str | None = None
        self._stream: CanStream | None = None
        self._ended = False
        self._n = 0
        self._owned = session is None
        self.session = session if session is not None else _open_session(config, self.path)
        self.subscriber = self.session.declare_subscriber(self.key, self._on_sample)
        self._closed = False

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._queue.put(sample.payload.to_bytes())

    @property
    def codec(self) -> VectorCodec:
        if self._codec is None:
            self._codec = self._dbc if isinstance(self._dbc, VectorCodec) else VectorCodec(self._dbc)
        return self._codec

    def _next_payload(self) -> tuple[str, object] | None:
        """('samples', Samples) | ('can', Frames) | ('end', None) | None at timeout."""
        while True:
            try:
                payload = self._queue.get(timeout=self.timeout_s)
            except queue.Empty:
                return None
            where = f"payload {self._n}"
            self._n += 1
            try:
                if payload[:4] == CAN_MAGIC:
                    item: tuple[str, object] = ("can", payload_to_frames(payload, where))
                    if len(item[1]) == 0:
                        return ("end", None)
                else:
                    s = json_to_samples(payload, where)
                    if s is None:
                        return ("end", None)
                    self.report.records_read += 1
                    item = ("samples", s)
            except LogFormatError as e:
                self.report.skip("bad_payload", where, str(e).split(": ", 1)[1])
                continue
            if self._kind is None:
                self._kind = item[0]
            elif item[0] != self._kind:
                self.report.skip("mixed_payload", where,
                                 f"{item[0]} payload on a stream of {self._kind} payloads; skipped")
                continue
            return item

    def _start_can(self, frames: Frames) -> None:
        """Alignment plan of a CAN payload stream: from ``signals`` or from the first frames."""
        if self._signals is not None:
            plan = make_plan(self.codec, None, self._signals, source=self.path, **self._align)
        else:
            plan = probe_plan(self.codec, frames, self.path, **self._align)
        self._signals = plan.signals
        self._stream = CanStream(self.codec, plan, self.report)

    @property
    def signals(self) -> tuple[str, ...]:
        if self._signals is None:
            item = None if self._ended else self._next_payload()
            if item is None or item[0] == "end":
                self._ended = True
                raise SourceError(f"{self.path}: nothing received within {self.timeout_s} s")
            self._first.append(item)
            kind, obj = item
            if kind == "samples":
                self._signals = obj.names
            else:
                self._start_can(obj)
        return self._signals

    def _blocks(self, kind: str, obj, size: int) -> Iterator[Samples]:
        if kind == "samples":
            missing = [s for s in self._signals if s not in obj.signals]
            if missing:
                self.report.skip("missing_signal", f"payload with {len(obj)} samples",
                                 f"signals {', '.join(missing)} missing; expected {', '.join(self._signals)}")
                return
            blk = Samples(obj.t_ns, {s: obj.signals[s] for s in self._signals})
            self.report.samples_out += len(blk)
            yield from _split(blk, size)
        else:
            if self._stream is None:
                self._start_can(obj)
            yield from _split(self._stream.feed(obj), size)

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Sample blocks as payloads arrive, until the end marker or the receive timeout."""
        if not self._ended:
            self.signals  # noqa: B018 - waits for the first payload when signals are not given
        items, self._first = self._first, []
        for kind, obj in items:
            yield from self._blocks(kind, obj, size)
        while not self._ended:
            item = self._next_payload()
            if item is None:
                self.report.problems.append(Problem(self.path, "end of stream",
                                                    f"no payload for {self.timeout_s} s; stream ended"))
                self._ended = True
            elif item[0] == "end":
                self._ended = True
            else:
                yield from self._blocks(item[0], item[1], size)
        if self._stream is not None:
            yield from _split(self._stream.flush(), size)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.subscriber.undeclare()
        if self._owned:
            self.session.close()
