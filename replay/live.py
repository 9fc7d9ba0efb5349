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

SI units (``fpdd.units.SIGNALS``), every list as long as ``t_ns``, ``t_ns`` integers
in the int64 range, ``null`` for a missing value (delivered as NaN: the tracker takes
it as a missing measurement).  A single sample is a block of one (scalars instead of
lists).  The end of a stream is ``{"format": "fpdd.samples/1", "end": true}``.

``fpdd.can/1`` — raw CAN frames, binary, encoding ``application/octet-stream``:
an 8-byte header ``b"FCAN"``, uint16 version (1), uint16 record size (24), then
little-endian records ``int64 t_ns, uint32 id (bit 31 set for 29-bit ids),
uint8 dlc, uint8 kind (0 data, 1 remote, 2 error), 2 pad bytes, 8 data bytes``.  A
header with no records ends the stream.  By convention the key is
``fpdd/<rig>/can``.  This is how CAN frames cross processes here (the ``virtual``
bus of python-can is in-process only); the receiving side decodes them with the DBC
exactly as a CAN log (:mod:`replay.can.logs`).

Zenoh sessions are opened from :func:`zenoh_config` (explicit endpoints, multicast
scouting optional) and closed on ``close()``; sources and sinks are context managers.

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
came (the iteration itself keeps waiting).
"""

from __future__ import annotations

import abc
import dataclasses
import json
import logging
import math
import queue
import threading
import time
from collections import Counter
from collections.abc import Iterator, Sequence

import numpy as np
import zenoh

from fpdd.zenohconf import open_session, zenoh_config
from replay.base import Problem, ReadReport, Samples, Sink, Source
from replay.can.decode import CanStream, split_block, make_plan, probe_plan
from replay.can.encode import FrameScheduler
from replay.can.codec import Frames, VectorCodec
from replay.quality import QualityGate, QualityOptions
from fpdd.errors import DataError, LogFormatError, SourceError, TwinError

log = logging.getLogger("replay.live")

SAMPLES_FORMAT = "fpdd.samples/1"
CAN_MAGIC = b"FCAN"
CAN_VERSION = 1
#: One raw CAN frame on Zenoh (``fpdd.can/1``).
CAN_RECORD = np.dtype([("t_ns", "<i8"), ("key", "<u4"), ("dlc", "u1"), ("kind", "u1"),
                       ("pad", "u1", (2,)), ("data", "u1", (8,))])
assert CAN_RECORD.itemsize == 24

#: Defaults of the validation limits (see the module docstring).
MAX_PAYLOAD_BYTES = 8 << 20
MAX_BLOCK = 100_000
MAX_QUEUE = 256
MAX_FRAMES_PER_S = 20_000  # a classic CAN bus at 1 Mbit/s carries at most about 9 000 frames/s
#: Seconds between two log lines of the same drop cause.
LOG_EVERY_S = 10.0
_INT64 = (-(1 << 63), (1 << 63) - 1)


# --- URIs and configuration --------------------------------------------------------------


def parse_zenoh_uri(uri: str) -> str:
    """``zenoh://KEYEXPR`` -> key expression."""
    if not uri.startswith("zenoh://") or len(uri) <= len("zenoh://"):
        raise SourceError(f"{uri}: expected a Zenoh URI of the form zenoh://KEY/EXPR, e.g. zenoh://fpdd/msp25/samples")
    return uri[len("zenoh://"):]


def _open_session(conf: zenoh.Config | None, what: str) -> zenoh.Session:
    """A session from ``conf`` (default: peer, scouting on, to find the rig's publisher on the LAN)."""
    return open_session(conf if conf is not None else zenoh_config(multicast_scouting=True), what)


# --- payloads ------------------------------------------------------------------------------------

class PayloadError(LogFormatError):
    """A live payload that cannot be used; ``cause`` is the drop cause it is counted under."""

    def __init__(self, cause: str, message: str) -> None:
        super().__init__(message)
        self.cause = cause


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


_EXPECTED = (f'expected {{"format": "{SAMPLES_FORMAT}", "t_ns": [int ns, ...], '
             '"signals": {"name": [number or null, ...], ...}}')


