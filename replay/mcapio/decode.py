"""Rig samples from MCAP messages: the block topic's base64 arrays, the per-sample JSON rows, and a damaged
block chunk filled from the per-sample topic (the part of :class:`~replay.mcapio.reader.McapSource` that
decodes; the reader walks the file)."""

from __future__ import annotations

import base64
import binascii
import json
import math
from typing import Any
from collections.abc import Iterator, Sequence

import numpy as np
from mcap.records import Channel, Schema

from replay.base import Problem, ReadReport, Samples
from replay.mcapio.layout import BLOCK_SCHEMA, BLOCK_TOPIC, SIGNALS_TOPIC
from replay.mcapio.index import INT64_MAX


class SampleDecoding:
    """Decoding of :class:`~replay.mcapio.reader.McapSource`: what it needs of the reader is declared here."""

    path: str
    report: ReadReport
    _signals: tuple[str, ...]
    _channel: Channel | None
    _by_topic: dict[str, Channel]
    _end_ns: int | None

    def _messages(self, topics: Sequence[str] | None, start_ns: int | None, end_ns: int | None,
                  report: ReadReport) -> Iterator[tuple[Channel | None, Any]]:
        raise NotImplementedError

    def _channel_signals(self, channel: Channel, schema: Schema | None) -> tuple[str, ...]:
        raise NotImplementedError

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
            if msg.log_time > INT64_MAX:  # a uint64 MCAP time no int64 ns holds: never allocated or converted
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

