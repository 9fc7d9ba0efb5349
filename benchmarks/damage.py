"""How much of a log survives one damaged byte, and how many chunks a twin output gets.

    python -m benchmarks.damage

Writes a seeded 5 s, 1 kHz MSP25 record (5000 samples) as MCAP and as every CAN log
format, damages each once (a flipped byte in the middle of the first MCAP chunk; one
bad character in the frame line at 10 % of a text log; one flipped bit at 10 % of the
BLF file) and prints how many samples each read keeps and what the report says.  Then
writes 607 twin messages over 12 s with ``McapSink.write_message`` and counts chunks.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader

from benchmarks.can import msp25_samples
from replay.can.logs import CanLogSink
from replay.factory import open_source
from replay.mcapio import McapSink


def kept(path: Path) -> str:
    try:
        with open_source(path) as src:
            return f"{len(src.read_all())} kept; {src.report.summary()}"
    except Exception as e:  # noqa: BLE001 - the figure is what happens
        return f"refused: {type(e).__name__}: {e}"


def main() -> None:
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


if __name__ == "__main__":
    main()
