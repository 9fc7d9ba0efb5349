"""MCAP files (the ``mcap`` library): rig samples and the twin's own messages.

Channel layout (written by :class:`McapSink`, plotted by Foxglove as is)
=========================================================================

Every channel has ``message_encoding = "json"`` and a ``jsonschema`` schema.  Message
``log_time`` and ``publish_time`` are the sample time in integer nanoseconds (the time
convention of :mod:`replay.base`).

``/rig/signals`` -- schema ``fpdd.RigSignals``, one message per sample::

    {"t": 12.345, "timestamp": {"sec": 12, "nsec": 345000000},
     "x_ref": 0.01, "u": 0.2, "x": 0.0099, "pA": 2.1e6, "pB": 1.9e6}

  ``t`` is the sample time in seconds (``log_time / 1e9``, for plotting only: readers
  take the exact time from ``log_time``), ``timestamp`` the same time exactly as the
  Foxglove ``time`` type (:data:`TIME_SCHEMA`), every other field a signal in its SI unit
  (:data:`fpdd.units.SIGNALS`; a non-finite value is written as ``null``).  Foxglove
  plots ``/rig/signals.x`` directly.  The channel metadata ``signals`` and ``units``
  list the fields in order (comma separated).

``/rig/signals_block`` -- schema ``fpdd.RigSignalsBlock``, one message per block of
samples (at most one flush period, 1 s by default), the same samples as
``/rig/signals`` in compact form for fast reading::

    {"t0": 12.345, "timestamp": {"sec": 12, "nsec": 345000000}, "n": 1000,
     "t_ns": "<base64 of n little-endian int64: sample times, ns>",
     "signals": {"x_ref": "<base64 of n little-endian float64, SI unit>", ...}}

  ``log_time`` is the time of the block's first sample, ``t0`` the same in seconds.
  The schema marks the arrays ``contentEncoding: base64`` and
  ``contentMediaType: application/octet-stream``; staying JSON keeps the file valid for
  every MCAP tool (Foxglove shows the block topic as raw messages).

Each flush writes the block message into its own chunk, then the per-sample messages of
the same samples into the next chunk, so that reading ``/rig/signals_block`` through
the chunk index touches only the small block chunks.

``/twin/estimate``, ``/twin/alarm``, ``/twin/status`` and any other topic:
:meth:`McapSink.write_message` -- a JSON object per message, with a schema registered
on first use (given, or derived from the first payload's fields).  Every message gets
``"timestamp": {"sec": .., "nsec": ..}`` (its ``log_time``; the Foxglove time type,
exact where a JSON reader holds numbers as doubles: ``t_ns`` above 2**53 is not), and
every schema declares it.

A metadata record ``fpdd.layout`` holds ``version``, ``signals_topic``,
``block_topic`` and ``block_max_span_ns`` (the longest block, which a time-range read
needs to know).  It is written with the first samples, so a file of other topics only
(a twin output) has none: it never names a topic the file does not contain.

Why the block topic (measured with ``python -m benchmarks.replay``, 2 cores, mcap 1.6): the
naive path -- ``mcap``'s reader plus one ``json.loads`` per message -- reads about
80 000 samples/s, i.e. 45 s for a one-hour 1 kHz record (3.6 M samples); batching the
``json.loads`` helps only 1.4x.  The block topic reads the same hour in 1.7 s
(2.1 M samples/s, 26x).  Writing both topics runs at about 137 000 samples/s (26 s for
the hour): formatting JSON floats with ``repr`` is half of it, ``mcap``'s
``add_message`` the rest.

Reading
=======

CRC validation is always on: a corrupt chunk is detected, never silently used.  A
damaged chunk costs only itself:

* With a readable summary the reader seeks through the chunk index (by topic and time
  range) and reads every chunk on its own; a chunk that fails (CRC, decompression,
  framing) is counted under ``damaged_chunk``, named by number, byte range and time
  span with the count of messages lost (from its message index), and the chunks after
  it are read.  A lost ``/rig/signals_block`` chunk is filled from the per-sample
  ``/rig/signals`` messages of the same time span when the file has them (they sit in
  another chunk); what cannot be recovered is added to ``report.samples_lost``.
* Without a summary (a killed writer, a truncated copy) the records are walked in
  file order; after a damaged record the walk resynchronises at the next chunk whose
  CRC checks.  A file cut short sets ``report.truncated`` and says how much was kept.

The block topic is read when the file has it, else ``/rig/signals``.

Writing
=======

Samples are buffered and flushed (chunk finished, file flushed) every
``flush_period_s`` of sample time (1 s) or ``flush_messages`` messages, whichever
comes first, so a killed writer loses at most the last second; a chunk therefore holds
about one second of data (messages of :meth:`McapSink.write_message` too: a twin
output of 600 messages over 12 s has about a dozen chunks, not one per message).
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import heapq
import io
import json
import math
import mmap
import os
import struct
import zlib
from typing import IO, Any
from collections.abc import Iterator, Mapping, Sequence

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, MessageIndex, Schema
from mcap.stream_reader import breakup_chunk
from mcap.summary import Summary
from mcap.writer import CompressionType, Writer

from fpdd import jsonio
from fpdd.units import SIGNALS
from replay.base import Problem, ReadReport, Samples, Sink, Source
from replay.quality import QualityGate, QualityOptions, require_signals
from fpdd.errors import DataError, LogFormatError, SourceError

SIGNALS_TOPIC = "/rig/signals"
SIGNALS_SCHEMA = "fpdd.RigSignals"
BLOCK_TOPIC = "/rig/signals_block"
BLOCK_SCHEMA = "fpdd.RigSignalsBlock"
LAYOUT_METADATA = "fpdd.layout"
LAYOUT_VERSION = "1"

MCAP_MAGIC = b"\x89MCAP0\r\n"

#: Fields of a JSON message that carry its time, not a signal.
_TIME_FIELDS = frozenset({"t", "t_ns", "timestamp"})

#: Errors a damaged file raises inside ``mcap`` (CRC mismatch is a ValueError there).
_DAMAGE = (McapError, ValueError, struct.error, EOFError, zstandard.ZstdError)
_RECORD_SIZE_LIMIT = 1 << 30  # 1 GiB: a damaged length field must not allocate more
_INT64_MAX = (1 << 63) - 1


# --- schemas -------------------------------------------------------------------------------

def signals_schema(signals: Sequence[str]) -> dict:
    """JSON Schema of ``/rig/signals`` for these signals."""
    props: dict[str, Any] = {"t": {"type": "number", "description": "sample time, s (log_time / 1e9)"},
                             "timestamp": TIME_SCHEMA}
    for name in signals:
        spec = SIGNALS.get(name)
        desc = f"{spec.meaning}, {spec.unit}" if spec else "extra signal, SI unit"
        props[name] = {"type": ["number", "null"], "description": desc}
    return {"title": SIGNALS_SCHEMA, "type": "object", "properties": props,
            "required": ["t", "timestamp", *signals]}


def block_schema(signals: Sequence[str]) -> dict:
    """JSON Schema of ``/rig/signals_block`` for these signals."""
    arr = {"type": "string", "contentEncoding": "base64", "contentMediaType": "application/octet-stream"}
    return {
        "title": BLOCK_SCHEMA,
        "type": "object",
        "description": "a block of samples: little-endian int64 times (ns) and float64 signals (SI)",
        "properties": {
            "t0": {"type": "number", "description": "time of the first sample, s"},
            "timestamp": TIME_SCHEMA,
            "n": {"type": "integer", "description": "number of samples"},
            "t_ns": {**arr, "description": "n little-endian int64 sample times, ns"},
            "signals": {"type": "object", "properties": {
                name: {**arr, "description": f"n little-endian float64, "
                                             f"{SIGNALS[name].unit if name in SIGNALS else 'SI unit'}"}
                for name in signals}},
        },
        "required": ["t0", "timestamp", "n", "t_ns", "signals"],
    }


#: The Foxglove ``time`` type: a message's time as whole seconds and nanoseconds (exact in
#: every JSON reader; an int64 ``t_ns`` above 2**53 is not exact in JavaScript).
TIME_SCHEMA: dict[str, Any] = {
    "title": "time", "type": "object", "description": "message time (log_time), Foxglove time type",
    "properties": {"sec": {"type": "integer", "description": "whole seconds (UNIX epoch or record start)"},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999,
                            "description": "nanoseconds within the second"}},
    "required": ["sec", "nsec"],
}
TIME_FIELD = "timestamp"


def foxglove_time(t_ns: int) -> dict[str, int]:
    """``{"sec": ..., "nsec": ...}`` of integer nanoseconds (``nsec`` in [0, 1e9))."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def with_time_schema(schema: Mapping[str, Any]) -> dict:
    """``schema`` with the :data:`TIME_FIELD` property (Foxglove time) added and required."""
    out = dict(schema)
    props = dict(out.get("properties", {}))
    props.setdefault(TIME_FIELD, TIME_SCHEMA)
    out["properties"] = props
    req = list(out.get("required", []))
    if TIME_FIELD not in req:
        req.append(TIME_FIELD)
    out["required"] = req
    return out


