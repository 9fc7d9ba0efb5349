"""Reading rig samples and messages from MCAP files (:class:`McapSource`, layout in :mod:`replay.mcapio.layout`).

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
"""

from __future__ import annotations

import dataclasses
import heapq
import io
import json
import mmap
import os
import zlib
from typing import IO, Any
from collections.abc import Iterator, Sequence

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, MessageIndex, Schema
from mcap.stream_reader import breakup_chunk
from mcap.summary import Summary

from replay.base import Problem, ReadReport, Samples, Source
from replay.quality import QualityGate, QualityOptions, require_signals
from fpdd.errors import LogFormatError, SourceError
from replay.mcapio.layout import BLOCK_SCHEMA, BLOCK_TOPIC, LAYOUT_METADATA, SIGNALS_TOPIC, TIME_FIELDS
from replay.mcapio.decode import SampleDecoding
from replay.mcapio.index import (DAMAGE, MCAP_MAGIC, OPCODES, RECORD_SIZE_LIMIT, ChunkTable, Lost,
                                 McapMessage, TopicInfo)


class McapSource(SampleDecoding, Source):
    """Read rig samples from an MCAP file (layout: :mod:`replay.mcapio.layout`).

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
            reader = SeekingReader(self._rewound(), validate_crcs=True, record_size_limit=RECORD_SIZE_LIMIT)
            self._summary = reader.get_summary()
            if self._summary is not None:
                self._check_summary_crc()
                self._summary.chunk_indexes = ChunkTable(self._summary.chunk_indexes)  # type: ignore[assignment]
        except (*DAMAGE, OSError) as exc:
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
        except (*DAMAGE, KeyError):
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
            names = tuple(k for k in props if k not in TIME_FIELDS)
            if names:
                return names
        for msg in self.messages([channel.topic]):
            if isinstance(msg.data, dict):
                return tuple(k for k in msg.data if k not in TIME_FIELDS)
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
        """(channel, message) pairs in log-time order; ``(None, Lost)`` where a chunk is damaged.

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
            if isinstance(record, Lost):
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
        assert isinstance(table, ChunkTable)  # made at open
        top = (1 << 64) - 1  # log times are unsigned 64-bit
        keep = np.ones(len(table), dtype=bool)
        if start_ns is not None:
            keep &= table.t1 >= min(max(int(start_ns), 0), top) if start_ns <= top else False
        if end_ns is not None:
            keep &= table.t0 < max(int(end_ns), 0) if end_ns <= top else True
        idxs = np.array([k for k in np.flatnonzero(keep)
                         if wanted is None or not (ch := table.channels(int(k))) or wanted & ch], dtype=np.int64)
        rank = np.empty(len(table), dtype=np.int64)
        rank[np.argsort(table.offset, kind="stable")] = np.arange(len(table))
        channels = self._channels_by_id
        in_file = idxs[np.argsort(table.offset[idxs], kind="stable")]
        if wanted is not None and _time_goes_back(table, in_file, wanted):
            # The log time of these topics jumps back in the file: read them in file order, as the file has
            # them, so the jump is seen (and counted by the quality gate) rather than sorted away.
            for ck in in_file:
                ci = table[int(ck)]
                try:
                    records = self._read_chunk(ci)
                except DAMAGE as exc:
                    yield None, self._lost_chunk(ci, int(rank[ck]), exc, wanted, report)
                    continue
                for r in records:
                    if isinstance(r, Message) and r.channel_id in wanted and r.channel_id in channels \
                            and (start_ns is None or r.log_time >= start_ns) \
                            and (end_ns is None or r.log_time < end_ns):
                        yield channels[r.channel_id], r
            return
        idxs = idxs[np.lexsort((table.offset[idxs], table.t0[idxs]))]
        heap: list[tuple[int, int, int, Message]] = []
        seq = 0
        for k, ck in enumerate(idxs):
            ci = table[int(ck)]
            while heap and heap[0][0] < ci.message_start_time:
                item = heapq.heappop(heap)
                yield channels[item[3].channel_id], item[3]
            try:
                records = self._read_chunk(ci)
            except DAMAGE as exc:
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
        """The records of the chunk ``ci`` points at, CRC-checked; raises one of ``DAMAGE``."""
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
        except DAMAGE:
            return None
        return total if ci.message_index_offsets else None

    def _lost_chunk(self, ci, number: int, exc: BaseException, wanted: set[int] | None,
                    report: ReadReport) -> Lost:
        n = self._count_indexed(ci, wanted)
        names = sorted({self._channels_by_id[c].topic for c in ci.message_index_offsets
                        if c in self._channels_by_id and (wanted is None or c in wanted)})
        report.skip("damaged_chunk", f"chunk {number} at bytes {ci.chunk_start_offset}.."
                    f"{ci.chunk_start_offset + ci.chunk_length} (t={ci.message_start_time * 1e-9:.6f}.."
                    f"{ci.message_end_time * 1e-9:.6f} s)",
                    f"{type(exc).__name__}: {exc or 'damaged'}; "
                    + (f"its {n} message(s)" if n is not None else "its messages")
                    + (f" of {', '.join(names)}" if names else "") + " are lost, the chunks after it are read")
        return Lost(ci.message_start_time, ci.message_end_time, n)

    def _walk(self, report: ReadReport, wanted: set[int] | None = None) -> Iterator[Any]:
        """Every record in file order (chunks broken up), without the index.

        A damaged record is reported (``damaged_chunk`` with its byte offset, a ``Lost``
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
            if op not in OPCODES or length > RECORD_SIZE_LIMIT:
                err: BaseException = McapError(f"no valid record at byte {pos} (opcode 0x{op:02x}, length {length})")
            elif pos + 9 + length > size:
                report.truncated = True
                report.skip("damaged_record", f"record at byte {pos} of {size}",
                            f"{Opcode(op).name if op in OPCODES else op} record of {length} bytes is cut by the "
                            f"end of the file (writer killed or file cut); everything before it is kept: "
                            f"recovered {count} message(s)"
                            + (f", up to t = {last_t * 1e-9:.6f} s" if last_t is not None else ""))
                yield Lost(None, None, None)
                return
            else:
                body = f.read(length)
                try:
                    records = self._parse_record(op, length, body)
                except DAMAGE as exc:
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
            yield Lost(None, None, None)
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
                    except DAMAGE:
                        pass
                pos += 1
        finally:
            if isinstance(data, mmap.mmap):  # a non-empty file
                data.close()


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


def _time_goes_back(table, in_file: np.ndarray, wanted: set[int]) -> bool:
    """Whether a chunk holding only ``wanted`` channels starts, in file order, before an earlier such chunk
    ended: the log time of those topics jumps back in the file (a writer's clock stepped back)."""
    own = [int(k) for k in in_file if (ch := table.channels(int(k))) and ch <= wanted]
    if len(own) < 2:
        return False
    t0 = table.t0[own].astype(np.float64)
    t1 = table.t1[own].astype(np.float64)
    return bool(np.any(t0[1:] < np.maximum.accumulate(t1)[:-1]))
