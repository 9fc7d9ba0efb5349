# mypy: disable-error-code="misc"
# (the corpus binds loop variables as lambda defaults, whose types mypy does not infer)
"""How replay and the service's configuration take damaged and hostile input: a generated corpus and its counts.

    python -m benchmarks.damage [--json] [--only KIND] [--timeout S] [--verbose]
    python -m benchmarks.damage --survival

Generates (seeded, deterministic) a corpus of damaged inputs from one 0.5 s, 1 kHz MSP25
record written as CSV, MCAP and every CAN log format (ASC, BLF, candump ``.log``, TRC),
and a corpus of rig configurations (``rigs.toml``) around a valid one, then reads each
input through :func:`replay.factory.open_source` and validates each configuration with
:func:`twin.service.config.load_config`, every one in its own process with a time limit.
Each outcome is one of:

``clear``
    refused with one line naming the file (an input) or the file and key (a configuration),
    or read with what was lost said in the read report (``lossy``) or a time gap reported;
``ok``
    read completely and equal to the undamaged record (the damage cost nothing), or a
    valid configuration accepted;
``silent``
    read with nothing said, but different from the undamaged record; or a configuration
    that should be refused accepted;
``traceback``
    any other exception, or an error message of more than one line or not naming the file;
``hang``
    not done within the time limit (default 30 s).

The damage kinds go beyond single bit flips and cuts: bit flips and zeroed runs
anywhere, cuts at every part of a file, chunk header fields (sizes, times) set to
absurd values, message times at and beyond 2^63 ns, time jumps of 1e9 s, negative
times, a CSV header of 200 000 columns and lines of megabytes, NUL bytes, junk and
duplicated or swapped lines, values of 1e999, CAN timestamps far in the future.
The configurations cover every key with wrong types, non-finite, huge and tiny
numbers, NUL bytes and very long strings in paths and names, unknown CAN
interfaces and Zenoh sources that would read the service's own outputs.

A CSV cut exactly at a line end and a digit changed inside a text value are not in
the corpus: nothing in a CSV or text CAN log can tell them from a good file.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import struct
import sys
import tempfile
import time
import zlib
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

OUTCOMES = ("clear", "ok", "silent", "traceback", "hang")


@dataclasses.dataclass
class Input:
    """One damaged input: ``make(dir)`` writes it and returns its path; ``base`` names the undamaged file."""

    id: str
    make: Callable[[Path], Path]
    base: str
    options: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class Config:
    """One configuration: its text (``LOG``, ``JOURNAL`` and ``ROOT`` are put in) and whether it is valid."""

    id: str
    text: str
    valid: bool


# --- the undamaged record -------------------------------------------------------------------------

def _rng(name: str) -> np.random.Generator:
    return np.random.default_rng(zlib.crc32(name.encode()))


def write_bases(d: Path) -> dict[str, Path]:
    """The undamaged record (0.5 s of MSP25 signals) as CSV, MCAP and each CAN log format."""
    from benchmarks.can import msp25_samples
    from replay.can.logs import CanLogSink
    from replay.csvio import CsvSink
    from replay.mcapio import McapSink

    s = msp25_samples(0.5, seed=3)
    rig = type(s)(s.t_ns - s.t_ns[0], {k: s[k] for k in ("x_ref", "u", "x", "pA", "pB")})  # record-relative
    out: dict[str, Path] = {}
    with CsvSink(d / "base.csv") as sink:
        sink.write(rig)
    out[".csv"] = d / "base.csv"
    with McapSink(d / "base.mcap", flush_period_s=0.1) as sink:
        sink.write(s)
    out[".mcap"] = d / "base.mcap"
    with McapSink(d / "rows.mcap", flush_period_s=0.1, block=False) as sink:
        sink.write(s)
    out["rows.mcap"] = d / "rows.mcap"
    for suf in (".asc", ".blf", ".log", ".trc"):
        with CanLogSink(d / f"base{suf}") as sink:
            sink.write(s)
        out[suf] = d / f"base{suf}"
    return out


# --- damage primitives ------------------------------------------------------------------------------

def _bytes_case(d: Path, bases: dict[str, Path], base: str, name: str, edit: Callable[[bytearray], bytes | bytearray],
                suffix: str | None = None) -> Path:
    data = bytearray(bases[base].read_bytes())
    p = d / f"{name}{suffix or bases[base].suffix}"
    p.write_bytes(bytes(edit(data)))
    return p


def _flip(offset_frac: float, mask: int) -> Callable[[bytearray], bytearray]:
    def edit(b: bytearray) -> bytearray:
        i = min(len(b) - 1, int(offset_frac * len(b)))
        b[i] ^= mask
        return b
    return edit


def _zero(offset_frac: float, n: int) -> Callable[[bytearray], bytearray]:
    def edit(b: bytearray) -> bytearray:
        i = int(offset_frac * len(b))
        b[i:i + n] = bytes(len(b[i:i + n]))
        return b
    return edit


def _cut(frac: float, avoid_line_end: bool = False) -> Callable[[bytearray], bytearray]:
    def edit(b: bytearray) -> bytearray:
        i = max(1, int(frac * len(b)))
        while avoid_line_end and 0 < i < len(b) and (b[i - 1:i] == b"\n" or b[i:i + 1] in (b"\n", b"\r")):
            i += 1
        return b[:i]
    return edit


def _lines(edit: Callable[[list[bytes]], None]) -> Callable[[bytearray], bytes]:
    def run(b: bytearray) -> bytes:
        lines = bytes(b).split(b"\n")
        edit(lines)
        return b"\n".join(lines)
    return run


# --- MCAP structure -----------------------------------------------------------------------------------

def _chunks(path: Path) -> list[tuple[int, int]]:
    """(offset, length) of every chunk record, by walking the records."""
    data = path.read_bytes()
    pos, out = 8, []
    while pos + 9 <= len(data):
        op, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], "little")
        if op == 0x06:
            out.append((pos, 9 + length))
        if op == 0x0F:  # data end
            break
        pos += 9 + length
    return out


def _chunk_field(k: int, field: str, value: int) -> Callable[[Path, bytearray], bytearray]:
    """Set a chunk header field: start/end time (u64), uncompressed size (u64) or the record length."""
    offsets = {"start": 9, "end": 17, "size": 25, "length": 1}

    def edit(path: Path, b: bytearray) -> bytearray:
        pos, _ = _chunks(path)[k]
        struct.pack_into("<Q", b, pos + offsets[field], value)
        return b
    return edit


def _mcap_messages(d: Path, name: str, times: list[int]) -> Path:
    """A per-sample MCAP written by the mcap library with the given log times (ns, any uint64)."""
    from mcap.writer import Writer

    p = d / f"{name}.mcap"
    with open(p, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("rig", "jsonschema", b'{"type":"object"}')
        cid = w.register_channel("/rig/signals", "json", sid)
        for i, t in enumerate(times):
            w.add_message(cid, log_time=t, publish_time=t, data=json.dumps({"x": 1e-4 * i, "pA": 1e7}).encode())
        w.finish()
    return p


# --- the input corpus ---------------------------------------------------------------------------------

def inputs() -> list[Input]:
    """Every damaged input of the corpus (ids unique, generation seeded by the id)."""
    cases: list[Input] = []

    def add(id_: str, base: str, make: Callable[[Path, dict[str, Path]], Path], **options) -> None:
        cases.append(Input(id_, lambda d, m=make: m(d, write_bases_cached(d)), base, options))

    def byte_edit(id_: str, base: str, edit: Callable[[bytearray], bytes | bytearray], suffix: str | None = None,
                  **options) -> None:
        add(id_, base, lambda d, b, e=edit, i=id_: _bytes_case(d, b, base, i, e, suffix), **options)

    # MCAP (block and per-sample topics) and MCAP with only the per-sample topic
    for base in (".mcap", "rows.mcap"):
        tag = "mcap" if base == ".mcap" else "mcap-rows"
        for k in range(32):
            r = _rng(f"{tag}-flip-{k}")
            byte_edit(f"{tag}-bitflip-{k}", base, _flip(float(r.uniform(0.01, 0.99)), 1 << int(r.integers(8))))
        for k in range(6):
            r = _rng(f"{tag}-zero-{k}")
            byte_edit(f"{tag}-zeroed-{k}", base, _zero(float(r.uniform(0.01, 0.95)), int(r.integers(16, 600))))
        for k in range(10):
            byte_edit(f"{tag}-cut-{k}", base, _cut(float(_rng(f"{tag}-cut-{k}").uniform(0.02, 0.999))))
        for k, (field, value) in enumerate((("size", 1 << 62), ("size", 0), ("start", (1 << 64) - 1),
                                            ("end", 1 << 63), ("length", 1 << 40), ("length", 3),
                                            ("size", 1 << 31))):
            edit = _chunk_field(k % 3, field, value)
            add(f"{tag}-chunk-{field}-{value}", base,
                lambda d, b, e=edit, i=f"{tag}-chunk-{field}-{value}", bb=base: _bytes_case(
                    d, b, bb, i, lambda data, e=e, p=b[bb]: e(p, data)))
    for n in (8, 9, 12, 16, 20, 24, 30):
        byte_edit(f"mcap-first-{n}-bytes", ".mcap", lambda b, n=n: b[:n])
    byte_edit("mcap-magic-twice", ".mcap", lambda b: b[:8] + b[:8])
    byte_edit("mcap-garbage-after-magic", ".mcap", lambda b: b[:8] + bytes(_rng("g").integers(0, 256, 4000,
                                                                                         dtype=np.uint8)))
    t0 = 1_700_000_000_000_000_000
    for name, bad in (("2^63", 1 << 63), ("2^64-1", (1 << 64) - 1), ("2^63-1", (1 << 63) - 1), ("0", 0)):
        add(f"mcap-log-time-{name}", "times.mcap",
            lambda d, b, bad=bad, name=name: _mcap_messages(d, f"t{name}", [t0 + i * 1_000_000 if i != 250 else bad
                                                                             for i in range(500)]))
    add("mcap-log-time-jump-1e9s", "times.mcap", lambda d, b: _mcap_messages(
        d, "jump", [t0 + i * 1_000_000 + (10**18 if i >= 250 else 0) for i in range(500)]))
    add("mcap-log-times-all-beyond-int64", "times.mcap", lambda d, b: _mcap_messages(
        d, "beyond", [(1 << 63) + i * 1_000_000 for i in range(500)]))

    # CSV
    for k in range(16):
        r = _rng(f"csv-cut-{k}")
        byte_edit(f"csv-cut-{k}", ".csv", _cut(float(r.uniform(0.01, 0.999)), avoid_line_end=True))
    for k in range(4):  # inside the last number of a row: the row still parses, to a smaller value
        byte_edit(f"csv-cut-in-last-field-{k}", ".csv", lambda b, k=k: b[:[i for i, c in enumerate(b) if c == 10][
            int(_rng(f"csv-cut-last-{k}").integers(5, 400))] - 3])
    for k in range(6):
        byte_edit(f"csv-nul-run-{k}", ".csv", _zero(float(_rng(f"csv-nul-{k}").uniform(0.05, 0.95)), 8))

    def csv_row_edit(id_: str, fn: Callable[[list[bytes], np.random.Generator], None]) -> None:
        byte_edit(id_, ".csv", _lines(lambda ls, f=fn, i=id_: f(ls, _rng(i))))

    def data_row(ls: list[bytes], r: np.random.Generator) -> int:
        return int(r.integers(2, len(ls) - 2))

    for k in range(4):
        csv_row_edit(f"csv-junk-line-{k}", lambda ls, r: ls.insert(data_row(ls, r), bytes(
            r.integers(33, 127, 30, dtype=np.uint8)).replace(b"#", b"!")))
        csv_row_edit(f"csv-duplicated-row-{k}", lambda ls, r: ls.insert((i := data_row(ls, r)), ls[i]))
        csv_row_edit(f"csv-swapped-rows-{k}", lambda ls, r: ls.__setitem__(
            slice((i := data_row(ls, r)), i + 2), [ls[i + 1], ls[i]]))
        csv_row_edit(f"csv-text-field-{k}", lambda ls, r: ls.__setitem__(
            (i := data_row(ls, r)), ls[i].replace(b",", b",abc", 1)))
        csv_row_edit(f"csv-missing-field-{k}", lambda ls, r: ls.__setitem__(
            (i := data_row(ls, r)), ls[i].rsplit(b",", 1)[0]))
        csv_row_edit(f"csv-extra-field-{k}", lambda ls, r: ls.__setitem__((i := data_row(ls, r)), ls[i] + b",7"))
        csv_row_edit(f"csv-1e999-{k}", lambda ls, r: ls.__setitem__(
            (i := data_row(ls, r)), b",".join(ls[i].split(b",")[:3] + [b"1e999"] + ls[i].split(b",")[4:])))
        csv_row_edit(f"csv-wild-time-{k}", lambda ls, r: ls.__setitem__(
            (i := data_row(ls, r)), b"%.9f" % (float(ls[i].split(b",")[0]) + 1e6) + b"," + ls[i].split(b",", 1)[1]))
        csv_row_edit(f"csv-long-line-{k}", lambda ls, r: ls.insert(data_row(ls, r), b"1" * (3 << 20)))
    csv_row_edit("csv-time-jump-1e9s", lambda ls, r: ls.__setitem__(slice(250, None), [
        b"%.9f" % (float(x.split(b",")[0]) + 1e9) + b"," + x.split(b",", 1)[1] if x else x for x in ls[250:]]))
    csv_row_edit("csv-time-beyond-int64", lambda ls, r: ls.__setitem__(
        100, b"9.3e9," + ls[100].split(b",", 1)[1]))
    csv_row_edit("csv-times-negative-pretrigger", lambda ls, r: ls.__setitem__(slice(1, None), [
        b"%.9f" % (float(x.split(b",")[0]) - 0.1) + b"," + x.split(b",", 1)[1] if x else x for x in ls[1:]]))
    csv_row_edit("csv-x-1e308", lambda ls, r: ls.__setitem__(
        (i := data_row(ls, r)), b",".join(ls[i].split(b",")[:3] + [b"1e308"] + ls[i].split(b",")[4:])))
    for n in (5000, 200_000):
        byte_edit(f"csv-header-{n}-columns", ".csv", lambda b, n=n: b",".join(b"c%d" % i for i in range(n)) + b"\n"
                  + b"\n".join(b",".join([b"0"] * n) for _ in range(3)) + b"\n")
    byte_edit("csv-header-2MB-line", ".csv", lambda b: b"t," + b"x" * (2 << 20) + b"\n0,1\n")
    byte_edit("csv-no-newline-at-all", ".csv", lambda b: bytes(b).replace(b"\n", b";"))
    byte_edit("csv-crlf", ".csv", lambda b: bytes(b).replace(b"\n", b"\r\n"))
    byte_edit("csv-bom", ".csv", lambda b: b"\xef\xbb\xbf" + bytes(b))
    byte_edit("csv-quoted-header", ".csv", lambda b: b",".join(b'"%s"' % c for c in bytes(b).split(b"\n", 1)[0]
                                                               .split(b",")) + b"\n" + bytes(b).split(b"\n", 1)[1])
    byte_edit("csv-trailing-delimiters", ".csv", lambda b: b"\n".join(x + b"," if x else x
                                                                      for x in bytes(b).split(b"\n")))
    byte_edit("csv-header-only", ".csv", lambda b: bytes(b).split(b"\n", 1)[0] + b"\n")
    byte_edit("csv-utf16", ".csv", lambda b: bytes(b).decode().encode("utf-16"))
    byte_edit("csv-gzip", ".csv", lambda b: __import__("gzip").compress(bytes(b)), suffix=".csv.gz")
    byte_edit("csv-gzip-cut", ".csv", lambda b: __import__("gzip").compress(bytes(b))[:2000], suffix=".csv.gz")
    byte_edit("csv-not-gzip", ".csv", lambda b: b, suffix=".csv.gz")
    byte_edit("csv-empty", ".csv", lambda b: b"")
    byte_edit("csv-only-newlines", ".csv", lambda b: b"\n" * 100000)
    byte_edit("csv-no-time-column", ".csv", lambda b: bytes(b).replace(b"t,", b"time,", 1))
    byte_edit("csv-no-time-column-rate", ".csv", lambda b: b"\n".join(x.split(b",", 1)[1] if b"," in x else x
                                                                      for x in bytes(b).split(b"\n")),
              rate_hz=1000.0)
    byte_edit("csv-absurd-rate", ".csv", lambda b: b"\n".join(x.split(b",", 1)[1] if b"," in x else x
                                                             for x in bytes(b).split(b"\n")), rate_hz=1e15)

    # CAN logs: text formats
    for suf in (".asc", ".log", ".trc"):
        tag = suf[1:]
        for k in range(6):
            byte_edit(f"{tag}-cut-{k}", suf, _cut(float(_rng(f"{tag}-cut-{k}").uniform(0.02, 0.99)),
                                                  avoid_line_end=True))
        for k in range(3):
            byte_edit(f"{tag}-nul-run-{k}", suf, _zero(float(_rng(f"{tag}-nul-{k}").uniform(0.1, 0.9)), 6))
            byte_edit(f"{tag}-junk-line-{k}", suf, _lines(lambda ls, i=f"{tag}-junk-{k}": ls.insert(
                int(_rng(i).integers(len(ls) // 4, len(ls) - 2)), bytes(_rng(i).integers(
                    33, 127, 40, dtype=np.uint8)).replace(b";", b":").replace(b"/", b":"))))
            byte_edit(f"{tag}-non-hex-{k}", suf, _lines(lambda ls, i=f"{tag}-hex-{k}": ls.__setitem__(
                (j := int(_rng(i).integers(len(ls) // 4, len(ls) - 2))), ls[j].rstrip()[:-1] + b"Z")))
        byte_edit(f"{tag}-long-line", suf, _lines(lambda ls: ls.insert(len(ls) // 2, b"0" * (3 << 20))))
        byte_edit(f"{tag}-binary", suf, lambda b, t=tag: bytes(_rng(t).integers(0, 256, 5000, dtype=np.uint8)))
        byte_edit(f"{tag}-empty", suf, lambda b: b"")
    for name, t in (("1e12s", b"1000000000000.000000"), ("negative", b"-5.000000"), ("1e300s", b"1e300")):
        byte_edit(f"log-timestamp-{name}", ".log", _lines(lambda ls, t=t: ls.__setitem__(
            len(ls) // 2, b"(" + t + b")" + ls[len(ls) // 2].split(b")", 1)[1])))
    byte_edit("log-time-jump-1e9s", ".log", _lines(lambda ls: ls.__setitem__(slice(len(ls) // 2, None), [
        b"(%.6f)" % (float(x[1:].split(b")")[0]) + 1e9) + x.split(b")", 1)[1] if x.startswith(b"(") else x
        for x in ls[len(ls) // 2:]])))
    # BLF
    for k in range(30):
        r = _rng(f"blf-flip-{k}")
        byte_edit(f"blf-bitflip-{k}", ".blf", _flip(float(r.uniform(0.0, 0.99)), 1 << int(r.integers(8))))
    for k in range(6):
        byte_edit(f"blf-cut-{k}", ".blf", _cut(float(_rng(f"blf-cut-{k}").uniform(0.01, 0.99))))
        byte_edit(f"blf-zeroed-{k}", ".blf", _zero(float(_rng(f"blf-zero-{k}").uniform(0.0, 0.95)), 64))
    for name, value in (("huge", 0x7FFFFFFF), ("zero", 0), ("tiny", 5)):
        byte_edit(f"blf-object-size-{name}", ".blf", lambda b, v=value: _blf_size(b, v))
    byte_edit("blf-header-only", ".blf", lambda b: b[:144])
    return cases


def _blf_size(b: bytearray, value: int) -> bytearray:
    """Set the size field of the first top-level BLF object (after the file header)."""
    pos = struct.unpack_from("<4sI", b)[1]
    struct.pack_into("<I", b, pos + 8, value)
    return b


_BASES: dict[str, dict[str, Path]] = {}


def write_bases_cached(d: Path) -> dict[str, Path]:
    key = str(d)
    if key not in _BASES:
        _BASES[key] = write_bases(d)
    return _BASES[key]


# --- the configuration corpus -------------------------------------------------------------------------

GOOD = """\
[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:7447"]

[service]
journal_dir = "JOURNAL"
estimate_every = 50

[[rig]]
name = "msp25-a"
source = "LOG"
speed = 1.0
track = ["Ffric", "CdAleak"]
controller = "digital"
[rig.params]
KP = 450
[rig.baseline.Ffric]
value = 60.0
rel_band = 0.5
"""


def configs() -> list[Config]:
    """Configurations: the valid one, variants that are valid, and one bad value per key and kind."""
    out = [Config("good", GOOD, True)]

    def sub(id_: str, old: str, new: str, valid: bool = False) -> None:
        assert old in GOOD, old
        out.append(Config(id_, GOOD.replace(old, new, 1), valid))

    long_path = "/tmp/" + "/".join(["d" * 200] * 25)
    for key, old in (("speed", "speed = 1.0"), ("estimate_every", "estimate_every = 50"),
                     ("rel_band", "rel_band = 0.5"), ("value", "value = 60.0"), ("KP", "KP = 450")):
        name = old.split(" =")[0]
        for tag, v in (("nan", "nan"), ("inf", "inf"), ("-inf", "-inf"), ("1e308", "1e308"), ("-1", "-1"),
                       ("string", '"x"'), ("bool", "true"), ("list", "[1]"), ("table", "{a = 1}")):
            sub(f"{key}-{tag}", old, f"{name} = {v}")
    for tag, v in (("1e-300", "1e-300"), ("1e5", "1e5")):
        sub(f"speed-{tag}", "speed = 1.0", f"speed = {v}")
    sub("speed-0-as-fast-as-possible", "speed = 1.0", "speed = 0", valid=True)
    sub("speed-1e-3", "speed = 1.0", "speed = 0.001", valid=True)
    sub("rel_band-1e3", "rel_band = 0.5", "rel_band = 1e3")
    sub("rel_band-2", "rel_band = 0.5", "rel_band = 2.0", valid=True)
    sub("band-lo-tiny", "rel_band = 0.5", "lo = 1e-12\nhi = 70.0")
    for tag, v in (("1e12", "digital:1e12"), ("1e6", "digital:1e6"), ("0", "digital:0"), ("nan", "digital:nan"),
                   ("neg", "digital:-5"), ("word", "digital:fast"), ("digital-word", "digitall")):
        sub(f"controller-{tag}", 'controller = "digital"', f'controller = "{v}"')
    sub("controller-5000", 'controller = "digital"', 'controller = "digital:5000"', valid=True)
    sub("controller-continuous", 'controller = "digital"', 'controller = "continuous"', valid=True)
    sub("controller-analog", 'controller = "digital"', 'controller = "analog"', valid=True)
    for tag, v in (("300-chars", "r" * 300), ("65-chars", "r" * 65), ("slash", "a/b"), ("star", "a*"), ("empty", ""),
                   ("nul", "a\\u0000b"), ("space", "a b"), ("dollar", "a$b")):
        sub(f"name-{tag}", 'name = "msp25-a"', f'name = "{v}"')
    sub("name-64-chars", 'name = "msp25-a"', f'name = "{"r" * 64}"', valid=True)
    for key, old in (("journal_dir", 'journal_dir = "JOURNAL"'), ("source", 'source = "LOG"')):
        name = old.split(" =")[0]
        for tag, v in (("nul", "ROOT/a\\u0000b.mcap"), ("5000-chars", "ROOT/" + "a" * 5000 + ".mcap"),
                       ("long-path", long_path + ".mcap"), ("newline", "ROOT/a\\nb.mcap"), ("empty", "")):
            sub(f"{key}-{tag}", old, f'{name} = "{v}"')
    sub("out_dir-nul", "estimate_every = 50", 'estimate_every = 50\nout_dir = "ROOT/o\\u0000"')
    sub("dbc-5000-chars", 'source = "LOG"', f'source = "LOG"\ndbc = "ROOT/{"b" * 5000}.dbc"')
    sub("commission-nul", 'source = "LOG"', 'source = "LOG"\ncommission = "ROOT/f\\u0000.json"')
    for tag, v in (("nosuchbus", "can://nosuchbus/0"), ("no-channel", "can://virtual/"), ("typo", "can://virtul/rig"),
                   ("fpdd-all", "zenoh://fpdd/**"), ("all", "zenoh://**"), ("alarms", "zenoh://fpdd/*/alarm"),
                   ("history", "zenoh://fpdd/msp25-a/alarm/history"), ("status", "zenoh://fpdd/$*/status"),
                   ("bad-keyexpr", "zenoh://a//b"), ("bad-star", "zenoh://fp*d/x"), ("ftp", "ftp://host/x"),
                   ("no-suffix", "ROOT/rig"), ("xyz", "ROOT/rig.xyz")):
        sub(f"source-{tag}", 'source = "LOG"', f'source = "{v}"')
    sub("source-can-virtual", 'source = "LOG"', 'source = "can://virtual/rig1"', valid=True)
    sub("source-zenoh-samples", 'source = "LOG"', 'source = "zenoh://fpdd/msp25-a/samples"', valid=True)
    sub("source-zenoh-other", 'source = "LOG"', 'source = "zenoh://lab/rig1/**"', valid=True)
    for tag, v in (("port-99999", "tcp/127.0.0.1:99999"), ("no-port", "tcp/127.0.0.1"), ("junk", "nonsense"),
                   ("nul", "tcp/127.0.0.1:7447\\u0000")):
        sub(f"listen-{tag}", 'listen = ["tcp/127.0.0.1:7447"]', f'listen = ["{v}"]')
    sub("workers-1e9", "estimate_every = 50", "estimate_every = 50\nworkers = 1000000000")
    sub("checkpoint-1e308", "estimate_every = 50", "estimate_every = 50\ncheckpoint_s = 1e308")
    sub("block-1e308", "estimate_every = 50", "estimate_every = 50\nblock_s = 1e308")
    sub("stale-1e308", "estimate_every = 50", "estimate_every = 50\nstale_s = 1e308")
    sub("track-1000", 'track = ["Ffric", "CdAleak"]', "track = [" + ", ".join(['"Ffric"'] * 1000) + "]")
    sub("noise-negative", 'controller = "digital"', 'controller = "digital"\nnoise = { x = -1.0 }')
    sub("noise-unit", 'controller = "digital"', 'controller = "digital"\nnoise = { x = "2um", pA = "20kPa" }',
        valid=True)
    sub("noise-wrong-unit", 'controller = "digital"', 'controller = "digital"\nnoise = { x = "20kPa" }')
    sub("rigs-1000-names-dup", "[[rig]]", "[[rig]]\n" + 'name = "msp25-a"\nsource = "LOG"\n[[rig]]')
    out.append(Config("not-toml", "[[rig]\nname =", False))
    out.append(Config("deep-nesting", "a = " + "[" * 5000 + "]" * 5000 + "\n", False))
    out.append(Config("huge-string", 'x = "' + "a" * (4 << 20) + '"\n' + GOOD, False))
    out.append(Config("utf16", "\ufeff" + GOOD, True))  # a UTF-8 BOM: read
    return out


# --- running one case in its own process ---------------------------------------------------------------

def _read(path: Path, options: dict) -> dict:
    from fpdd.errors import TwinError
    from replay.factory import open_source

    try:
        with open_source(path, **options) as src:
            got = src.read_all()
            rep = src.report
    except TwinError as exc:
        return {"error": str(exc), "kind": "twin"}
    except BaseException as exc:  # noqa: BLE001 - the outcome is what is measured
        return {"error": f"{type(exc).__name__}: {exc}"[:300], "kind": "other"}
    return {"t_ns": got.t_ns.tolist(), "signals": {k: v.tolist() for k, v in got.signals.items()},
            "lossy": rep.lossy, "gaps": len(rep.gaps), "summary": rep.summary()[:300]}


def _load(path: Path) -> dict:
    from fpdd.errors import TwinError
    from twin.service.config import load_config

    try:
        load_config(str(path))
    except TwinError as exc:
        return {"error": str(exc), "kind": "twin"}
    except BaseException as exc:  # noqa: BLE001
        return {"error": f"{type(exc).__name__}: {exc}"[:300], "kind": "other"}
    return {}


def _child(conn, fn, args) -> None:  # pragma: no cover - runs in the child
    try:
        conn.send(fn(*args))
    finally:
        conn.close()


def run_isolated(fn, args: tuple, timeout_s: float) -> dict | None:
    """``fn(*args)`` in a forked process; None when it did not finish within ``timeout_s``."""
    ctx = multiprocessing.get_context("fork")
    a, b = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(b, fn, args), daemon=True)
    proc.start()
    b.close()
    result = a.recv() if a.poll(timeout_s) else None
    proc.join(1.0 if result is not None else 0.0)
    if proc.is_alive():
        proc.kill()
        proc.join()
    return result


def _same(a: dict, b: dict, relative: bool = False) -> bool:
    """Equal reads (``relative``: times equal from each record's first sample)."""
    ta, tb = a["t_ns"], b["t_ns"]
    if relative and ta and tb:
        ta, tb = [t - ta[0] for t in ta], [t - tb[0] for t in tb]
    if ta != tb or set(a["signals"]) != set(b["signals"]):
        return False
    return all(np.allclose(a["signals"][k], b["signals"][k], rtol=1e-12, atol=0.0, equal_nan=True)
               for k in a["signals"])


def classify_read(result: dict | None, path: Path, reference: dict | None) -> tuple[str, str]:
    if result is None:
        return "hang", ""
    if "error" in result:
        msg = result["error"]
        if result["kind"] != "twin" or "\n" in msg or str(path) not in msg:
            return "traceback", msg
        return "clear", msg
    if result["lossy"] or result["gaps"]:
        return "clear", result["summary"]
    if reference is not None and "error" not in reference and _same(result, reference, "pretrigger" in str(path)):
        return "ok", result["summary"]
    return "silent", result["summary"]


def classify_config(result: dict | None, path: Path, valid: bool) -> tuple[str, str]:
    if result is None:
        return "hang", ""
    if "error" in result:
        msg = result["error"]
        if result["kind"] != "twin" or "\n" in msg or str(path) not in msg:
            return "traceback", msg
        return ("clear", msg) if not valid else ("traceback", f"a valid configuration refused: {msg}")
    return ("ok", "") if valid else ("silent", "accepted")


# --- one damaged byte per format (--survival) ---

def kept(path: Path) -> str:
    from replay.factory import open_source

    try:
        with open_source(path) as src:
            return f"{len(src.read_all())} kept; {src.report.summary()}"
    except Exception as e:  # noqa: BLE001 - the figure is what happens
        return f"refused: {type(e).__name__}: {e}"


def survival() -> None:
    """How much of a log survives one damaged byte, and how many chunks a twin output gets (``--survival``).

    Writes a seeded 5 s, 1 kHz MSP25 record (5000 samples) as MCAP and as every CAN log format, damages each
    once (a flipped byte in the middle of the first MCAP chunk; one bad character in the frame line at 10 % of
    a text log; one flipped bit at 10 % of the BLF file) and prints how many samples each read keeps and what
    the report says.  Then writes 607 twin messages over 12 s with ``McapSink.write_message`` and counts
    chunks.
    """
    from mcap.reader import make_reader
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    from benchmarks.can import msp25_samples
    from replay.can.logs import CanLogSink
    from replay.mcapio import McapSink

    s = msp25_samples(5.0, seed=1)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "a.mcap"
        with McapSink(p) as sink:
            sink.write(s)
        data = bytearray(p.read_bytes())
        with open(p, "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None  # McapSink writes a summary
        first = min(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        data[first.chunk_start_offset + first.chunk_length // 2] ^= 0xFF
        bad = Path(d) / "bad.mcap"
        bad.write_bytes(bytes(data))
        print(f"{len(s)} samples written")
        print(f"mcap, a flipped byte in the first chunk: {kept(bad)}")
        for suf in (".trc", ".asc", ".log", ".blf"):
            p = Path(d) / f"a{suf}"
            with CanLogSink(p) as sink:
                sink.write(s)
            b = bytearray(p.read_bytes())
            if suf == ".blf":
                b[len(b) // 10] ^= 0x01
            else:
                lines = b.split(b"\n")
                i = len(lines) // 10
                ln = bytearray(lines[i])
                ln[-2] = ord("Z")  # a character of the data bytes
                lines[i] = ln
                b = bytearray(b"\n".join(lines))
            bad = Path(d) / f"bad{suf}"
            bad.write_bytes(bytes(b))
            print(f"{suf[1:]}, one damaged {'bit' if suf == '.blf' else 'line'} at 10 %: {kept(bad)}")
        p = Path(d) / "rig.twin.mcap"
        with McapSink(p) as sink:
            for i in range(607):
                sink.write_message("/twin/estimate", 1_700_000_000_000_000_000 + i * 20_000_000,
                                   {"t_ns": i, "v": 1.0})
        with open(p, "rb") as f:
            n = sum(isinstance(r, Chunk) for r in StreamReader(f, emit_chunks=True).records)
        print(f"twin output, 607 messages over 12.1 s: {n} chunks")


# --- the runs -----------------------------------------------------------------------------------------

def run_inputs(d: Path, timeout_s: float, only: str | None = None) -> list[dict]:
    bases = write_bases_cached(d)
    refs: dict[str, dict] = {}
    rows = []
    for case in inputs():
        if only and only not in case.id:
            continue
        path = case.make(d)
        base = case.base
        if base not in refs:
            refs[base] = _read(bases[base], {}) if base in bases else {"error": "no base", "kind": "none"}
        ref = refs[base]
        if case.id.startswith(("csv-no-time-column-rate", "csv-crlf", "csv-bom", "csv-quoted", "csv-trailing",
                               "csv-gzip")) and "gzip-cut" not in case.id:
            ref = refs[".csv"]
        t = time.perf_counter()
        result = run_isolated(_read, (path, case.options), timeout_s)
        outcome, note = classify_read(result, path, ref if case.base != "times.mcap" else None)
        rows.append({"id": case.id, "outcome": outcome, "note": note[:240], "s": round(time.perf_counter() - t, 3)})
    return rows


def run_configs(d: Path, timeout_s: float, only: str | None = None) -> list[dict]:
    from benchmarks.can import msp25_samples
    from replay.mcapio import McapSink

    log = d / "cfg-log.mcap"
    if not log.exists():
        with McapSink(log) as sink:
            sink.write(msp25_samples(0.2, seed=1))
    rows = []
    for case in configs():
        if only and only not in case.id:
            continue
        path = d / f"cfg-{case.id}.toml"
        text = case.text.replace("JOURNAL", str(d / "journal")).replace("LOG", str(log)).replace("ROOT", str(d))
        path.write_text(text, encoding="utf-8")
        t = time.perf_counter()
        result = run_isolated(_load, (path,), timeout_s)
        outcome, note = classify_config(result, path, case.valid)
        rows.append({"id": f"config-{case.id}", "outcome": outcome, "note": note[:240],
                     "s": round(time.perf_counter() - t, 3)})
    return rows


def counts(rows: list[dict]) -> dict[str, int]:
    c = Counter(r["outcome"] for r in rows)
    return {k: c.get(k, 0) for k in OUTCOMES}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.damage", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", action="store_true", help="print the counts and every case's outcome as JSON")
    p.add_argument("--only", metavar="TEXT", help="only the cases whose id contains TEXT")
    p.add_argument("--timeout", metavar="S", type=float, default=30.0,
                   help="time limit per case in seconds (default 30); beyond it the case is a hang")
    p.add_argument("--verbose", action="store_true", help="print every case that is not clear or ok")
    p.add_argument("--survival", action="store_true",
                   help="instead: how much of a 5 s log survives one damaged byte per format, and how many chunks "
                        "a twin output of 607 messages gets")
    args = p.parse_args(argv)
    if args.survival:
        survival()
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        inp = run_inputs(d, args.timeout, args.only)
        cfg = run_configs(d, args.timeout, args.only)
    result: dict[str, Any] = {"inputs": {"cases": len(inp), **counts(inp)}, "configs": {"cases": len(cfg), **counts(cfg)},
              "cases": inp + cfg}
    if args.json:
        json.dump(result, sys.stdout, indent=1)
        print()
    else:
        for what in ("inputs", "configs"):
            c = result[what]
            print(f"{what}: {c['cases']} cases: " + ", ".join(f"{k} {c[k]}" for k in OUTCOMES))
        for r in inp + cfg:
            if args.verbose and r["outcome"] not in ("clear", "ok"):
                print(f"  {r['outcome']:9s} {r['id']}: {r['note']}")
    bad = sum(result[w][k] for w in ("inputs", "configs") for k in ("silent", "traceback", "hang"))
    return 1 if bad else 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    sys.exit(main())
