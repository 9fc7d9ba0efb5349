"""A corpus of damaged inputs for replay, generated (seeded, deterministic) from the good
reference files in tests/data/.

Each case damages one good file in one way and asserts what replay says (a substring
of the error naming the file and what was expected, or of the problem naming the line,
chunk or object) and what it kept.  A damaged part must cost only itself: the rest of
the file is read.  Cases: MCAP (bit flips per chunk, truncations, summary, magic), BLF
(flips per container, object header, file header, truncation), ASC / candump / TRC
(a bad character, a wild timestamp, a garbage line, a cut), CSV (random bytes, UTF-16,
wrong columns, a time column in ms or us, duplicate and backward times, NaN, inf, text
and empty cells, pressures in bar) and live payloads (JSON and CAN frames).
"""

from __future__ import annotations

import dataclasses
import functools
import struct
import zlib
from pathlib import Path
from typing import Any
from collections.abc import Callable

import can
import numpy as np
import pytest
from mcap.reader import make_reader

from replay import cli
from replay.base import Samples
from replay.csvio import CsvSource, parse_map
from replay.factory import open_source
from replay.live import PayloadError, frames_to_payload, json_to_samples, payload_to_frames
from replay.mcapio import BLOCK_TOPIC, SIGNALS_TOPIC, McapSink
from fpdd.errors import TwinError

DATA = Path(__file__).parent / "data"
N_REF = 200  # samples of reference.csv / reference.mcap
N_CAN = 50   # samples of msp25_short.*


@functools.cache
def ref() -> Samples:
    """The reference samples as the CSV gives them (float seconds: times within 0.2 us of whole ms)."""
    with CsvSource(DATA / "reference.csv") as src:
        return src.read_all()


@functools.cache
def ref_mcap() -> Samples:
    """The reference samples as the MCAP gives them (exact integer ns)."""
    with open_source(DATA / "reference.mcap") as src:
        return src.read_all()


def rng_for(name: str) -> np.random.Generator:
    return np.random.default_rng(zlib.crc32(name.encode()))  # one fixed seed per case


def flip(path: Path, offset: int, mask: int = 0x01) -> Path:
    data = bytearray(path.read_bytes())
    data[offset] ^= mask
    path.write_bytes(bytes(data))
    return path


def cut(path: Path, fraction: float) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


# --- MCAP: the reference samples in 4 blocks of 50 (own chunks), per-sample messages in 4 more ----

def mcap(tmp: Path, name: str = "rig.mcap", **kw: Any) -> Path:
    p = tmp / name
    with McapSink(p, flush_period_s=0.05, **kw) as sink:
        sink.write(ref_mcap())
    return p


def mcap_stepped_back(at: int, back_ms: int, block: bool = True) -> Callable[[Path], Path]:
    """The reference MCAP written as a logger whose clock steps back ``back_ms`` before sample ``at`` (its log
    time goes back in the file)."""
    def make(tmp: Path) -> Path:
        good = ref_mcap()
        t = good.t_ns.copy()
        t[at:] -= back_ms * 1_000_000
        stepped = Samples(t, good.signals)
        p = tmp / "stepped.mcap"
        with McapSink(p, flush_period_s=0.001, block=block) as sink:  # each write its own chunks, in file order
            for i in range(0, len(t), 10):
                sink.write(stepped.slice(i, min(i + 10, len(t))))
        return p
    return make


def chunks_of(path: Path, topic: str) -> list:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    cid = next(c.id for c in summary.channels.values() if c.topic == topic)
    return sorted((ci for ci in summary.chunk_indexes if cid in ci.message_index_offsets),
                  key=lambda ci: ci.message_start_time)