def _generic_schema(title: str, payload: Mapping[str, Any]) -> dict:
    def kind(v: Any) -> str:
        if isinstance(v, bool):
            return "boolean"
        if isinstance(v, (int, float, np.number)):
            return "number"
        if isinstance(v, str):
            return "string"
        if isinstance(v, Mapping):
            return "object"
        return "array"
    return {"title": title, "type": "object",
            "properties": {k: {"type": [kind(v), "null"]} for k, v in payload.items() if k != TIME_FIELD}}


def encode_json(payload: Mapping[str, Any]) -> bytes:
    """Compact JSON bytes; non-finite numbers become ``null`` (:func:`fpdd.jsonio.compact`)."""
    return jsonio.compact(payload)


# --- writing ------------------------------------------------------------------------------

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapSink(Sink):
    """Write rig samples (and other JSON topics) to an MCAP file in the layout above.

    ``signals``: the signal fields, in order (default: those of the first block).
    ``per_sample``: write ``/rig/signals`` (one message per sample, for Foxglove).
    ``block``: write ``/rig/signals_block`` (fast reading).  ``flush_period_s`` (s of
    sample time) and ``flush_messages``: flush at whichever comes first.
    ``compression``: ``"zstd"``, ``"lz4"`` or ``"none"``.  ``metadata``: written as a
    metadata record ``fpdd.record``.
    """

    def __init__(self, path: str | os.PathLike, signals: Sequence[str] | None = None, *,
                 per_sample: bool = True, block: bool = True, flush_period_s: float = 1.0,
                 flush_messages: int = 10_000, compression: str = "zstd",
                 metadata: Mapping[str, str] | None = None) -> None:
        if not flush_period_s > 0:
            raise ValueError(f"flush_period_s (={flush_period_s}) must be > 0 s")
        if flush_messages < 1:
            raise ValueError(f"flush_messages (={flush_messages}) must be >= 1")
        if not (per_sample or block):
            raise ValueError("per_sample and block are both off: nothing would be written")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression {compression!r} unknown, expected one of {sorted(_COMPRESSION)}")
        self.path = str(path)
        self._signals: tuple[str, ...] | None = tuple(signals) if signals is not None else None
        self._per_sample = per_sample
        self._block = block
        self._period_ns = int(round(flush_period_s * 1e9))
        self._flush_messages = flush_messages
        try:
            self._file: IO[bytes] = open(self.path, "wb")
        except OSError as exc:
            raise SourceError(f"{self.path}: cannot create MCAP file: {exc.strerror or exc}") from exc
        # chunks end only when this sink flushes: the size limit is a backstop
        self._writer = Writer(self._file, chunk_size=64 << 20, compression=_COMPRESSION[compression])
        self._writer.start(profile="", library="fpdd-twin replay.mcapio")
        if metadata:
            self._writer.add_metadata("fpdd.record", {str(k): str(v) for k, v in metadata.items()})
        self._channels: dict[str, int] = {}
        self._pending: list[Samples] = []
        self._pending_n = 0
        self._block_start_ns = 0  # time of the first buffered sample, ns
        self._last_flush_ns: int | None = None
        self._latest_ns: int | None = None  # latest message time written
        self._layout_written = False
        self._unflushed = 0  # messages since the last flush
        self._closed = False

    # -- channels ------------------------------------------------------------------------------

    def _channel(self, topic: str, schema: Mapping[str, Any], metadata: Mapping[str, str] | None = None) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._writer.register_schema(str(schema.get("title", topic)), "jsonschema",
                                               json.dumps(schema).encode())
            cid = self._writer.register_channel(topic, "json", sid, dict(metadata or {}))
            self._channels[topic] = cid
        return cid

    def _sample_channels(self) -> tuple[int | None, int | None]:
        assert self._signals is not None
        if not self._layout_written:  # only when the sample topics exist: it names them
            self._layout_written = True
            self._writer.add_metadata(LAYOUT_METADATA, {
                "version": LAYOUT_VERSION, "signals_topic": SIGNALS_TOPIC if self._per_sample else "",
                "block_topic": BLOCK_TOPIC if self._block else "", "block_max_span_ns": str(self._period_ns)})
        meta = {"signals": ",".join(self._signals),
                "units": ",".join(SIGNALS[s].unit if s in SIGNALS else "" for s in self._signals)}
        block = self._channel(BLOCK_TOPIC, block_schema(self._signals), meta) if self._block else None
        per = self._channel(SIGNALS_TOPIC, signals_schema(self._signals), meta) if self._per_sample else None
        return block, per

    # -- Sink ----------------------------------------------------------------------------------

    def write(self, samples: Samples) -> None:
        """Buffer a block of samples (time ordered); flush every period of sample time."""
        if self._closed:
            raise SourceError(f"{self.path}: write after close")
        if self._signals is None:
            self._signals = samples.names
            self._sample_channels()
        missing = [s for s in self._signals if s not in samples.signals]
        if missing:
            raise DataError(f"{self.path}: block to write lacks signal(s) {missing}; "
                            f"the record's signals are {list(self._signals)}")
        if not len(samples):
            return
        if not self._pending:
            self._block_start_ns = int(samples.t_ns[0])
            if self._last_flush_ns is None:
                self._last_flush_ns = self._block_start_ns
        self._pending.append(samples)
        self._pending_n += len(samples)
        if int(samples.t_ns[-1]) - self._block_start_ns < self._period_ns \
                and self._pending_n + self._unflushed < self._flush_messages:
            self._pending[-1] = samples.slice(0, len(samples))  # a copy: the caller may reuse its arrays
            return
        buf = Samples.concat(self._pending) if len(self._pending) > 1 else self._pending[0]
        self._pending, self._pending_n = [], 0
        i, n = 0, len(buf)
        while i < n:
            end = int(np.searchsorted(buf.t_ns[i:], int(buf.t_ns[i]) + self._period_ns, side="left"))
            room = self._flush_messages - self._unflushed
            if end >= n - i and n - i < room:  # an incomplete period stays buffered
                rest = buf.slice(i, n)
                self._pending, self._pending_n = [rest], n - i
                self._block_start_ns = int(rest.t_ns[0])
                break
            cut = max(1, min(end, room))
            self._emit(buf.slice(i, i + cut))
            self.flush()
            i += cut

    def write_message(self, topic: str, t_ns: int, payload: Mapping[str, Any], *,
                      schema: Mapping[str, Any] | None = None) -> None:
        """Write one JSON message on ``topic`` at ``t_ns`` (ns).

        The schema is registered on first use of the topic: ``schema`` (a JSON Schema
        dict) or one derived from the payload's fields, titled ``fpdd`` + topic with
        dots (``/twin/alarm`` -> ``fpdd.twin.alarm``).
        """
        if self._closed:
            raise SourceError(f"{self.path}: write after close")
        if topic in (SIGNALS_TOPIC, BLOCK_TOPIC):
            raise DataError(f"{self.path}: topic {topic!r} is written by write(), not write_message()")
        if topic not in self._channels:
            title = "fpdd" + topic.replace("/", ".")
            self._channel(topic, with_time_schema(schema or _generic_schema(title, payload)))
        t_ns = int(t_ns)
        if TIME_FIELD not in payload:
            payload = {**payload, TIME_FIELD: foxglove_time(t_ns)}
        self._writer.add_message(self._channels[topic], t_ns, encode_json(payload), t_ns)
        self._unflushed += 1
        self._latest_ns = t_ns if self._latest_ns is None else max(self._latest_ns, t_ns)
        if self._last_flush_ns is None:
            self._last_flush_ns = t_ns
        if self._unflushed >= self._flush_messages or t_ns - self._last_flush_ns >= self._period_ns:
            self.flush()

    def flush(self) -> None:
        """Write everything buffered, finish the chunk and flush the file."""
        if self._pending:
            buf = Samples.concat(self._pending)
            self._pending, self._pending_n = [], 0
            self._emit(buf)
        self._writer.flush()
        self._unflushed = 0
        if self._latest_ns is not None:
            self._last_flush_ns = self._latest_ns

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            if self._signals is not None and not self._channels:
                self._sample_channels()
            self.flush()
            self._writer.finish()
        finally:
            self._file.close()

    # -- encoding --------------------------------------------------------------------------------

    def _emit(self, block: Samples) -> None:
        """Write one block: the block message (own chunk), then one message per sample."""
        assert self._signals is not None
        block_ch, per_ch = self._sample_channels()
        t_ns = block.t_ns
        t0 = int(t_ns[0])
        if block_ch is not None:
            msg = {"t0": t0 * 1e-9, TIME_FIELD: foxglove_time(t0), "n": len(block),
                   "t_ns": base64.b64encode(t_ns.astype("<i8").tobytes()).decode(),
                   "signals": {k: base64.b64encode(block.signals[k].astype("<f8").tobytes()).decode()
                               for k in self._signals}}
            self._writer.add_message(block_ch, t0, json.dumps(msg, separators=(",", ":")).encode(), t0)
            if per_ch is not None:
                self._writer.flush()
        if per_ch is not None:
            add = self._writer.add_message
            for t, data in zip(t_ns.tolist(), _json_rows(t_ns, [block.signals[k] for k in self._signals],
                                                          self._signals)):
                add(per_ch, t, data, t)
        self._unflushed += len(block)
        self._last_flush_ns = int(t_ns[-1])
        self._latest_ns = self._last_flush_ns if self._latest_ns is None else max(self._latest_ns, self._last_flush_ns)


