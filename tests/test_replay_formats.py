"""CSV and MCAP readers and writers, the factory, and MCAP damage recovery."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Metadata
from mcap.stream_reader import StreamReader

from replay.base import Samples
from replay.csvio import CsvSink, CsvSource
from replay.factory import open_sink, open_source
from replay.mcapio import (BLOCK_SCHEMA, BLOCK_TOPIC, LAYOUT_METADATA, SIGNALS_SCHEMA, SIGNALS_TOPIC, McapSink,
                           McapSource)
from roundtrip_base import DATA, RoundTripBase
from twin.errors import DataError, LogFormatError, SourceError

sys.path.insert(0, str(DATA))
from make_reference import oscillator_samples, reference_samples  # noqa: E402


# --- round trips -----------------------------------------------------------------------------

class TestCsvRoundTrip(RoundTripBase):
    suffix = ".csv"
    # float64 seconds hold epoch times to ~0.24 us: the CSV time column is exact to 1 us
    time_tol_ns = 1_000
    reference = DATA / "reference.csv"


class TestCsvRoundTripExtras(TestCsvRoundTrip):
    signals = ("x_ref", "u", "x", "pA", "pB", "F", "T_oil", "pP")


class TestMcapRoundTrip(RoundTripBase):
    suffix = ".mcap"
    reference = DATA / "reference.mcap"


class TestMcapPerSampleOnly(RoundTripBase):
    """Without the block topic the reader decodes /rig/signals (a foreign writer's layout)."""

    suffix = ".mcap"

    def make_sink(self, path: Path) -> McapSink:
        return McapSink(path, block=False)


class TestMcapBlockOnly(RoundTripBase):
    suffix = ".mcap"

    def make_sink(self, path: Path) -> McapSink:
        return McapSink(path, per_sample=False)


def test_reference_files_hold_the_reference_samples() -> None:
    want = reference_samples()
    with open_source(DATA / "reference.mcap") as src:
        got = src.read_all()
    assert np.array_equal(got.t_ns, want.t_ns)
    assert all(np.array_equal(got[k], want[k]) for k in want.names)
    with open_source(DATA / "reference.csv") as src:
        got = src.read_all()
    assert np.abs(got.t_ns - want.t_ns).max() <= 1_000
    assert all(np.array_equal(got[k], want[k]) for k in want.names)


def test_oscillator_contract_csv() -> None:
    want = oscillator_samples()
    with open_source(DATA / "oscillator.csv", required=("u", "y")) as src:
        assert src.signals == ("u", "y")
        got = src.read_all()
    assert np.array_equal(got.t_ns, want.t_ns)
    assert np.array_equal(got["y"], want["y"]) and np.array_equal(got["u"], want["u"])


# --- CSV specifics -----------------------------------------------------------------------------

def test_csv_mapping_renames_and_converts_units(tmp_path: Path) -> None:
    path = tmp_path / "foreign.csv"
    path.write_text("time_ms,pos_mm,p_a_bar,valve_mV,temp_C\n"
                    "0,1.5,100,250,40\n"
                    "1,2.5,120,-250,40.5\n")
    mapping = {"time_ms": ("t", "ms"), "pos_mm": ("x", "mm"), "p_a_bar": ("pA", "bar"),
               "valve_mV": ("u", "mV"), "temp_C": ("T_oil", "degC")}
    with CsvSource(path, mapping=mapping) as src:
        assert src.signals == ("x", "pA", "u", "T_oil")
        got = src.read_all()
    assert got.t_ns.tolist() == [0, 1_000_000]
    np.testing.assert_allclose(got["x"], [1.5e-3, 2.5e-3], rtol=1e-15)
    np.testing.assert_allclose(got["pA"], [100e5, 120e5], rtol=1e-15)
    np.testing.assert_allclose(got["u"], [0.25, -0.25], rtol=1e-15)
    np.testing.assert_allclose(got["T_oil"], [313.15, 313.65], rtol=1e-15)


def test_csv_mapping_rejects_a_unit_of_the_wrong_quantity(tmp_path: Path) -> None:
    path = tmp_path / "foreign.csv"
    path.write_text("t,pos\n0,1\n")
    with pytest.raises(DataError, match=r"'pos'.*bar converts to Pa.*'x' is in m"):
        CsvSource(path, mapping={"pos": ("x", "bar")})
    with pytest.raises(DataError, match=r"unknown unit 'furlong'"):
        CsvSource(path, mapping={"pos": ("x", "furlong")})


def test_csv_bad_rows_are_counted_with_line_numbers(tmp_path: Path) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(textwrap.dedent("""\
        # exported by a rig PC
        t,x,pA
        0.000,0.001,1e6
        0.001,0.002
        0.002,abc,1e6

        0.003,0.004,
        0.004,0.005,1e6
        """))
    with CsvSource(path) as src:
        got = src.read_all()
        report = src.report
    assert got.t_ns.tolist() == [0, 4_000_000]
    assert report.skipped["bad_row"] == 3
    text = "\n".join(map(str, report.problems))
    assert f"{path}: line 4: 2 fields, expected 3 (t,x,pA)" in text
    assert f"{path}: line 5: field 'x' = 'abc' is not a number" in text
    assert f"{path}: line 7: field 'pA' is empty" in text
    assert report.records_read == 5


def test_csv_without_time_column_names_what_the_file_has(tmp_path: Path) -> None:
    path = tmp_path / "no_t.csv"
    path.write_text("time,x\n0,1\n")
    with pytest.raises(DataError, match=r"no time column 't'.*'time', 'x'"):
        CsvSource(path)


def test_csv_header_problems(tmp_path: Path) -> None:
    empty = tmp_path / "empty.csv"
    empty.write_text("\n# nothing\n")
    with pytest.raises(LogFormatError, match="empty file .only blank or comment lines., expected a header row"):
        CsvSource(empty)
    numbers = tmp_path / "numbers.csv"
    numbers.write_text("0,1,2\n")
    with pytest.raises(LogFormatError, match="line 1: expected a header row"):
        CsvSource(numbers)
    dup = tmp_path / "dup.csv"
    dup.write_text("t,x,x\n0,1,2\n")
    with pytest.raises(LogFormatError, match="column.* x appear more than once"):
        CsvSource(dup)


def test_csv_sink_writes_exact_decimal_seconds(tmp_path: Path) -> None:
    path = tmp_path / "neg.csv"
    with CsvSink(path) as sink:
        sink.write(Samples(np.array([-1_500_000_000, 0, 1_000_000_001]), {"x": np.array([0.1, np.nan, 0.3])}))
    assert path.read_text().splitlines() == ["t,x", "-1.500000000,0.1", "0.000000000,nan", "1.000000001,0.3"]


# --- MCAP specifics ----------------------------------------------------------------------------

def _rig(n: int, rate_hz: float = 1000.0, seed: int = 7) -> Samples:
    rng = np.random.default_rng(seed)
    return Samples(np.arange(n, dtype=np.int64) * int(round(1e9 / rate_hz)),
                   {"x": rng.uniform(-0.05, 0.05, n), "pA": rng.uniform(1e6, 2e7, n)})


def test_mcap_layout_is_what_foxglove_plots(tmp_path: Path) -> None:
    path = tmp_path / "layout.mcap"
    with McapSink(path) as sink:
        sink.write(_rig(1500))
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {SIGNALS_TOPIC, BLOCK_TOPIC}
        for topic, schema_name in ((SIGNALS_TOPIC, SIGNALS_SCHEMA), (BLOCK_TOPIC, BLOCK_SCHEMA)):
            ch = topics[topic]
            schema = summary.schemas[ch.schema_id]
            assert (ch.message_encoding, schema.encoding, schema.name) == ("json", "jsonschema", schema_name)
            assert ch.metadata["signals"] == "x,pA" and ch.metadata["units"] == "m,Pa"
        props = json.loads(summary.schemas[topics[SIGNALS_TOPIC].schema_id].data)["properties"]
        assert set(props) == {"t", "timestamp", "x", "pA"} and props["timestamp"]["title"] == "time"
        counts = summary.statistics.channel_message_counts
        assert counts[topics[SIGNALS_TOPIC].id] == 1500 and counts[topics[BLOCK_TOPIC].id] == 2
        _, _, msg = next(reader.iter_messages(topics=[SIGNALS_TOPIC]))
        first = json.loads(msg.data)
        assert set(first) == {"t", "timestamp", "x", "pA"} and first["t"] == msg.log_time * 1e-9
        assert first["timestamp"]["sec"] * 10**9 + first["timestamp"]["nsec"] == msg.log_time
        # each flush is its own chunks: block chunks hold no per-sample messages
        block_chunks = [ci for ci in summary.chunk_indexes if topics[BLOCK_TOPIC].id in ci.message_index_offsets]
        assert block_chunks and all(len(ci.message_index_offsets) == 1 for ci in block_chunks)


def test_mcap_time_range_read(tmp_path: Path) -> None:
    path = tmp_path / "range.mcap"
    want = _rig(4000)
    with McapSink(path) as sink:
        sink.write(want)
    for topic in (BLOCK_TOPIC, SIGNALS_TOPIC):
        with McapSource(path, topic=topic, start_ns=1_500_000_000, end_ns=2_250_000_000) as src:
            got = src.read_all()
        assert got.t_ns[0] == 1_500_000_000 and got.t_ns[-1] == 2_249_000_000 and len(got) == 750
        assert np.array_equal(got["x"], want["x"][1500:2250])


def test_mcap_generic_messages(tmp_path: Path) -> None:
    path = tmp_path / "twin.mcap"
    with McapSink(path) as sink:
        sink.write(_rig(10))
        sink.write_message("/twin/estimate", 1_000, {"theta": np.array([1.0, 2.0]), "nis": np.float32(0.5)})
        sink.write_message("/twin/alarm", 2_000, {"level": "warn", "score": float("nan")})
        sink.write_message("/twin/estimate", 3_000, {"theta": [1.5, 2.5], "nis": 0.25})
    with McapSource(path) as src:
        msgs = list(src.messages(["/twin/estimate", "/twin/alarm"]))
        topics = {t.topic: t for t in src.topics()}
    assert [(m.topic, m.t_ns) for m in msgs] == [("/twin/estimate", 1_000), ("/twin/alarm", 2_000),
                                                 ("/twin/estimate", 3_000)]
    assert msgs[0].data == {"theta": [1.0, 2.0], "nis": 0.5, "timestamp": {"sec": 0, "nsec": 1_000}}
    assert msgs[1].data == {"level": "warn", "score": None, "timestamp": {"sec": 0, "nsec": 2_000}}
    assert topics["/twin/estimate"].schema == "fpdd.twin.estimate" and topics["/twin/estimate"].messages == 2
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert len(summary.schemas) == 4  # registered once per topic
    for schema in summary.schemas.values():  # every schema declares the Foxglove time
        assert json.loads(schema.data)["properties"]["timestamp"]["required"] == ["sec", "nsec"]


def test_mcap_twin_output_chunks_hold_about_a_second_and_no_layout(tmp_path: Path) -> None:
    """A messages-only file (a twin output): one chunk per second of message time, not per
    message; no fpdd.layout metadata naming sample topics it does not have; t_ns beyond 2**53
    travels exactly as timestamp {sec, nsec}."""
    path = tmp_path / "rig.twin.mcap"
    t0 = 1_700_000_000_123_456_789
    with McapSink(path) as sink:
        for i in range(607):
            sink.write_message("/twin/estimate", t0 + i * 20_000_000, {"t_ns": t0 + i * 20_000_000, "v": 1.0})
    with open(path, "rb") as f:
        records = list(StreamReader(f, emit_chunks=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert 11 <= len(chunks) <= 14, len(chunks)  # 12.1 s of messages
    assert not [r for r in records if isinstance(r, Metadata) and r.name == LAYOUT_METADATA]
    with McapSource(path, any_topic=True) as src:
        last = list(src.messages())[-1]
    assert last.data["timestamp"] == {"sec": (t0 + 606 * 20_000_000) // 10**9,
                                      "nsec": (t0 + 606 * 20_000_000) % 10**9}


def test_mcap_truncated_keeps_the_readable_prefix(tmp_path: Path) -> None:
    whole = tmp_path / "whole.mcap"
    with McapSink(whole) as sink:
        sink.write(_rig(5000))
    data = whole.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 6 // 10])
    with open_source(cut) as src:
        got = src.read_all()
        report = src.report
    assert report.truncated and report.skipped["damaged_record"] == 1
    assert 2000 <= len(got) < 5000
    assert np.array_equal(got.t_ns, np.arange(len(got)) * 1_000_000)  # a prefix, nothing invented
    text = "\n".join(map(str, report.problems))
    assert "reading the file as a stream" in text and f"recovered {len(got) // 1000} message(s)" in text, text


@pytest.mark.parametrize("per_sample", [True, False])
def test_mcap_corrupt_chunk_costs_only_itself(tmp_path: Path, per_sample: bool) -> None:
    """One flipped bit in the third block chunk: the CRC finds it, the chunks after it are read,
    and the block's samples come back from /rig/signals when the file has that topic."""
    path = tmp_path / "crc.mcap"
    ref = _rig(5000)
    with McapSink(path, compression="none", per_sample=per_sample) as sink:
        sink.write(ref)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    block_id = next(c.id for c in summary.channels.values() if c.topic == BLOCK_TOPIC)
    third = [ci for ci in summary.chunk_indexes if block_id in ci.message_index_offsets][2]
    data = bytearray(path.read_bytes())
    data[third.chunk_start_offset + third.chunk_length // 2] ^= 0x01  # one bit of a float payload
    path.write_bytes(bytes(data))
    with McapSource(path) as src:
        got = src.read_all()
        report = src.report
    assert report.skipped["damaged_chunk"] == 1 and not report.truncated and report.lossy
    text = "\n".join(map(str, report.problems))
    assert "crc validation failed" in text and "its 1 message(s) of /rig/signals_block are lost" in text, text
    if per_sample:
        assert len(got) == 5000 and report.samples_lost == 0
        np.testing.assert_array_equal(got.t_ns, ref.t_ns)
        np.testing.assert_array_equal(got["x"], ref["x"])
        assert "1000 sample(s) of the damaged /rig/signals_block chunk recovered from /rig/signals" in text
    else:
        assert len(got) == 4000 and report.samples_lost == 1000
        keep = (ref.t_ns < 2_000_000_000) | (ref.t_ns >= 3_000_000_000)
        np.testing.assert_array_equal(got.t_ns, ref.t_ns[keep])


def test_mcap_killed_writer_loses_at_most_one_second(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(f"""
        import os, signal, numpy as np
        from replay.base import Samples
        from replay.mcapio import McapSink
        sink = McapSink({str(path)!r})
        rng = np.random.default_rng(1)
        for i in range(35):  # 3.5 s at 1 kHz, 100 samples per write, as a live recorder would
            t = (np.arange(100) + 100 * i) * 1_000_000
            sink.write(Samples(t, {{"x": rng.uniform(-0.01, 0.01, 100)}}))
        os.kill(os.getpid(), signal.SIGKILL)
        """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    with McapSource(path) as src:
        got = src.read_all()
        assert src.report.truncated
    assert got.t_ns[-1] >= 3_499_000_000 - 1_000_000_000
    assert np.array_equal(got.t_ns, np.arange(len(got)) * 1_000_000)


def test_not_an_mcap_file(tmp_path: Path) -> None:
    path = tmp_path / "fake.mcap"
    path.write_text("t,x\n0,1\n")
    with pytest.raises(LogFormatError, match=r"fake.mcap: not an MCAP file"):
        open_source(path)


def test_mcap_without_samples_topic(tmp_path: Path) -> None:
    path = tmp_path / "only_status.mcap"
    with McapSink(path, signals=()) as sink:
        sink.write_message("/twin/status", 0, {"state": "ok"})
    with pytest.raises(LogFormatError, match=r"no topic '/rig/signals' with rig samples; the file has .*/twin/status"):
        McapSource(path, topic="/rig/signals")


# --- factory ---------------------------------------------------------------------------------

def test_unknown_format_names_file_and_known_formats(tmp_path: Path) -> None:
    path = tmp_path / "record.parquet"
    path.write_bytes(b"PAR1")
    with pytest.raises(LogFormatError, match=r"record.parquet: unknown format.*\.csv, \.mcap, \.asc"):
        open_source(path)
    with pytest.raises(LogFormatError, match=r"unknown URI scheme 'ftp'"):
        open_source("ftp://host/file.csv")
    with pytest.raises(LogFormatError, match=r"unknown output format"):
        open_sink(tmp_path / "out.xlsx")


def test_unreadable_file_is_a_source_error(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"missing.mcap: cannot read log file: does not exist"):
        open_source(tmp_path / "missing.mcap")
    folder = tmp_path / "folder.csv"
    folder.mkdir()
    with pytest.raises(SourceError, match=r"folder.csv: cannot read log file: is a directory"):
        open_source(folder)
    with pytest.raises(SourceError, match=r"cannot create output file"):
        open_sink(tmp_path / "nowhere" / "out.csv")
    assert isinstance(SourceError("x"), OSError)


def test_factory_passes_options(tmp_path: Path) -> None:
    with open_source(DATA / "reference.csv", required=("x", "pA")) as src:
        assert isinstance(src, CsvSource)
    with pytest.raises(DataError, match=r"required signal\(s\) 'F' missing; the file has 'x_ref'"):
        open_source(DATA / "reference.mcap", required=("F",))
    with open_sink(tmp_path / "o.mcap", flush_period_s=0.5) as sink:
        assert isinstance(sink, McapSink)