def _times(where: str, t) -> np.ndarray:
    arr = np.array(t)
    if arr.dtype == np.int64 and arr.ndim == 1:
        return arr
    for i, x in enumerate(t):
        if type(x) is not int:
            raise PayloadError("bad_time", f"{where}: t_ns[{i}] = {x!r} is a {type(x).__name__}, "
                                           "expected an integer number of ns")
        if not _INT64[0] <= x <= _INT64[1]:
            raise PayloadError("bad_time", f"{where}: t_ns[{i}] = {x} is beyond the int64 range of ns "
                                           f"[{_INT64[0]}, {_INT64[1]}]")
    raise PayloadError("bad_time", f"{where}: t_ns is not a list of integers")


def json_to_samples(payload: bytes, where: str, max_block: int = MAX_BLOCK) -> tuple[Samples, np.ndarray] | None:
    """Samples of an ``fpdd.samples/1`` payload and the mask of non-finite (not null) values.

    None for the end marker; :class:`PayloadError` (with its drop ``cause``) if malformed.
    """
    try:
        obj = json.loads(payload)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise PayloadError("bad_json", f"{where}: payload is not JSON ({str(e)[:80]}); {_EXPECTED}") from None
    if not isinstance(obj, dict):
        raise PayloadError("bad_schema", f"{where}: JSON {type(obj).__name__}, not an object; {_EXPECTED}")
    if obj.get("format") != SAMPLES_FORMAT:
        raise PayloadError("bad_schema", f"{where}: \"format\" is {obj.get('format')!r}, expected "
                                         f"\"{SAMPLES_FORMAT}\"; {_EXPECTED}")
    if obj.get("end") is True:
        return None
    t = obj.get("t_ns")
    sig = obj.get("signals")
    if not isinstance(sig, dict) or not sig or not all(isinstance(k, str) for k in sig):
        raise PayloadError("bad_schema", f"{where}: \"signals\" is {type(sig).__name__}"
                                         f"{' (empty)' if isinstance(sig, dict) else ''}, expected an object of "
                                         f"signal name -> list of values; {_EXPECTED}")
    if isinstance(t, int) and not isinstance(t, bool):  # a single sample: scalars
        t = [t]
        if any(isinstance(v, list) for v in sig.values()):
            raise PayloadError("bad_schema", f"{where}: scalar \"t_ns\" with list signals; {_EXPECTED}")
        sig = {k: [v] for k, v in sig.items()}
    if not isinstance(t, list):
        raise PayloadError("bad_time" if isinstance(t, (float, bool, str)) else "bad_schema",
                           f"{where}: \"t_ns\" is {t!r:.40}, expected an integer or a list of integers (ns)")
    if len(t) > max_block:
        raise PayloadError("oversized", f"{where}: {len(t)} samples in one payload, at most {max_block} accepted")
    t_ns = _times(where, t) if t else np.zeros(0, np.int64)
    cols: dict[str, np.ndarray] = {}
    bad = np.zeros(len(t_ns), dtype=bool)
    for k, v in sig.items():
        if not isinstance(v, list) or len(v) != len(t_ns):
            raise PayloadError("bad_schema", f"{where}: signal {k!r} is "
                                             + (f"a list of {len(v)}" if isinstance(v, list) else type(v).__name__)
                                             + f", expected a list as long as t_ns ({len(t_ns)})")
        none = [x is None for x in v]
        arr = np.array([math.nan if n else x for n, x in zip(none, v)])
        if arr.size and arr.dtype.kind not in "fi":
            i = next(j for j, x in enumerate(v) if x is not None and (type(x) not in (int, float)))
            raise PayloadError("bad_schema", f"{where}: signal {k!r}[{i}] = {v[i]!r:.40} is not a number; "
                                             "expected numbers or null")
        arr = arr.astype(np.float64)
        bad |= ~np.isfinite(arr) & ~np.array(none, dtype=bool)
        cols[k] = arr
    return Samples(t_ns, cols), bad


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
    """Frames of an ``fpdd.can/1`` payload; :class:`PayloadError` (``bad_payload``) if malformed."""
    if len(payload) < 8 or payload[:4] != CAN_MAGIC:
        raise PayloadError("bad_payload", f"{where}: not an fpdd.can payload (expected header {CAN_MAGIC!r})")
    ver, size = np.frombuffer(payload[4:8], "<u2")
    if ver != CAN_VERSION or size != CAN_RECORD.itemsize or (len(payload) - 8) % size:
        raise PayloadError("bad_payload", f"{where}: fpdd.can version {ver}, record size {size}, "
                                          f"{len(payload) - 8} bytes of records; expected version {CAN_VERSION}, "
                                          f"records of {CAN_RECORD.itemsize} bytes")
    rec = np.frombuffer(payload[8:], CAN_RECORD)
    if (rec["dlc"] > 8).any() or (rec["kind"] > 3).any():
        raise PayloadError("bad_payload", f"{where}: fpdd.can record with DLC > 8 or unknown kind")
    return Frames(rec["t_ns"], rec["key"], rec["dlc"], rec["data"], rec["kind"])