def _json_rows(t_ns: np.ndarray, cols: list[np.ndarray], names: Sequence[str]) -> list[bytes]:
    """One compact JSON object per sample, floats in shortest round-trip form."""
    fmt = '{"t":%s,"timestamp":{"sec":%d,"nsec":%d}' + "".join(f',"{k}":%s' for k in names) + "}"
    sec, nsec = np.divmod(t_ns, 1_000_000_000)
    strs = [list(map(repr, (t_ns * 1e-9).tolist())), sec.tolist(), nsec.tolist()]
    for c in cols:
        s = list(map(repr, c.tolist()))
        bad = np.flatnonzero(~np.isfinite(c))
        for i in bad.tolist():
            s[i] = "null"
        strs.append(s)
    return [(fmt % row).encode() for row in zip(*strs)]


# --- reading ------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class TopicInfo:
    """One channel of an MCAP file."""

    topic: str
    schema: str
    encoding: str
    messages: int | None  # None when the summary is unreadable and the topic was not counted
    signals: tuple[str, ...]
    t_first_ns: int | None = None  # first and last log time, when the messages were scanned
    t_last_ns: int | None = None


@dataclasses.dataclass(frozen=True)
class McapMessage:
    """A decoded JSON message: topic, log time (ns) and payload."""

    topic: str
    t_ns: int
    data: Any


