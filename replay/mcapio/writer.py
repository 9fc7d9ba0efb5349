"""Writing rig samples and the twin's messages to MCAP (:class:`McapSink`, layout in :mod:`replay.mcapio.layout`).

Samples are buffered and flushed (chunk finished, file flushed) every
``flush_period_s`` of sample time (1 s) or ``flush_messages`` messages, whichever
comes first, so a killed writer loses at most the last second; a chunk therefore holds
about one second of data (messages of :meth:`McapSink.write_message` too: a twin
output of 600 messages over 12 s has about a dozen chunks, not one per message).
"""

from __future__ import annotations

import base64
import json
import os
from typing import IO, Any
from collections.abc import Mapping, Sequence

import numpy as np
from mcap.writer import CompressionType, Writer

from fpdd.units import SIGNALS, display
from replay.base import Samples, Sink
from fpdd.errors import DataError, SourceError
from replay.mcapio.layout import (BLOCK_TOPIC, LAYOUT_METADATA, LAYOUT_VERSION, SIGNALS_TOPIC, TIME_FIELD,
                                  block_schema, encode_json, foxglove_time, generic_schema, signals_schema,
                                  with_time_schema)


_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class McapSink(Sink):
    """Write rig samples (and other JSON topics) to an MCAP file in the layout of :mod:`replay.mcapio.layout`.

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
                 metadata: Mapping[str, str] | None = None, rig: str | None = None) -> None:
        if not flush_period_s > 0:
            raise ValueError(f"flush_period_s (={flush_period_s}) must be > 0 s")
        if flush_messages < 1:
            raise ValueError(f"flush_messages (={flush_messages}) must be >= 1")
        if not (per_sample or block):
            raise ValueError("per_sample and block are both off: nothing would be written")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression {compression!r} unknown, expected one of {sorted(_COMPRESSION)}")
        self.path = str(path)
        self.rig = str(rig or (metadata or {}).get("rig") or _stem(self.path))
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
        self._rows_by_message = False  # /rig/signals written as messages (a twin's decimated signals)

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
        units = [SIGNALS[s].unit if s in SIGNALS else "" for s in self._signals]
        meta = {"signals": ",".join(self._signals), "units": ",".join(units)}
        block = self._channel(BLOCK_TOPIC, block_schema(self._signals), meta) if self._block else None
        per = self._channel(SIGNALS_TOPIC, signals_schema(self._signals), {
            **meta, "rig": self.rig, "display_units": ",".join(display(u)[0] for u in units)}) \
            if self._per_sample else None
        return block, per

    # -- Sink ----------------------------------------------------------------------------------

    def write(self, samples: Samples) -> None:
        """Buffer a block of samples (time ordered); flush every period of sample time."""
        if self._closed:
            raise SourceError(f"{self.path}: write after close")
        if self._rows_by_message:
            raise DataError(f"{self.path}: {SIGNALS_TOPIC} is written message by message (write_message) in "
                            "this file, not by write()")
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
                      schema: Mapping[str, Any] | None = None, metadata: Mapping[str, str] | None = None) -> None:
        """Write one JSON message on ``topic`` at ``t_ns`` (ns).

        The schema is registered on first use of the topic: ``schema`` (a JSON Schema
        dict) or one derived from the payload's fields, titled ``fpdd`` + topic with
        dots (``/twin/alarm`` -> ``fpdd.twin.alarm``); ``metadata``: the channel's, on first use.
        ``/rig/signals`` may be written so (a twin's decimated signals, as the live view shows them, the
        channel's ``signals`` metadata naming the signal fields) in a file whose samples :meth:`write` does not
        write.
        """
        if self._closed:
            raise SourceError(f"{self.path}: write after close")
        if topic == BLOCK_TOPIC or (topic == SIGNALS_TOPIC and self._signals is not None):
            raise DataError(f"{self.path}: topic {topic!r} is written by write(), not write_message()")
        if topic == SIGNALS_TOPIC:
            self._rows_by_message = True
        if topic not in self._channels:
            title = "fpdd" + topic.replace("/", ".")
            self._channel(topic, with_time_schema(schema or generic_schema(title, payload)), metadata)
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
                                                          self._signals, self.rig)):
                add(per_ch, t, data, t)
        self._unflushed += len(block)
        self._last_flush_ns = int(t_ns[-1])
        self._latest_ns = self._last_flush_ns if self._latest_ns is None else max(self._latest_ns, self._last_flush_ns)


def _stem(path: str) -> str:
    name = os.path.basename(path)
    return name[:-5] if name.lower().endswith(".mcap") else name


#: Significant digits of the display numbers of ``/rig/signals`` (a plot's; the SI numbers are exact, ``repr``):
#: x to 1e-6 mm at 10 mm, pressures to 1e-5 MPa; twice as fast to write as ``repr``.
DISPLAY_DIGITS = 7


def _json_rows(t_ns: np.ndarray, cols: list[np.ndarray], names: Sequence[str], rig: str = "") -> list[bytes]:
    """One compact JSON object per sample: the time, the rig's name, the signals in SI (shortest round-trip form,
    ``repr``) and the same in display units under ``display`` (:data:`DISPLAY_DIGITS` significant digits); a
    non-finite value is ``null``."""
    scales = [display(SIGNALS[k].unit)[1] if k in SIGNALS else 1.0 for k in names]
    values = [*cols, *(c * k if k != 1.0 else c for c, k in zip(cols, scales))]
    head = '{"t":%r,"timestamp":{"sec":%d,"nsec":%d},"rig":' + json.dumps(rig).replace("%", "%%")

    def template(si: str, shown: str) -> str:
        return (head + "".join(f',"{k}":{si}' for k in names) + ',"display":{'
                + ",".join(f'"{k}":{shown}' for k in names) + "}}")

    sec, nsec = np.divmod(t_ns, 1_000_000_000)
    columns = [(t_ns * 1e-9).tolist(), sec.tolist(), nsec.tolist(), *(v.tolist() for v in values)]
    fmt = template("%r", f"%.{DISPLAY_DIGITS}g")
    rows = [(fmt % row).encode() for row in zip(*columns)]
    if values:
        bad = np.flatnonzero(~np.isfinite(np.vstack(values)).all(axis=0))
        if bad.size:  # the rare row with a non-finite value: null in its place
            slow = template("%s", "%s")
            n = len(names)
            for i in bad.tolist():
                row = [columns[0][i], columns[1][i], columns[2][i]]
                row += [("null" if not np.isfinite(c[i]) else repr(c[i]) if j < n else f"{c[i]:.{DISPLAY_DIGITS}g}")
                        for j, c in enumerate(columns[3:])]
                rows[i] = (slow % tuple(row)).encode()
    return rows