# --- what live sources share: drop counting, rate-limited logging, staleness ---------------------

class _Live:
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


# --- live CAN bus ------------------------------------------------------------------------------


# --- Zenoh -------------------------------------------------------------------------------------

class _ZenohPublisher(Sink):
    def __init__(self, key: str, config: zenoh.Config | None, encoding: zenoh.Encoding,
                 session: zenoh.Session | None) -> None:
        self.key = parse_zenoh_uri(key) if key.startswith("zenoh://") else key
        self._owned = session is None
        self.session = session if session is not None else _open_session(config, f"zenoh://{self.key}")
        try:  # BLOCK: a replay is lossless (zenoh's default, DROP, may drop even the end marker under load)
            self.publisher = self.session.declare_publisher(self.key, encoding=encoding,
                                                            congestion_control=zenoh.CongestionControl.BLOCK)
        except Exception as e:  # ZError: an invalid key expression
            if self._owned:
                self.session.close()
            raise SourceError(f"zenoh://{self.key}: cannot publish: {e}") from e
        self._matched = threading.Event()
        self._listener = self.publisher.declare_matching_listener(self._on_matching)
        if self.publisher.matching_status.matching:  # type: ignore[attr-defined]  # a MatchingStatus, not the stub's bool
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
        for part in split_block(samples, self.max_block):
            self._put(samples_to_json(part))

    def _send_end(self) -> None:
        if self.end_marker:
            self._put(json.dumps({"format": SAMPLES_FORMAT, "end": True}).encode())


class ZenohCanSink(_ZenohPublisher):
    """Publishes raw CAN frames (``fpdd.can/1``) on a key, e.g. ``fpdd/msp25/can``.

    ``write(samples)`` encodes samples into the rig's frames with the DBC (like
    :class:`~replay.can.logs.CanLogSink`); ``write_frames(frames)`` forwards frames as they
    are (a bus or a log bridged to Zenoh).
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

    def _send_end(self) -> None:
        if self.end_marker:
            self._put(frames_to_payload(Frames.empty()))


class ZenohSource(_Live, Source):
    """Rig samples received on a Zenoh key expression (either payload of the module docstring).

    The subscriber is declared in the constructor, so a publisher started afterwards
    is not missed (Zenoh does not replay what was published before a subscriber joined).
    The stream ends at the sender's end marker or on :meth:`close`; a quiet key only
    makes the source stale (module docstring).  Every payload is validated; what
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
        self._first: list[tuple[str, object]] = []  # payloads received while finding `signals`
        self._kind: str | None = None
        self._stream: CanStream | None = None
        self._ended = False
        self._n = 0  # payloads received (numbers them in messages)
        self._gate = QualityGate(self.report, dataclasses.replace(quality or QualityOptions(), keep_nan=True,
                                                                  systematic="drop"))
        self._owned = session is None
        self.session = session if session is not None else _open_session(config, self.path)
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
            try:
                self._queue.put_nowait((n, sample.payload.to_bytes()))
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
                if time.monotonic() >= deadline:
                    return None
                continue
            if got is None:  # close() wakes the consumer
                return None
            item = self._parse(*got)
            if item is not None:
                return item
        return None

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
