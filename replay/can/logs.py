"""CAN logs (ASC, BLF, candump ``.log``, TRC) as a sample stream, and samples as CAN logs.

Reading goes through python-can's own log readers (:class:`can.ASCReader`,
:class:`can.BLFReader`, :class:`can.CanutilsLogReader`, :class:`can.TRCReader`);
frames are collected into numpy blocks (:class:`replay.can.codec.Frames`), checked, decoded
with the DBC-driven :class:`replay.can.codec.VectorCodec` and aligned onto one grid
(:mod:`replay.can.decode`, where the alignment rule and the counted problems are described).

Damage costs only itself: python-can's text readers are restarted after a bad line
(the header is replayed to them), so the lines after it are read; a BLF file is walked
object by object here (python-can's structs and its container parser) and
resynchronised at the next ``LOBJ`` signature; a container that fails to inflate keeps
what inflated before the damage.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from collections import Counter
from pathlib import Path
from typing import IO
from collections.abc import Iterable, Iterator, Sequence

import can
import numpy as np

from replay import formats
from replay.base import Problem, ReadReport, Samples, Sink, Source
from replay.can.codec import FrameCollector, Frames
from replay.quality import require_signals
from replay.can.decode import BLOCK_FRAMES, MAX_AGE_PERIODS, CanStream, as_codec, probe_plan, split_block
from replay.can.encode import FrameScheduler, frames_to_messages
from fpdd.errors import LogFormatError, SourceError

#: CAN log formats by suffix -> (python-can reader, python-can writer, text format?), from the
#: one registry :data:`replay.formats.FORMATS`.
FORMATS: dict[str, tuple[type, type, bool]] = {
    suf: (*formats.python_can_classes(suf), formats.FORMATS[suf].text) for suf in formats.CAN_LOG_SUFFIXES
}

# --- reading logs ----------------------------------------------------------------------------

def _suffix(path: Path) -> str:
    return formats.lookup(path, kind="can", what="CAN log").suffix


#: Bytes of a BLF object beyond which its size field is taken as damaged (CAN objects are < 100 bytes).
_BLF_MAX_OBJECT = 1 << 20
_BLF_CAN_OBJECT = 48  # bytes of a CAN_MESSAGE object with a v1 header: frames lost per byte of a lost container


@dataclasses.dataclass
class _ReadState:
    n: int = 0                      # frames read
    last_t: float | None = None     # timestamp of the last frame read, s
    blf_declared: tuple[int, int] | None = None  # (file size, object count) from a BLF header
    damaged: int = 0                # damaged lines / objects skipped (resynchronised after)


_ASC_FRAME_START = re.compile(r"^\S+\s+(\d+|canfd)\s+\S+", re.IGNORECASE)  # time, channel, id
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")  # control characters: damage, never an event line
_MAX_T_S = 9.2e9  # what int64 nanoseconds hold, in seconds
#: A text-log line longer than this is damage (a frame line is under 200 characters); it is never held whole.
MAX_LINE_BYTES = 1 << 16
_ASC_EVENT = re.compile(r"statistic|status|j1939|chip|error ?frame|swstat|log trigger")


def _classify_line(suf: str, text: str) -> str | None:
    """What a text-log line that gave no frame is: None (structure), ``bad_line`` or ``ignored_line``."""
    t = text.strip()
    if not t:
        return None
    if suf == ".trc":
        return None if t.startswith(";") else "bad_line"
    if suf == ".asc":
        low = t.lower()
        if low.startswith(("date ", "base ", "//", "begin triggerblock", "end triggerblock", "internal events",
                           "no internal events")) or "start of measurement" in low:
            return None
        if "\ufffd" in t or _CONTROL.search(t) or (_ASC_FRAME_START.match(t) and not _ASC_EVENT.search(low)):
            return "bad_line"
        return "ignored_line"
    return "bad_line"  # candump: every line is a frame


class _Lines:
    """The lines a python-can text reader iterates, with resynchronisation after a bad line.

    Hands out the header again after a restart (``head``), then the file from where the
    last reader stopped, decoding each line on its own (a byte that is not UTF-8 spoils
    that line only); remembers which file line it handed out last and reports a line
    that gave no frame (python-can skips some silently) under ``bad_line`` / ``ignored_line``.
    """

    def __init__(self, raw: IO[bytes], suf: str, path: Path, report: ReadReport) -> None:
        self.raw = raw
        self.suf = suf
        self.path = path
        self.report = report
        self.head: list[str] = []     # file lines before the first frame (the header)
        self.replay: list[str] = []
        self.line_no = 0
        self.current: str | None = None
        self.produced = 0             # file line of the last frame
        self.any_frame = False

    def __iter__(self) -> _Lines:
        return self

    def __next__(self) -> str:
        self.settle()
        if self.replay:
            return self.replay.pop(0)
        raw = self.raw.readline(MAX_LINE_BYTES)
        if not raw:
            raise StopIteration
        self.line_no += 1
        if len(raw) == MAX_LINE_BYTES and not raw.endswith(b"\n"):  # an over-long line: skip to its end
            while (more := self.raw.readline(MAX_LINE_BYTES)) and not more.endswith(b"\n"):
                pass
            raw = b"\x00line longer than %d bytes: " % MAX_LINE_BYTES + raw[:40]
        self.current = raw.decode("utf-8", "replace")
        if not self.any_frame:
            self.head.append(self.current)
        return self.current

    def settle(self) -> None:
        """Account for the line handed out last: a frame, structure, or a line lost."""
        text, self.current = self.current, None
        if text is None or self.produced == self.line_no:
            return
        kind = _classify_line(self.suf, text)
        if kind == "bad_line":
            self.lost(text, "not a CAN frame the python-can reader understands")
        elif kind == "ignored_line":
            self.report.skip("ignored_line", f"line {self.line_no}", f"not a CAN frame, ignored: {text.strip()[:60]!r}")

    def lost(self, text: str, why: str) -> None:
        if not self.any_frame and self.head and self.head[-1] is text:
            self.head.pop()
        self.report.skip("bad_line", f"line {self.line_no}",
                         f"{why}: {text.strip()[:60]!r}; expected a {self.suf[1:].upper()} frame line; "
                         "that frame is lost, reading goes on with the next line")

    def frame(self) -> None:
        if not self.any_frame:
            self.any_frame = True
            if self.head and self.head[-1] is self.current:
                self.head.pop()  # the first frame's line is no header
        self.produced = self.line_no

    def fail(self, exc: Exception) -> bool:
        """The reader raised on the current line: count it and arrange a restart; False if not a file line."""
        text, self.current = self.current, None
        if text is None:
            return False
        self.lost(text, f"{type(exc).__name__}: {exc}")
        self.replay = list(self.head)
        return True

    def readable(self) -> bool:
        return True

    def close(self) -> None:
        """python-can readers close their file on stop(); the underlying file stays open here."""


def _text_messages(path: Path, suf: str, report: ReadReport, state: _ReadState) -> Iterator[can.Message]:
    """Frames of a text log; a line that fails costs only itself (the reader restarts after it)."""
    reader_cls = formats.python_can_classes(suf)[0]
    relative = False
    try:
        raw = open(path, "rb")
    except OSError as e:
        raise SourceError(f"{path}: cannot open CAN log: {e.strerror or e}") from e
    with raw:
        lines = _Lines(raw, suf, path, report)
        while True:
            try:
                reader = reader_cls(lines, **({"relative_timestamp": relative} if suf == ".asc" else {}))
            except Exception as e:
                raise LogFormatError(f"{path}: not a {suf[1:].upper()} file: {type(e).__name__}: {e}") from e
            try:
                for msg in reader:
                    lines.frame()
                    state.n += 1
                    state.last_t = msg.timestamp
                    yield msg
                lines.settle()
                return
            except Exception as e:  # a line python-can cannot parse: skip it, restart after it
                if suf == ".asc" and state.n == 0 and not relative and "datetime" in str(e):
                    relative = True
                    report.skip("asc_date", "header", f"date not understood ({e}); timestamps are relative "
                                                      "to the start of measurement")
                    raw.seek(0)
                    lines = _Lines(raw, suf, path, report)
                    continue
                if not lines.fail(e):  # the header itself does not parse
                    if state.n == 0:
                        raise LogFormatError(f"{path}: not a readable {suf[1:].upper()} file: its header does not "
                                             f"parse ({type(e).__name__}: {e})") from e
                    _truncated(report, path, state.n, state.last_t, e)
                    return
                state.damaged += 1


def _blf_messages(path: Path, report: ReadReport, state: _ReadState) -> Iterator[can.Message]:
    """Frames of a BLF file, object by object: a damaged object or container costs only itself.

    The file header and the container framing are walked here (python-can's structs);
    the objects inside a container are parsed by python-can's ``BLFReader``.  After a
    damaged object the walk resynchronises at the next ``LOBJ`` signature.
    """
    import io
    import mmap

    from can.io import blf as B

    try:
        f = open(path, "rb")
    except OSError as e:
        raise SourceError(f"{path}: cannot open CAN log: {e.strerror or e}") from e
    with f:
        size = os.fstat(f.fileno()).st_size
        hs = B.FILE_HEADER_STRUCT.size
        if size < hs:
            raise LogFormatError(f"{path}: not a BLF file: {size} bytes, shorter than its {hs}-byte header")
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            head = bytearray(mm[:hs])
            h = B.FILE_HEADER_STRUCT.unpack_from(head)
            if h[0] != b"LOGG":
                if not (hs <= h[1] <= 4096 and mm.find(b"LOBJ", h[1], h[1] + 4) == h[1]):
                    raise LogFormatError(f"{path}: not a BLF file: starts with {bytes(head[:4])!r}, "
                                         "expected the BLF signature b'LOGG'")
                report.skip("damaged_header", "file header", f"signature {bytes(head[:4])!r} damaged, expected "
                            "b'LOGG'; the rest of the header is used as is")
                head[:4] = b"LOGG"
            try:
                parser = B.BLFReader(io.BytesIO(bytes(head) + b"\0" * max(0, h[1] - hs)))
            except Exception as e:  # a start time that is no date
                raise LogFormatError(f"{path}: not a readable BLF file: header: {type(e).__name__}: {e}") from e
            state.blf_declared = (h[10], h[12])
            pos = max(h[1], hs)
            obj = 0
            while pos + 16 <= size:
                sig, _hsize, _hver, osize, otype = B.OBJ_HEADER_BASE_STRUCT.unpack_from(mm, pos)
                if sig == b"LOBJ" and 16 <= osize <= size - pos:
                    body_end = pos + osize
                    nxt = body_end + osize % 4
                    if otype == B.LOG_CONTAINER:
                        yield from _blf_container(mm, pos, body_end, parser, report, state, path)
                    pos, obj = nxt, obj + 1
                    continue
                if sig == b"LOBJ" and osize > size - pos and mm.find(b"LOBJ", pos + 1) < 0:
                    report.truncated = True
                    n0 = state.n
                    if otype == B.LOG_CONTAINER:
                        quiet = ReadReport(report.file)
                        yield from _blf_container(mm, pos, size, parser, quiet, state, path)
                    report.problems.append(Problem(str(path), f"object {obj} at byte {pos}",
                                                   f"declares {osize} bytes, the file ends after {size - pos}: "
                                                   f"truncated; the {state.n} frame(s) read are kept "
                                                   f"({state.n - n0} from the cut object)"))
                    break
                found = mm.find(b"LOBJ", pos + 1)
                report.skip("damaged_object", f"object {obj} at byte {pos}",
                            f"object header damaged (signature {bytes(sig)!r}, size {osize}); "
                            + (f"skipped {found - pos} bytes to the next object" if found >= 0 else
                               "no further object in the file"))
                state.damaged += 1
                parser._tail = b""
                if found < 0:
                    break
                pos, obj = found, obj + 1
        finally:
            mm.close()


def _inflate(cdata: bytes) -> tuple[bytes, str | None]:
    """zlib-inflate ``cdata``; on damage, what inflated before it and the error."""
    import zlib

    z = zlib.decompressobj()
    out = []
    step = 1024
    for i in range(0, len(cdata), step):
        try:
            out.append(z.decompress(cdata[i:i + step]))
        except zlib.error as e:
            return b"".join(out), f"zlib: {e} (compressed byte {i}..{i + step} of {len(cdata)})"
    if not z.eof:
        return b"".join(out), f"zlib: compressed data ends early ({len(cdata)} bytes)"
    return b"".join(out), None


def _blf_container(mm, pos: int, end: int, parser, report: ReadReport, state: _ReadState,
                   path: Path) -> Iterator[can.Message]:
    import struct

    from can.io import blf as B

    body = mm[pos + 16:end]
    where = f"container at byte {pos}"
    err: str | None = None
    usize = 0
    try:
        method, usize = B.LOG_CONTAINER_STRUCT.unpack_from(body)
        cdata = body[B.LOG_CONTAINER_STRUCT.size:]
        if method == B.ZLIB_DEFLATE:
            data, err = _inflate(cdata)
        elif method == B.NO_COMPRESSION:
            data = bytes(cdata)
        else:
            raise ValueError(f"unknown compression method {method}")
    except (ValueError, struct.error) as e:
        data, err = b"", f"{type(e).__name__}: {e}"
    if err is not None:
        lost = max(0, int(usize) - len(data)) // _BLF_CAN_OBJECT
        report.skip("damaged_object", where, f"{err}; " + (
            f"the frames of its first {len(data)} bytes are kept, " if data else "") +
            f"about {lost} frame(s) after the damage in this container are lost")
        state.damaged += 1
        if not data:
            parser._tail = b""
            return
    data = parser._tail + data
    parser._tail = b""
    off = 0
    while True:
        chunk = data[off:] if off else data
        bad_at = None
        try:
            for msg in parser._parse_data(chunk):
                state.n += 1
                state.last_t = msg.timestamp
                yield msg
        except struct.error:
            pass  # not enough data left for the next object: it continues in the next container
        except B.BLFParseError:
            bad_at = parser._pos
        tail = chunk[parser._pos:] if bad_at is None else b""
        if bad_at is None and len(tail) >= 16 and tail[:4] == b"LOBJ":
            osize = B.OBJ_HEADER_BASE_STRUCT.unpack_from(tail)[3]
            if osize > _BLF_MAX_OBJECT or osize < 16:
                bad_at = parser._pos
        if bad_at is None:
            parser._tail = tail
            return
        found = chunk.find(b"LOBJ", bad_at + 1)
        report.skip("damaged_object", f"{where}, byte {bad_at} of its data",
                    "object damaged (no valid object header where one should be); "
                    + ("resynchronised at the next object" if found >= 0 else "the rest of the container is lost"))
        state.damaged += 1
        if found < 0:
            return
        off += found


class _ReaderWarnings(logging.Filter):
    """Takes python-can's reader warnings (``Unknown object header version``, ``Failed to parse
    message``) off stderr while a log is read: the report already counts what they are about."""

    def __init__(self, report: ReadReport) -> None:
        super().__init__()
        self.report = report

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if "object header version" in msg:  # a BLF object whose header is garbage (damaged container)
            self.report.skip("damaged_object", "BLF object", f"python-can: {msg}; the object is skipped")
        return False


def iter_frames(path: str | Path, report: ReadReport, block_frames: int = BLOCK_FRAMES) -> Iterator[Frames]:
    """Frames of a CAN log in blocks, through python-can's reader for the suffix.

    A damaged line (text logs) or object (BLF) costs only itself: it is counted under
    ``bad_line`` / ``damaged_object`` with its line number or byte offset, and reading
    goes on after it.  A file cut short keeps every frame before the cut and sets
    ``report.truncated``.
    """
    path = Path(path)
    suf = _suffix(path)
    if not path.is_file():
        raise SourceError(f"{path}: CAN log not found")
    coll = FrameCollector()
    state = _ReadState()
    messages = _blf_messages(path, report, state) if suf == ".blf" else _text_messages(path, suf, report, state)
    quiet = _ReaderWarnings(report)
    loggers = [logging.getLogger(n) for n in ("can.io.blf", "can.io.trc", "can.io.asc", "can.io.canutils")]
    for lg in loggers:
        lg.addFilter(quiet)
    try:
        for msg in messages:
            t = msg.timestamp
            if not (math.isfinite(t) and abs(t) < _MAX_T_S):  # never converted to int64 ns (undefined beyond)
                report.skip("bad_time", f"frame {state.n} (id 0x{msg.arbitration_id:x})",
                            f"timestamp {t!r} s is not a time within +-{_MAX_T_S:g} s; that frame is lost")
                continue
            coll.add(msg)
            if len(coll) >= block_frames:
                yield coll.take()
    finally:
        for lg in loggers:
            lg.removeFilter(quiet)
    if len(coll):
        yield coll.take()
    _check_complete(path, suf, report, state)
    if state.n == 0 and not report.truncated:
        raise LogFormatError(f"{path}: no CAN frames found; expected a {suf[1:].upper()} log"
                             + (f" ({state.damaged} damaged line(s)/object(s) skipped)" if state.damaged else ""))


def _truncated(report: ReadReport, path: Path, n: int, last_t: float | None, e: Exception) -> None:
    report.truncated = True
    size = path.stat().st_size
    where = f"after frame {n - 1} (t={last_t:.6f} s)" if n else "before the first frame"
    report.problems.append(Problem(
        str(path), where, f"reading stopped: {type(e).__name__}: {e}; the {n} frame(s) read before are kept "
                          f"(file size {size} bytes)"))


def _check_complete(path: Path, suf: str, report: ReadReport, state: _ReadState) -> None:
    """Detect a file cut short that the reader accepted silently."""
    if report.truncated:
        return
    n = state.n
    size = path.stat().st_size
    if formats.FORMATS[suf].text:
        with open(path, "rb") as f:
            if size:
                f.seek(max(size - 64, 0))
                tail = f.read()
            else:
                tail = b""
        cut = bool(tail) and not tail.endswith(b"\n")
        if suf == ".asc" and b"end triggerblock" not in tail.lower():
            cut = True
        if cut:
            report.truncated = True
            report.problems.append(Problem(
                str(path), f"end of file after {n} frame(s)",
                "file ends without its closing line (" + ("'End TriggerBlock'" if suf == ".asc" else "newline")
                + "): truncated; the frames read are kept, a cut last frame is reported on its own"))
    elif suf == ".blf" and state.blf_declared is not None:
        declared, count = state.blf_declared
        if (declared and declared != size) or (count and n < count and not state.damaged):
            report.truncated = True
            report.problems.append(Problem(
                str(path), f"end of file after {n} frame(s)",
                f"BLF header declares {declared} bytes and {count} objects, the file has {size} bytes "
                f"and {n} CAN frame(s) could be read: truncated; the frames read are kept"))


class CanLogSource(Source):
    """Rig samples from a CAN log (ASC, BLF, candump ``.log``, TRC), decoded with a DBC.

    :param path: the log; the format is taken from the suffix.
    :param dbc: DBC path, loaded database or :class:`VectorCodec` (default: MSP25).
    :param grid_hz: uniform output grid in Hz (default: the master frames' own times).
    :param signals: rig signals to deliver (default: those present at the start of the log).
    :param window_s: same-cycle window in s (default: half the master period or grid step).
    :param max_age_s: max age of a held value in s (default: 2.5 periods of its message).
    :param probe_s: span of log time looked at to find which messages are present
        (default: 2.5 times the slowest DBC period, at least 50 ms).
    :param required: signals that must be delivered (DataError naming them if not).
    """

    def __init__(self, path: str | Path, dbc=None, grid_hz: float | None = None, *,
                 signals: Sequence[str] | None = None, window_s: float | None = None,
                 max_age_s: float | None = None, probe_s: float | None = None,
                 required: Sequence[str] = (), block_frames: int = BLOCK_FRAMES) -> None:
        self.path = str(path)
        _suffix(Path(path))
        if not Path(path).is_file():
            raise SourceError(f"{path}: CAN log not found")
        self.codec = as_codec(dbc)
        self.block_frames = block_frames
        self.report = ReadReport(self.path)
        periods = [m.period_s for m in self.codec.messages.values() if m.period_s and m.rig_signals]
        self.probe_s = probe_s if probe_s is not None else max(0.05, MAX_AGE_PERIODS * max(periods, default=0.02))
        head = self._head()
        if len(head) == 0:
            raise LogFormatError(f"{self.path}: no CAN frames found; expected a {Path(path).suffix[1:].upper()} log")
        self.plan = probe_plan(self.codec, head, self.path, signals, grid_hz, window_s, max_age_s)
        require_signals(self.path, self.plan.signals, required)

    def _head(self) -> Frames:
        span_ns = int(self.probe_s * 1e9)
        blocks = []
        t0 = None
        for fr in iter_frames(self.path, ReadReport(self.path), block_frames=4096):
            blocks.append(fr)
            if t0 is None and len(fr):
                t0 = int(fr.t_ns[0])
            if t0 is not None and int(fr.t_ns.max()) - t0 >= span_ns:
                break
        head = Frames.concat(blocks)
        if t0 is not None:
            head = head.take(np.flatnonzero(head.t_ns - t0 <= span_ns))
        return head

    @property
    def signals(self) -> tuple[str, ...]:
        return self.plan.signals

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Aligned sample blocks of at most ``size``; each call reads the log from the start."""
        self.report = ReadReport(self.path)
        stream = CanStream(self.codec, self.plan, self.report)
        for frames in iter_frames(self.path, self.report, self.block_frames):
            yield from split_block(stream.feed(frames), size)
        yield from split_block(stream.flush(), size)


# --- writing logs ---------------------------------------------------------------------------

#: Sample times from here on (2000-01-01T00:00Z, ns) are wall-clock times; earlier ones count from a record's start.
WALL_CLOCK_NS = 946_684_800 * 10**9


class CanLogSink(Sink):
    """Samples written as the rig's CAN frames to a log (ASC, BLF, candump ``.log``, TRC).

    :param path: the log to write; the format is taken from the suffix.
    :param dbc: DBC path, database or :class:`VectorCodec` (default: MSP25).
    :param decimate: send each message at its DBC period (True) or on every sample.
    :param channel: channel written into the log (python-can numbering from 0; ``can0`` for candump).
    :param start_ns: the record's start as wall-clock time (ns since the epoch) for samples whose times count from
        the record's start (before :data:`WALL_CLOCK_NS`, 2000-01-01); default the time the first samples are
        written. Samples already on the wall clock keep their times. The log's header (ASC date, BLF and TRC
        start) and every frame carry the wall-clock time, as a logger on the rig's bus writes them.
    """

    def __init__(self, path: str | Path, dbc=None, *, decimate: bool = True, channel: int | str = 0,
                 start_ns: int | None = None) -> None:
        self.path = Path(path)
        self.start_ns = start_ns
        self._shift: int | None = None
        suf = _suffix(self.path)
        self.codec = as_codec(dbc)
        self.scheduler = FrameScheduler(self.codec, decimate, str(self.path))
        writer_cls = FORMATS[suf][1]
        try:
            if writer_cls is can.CanutilsLogWriter:
                self.channel: str | int = channel if isinstance(channel, str) else f"can{channel}"
                self.writer = writer_cls(str(self.path), channel=self.channel)
            else:
                number = channel if isinstance(channel, int) else 0
                self.channel = number
                self.writer = writer_cls(str(self.path), channel=number + 1)
        except OSError as e:
            raise SourceError(f"{self.path}: cannot write CAN log: {e}") from e
        self._closed = False

    @property
    def frames_out(self) -> int:
        return self.scheduler.frames_out

    @property
    def skipped(self) -> Counter:
        return self.scheduler.skipped

    def write(self, samples: Samples) -> None:
        if len(samples) and self._shift is None:
            import time

            on_wall = int(samples.t_ns[0]) >= WALL_CLOCK_NS
            self._shift = 0 if on_wall else (self.start_ns if self.start_ns is not None else time.time_ns())
        if self._shift:
            samples = Samples(samples.t_ns + self._shift, samples.signals)
        fr = self.scheduler.frames(samples)
        write = self.writer.on_message_received
        for msg in frames_to_messages(fr, channel=self.channel if not isinstance(self.channel, str) else None):
            write(msg)

    def write_frames(self, frames: Iterable[can.Message]) -> None:
        """Write raw python-can messages (e.g. bad frames for a test, or a bus capture)."""
        for m in frames:
            self.writer.on_message_received(m)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.writer.stop()