class _ChunkRef:
    """What reading one chunk needs of its index record (made from a :class:`_ChunkTable` row when read)."""

    __slots__ = ("chunk_start_offset", "chunk_length", "message_start_time", "message_end_time",
                 "message_index_offsets")

    def __init__(self, offset: int, length: int, t0: int, t1: int, index_offsets: dict[int, int]) -> None:
        self.chunk_start_offset = offset
        self.chunk_length = length
        self.message_start_time = t0
        self.message_end_time = t1
        self.message_index_offsets = index_offsets


class _ChunkTable:
    """A file's chunk index in arrays: a replayed log keeps it for as long as it is read, and a long one has
    many chunks (a day at 1 kHz: ~10^5); as ``mcap`` records they cost ~650 B each, here ~110 B
    (``tests/test_memory.py``). Iterating yields :class:`_ChunkRef` rows in file-index order."""

    def __init__(self, cis: Sequence[Any]) -> None:
        self.offset = np.array([c.chunk_start_offset for c in cis], dtype=np.int64)
        self.length = np.array([c.chunk_length for c in cis], dtype=np.int64)
        self.t0 = np.array([c.message_start_time for c in cis], dtype=np.uint64)
        self.t1 = np.array([c.message_end_time for c in cis], dtype=np.uint64)
        counts = [len(c.message_index_offsets) for c in cis]
        self._bounds = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)
        self._cid = np.array([k for c in cis for k in c.message_index_offsets], dtype=np.int64)
        self._ioff = np.array([v for c in cis for v in c.message_index_offsets.values()], dtype=np.int64)

    def __len__(self) -> int:
        return len(self.offset)

    def __bool__(self) -> bool:
        return len(self.offset) > 0

    def __getitem__(self, k: int) -> _ChunkRef:
        a, b = int(self._bounds[k]), int(self._bounds[k + 1])
        return _ChunkRef(int(self.offset[k]), int(self.length[k]), int(self.t0[k]), int(self.t1[k]),
                         {int(c): int(o) for c, o in zip(self._cid[a:b], self._ioff[a:b])})

    def __iter__(self) -> Iterator[_ChunkRef]:
        return (self[k] for k in range(len(self)))

    def channels(self, k: int) -> set[int]:
        return {int(c) for c in self._cid[int(self._bounds[k]):int(self._bounds[k + 1])]}


@dataclasses.dataclass(frozen=True)
class _Lost:
    """A chunk (or stretch of records) that could not be read, in the message stream."""

    t_start: int | None  # first log time the chunk index declares, ns (None: unknown)
    t_end: int | None
    messages: int | None  # messages of the wanted channels in it (from the message index), None: unknown


_OPCODES = frozenset(int(o) for o in Opcode)