def mcap_flip(topics: tuple[str, ...], k: int, **kw: Any) -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        p = mcap(tmp, **kw)
        for topic in topics:
            ci = chunks_of(p, topic)[k]
            flip(p, ci.chunk_start_offset + ci.chunk_length // 2, 0x10)
        return p
    return make


def mcap_summary_flip(tmp: Path) -> Path:
    p = mcap(tmp)
    with open(p, "rb") as f:
        summary = make_reader(f).get_summary()
    end = max(ci.chunk_start_offset + ci.chunk_length for ci in summary.chunk_indexes)
    size = p.stat().st_size
    return flip(p, end + (size - end) // 2, 0x40)  # inside the summary section


# --- BLF: the short reference rewritten with small containers (about 20 frames each) -------------

def blf(tmp: Path, compression_level: int = 6) -> Path:
    msgs = list(can.BLFReader(str(DATA / "msp25_short.blf")))
    p = tmp / "rig.blf"
    w = can.BLFWriter(str(p), compression_level=compression_level, max_container_size=1024)
    for m in msgs:
        w.on_message_received(m)
    w.stop()
    return p


def blf_objects(p: Path) -> list[tuple[int, int]]:
    """(offset, size) of the top-level objects (the containers)."""
    data = p.read_bytes()
    pos = struct.unpack_from("<4sI", data)[1]
    out = []
    while pos + 16 <= len(data):
        sig, _, _, size, _ = struct.unpack_from("<4sHHII", data, pos)
        out.append((pos, size))
        pos += size + size % 4
    return out


def blf_flip_container(k: int) -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        p = blf(tmp)
        off, size = blf_objects(p)[k]
        return flip(p, off + 16 + 16 + (size - 32) // 3, 0x08)  # inside the compressed data
    return make


def blf_break_signature(k: int) -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        p = blf(tmp)
        off, _ = blf_objects(p)[k]
        return flip(p, off + 3, 0x04)  # "LOBJ" -> "LOBN"
    return make


def blf_flip_frame_id(tmp: Path) -> Path:
    p = blf(tmp, compression_level=0)  # uncompressed: a frame's bytes are in the file as is
    data = bytearray(p.read_bytes())
    first = blf_objects(p)[1][0] + 16 + 16  # second container's data
    obj = data.index(b"LOBJ", first)
    data[obj + 32 + 4] ^= 0x02  # CAN_MESSAGE: channel(2) flags(1) dlc(1) id(4): the id's low byte
    p.write_bytes(bytes(data))
    return p


# --- text CAN logs ---------------------------------------------------------------------------------

def frame_lines(suffix: str, lines: list[str]) -> list[int]:
    if suffix == ".trc":
        return [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith(";")]
    if suffix == ".asc":
        return [i for i, ln in enumerate(lines) if " Rx " in ln]
    return [i for i, ln in enumerate(lines) if ln.strip()]


def text_edit(suffix: str, edit: Callable[[list[str], list[int], np.random.Generator], None],
              name: str) -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        lines = (DATA / f"msp25_short{suffix}").read_text().split("\n")
        edit(lines, frame_lines(suffix, lines), rng_for(name))
        p = tmp / f"rig{suffix}"
        p.write_text("\n".join(lines))
        return p
    return make


def bad_char(at: float):
    def edit(lines, frames, rng):
        i = frames[int(at * (len(frames) - 1))]
        ln = lines[i].rstrip()
        j = len(ln) - 1 - int(rng.integers(0, 4))  # a character of the data bytes at the end of the line
        lines[i] = ln[:j] + "Z" + ln[j + 1:]
    return edit


def wild_time(suffix: str):
    def edit(lines, frames, rng):
        i = frames[len(frames) // 2]
        parts = lines[i].split()
        if suffix == ".asc":
            lines[i] = lines[i].replace(parts[0], f"{float(parts[0]) + 5:.6f}", 1)
        elif suffix == ".log":
            lines[i] = lines[i].replace(parts[0], f"({float(parts[0][1:-1]) + 5:.6f})", 1)
        else:
            lines[i] = lines[i].replace(parts[1], f"{float(parts[1]) + 5000:.3f}", 1)
    return edit


def garbage_line(lines, frames, rng):
    junk = "".join(chr(c) for c in rng.integers(33, 127, 40))
    lines.insert(frames[len(frames) // 3], junk.replace(";", ":"))


def truncate_mid_line(lines, frames, rng):
    i = frames[len(frames) // 2]
    del lines[i + 1:]
    lines[i] = lines[i][: len(lines[i]) // 2]


# --- CSV ------------------------------------------------------------------------------------------

def csv_text(tmp: Path, name: str, text: str | bytes) -> Path:
    p = tmp / name
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    return p


def ref_csv_lines() -> list[str]:
    return (DATA / "reference.csv").read_text().splitlines()


def csv_edit(edit: Callable[[list[str]], None], name: str = "rig.csv") -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        lines = ref_csv_lines()
        edit(lines)
        return csv_text(tmp, name, "\n".join(lines) + "\n")
    return make


def scale_time(factor: float):
    def edit(lines):
        for i in range(1, len(lines)):
            t, rest = lines[i].split(",", 1)
            lines[i] = f"{(float(t) - 1.7e9) * factor!r},{rest}"
    return edit


def set_cell(row: int, col: int, value: str):
    def edit(lines):
        cells = lines[row].split(",")
        cells[col] = value
        lines[row] = ",".join(cells)
    return edit


def dup_rows(lines):
    for i in range(190, 0, -10):  # every 10th row appears twice
        lines.insert(i, lines[i])


def swap_rows(lines):
    lines[50], lines[51] = lines[51], lines[50]


def bar_pressures(lines):
    for i in range(1, len(lines)):
        cells = lines[i].split(",")
        cells[4] = repr(float(cells[4]) / 1e5)
        cells[5] = repr(float(cells[5]) / 1e5)
        lines[i] = ",".join(cells)


def wild_csv_time(lines):
    t, rest = lines[100].split(",", 1)
    lines[100] = f"{float(t) + 1000:.9f},{rest}"


def bad_byte_line(tmp: Path) -> Path:
    data = (DATA / "reference.csv").read_bytes().split(b"\n")
    data[77] = data[77][:10] + b"\xff\xfe" + data[77][12:]
    return csv_text(tmp, "rig.csv", b"\n".join(data))


# --- the corpus ------------------------------------------------------------------------------------

@dataclasses.dataclass
class Case:
    id: str
    make: Callable[[Path], Path]
    error: str | None = None                  # substring of the error (which also names the file)
    kept: tuple[int, int] | None = None       # inclusive range of samples kept
    skipped: dict[str, int] = dataclasses.field(default_factory=dict)  # reasons that must be counted (>= n)
    problem: str | None = None                # substring of a problem (line, chunk, object named)
    lossy: bool | None = None
    truncated: bool | None = None
    options: dict = dataclasses.field(default_factory=dict)
    samples_lost: int | None = None
    same_times: bool = True                   # every kept time is a reference time (nothing invented)


CASES: list[Case] = []
add = CASES.append

# MCAP
for at in (60, 100, 140):  # a logger's clock stepped back: the jump is read in file order and counted
    for back_ms, block in ((30, True), (30, False), (1000, True), (1000, False)):
        n_back = min(back_ms, N_REF - at)  # samples behind the last one kept (the rest runs on past it)
        add(Case(f"mcap-log-time-back-{back_ms}ms-at-{at}-{'block' if block else 'rows'}",
                 mcap_stepped_back(at, back_ms, block), kept=(N_REF - n_back - 1, N_REF - n_back),
                 skipped={"time_backwards": n_back - 1}, lossy=True, same_times=False))
for k in range(4):
    add(Case(f"mcap-block-chunk-{k}-flipped", mcap_flip((BLOCK_TOPIC,), k), kept=(N_REF, N_REF),
             skipped={"damaged_chunk": 1}, problem=f"chunk {2 * k} at bytes", lossy=True, samples_lost=0))
    add(Case(f"mcap-row-chunk-{k}-flipped", mcap_flip((SIGNALS_TOPIC,), k), kept=(N_REF, N_REF), lossy=False))
    add(Case(f"mcap-both-chunks-{k}-flipped", mcap_flip((BLOCK_TOPIC, SIGNALS_TOPIC), k),
             kept=(N_REF - 50, N_REF - 50), skipped={"damaged_chunk": 2}, lossy=True, samples_lost=50,
             problem="crc validation failed"))
    add(Case(f"mcap-rows-only-chunk-{k}-flipped", mcap_flip((SIGNALS_TOPIC,), k, block=False),
             kept=(N_REF - 50, N_REF - 50), skipped={"damaged_chunk": 1}, samples_lost=50,
             problem=f"its 50 message(s) of {SIGNALS_TOPIC} are lost"))
for frac, kept in ((0.3, (0, 100)), (0.6, (50, 150))):
    add(Case(f"mcap-cut-at-{int(frac * 100)}pct", lambda tmp, f=frac: cut(mcap(tmp), f), kept=kept,
             truncated=True, problem="recovered", lossy=True))
add(Case("mcap-cut-in-the-summary", lambda tmp: cut(mcap(tmp), 0.95), kept=(N_REF, N_REF), lossy=False,
         problem="reading the file as a stream"))  # the data section is whole: nothing is lost
add(Case("mcap-summary-flipped", mcap_summary_flip, kept=(N_REF, N_REF), problem="reading the file as a stream"))
add(Case("mcap-magic-flipped", lambda tmp: flip(mcap(tmp), 1), error="not an MCAP file: starts with"))
add(Case("mcap-random-bytes", lambda tmp: csv_text(tmp, "r.mcap", rng_for("mcap").bytes(4096)),
         error="not an MCAP file"))
add(Case("mcap-empty", lambda tmp: csv_text(tmp, "e.mcap", b""), error="empty file (0 bytes)"))
add(Case("mcap-committed-reference-flipped",
         lambda tmp: flip(csv_text(tmp, "ref.mcap", (DATA / "reference.mcap").read_bytes()),
                          chunks_of(DATA / "reference.mcap", BLOCK_TOPIC)[0].chunk_start_offset + 60, 0x20),
         kept=(N_REF, N_REF), skipped={"damaged_chunk": 1}, problem="recovered from /rig/signals"))

# BLF
for k in (0, 2, 4):
    add(Case(f"blf-container-{k}-flipped", blf_flip_container(k), kept=(N_CAN - 12, N_CAN),
             skipped={"damaged_object": 1}, problem="container at byte", lossy=True))
add(Case("blf-object-signature-broken", blf_break_signature(3), kept=(N_CAN - 12, N_CAN - 1),
         skipped={"damaged_object": 1}, problem="object header damaged"))
add(Case("blf-file-signature-flipped", lambda tmp: flip(blf(tmp), 0, 0x01), kept=(N_CAN, N_CAN),
         skipped={"damaged_header": 1}, problem="expected b'LOGG'"))
add(Case("blf-frame-id-flipped", blf_flip_frame_id, kept=(N_CAN - 1, N_CAN), problem="is not in the DBC"))
add(Case("blf-cut-at-half", lambda tmp: cut(blf(tmp), 0.5), kept=(10, N_CAN - 10), truncated=True,
         problem="truncated"))
add(Case("blf-random-bytes", lambda tmp: csv_text(tmp, "r.blf", rng_for("blf").bytes(3000)),
         error="not a BLF file"))
add(Case("blf-empty", lambda tmp: csv_text(tmp, "e.blf", b""), error="empty file (0 bytes)"))

# text CAN logs
for suf in (".asc", ".log", ".trc"):
    for at in (0.1, 0.5, 0.9):
        add(Case(f"{suf[1:]}-bad-char-at-{int(at * 100)}pct", text_edit(suf, bad_char(at), f"{suf}{at}"),
                 kept=(N_CAN - 1, N_CAN), skipped={"bad_line": 1}, problem="that frame is lost", lossy=True))
    add(Case(f"{suf[1:]}-wild-timestamp", text_edit(suf, wild_time(suf), f"{suf}wild"), kept=(N_CAN - 1, N_CAN),
             skipped={"time_jump": 1}, problem="a wild timestamp"))
    add(Case(f"{suf[1:]}-garbage-line", text_edit(suf, garbage_line, f"{suf}junk"), kept=(N_CAN, N_CAN),
             skipped={"bad_line" if suf != ".asc" else "ignored_line": 1}))
    add(Case(f"{suf[1:]}-cut-mid-line", text_edit(suf, truncate_mid_line, f"{suf}cut"), kept=(N_CAN // 2 - 2,
             N_CAN // 2 + 1), truncated=True, problem="truncated"))
    add(Case(f"{suf[1:]}-binary-garbage", lambda tmp, s=suf: csv_text(tmp, f"g{s}", rng_for(s).bytes(2000)),
             error="no CAN frames found"))
    add(Case(f"{suf[1:]}-empty", lambda tmp, s=suf: csv_text(tmp, f"e{s}", b""), error="empty file (0 bytes)"))
    add(Case(f"{suf[1:]}-utf16", lambda tmp, s=suf: csv_text(
        tmp, f"u{s}", (DATA / f"msp25_short{s}").read_text().encode("utf-16")), error="no CAN frames found"))

# CSV
add(Case("csv-random-bytes", lambda tmp: csv_text(tmp, "r.csv", rng_for("csv").bytes(4000)),
         error="binary data (NUL byte at offset"))
add(Case("csv-random-high-bytes", lambda tmp: csv_text(tmp, "h.csv", bytes(rng_for("hi").integers(128, 256, 500,
         dtype=np.uint8))), error="not UTF-8 text: byte 0x"))
add(Case("csv-utf16", lambda tmp: csv_text(tmp, "u.csv", (DATA / "reference.csv").read_text().encode("utf-16")),
         error="UTF-16 encoded text (byte order mark ff fe)"))
add(Case("csv-utf16-no-bom", lambda tmp: csv_text(tmp, "u.csv", (DATA / "reference.csv").read_text()
                                                  .encode("utf-16-le")), error="UTF-16 encoded text without"))
add(Case("csv-utf8-bom", lambda tmp: csv_text(tmp, "b.csv", b"\xef\xbb\xbf" + (DATA / "reference.csv").read_bytes()),
         kept=(N_REF, N_REF), lossy=False))
add(Case("csv-empty", lambda tmp: csv_text(tmp, "e.csv", b""), error="empty file (0 bytes)"))
add(Case("csv-blank-lines-only", lambda tmp: csv_text(tmp, "b.csv", "\n\n# c\n"), error="empty file (only blank"))
add(Case("csv-header-only", lambda tmp: csv_text(tmp, "h.csv", "t,x\n"), error="no data rows after the header "
         "(line 1): an empty record"))
add(Case("csv-wrong-columns", csv_edit(lambda ls: ls.__setitem__(0, "time,dem,out,pos,pa,pb")),
         error="no time column 't' (s) and no column that is a known signal; found columns 'time', 'dem'"))
add(Case("csv-no-time-column", csv_edit(lambda ls: ls.__setitem__(0, "time,x_ref,u,x,pA,pB")),
         error="no time column 't' (s); found columns 'time', 'x_ref'"))
add(Case("csv-foreign-signals", csv_edit(lambda ls: ls.__setitem__(0, "t,a,b,c,d,e")),
         error="no column that is a known signal; found columns 't', 'a', 'b'"))
add(Case("csv-time-in-ms", csv_edit(scale_time(1e3)), error="(1.00007 Hz) is implausible for a rig record "
         "(expected 10 Hz to 200000 Hz in seconds); the times look like ms (1000.07 Hz): give the unit with "
         "--map t=t:ms"))
add(Case("csv-time-in-us", csv_edit(scale_time(1e6)), error="the times look like us (1000"))
add(Case("csv-time-in-ms-mapped", csv_edit(scale_time(1e3)), kept=(N_REF, N_REF),
         options={"mapping": parse_map(["t=t:ms"])}, lossy=False, same_times=False))
add(Case("csv-duplicate-times", csv_edit(dup_rows), kept=(N_REF, N_REF), skipped={"time_repeated": 19},
         problem="repeats", lossy=True))
add(Case("csv-time-backwards", csv_edit(swap_rows), kept=(N_REF - 1, N_REF - 1), skipped={"time_backwards": 1},
         problem="goes backwards"))
add(Case("csv-wild-time", csv_edit(wild_csv_time), kept=(N_REF - 1, N_REF - 1), skipped={"time_jump": 1},
         problem="jumps"))
add(Case("csv-nan-cells", csv_edit(lambda ls: [set_cell(r, 3, "nan")(ls) for r in (10, 20, 30)]),
         kept=(N_REF - 3, N_REF - 3), skipped={"nan": 3}, problem="signal 'x' is nan, expected a finite value"))
add(Case("csv-inf-cells", csv_edit(lambda ls: [set_cell(r, 4, "inf")(ls) for r in (40, 41)]),
         kept=(N_REF - 2, N_REF - 2), skipped={"inf": 2}, problem="signal 'pA' is inf"))
add(Case("csv-text-cell", csv_edit(set_cell(60, 2, "abc")), kept=(N_REF - 1, N_REF - 1), skipped={"bad_row": 1},
         problem="line 61: field 'u' = 'abc' is not a number, expected a float"))
add(Case("csv-empty-cell", csv_edit(set_cell(70, 5, "")), kept=(N_REF - 1, N_REF - 1), skipped={"bad_row": 1},
         problem="line 71: field 'pB' is empty"))
add(Case("csv-short-row", csv_edit(lambda ls: ls.__setitem__(90, "1700000000.5,1,2")), kept=(N_REF - 1, N_REF - 1),
         skipped={"bad_row": 1}, problem="line 91: 3 fields, expected 6"))
add(Case("csv-bad-byte-in-a-row", bad_byte_line, kept=(N_REF - 1, N_REF - 1), skipped={"bad_row": 1},
         problem="line 78: field"))
add(Case("csv-pressures-in-bar", csv_edit(bar_pressures), error="the values look like bar"))
# a ';'-separated export is read as one (its ',' in numbers would be decimal commas): nothing lost
add(Case("csv-semicolons", csv_edit(lambda ls: ls.__setitem__(slice(None), [x.replace(",", ";") for x in ls])),
         kept=(N_REF, N_REF), lossy=False))
add(Case("csv-oscillator-time-in-ms", lambda tmp: csv_text(tmp, "o.csv", "t,u,y\n" + "".join(
    f"{i * 10},{0.0},{1e-5 * i}\n" for i in range(50))), error="look like ms (100 Hz)"))
add(Case("csv-directory", lambda tmp: (tmp / "dir.csv").mkdir() or tmp / "dir.csv", error="is a directory"))
add(Case("csv-missing", lambda tmp: tmp / "missing.csv", error="does not exist"))


# hostile and unusual inputs: bounds before allocation, times beyond int64, real-world CSV shapes
def mcap_times(times: list[int]) -> Callable[[Path], Path]:
    def make(tmp: Path) -> Path:
        from mcap.writer import Writer

        p = tmp / "times.mcap"
        with open(p, "wb") as f:
            w = Writer(f)
            w.start()
            cid = w.register_channel(SIGNALS_TOPIC, "json", w.register_schema("rig", "jsonschema", b"{}"))
            for i, t in enumerate(times):
                w.add_message(cid, log_time=t, publish_time=t, data=b'{"x": %r}' % (1e-4 * i))
            w.finish()
        return p
    return make


T0 = 1_700_000_000_000_000_000
add(Case("mcap-only-its-magic", lambda tmp: csv_text(tmp, "m.mcap", b"\x89MCAP0\r\n"),
         error="MCAP file of 8 bytes ends right after its magic"))
add(Case("mcap-log-time-2^63", mcap_times([T0 + i * 10**6 if i != 20 else 1 << 63 for i in range(50)]),
         kept=(49, 49), skipped={"bad_time": 1}, problem="beyond the int64 ns range", lossy=True, same_times=False))
add(Case("mcap-log-time-2^64-1", mcap_times([T0 + i * 10**6 if i != 20 else (1 << 64) - 1 for i in range(50)]),
         kept=(49, 49), skipped={"bad_time": 1}, lossy=True, same_times=False))
add(Case("mcap-log-time-in-ms", mcap_times([1_700_000_000_000 + i for i in range(50)]),
         error="median time step 1e-09 s (1e+09 Hz) over the first 50 samples is not a rig record's rate"))
add(Case("csv-header-200000-columns", lambda tmp: csv_text(tmp, "w.csv", ",".join(f"c{i}" for i in range(200_000))
                                                           + "\n"), error="header longer than 1048576 characters"))
add(Case("csv-header-5000-columns", lambda tmp: csv_text(tmp, "w.csv", "t," + ",".join(f"c{i}" for i in range(4999))
                                                         + "\n0" + ",1" * 4999 + "\n"),
         error="header has 5000 columns, more than 4096"))
add(Case("csv-line-of-3-MB", csv_edit(lambda ls: ls.insert(50, "1" * (3 << 20))), kept=(N_REF, N_REF),
         skipped={"bad_row": 1}, problem="line 51: line longer than 1048576 characters", lossy=True))
add(Case("csv-time-jump-1e9-s", csv_edit(lambda ls: ls.__setitem__(slice(101, None), [
    f"{float(x.split(',')[0]) + 1e9:.9f},{x.split(',', 1)[1]}" for x in ls[101:]])), kept=(N_REF, N_REF),
    lossy=False, same_times=False))
add(Case("csv-time-beyond-int64", csv_edit(set_cell(30, 0, "9.3e9")), kept=(N_REF - 1, N_REF - 1),
         skipped={"bad_time": 1}, problem="is not a finite time in seconds within +-9.2e+09 s"))
add(Case("csv-pretrigger-negative-times", csv_edit(lambda ls: ls.__setitem__(slice(1, None), [
    f"{(i - 50) * 1e-3:.3f},{x.split(',', 1)[1]}" for i, x in enumerate(ls[1:])])), kept=(N_REF, N_REF),
    lossy=False, same_times=False))
add(Case("csv-trailing-delimiters-and-quotes", csv_edit(lambda ls: ls.__setitem__(slice(None), [
    ",".join(f'"{c}"' for c in ls[0].split(",")) + ","] + [x + "," for x in ls[1:]])), kept=(N_REF, N_REF),
    lossy=False))
add(Case("csv-gzip", lambda tmp: csv_text(tmp, "r.csv.gz", __import__("gzip").compress(
    (DATA / "reference.csv").read_bytes())), kept=(N_REF, N_REF), lossy=False))
def gzip_cut(tmp: Path) -> Path:
    import gzip

    rows = [f"{i * 1e-3:.3f},0.0,0.0,{1e-6 * (i % 97)!r},1e7,1e7" for i in range(20000)]
    data = gzip.compress(("t,x_ref,u,x,pA,pB\n" + "\n".join(rows) + "\n").encode())
    return csv_text(tmp, "cut.csv.gz", data[: len(data) * 3 // 5])


add(Case("csv-gzip-cut-after-the-first-block", gzip_cut, kept=(1000, 19999), truncated=True, lossy=True,
         problem="the gzip stream is cut or corrupt", same_times=False))
add(Case("csv-gzip-not-gzip", lambda tmp: csv_text(tmp, "r.csv.gz", (DATA / "reference.csv").read_bytes()),
         error="not a readable gzip file"))
add(Case("csv-no-time-column-and-no-rate", csv_edit(lambda ls: ls.__setitem__(slice(None), [
    x.split(",", 1)[1] for x in ls])), error="a file without a time column needs its sample rate: --rate HZ"))
add(Case("csv-no-time-column-absurd-rate", csv_edit(lambda ls: ls.__setitem__(slice(None), [
    x.split(",", 1)[1] for x in ls])), options={"rate_hz": 1e15}, error="expected a sample rate from 10 Hz"))
add(Case("asc-nul-bytes-in-a-frame-line", text_edit(".asc", lambda ls, fr, r: ls.__setitem__(
    fr[20], ls[fr[20]][:12] + "\x00\x00\x00" + ls[fr[20]][15:]), "ascnul"), kept=(N_CAN - 1, N_CAN),
    skipped={"bad_line": 1}, lossy=True))
add(Case("log-timestamp-1e300", text_edit(".log", lambda ls, fr, r: ls.__setitem__(
    fr[30], "(1e300)" + ls[fr[30]].split(")", 1)[1]), "log1e300"), kept=(N_CAN - 1, N_CAN),
    skipped={"bad_time": 1}, problem="is not a time within", lossy=True))
add(Case("trc-line-of-3-MB", text_edit(".trc", lambda ls, fr, r: ls.insert(fr[10], "1" * (3 << 20)), "trclong"),
         kept=(N_CAN - 1, N_CAN), skipped={"bad_line": 1}, lossy=True))


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_damaged_input(tmp_path: Path, case: Case) -> None:
    path = case.make(tmp_path)
    if case.error is not None:
        with pytest.raises(TwinError) as exc:
            with open_source(path, **case.options) as src:
                src.read_all()
        text = str(exc.value)
        assert text.startswith(f"{path}: ") or f"{path}" in text, text
        assert case.error in text, text
        assert "\n" not in text
        return
    with open_source(path, **case.options) as src:
        got = src.read_all()
        report = src.report
    problems = "\n".join(map(str, report.problems))
    lo, hi = case.kept
    assert lo <= len(got) <= hi, (len(got), report.summary(), problems)
    ref_t = {".csv": ref().t_ns, ".mcap": ref_mcap().t_ns, ".gz": ref().t_ns}.get(path.suffix)
    if ref_t is not None and len(got) and case.same_times:  # nothing invented: every time kept is a reference time
        assert np.isin(got.t_ns, ref_t).all() and (np.diff(got.t_ns) > 0).all()
    for reason, n in case.skipped.items():
        assert report.skipped[reason] >= n, (reason, report.skipped, problems)
    if case.problem is not None:
        assert case.problem in problems, problems
    if case.lossy is not None:
        assert report.lossy == case.lossy, report.summary()
    if case.truncated is not None:
        assert report.truncated == case.truncated, report.summary()
    if case.samples_lost is not None:
        assert report.samples_lost == case.samples_lost, report.summary()


def test_the_corpus_is_large_enough() -> None:
    assert len(CASES) + len(PAYLOADS) + len(CLI) >= 60


@pytest.mark.slow
def test_generated_corpus_is_never_silent(tmp_path: Path) -> None:
    """The generated corpus of ``python -m benchmarks.damage`` (>= 300 damaged inputs of every format): each one
    is refused with one line naming the file, read with its loss reported, or read equal to the undamaged
    record; none takes longer than 30 s (a hang), none raises anything else."""
    import concurrent.futures

    from benchmarks import damage

    bases = damage.write_bases_cached(tmp_path)
    refs = {k: damage._read(p, {}) for k, p in bases.items()}
    cases = damage.inputs()
    assert len(cases) >= 300 and len({c.id for c in cases}) == len(cases)
    outcomes: dict[str, list[str]] = {k: [] for k in damage.OUTCOMES}
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        for case in cases:
            path = case.make(tmp_path)
            ref = refs.get(".csv" if case.id.startswith(("csv-no-time-column-rate", "csv-crlf", "csv-bom",
                                                         "csv-quoted", "csv-trailing")) or case.id == "csv-gzip"
                           else case.base)
            try:
                result = pool.submit(damage._read, path, case.options).result(timeout=30)
            except concurrent.futures.TimeoutError:
                result = None
            outcome, note = damage.classify_read(result, path, ref)
            outcomes[outcome].append(f"{case.id}: {note}")
            if result is None:
                break  # the worker is stuck: the rest cannot run
    bad = outcomes["silent"] + outcomes["traceback"] + outcomes["hang"]
    assert not bad, "\n".join(bad)
    assert len(outcomes["clear"]) >= 200 and len(outcomes["ok"]) >= 20  # damage is found, benign edits pass


# --- live payloads ---------------------------------------------------------------------------------

def _good_frames() -> bytes:
    from benchmarks.can import msp25_samples
    from replay.can.encode import FrameScheduler
    from replay.can.codec import VectorCodec

    return frames_to_payload(FrameScheduler(VectorCodec()).frames(msp25_samples(0.01, seed=1)))


PAYLOADS = [
    ("not-json", b"{not json", "bad_json", "payload is not JSON"),
    ("random-bytes", bytes(rng_for("payload").integers(0, 256, 200, dtype=np.uint8)), "bad_json", "not JSON"),
    ("array", b"[1,2,3]", "bad_schema", "JSON list, not an object"),
    ("no-format", b'{"t_ns":5,"signals":[1,2]}', "bad_schema", "\"format\" is None"),
    ("signals-list", b'{"format":"fpdd.samples/1","t_ns":5,"signals":[1,2]}', "bad_schema",
     "\"signals\" is list"),
    ("lengths-differ", b'{"format":"fpdd.samples/1","t_ns":[1,2],"signals":{"x":[1.0]}}', "bad_schema",
     "signal 'x' is a list of 1, expected a list as long as t_ns (2)"),
    ("text-value", b'{"format":"fpdd.samples/1","t_ns":[1],"signals":{"x":["1"]}}', "bad_schema",
     "signal 'x'[0] = '1' is not a number"),
    ("t-beyond-int64", b'{"format":"fpdd.samples/1","t_ns":[1180591620717411303424],"signals":{"x":[0]}}',
     "bad_time", "beyond the int64 range"),
    ("t-float", b'{"format":"fpdd.samples/1","t_ns":[1.5],"signals":{"x":[0]}}', "bad_time",
     "t_ns[0] = 1.5 is a float"),
    ("t-bool", b'{"format":"fpdd.samples/1","t_ns":true,"signals":{"x":0}}', "bad_time", "\"t_ns\" is True"),
    ("too-many-samples", b'{"format":"fpdd.samples/1","t_ns":[' + b",".join([b"1"] * 101) +
     b'],"signals":{"x":[0]}}', "oversized", "101 samples in one payload, at most 100 accepted"),
    ("can-bad-magic", b"XCAN" + bytes(28), "bad_payload", "not an fpdd.can payload"),
    ("can-bad-version", b"FCAN\x07\x00\x18\x00", "bad_payload", "fpdd.can version 7"),
    ("can-cut-record", _good_frames()[:-5], "bad_payload", "records of 24 bytes"),
    ("can-dlc-too-big", _good_frames()[:8] + _good_frames()[8:20] + b"\x09" + _good_frames()[21:32], "bad_payload",
     "DLC > 8"),
]


@pytest.mark.parametrize("payload, cause, message", [p[1:] for p in PAYLOADS], ids=[p[0] for p in PAYLOADS])
def test_bad_live_payload(payload: bytes, cause: str, message: str) -> None:
    with pytest.raises(PayloadError) as exc:
        if payload[:4] in (b"FCAN", b"XCAN"):
            payload_to_frames(payload, "payload 7")
        else:
            json_to_samples(payload, "payload 7", max_block=100)
    assert exc.value.cause == cause
    assert str(exc.value).startswith("payload 7: ") and message in str(exc.value), str(exc.value)


def test_non_finite_live_values_are_marked_not_null() -> None:
    s, bad = json_to_samples(b'{"format":"fpdd.samples/1","t_ns":[1,2,3],"signals":{"x":[NaN,null,1e999]}}', "p")
    assert bad.tolist() == [True, False, True] and np.isnan(s["x"][1])


# --- through the command line: one line, the right exit status ------------------------------------

CLI = [
    ("csv-random-bytes", lambda tmp: csv_text(tmp, "r.csv", rng_for("cli").bytes(1000)), 1, "binary data"),
    ("csv-wrong-columns", csv_edit(lambda ls: ls.__setitem__(0, "time,dem,out,pos,pa,pb")), 1,
     "map foreign columns with --map NAME=COLUMN[:UNIT]"),
    ("csv-ms", csv_edit(scale_time(1e3)), 1, "--map t=t:ms"),
    ("csv-text-cell", csv_edit(set_cell(60, 2, "abc")), 3, "input lost (bad_row=1); 199 samples kept"),
    ("mcap-both-chunks", mcap_flip((BLOCK_TOPIC, SIGNALS_TOPIC), 1), 3, "input lost (damaged_chunk=2"),
    ("trc-bad-char", text_edit(".trc", bad_char(0.5), "cli.trc"), 3, "input lost (bad_line=1)"),
    ("blf-container", blf_flip_container(2), 3, "damaged_object="),
    ("directory", lambda tmp: tmp, 1, "is a directory"),
]


@pytest.mark.parametrize("make, code, message", [c[1:] for c in CLI], ids=[c[0] for c in CLI])
def test_damaged_input_on_the_command_line(tmp_path, capsys, make, code, message) -> None:
    path = make(tmp_path)
    assert cli.main(["info", str(path)]) == code
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and str(path) in err, err
    assert "Traceback" not in err


@pytest.mark.slow
def test_track_takes_a_huge_time_jump_and_a_pretrigger_record(tmp_path, capsys) -> None:
    """A 1e9 s jump in the middle of a record (the drift test once sized a buffer by the time spanned: 4.37 TiB)
    and a record whose times start at -50 ms (events need ingest times >= 0: shifted to start at 0) both run."""
    import json

    from twin import cli as twin_cli

    jump = csv_edit(lambda ls: ls.__setitem__(slice(101, None), [
        f"{float(x.split(',')[0]) + 1e9:.9f},{x.split(',', 1)[1]}" for x in ls[101:]]), "jump.csv")(tmp_path)
    pre = csv_edit(lambda ls: ls.__setitem__(slice(1, None), [
        f"{(i - 50) * 1e-3:.3f},{x.split(',', 1)[1]}" for i, x in enumerate(ls[1:])]), "pre.csv")(tmp_path)
    for path in (jump, pre):
        assert twin_cli.main(["track", str(path), "--out", str(tmp_path / path.stem), "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["samples"] == N_REF


def test_serve_replays_a_pretrigger_record(tmp_path, capsys) -> None:
    """``twin serve`` replays a log whose times start below 0 from 0 (it failed on the first estimate's time)."""
    from net_helpers import free_port
    from twin import cli as twin_cli

    pre = csv_edit(lambda ls: ls.__setitem__(slice(1, None), [
        f"{(i - 50) * 1e-3:.3f},{x.split(',', 1)[1]}" for i, x in enumerate(ls[1:])]), "pre.csv")(tmp_path)
    config = tmp_path / "rigs.toml"
    config.write_text(f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{free_port()}"]\n[service]\n'
                      f'journal_dir = "{tmp_path / "journal"}"\n[[rig]]\nname = "pre"\nsource = "{pre}"\nspeed = 0\n')
    assert twin_cli.main(["serve", "--config", str(config)]) == 0
    assert f"summary pre: finished, {N_REF} samples" in capsys.readouterr().err