class McapSource(Source):
    """Read rig samples from an MCAP file (layout in the module docstring).

    ``topic``: the samples topic (default: ``/rig/signals_block`` when present, else
    ``/rig/signals``; a per-sample JSON topic of another writer works too: its fields
    are the signals, its ``log_time`` the sample time).  ``start_ns``/``end_ns``:
    half-open time range ``[start_ns, end_ns)`` in ns.  ``signals``: keep only these.
    ``required``: signals that must be present.  ``quality``: gate options.
    ``any_topic``: open a file without a samples topic too (e.g. a twin output, for
    :meth:`topics` and :meth:`messages`); :meth:`chunks` then yields nothing.
    """

    def __init__(self, path: str | os.PathLike, *, topic: str | None = None,
                 start_ns: int | None = None, end_ns: int | None = None,
                 signals: Sequence[str] | None = None, required: Sequence[str] = (),
                 quality: QualityOptions | None = None, any_topic: bool = False) -> None:
        self.path = str(path)
        self.report = ReadReport(self.path)
        self._start_ns = start_ns
        self._end_ns = end_ns
        self._any_topic = any_topic
        options = quality or QualityOptions()
        if required:
            options = dataclasses.replace(options, required=tuple(required))
        try:
            self._file: IO[bytes] = open(self.path, "rb")
            self._size = os.fstat(self._file.fileno()).st_size
        except IsADirectoryError:
            raise SourceError(f"{self.path}: cannot open MCAP file: is a directory, expected a file") from None
        except OSError as exc:
            raise SourceError(f"{self.path}: cannot open MCAP file: {exc.strerror or exc}") from exc
        try:
            self._open(topic, signals, options)
        except Exception:
            self._file.close()
            raise

    def _open(self, topic: str | None, signals: Sequence[str] | None, options: QualityOptions) -> None:
        magic = self._file.read(len(MCAP_MAGIC))
        if magic != MCAP_MAGIC:
            if not magic:
                raise LogFormatError(f"{self.path}: empty file (0 bytes), expected an MCAP file")
            raise LogFormatError(f"{self.path}: not an MCAP file: starts with {magic!r}, "
                                 f"expected the MCAP magic {MCAP_MAGIC!r}")
        if self._size <= len(MCAP_MAGIC):
            raise LogFormatError(f"{self.path}: MCAP file of {self._size} bytes ends right after its magic: no "
                                 "header and no records; the writer was killed at once or the file was cut")
        self._summary: Summary | None = None
        self._reader: SeekingReader | None = None
        try:
            reader = SeekingReader(self._rewound(), validate_crcs=True, record_size_limit=_RECORD_SIZE_LIMIT)
            self._summary = reader.get_summary()
            if self._summary is not None:
                self._check_summary_crc()
                self._summary.chunk_indexes = _ChunkTable(self._summary.chunk_indexes)  # type: ignore[assignment]
        except (*_DAMAGE, OSError) as exc:
            self.report.problems.append(Problem(
                self.path, "footer and summary", f"unreadable ({type(exc).__name__}: "
                f"{exc or 'file ends early'}): writer killed or file cut; reading the file as a stream"))
            self._summary = None
        else:
            self._reader = reader
        self._seek = self._summary is not None and bool(self._summary.chunk_indexes)
        self._schemas, self._channels_by_id = self._scan_channels()
        self._block_span_ns = self._layout_span()
        self._by_topic = {c.topic: c for c in self._channels_by_id.values()}
        if topic is None:
            topic = BLOCK_TOPIC if BLOCK_TOPIC in self._by_topic else SIGNALS_TOPIC
        self._gate = QualityGate(self.report, options)
        self._done = False
        self._channel: Channel | None = None
        self._is_block = False
        self._signals: tuple[str, ...] = ()
        if topic not in self._by_topic:
            if self._any_topic:
                return
            raise LogFormatError(f"{self.path}: no topic {topic!r} with rig samples; the file has "
                                 f"{', '.join(sorted(self._by_topic)) or 'no channels'}")
        self._channel = self._by_topic[topic]
        schema = self._schemas.get(self._channel.schema_id)
        self._is_block = schema is not None and schema.name == BLOCK_SCHEMA
        if self._channel.message_encoding != "json":
            raise LogFormatError(f"{self.path}: topic {topic!r} is encoded as "
                                 f"{self._channel.message_encoding!r}, expected 'json'")
        have = self._channel_signals(self._channel, schema)
        if signals is not None:
            missing = [s for s in signals if s not in have]
            require_signals(self.path, have, missing)
            have = tuple(signals)
        require_signals(self.path, have, options.required)
        self._signals = have

    def _check_summary_crc(self) -> None:
        """The footer's CRC of the summary section (``mcap`` does not check it); McapError if it differs."""
        f = self._file
        footer = self._size - len(MCAP_MAGIC) - 29  # opcode, length, summary_start, summary_offset_start, crc
        f.seek(footer)
        rec = f.read(29)
        if len(rec) < 29 or rec[0] != Opcode.FOOTER:
            return
        summary_start = int.from_bytes(rec[9:17], "little")
        crc = int.from_bytes(rec[25:29], "little")
        if not crc or not 0 < summary_start <= footer:
            return
        f.seek(summary_start)
        body = f.read(footer - summary_start) + rec[:25]
        if zlib.crc32(body) != crc:
            raise McapError(f"summary CRC mismatch (footer says 0x{crc:08x}, the {len(body)} summary bytes give "
                            f"0x{zlib.crc32(body):08x})")

    def _rewound(self) -> IO[bytes]:
        self._file.seek(0)
        return self._file

    # -- channels --------------------------------------------------------------------------------

    def _scan_channels(self) -> tuple[dict[int, Schema], dict[int, Channel]]:
        """Schemas and channels from the summary, or from the records (up to the first samples)."""
        if self._summary is not None and self._summary.channels:
            return dict(self._summary.schemas), dict(self._summary.channels)
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        for record in self._walk(ReadReport(self.path)):
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message) and {c.topic for c in channels.values()} & {SIGNALS_TOPIC, BLOCK_TOPIC}:
                break
        return schemas, channels

    def _layout_span(self) -> int:
        """Longest block in ns, from the ``fpdd.layout`` metadata (default 60 s)."""
        default = 60_000_000_000
        if self._reader is None or self._summary is None:
            return default
        try:
            for meta in self._reader.iter_metadata():
                if meta.name == LAYOUT_METADATA:
                    return int(meta.metadata.get("block_max_span_ns", default))
        except (*_DAMAGE, KeyError):
            return default
        return default

    def _channel_signals(self, channel: Channel, schema: Schema | None) -> tuple[str, ...]:
        listed = channel.metadata.get("signals")
        if listed:
            return tuple(s for s in listed.split(",") if s)
        if schema is not None and schema.encoding == "jsonschema":
            try:
                props = json.loads(schema.data).get("properties", {})
            except ValueError:
                props = {}
            names = tuple(k for k in props if k not in _TIME_FIELDS)
            if names:
                return names
        for msg in self.messages([channel.topic]):
            if isinstance(msg.data, dict):
                return tuple(k for k in msg.data if k not in _TIME_FIELDS)
            break
        raise LogFormatError(f"{self.path}: topic {channel.topic!r}: cannot tell its signals "
                             "(no 'signals' channel metadata, no JSON Schema properties, no message)")

    def topics(self, scan: bool = False) -> list[TopicInfo]:
        """Every channel of the file with its message count.

        Counts come from the summary; with ``scan`` (or when the summary is gone) every
        message is read, which also gives each topic's first and last log time.
        """
        counts: dict[int, int] = {}
        spans: dict[int, list[int]] = {}
        if scan or self._summary is None or self._summary.statistics is None:
            probe = ReadReport(self.path)
            for channel, msg in self._messages(None, None, None, probe):
                if channel is None:
                    continue
                counts[channel.id] = counts.get(channel.id, 0) + 1
                span = spans.setdefault(channel.id, [msg.log_time, msg.log_time])
                span[0], span[1] = min(span[0], msg.log_time), max(span[1], msg.log_time)
            for p in probe.problems:
                if len(self.report.problems) < self.report.max_problems:
                    self.report.problems.append(p)
            for k, v in probe.skipped.items():
                self.report.skipped[k] += v
            self.report.truncated = self.report.truncated or probe.truncated  # a cut file says so here too
        else:
            counts = dict(self._summary.statistics.channel_message_counts)
        out = []
        for cid, ch in sorted(self._channels_by_id.items()):
            schema = self._schemas.get(ch.schema_id)
            sig = ch.metadata.get("signals", "")
            first_last: Sequence[int | None] = spans.get(cid, (None, None))
            out.append(TopicInfo(ch.topic, schema.name if schema else "", ch.message_encoding,
                                 counts.get(cid, 0), tuple(s for s in sig.split(",") if s),
                                 first_last[0], first_last[1]))
        return out

    def describe(self) -> dict:
        """Format-specific facts for ``replay info``: topics, schemas, message counts."""
        return {"format": "mcap", "samples_topic": self._channel.topic if self._channel else None,
                "summary": self._summary is not None,
                "topics": [dataclasses.asdict(t) for t in self.topics()]}

    # -- Source ----------------------------------------------------------------------------------

    @property
    def signals(self) -> tuple[str, ...]:
        return self._signals

    def close(self) -> None:
        self._file.close()

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Blocks of at most ``size`` samples; the samples are read once (a second call yields none)."""
        if self._done or self._channel is None:
            return
        self._done = True
        start, end = self._start_ns, self._end_ns
        query_start = start
        if self._is_block and start is not None:
            query_start = start - self._block_span_ns
        decode = self._decode_blocks if self._is_block else self._decode_rows
        pending: list[Samples] = []
        pending_n = 0
        for block, labels in decode(self._messages([self._channel.topic], query_start, end, self.report)):
            if start is not None or end is not None:
                inside = np.ones(len(block), dtype=bool)
                if start is not None:
                    inside &= block.t_ns >= start
                if end is not None:
                    inside &= block.t_ns < end
                if not inside.all():
                    block = Samples(block.t_ns[inside], {k: v[inside] for k, v in block.signals.items()})
                    labels = labels[inside]
            block = self._gate.apply(block, labels, "message")
            if not len(block):
                continue
            pending.append(block)
            pending_n += len(block)
            while pending_n >= size:
                buf = Samples.concat(pending)
                yield buf.slice(0, size)
                rest = buf.slice(size, len(buf))
                pending, pending_n = ([rest] if len(rest) else []), len(rest)
        if pending_n:
            yield Samples.concat(pending)

    def messages(self, topics: Sequence[str] | None = None, start_ns: int | None = None,
                 end_ns: int | None = None) -> Iterator[McapMessage]:
        """Decoded JSON messages of ``topics`` (all when None) in ``[start_ns, end_ns)``, time order.

        A message that is not valid JSON is skipped and counted under ``bad_message``;
        a damaged chunk under ``damaged_chunk`` (the chunks after it are read).
        """
        for channel, msg in self._messages(topics, start_ns, end_ns, self.report):
            if channel is None:
                continue
            try:
                data = json.loads(msg.data)
            except ValueError as exc:
                self.report.skip("bad_message", f"topic {channel.topic!r} message at {msg.log_time} ns",
                                 f"not valid JSON ({exc})")
                continue
            yield McapMessage(channel.topic, msg.log_time, data)

    # -- record iteration with recovery ------------------------------------------------------------

    def _messages(self, topics: Sequence[str] | None, start_ns: int | None, end_ns: int | None,
                  report: ReadReport) -> Iterator[tuple[Channel | None, Any]]:
        """(channel, message) pairs in log-time order; ``(None, _Lost)`` where a chunk is damaged.

        With a chunk index every chunk is read on its own (a damaged one costs only
        itself); without one the records are walked in file order and the walk
        resynchronises at the next intact chunk after damage.
        """
        wanted = None if topics is None else {cid for cid, c in self._channels_by_id.items() if c.topic in topics}
        if wanted is not None and not wanted:
            return
        if self._seek:
            yield from self._seek_messages(wanted, start_ns, end_ns, report)
            return
        channels: dict[int, Channel] = dict(self._channels_by_id)
        for record in self._walk(report, wanted=wanted):
            if isinstance(record, _Lost):
                yield None, record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                channel = channels.get(record.channel_id)
                if channel is None:
                    report.skip("bad_message", f"message at {record.log_time} ns",
                                f"channel id {record.channel_id} was never declared")
                    continue
                if wanted is not None and record.channel_id not in wanted:
                    continue
                if (start_ns is not None and record.log_time < start_ns) or \
                        (end_ns is not None and record.log_time >= end_ns):
                    continue
                yield channel, record

    def _seek_messages(self, wanted: set[int] | None, start_ns: int | None, end_ns: int | None,
                       report: ReadReport) -> Iterator[tuple[Channel | None, Any]]:
        assert self._summary is not None
        table = self._summary.chunk_indexes
        assert isinstance(table, _ChunkTable)  # made at open
        top = (1 << 64) - 1  # log times are unsigned 64-bit
        keep = np.ones(len(table), dtype=bool)
        if start_ns is not None:
            keep &= table.t1 >= min(max(int(start_ns), 0), top) if start_ns <= top else False
        if end_ns is not None:
            keep &= table.t0 < max(int(end_ns), 0) if end_ns <= top else True
        idxs = np.array([k for k in np.flatnonzero(keep)
                         if wanted is None or not (ch := table.channels(int(k))) or wanted & ch], dtype=np.int64)
        idxs = idxs[np.lexsort((table.offset[idxs], table.t0[idxs]))]
        rank = np.empty(len(table), dtype=np.int64)
        rank[np.argsort(table.offset, kind="stable")] = np.arange(len(table))
        channels = self._channels_by_id
        heap: list[tuple[int, int, int, Message]] = []
        seq = 0
        for k, ck in enumerate(idxs):
            ci = table[int(ck)]
            while heap and heap[0][0] < ci.message_start_time:
                item = heapq.heappop(heap)
                yield channels[item[3].channel_id], item[3]
            try:
                records = self._read_chunk(ci)
            except _DAMAGE as exc:
                yield None, self._lost_chunk(ci, int(rank[ck]), exc, wanted, report)
                continue
            msgs = [r for r in records if isinstance(r, Message)
                    and (wanted is None or r.channel_id in wanted) and r.channel_id in channels
                    and (start_ns is None or r.log_time >= start_ns) and (end_ns is None or r.log_time < end_ns)]
            if not msgs:
                continue
            msgs.sort(key=lambda m: m.log_time)
            nxt = int(table.t0[idxs[k + 1]]) if k + 1 < len(idxs) else None
            if not heap and (nxt is None or msgs[-1].log_time <= nxt):
                for m in msgs:
                    yield channels[m.channel_id], m
                continue
            for m in msgs:
                heapq.heappush(heap, (m.log_time, ci.chunk_start_offset, seq, m))
                seq += 1
        while heap:
            item = heapq.heappop(heap)
            yield channels[item[3].channel_id], item[3]

    def _read_chunk(self, ci) -> list:
        """The records of the chunk ``ci`` points at, CRC-checked; raises one of ``_DAMAGE``."""
        f = self._file
        f.seek(ci.chunk_start_offset)
        head = f.read(9)
        if len(head) < 9:
            raise EOFError(f"the file ends before the chunk at byte {ci.chunk_start_offset}")
        length = int.from_bytes(head[1:], "little")
        if head[0] != Opcode.CHUNK or length != ci.chunk_length - 9:
            raise McapError(f"no chunk record at byte {ci.chunk_start_offset} (opcode 0x{head[0]:02x}, "
                            f"length {length}; the index says a chunk of {ci.chunk_length - 9} bytes)")
        body = f.read(length)
        if len(body) < length:
            raise EOFError(f"the file ends inside the chunk at byte {ci.chunk_start_offset}")
        chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
        return breakup_chunk(chunk, validate_crc=True)

    def _count_indexed(self, ci, wanted: set[int] | None) -> int | None:
        """Messages of ``wanted`` channels in chunk ``ci``, from its message index records."""
        total = 0
        try:
            for cid, off in ci.message_index_offsets.items():
                if wanted is not None and cid not in wanted:
                    continue
                self._file.seek(off)
                head = self._file.read(9)
                if len(head) < 9 or head[0] != Opcode.MESSAGE_INDEX:
                    return None
                body = self._file.read(int.from_bytes(head[1:], "little"))
                total += len(MessageIndex.read(ReadDataStream(io.BytesIO(body))).records)
        except _DAMAGE:
            return None
        return total if ci.message_index_offsets else None

    def _lost_chunk(self, ci, number: int, exc: BaseException, wanted: set[int] | None,
                    report: ReadReport) -> _Lost:
        n = self._count_indexed(ci, wanted)
        names = sorted({self._channels_by_id[c].topic for c in ci.message_index_offsets
                        if c in self._channels_by_id and (wanted is None or c in wanted)})
        report.skip("damaged_chunk", f"chunk {number} at bytes {ci.chunk_start_offset}.."
                    f"{ci.chunk_start_offset + ci.chunk_length} (t={ci.message_start_time * 1e-9:.6f}.."
                    f"{ci.message_end_time * 1e-9:.6f} s)",
                    f"{type(exc).__name__}: {exc or 'damaged'}; "
                    + (f"its {n} message(s)" if n is not None else "its messages")
                    + (f" of {', '.join(names)}" if names else "") + " are lost, the chunks after it are read")
        return _Lost(ci.message_start_time, ci.message_end_time, n)

    def _walk(self, report: ReadReport, wanted: set[int] | None = None) -> Iterator[Any]:
        """Every record in file order (chunks broken up), without the index.

        A damaged record is reported (``damaged_chunk`` with its byte offset, a ``_Lost``
        marker in the stream) and the walk resynchronises at the next chunk whose CRC
        checks; a file cut short sets ``report.truncated`` after what was readable.
        """
        f = self._file
        size = self._size
        pos = len(MCAP_MAGIC)
        count = 0
        last_t: int | None = None
        while pos + 9 <= size:
            f.seek(pos)
            head = f.read(9)
            op, length = head[0], int.from_bytes(head[1:], "little")
            if op not in _OPCODES or length > _RECORD_SIZE_LIMIT:
                err: BaseException = McapError(f"no valid record at byte {pos} (opcode 0x{op:02x}, length {length})")
            elif pos + 9 + length > size:
                report.truncated = True
                report.skip("damaged_record", f"record at byte {pos} of {size}",
                            f"{Opcode(op).name if op in _OPCODES else op} record of {length} bytes is cut by the "
                            f"end of the file (writer killed or file cut); everything before it is kept: "
                            f"recovered {count} message(s)"
                            + (f", up to t = {last_t * 1e-9:.6f} s" if last_t is not None else ""))
                yield _Lost(None, None, None)
                return
            else:
                body = f.read(length)
                try:
                    records = self._parse_record(op, length, body)
                except _DAMAGE as exc:
                    err = exc
                else:
                    if records is None:
                        return  # data end / footer
                    for r in records:
                        if isinstance(r, Message) and (wanted is None or r.channel_id in wanted):
                            count += 1
                            last_t = r.log_time
                        yield r
                    pos += 9 + length
                    continue
            nxt = self._next_chunk(pos + 1)
            report.skip("damaged_chunk", f"record at byte {pos} of {size}",
                        f"{type(err).__name__}: {err or 'damaged'}; "
                        + (f"{nxt - pos} bytes skipped to the next intact chunk at byte {nxt}" if nxt is not None
                           else "no intact chunk after it: the rest of the file is not read"))
            yield _Lost(None, None, None)
            if nxt is None:
                report.truncated = True
                return
            pos = nxt
        report.truncated = True
        report.problems.append(Problem(self.path, f"end of file at byte {size}",
                                       "no data-end and footer records (writer killed or file cut); "
                                       f"everything before is kept: {count} message(s)"
                                       + (f", up to t = {last_t * 1e-9:.6f} s" if last_t is not None else "")))

    @staticmethod
    def _parse_record(op: int, length: int, body: bytes) -> list | None:
        stream = ReadDataStream(io.BytesIO(body))
        if op == Opcode.CHUNK:
            return breakup_chunk(Chunk.read(stream), validate_crc=True)
        if op == Opcode.MESSAGE:
            return [Message.read(stream, length)]
        if op == Opcode.CHANNEL:
            return [Channel.read(stream)]
        if op == Opcode.SCHEMA:
            return [Schema.read(stream)]
        if op in (Opcode.DATA_END, Opcode.FOOTER):
            return None
        return []

    def _next_chunk(self, start: int) -> int | None:
        """Byte offset of the next chunk record at or after ``start`` whose CRC checks, or None."""
        f = self._file
        size = self._size
        f.seek(0)
        data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
        try:
            pos = start
            while True:
                pos = data.find(b"\x06", pos)
                if pos < 0 or pos + 9 > size:
                    return None
                length = int.from_bytes(data[pos + 1:pos + 9], "little")
                if 40 <= length <= size - pos - 9:
                    try:
                        self._parse_record(Opcode.CHUNK, length, data[pos + 9:pos + 9 + length])
                        return pos
                    except _DAMAGE:
                        pass
                pos += 1
        finally:
            if isinstance(data, mmap.mmap):  # a non-empty file
                data.close()

    # -- decoding ----------------------------------------------------------------------------------

    def _lost_samples(self, n_messages: int | None, hole: tuple[int, int | None], step: int | None,
                      typical_n: int | None) -> int:
        a, b = hole
        if b is not None and step:
            return max(0, int(round((b - a) / step)))
        if n_messages is not None and typical_n:
            return n_messages * typical_n
        return 0

    def _recover(self, a: int, b: int | None) -> Iterator[tuple[Samples, np.ndarray]]:
        """Samples in ``[a, b)`` from the per-sample topic, for a damaged block chunk."""
        if SIGNALS_TOPIC not in self._by_topic or self._channel is None or self._channel.topic != BLOCK_TOPIC:
            return
        missing = [s for s in self._signals
                   if s not in self._channel_signals(self._by_topic[SIGNALS_TOPIC], None)]
        if missing:
            return
        yield from self._decode_rows(self._messages([SIGNALS_TOPIC], a, b, self.report), topic=SIGNALS_TOPIC,
                                     count_lost=False)

    def _decode_blocks(self, messages: Iterator[tuple[Channel | None, Any]]) -> Iterator[tuple[Samples, np.ndarray]]:
        index = 0
        hole: int | None = None  # start of samples lost with a damaged block chunk
        hole_msgs: int | None = 0
        step: int | None = None
        typical_n: int | None = None

        def fill(start: int, until: int | None) -> Iterator[tuple[Samples, np.ndarray]]:
            got = 0
            for block, labels in self._recover(start, until):
                got += len(block)
                yield block, labels
            lost = self._lost_samples(hole_msgs, (start, until), step, typical_n)
            self.report.samples_lost += max(0, lost - got)
            if got and len(self.report.problems) < self.report.max_problems:
                self.report.problems.append(Problem(
                    self.path, f"t={start * 1e-9:.6f} s" + (f"..{until * 1e-9:.6f} s" if until is not None else ".."),
                    f"{got} sample(s) of the damaged {BLOCK_TOPIC} chunk recovered from {SIGNALS_TOPIC}"))

        for channel, msg in messages:
            if channel is None:
                if msg.t_start is not None and hole is None:
                    hole, hole_msgs = msg.t_start, msg.messages
                elif msg.t_start is not None:
                    hole_msgs = None if hole_msgs is None or msg.messages is None else hole_msgs + msg.messages
                continue
            self.report.records_read += 1
            index += 1
            try:
                d = json.loads(msg.data)
                n = int(d["n"])
                t = np.frombuffer(base64.b64decode(d["t_ns"], validate=True), dtype="<i8")
                cols = {k: np.frombuffer(base64.b64decode(d["signals"][k], validate=True), dtype="<f8")
                        for k in self._signals}
                bad = [k for k, v in cols.items() if v.shape != (n,)]
                if t.shape != (n,) or bad:
                    raise ValueError(f"array lengths differ from n={n}: t_ns {t.shape[0]}"
                                     + "".join(f", {k} {cols[k].shape[0]}" for k in bad))
            except (ValueError, KeyError, TypeError, binascii.Error) as exc:
                self.report.skip("bad_message", f"topic {channel.topic!r} message {index} at {msg.log_time} ns",
                                 f"not a {BLOCK_SCHEMA} block ({type(exc).__name__}: {exc})")
                continue
            if n > 1:
                step = int(np.median(np.diff(t[:64])))
            typical_n = typical_n or n
            if hole is not None:  # the samples of the damaged chunk(s) before this block
                yield from fill(hole, msg.log_time)
                hole = None
            typical_n = n
            labels = np.full(n, index, dtype=np.int64)
            yield Samples(t.astype(np.int64), {k: v.astype(np.float64) for k, v in cols.items()}), labels
        if hole is not None:
            yield from fill(hole, self._end_ns)

    def _decode_rows(self, messages: Iterator[tuple[Channel | None, Any]], batch: int = 16384,
                     topic: str | None = None, count_lost: bool = True) -> Iterator[tuple[Samples, np.ndarray]]:
        datas: list[bytes] = []
        times: list[int] = []
        first = 1
        for channel, msg in messages:
            if channel is None:
                if msg.messages and count_lost:
                    self.report.samples_lost += msg.messages
                continue
            if msg.log_time > _INT64_MAX:  # a uint64 MCAP time no int64 ns holds: never allocated or converted
                self.report.skip("bad_time", f"topic {topic or channel.topic!r} message at {msg.log_time} ns",
                                 f"log_time {msg.log_time} is beyond the int64 ns range (2^63 - 1), expected a "
                                 "time in ns since the UNIX epoch or the record's start")
                continue
            datas.append(msg.data)
            times.append(msg.log_time)
            if len(datas) >= batch:
                yield self._rows_to_samples(datas, times, first, topic)
                first += len(datas)
                datas, times = [], []
        if datas:
            yield self._rows_to_samples(datas, times, first, topic)

    def _rows_to_samples(self, datas: list[bytes], times: list[int], first: int,
                         topic: str | None = None) -> tuple[Samples, np.ndarray]:
        """Decode a batch of per-sample JSON messages in one ``json.loads``."""
        topic = topic or (self._channel.topic if self._channel else "")
        self.report.records_read += len(datas)
        labels = np.arange(first, first + len(datas))
        try:
            rows = json.loads(b"[" + b",".join(datas) + b"]")
            cols = {k: np.array([r.get(k) for r in rows], dtype=np.float64) for k in self._signals}
            return Samples(np.array(times, dtype=np.int64), cols), labels
        except (ValueError, TypeError, AttributeError):
            pass
        keep: list[int] = []
        values: list[list[float]] = []
        for i, data in enumerate(datas):
            try:
                row = json.loads(data)
                values.append([math.nan if row.get(k) is None else float(row[k]) for k in self._signals])
            except (ValueError, TypeError, AttributeError) as exc:
                self.report.skip("bad_message", f"topic {topic!r} message {first + i} "
                                 f"at {times[i]} ns", f"not a JSON object of numbers ({exc})")
                continue
            keep.append(i)
        arr = np.array(values, dtype=np.float64).reshape(len(keep), len(self._signals))
        t = np.array(times, dtype=np.int64)[keep]
        return Samples(t, {k: arr[:, j] for j, k in enumerate(self._signals)}), labels[keep]


def inspect(path: str | os.PathLike) -> dict:
    """What an MCAP file holds, whether or not it has rig samples: every topic with its
    schema, message count and first/last log time (ns), and the read report (damage)."""
    with McapSource(path, any_topic=True) as src:
        topics = src.topics(scan=True)
        t0 = [t.t_first_ns for t in topics if t.t_first_ns is not None]
        t1 = [t.t_last_ns for t in topics if t.t_last_ns is not None]
        return {"format": "mcap", "file": str(path), "samples_topic": src._channel.topic if src._channel else None,
                "summary": src._summary is not None, "topics": [dataclasses.asdict(t) for t in topics],
                "messages": sum(t.messages or 0 for t in topics),
                "t_first_ns": min(t0) if t0 else None, "t_last_ns": max(t1) if t1 else None,
                "report": src.report.to_dict(), "lossy": src.report.lossy,
                "loss_line": src.report.loss_line()}


__all__ = ["McapSink", "McapSource", "McapMessage", "TopicInfo", "SIGNALS_TOPIC", "BLOCK_TOPIC",
           "SIGNALS_SCHEMA", "BLOCK_SCHEMA", "LAYOUT_METADATA", "signals_schema", "block_schema",
           "encode_json", "inspect"]
