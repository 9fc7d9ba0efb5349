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
from replay.quality import QualityOptions
from replay.mcapio import (BLOCK_SCHEMA, BLOCK_TOPIC, LAYOUT_METADATA, SIGNALS_SCHEMA, SIGNALS_TOPIC, McapSink,
                           McapSource)
from roundtrip_base import DATA, RoundTripBase
from fpdd.errors import DataError, LogFormatError, SourceError

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
    """The reader gives back exactly the numbers the file holds (parsed here on their own, text by text), and those
    are the generator's to within the last place: the generator's ``exp`` may round differently on another CPU, so
    the exact comparison is against the file, never against a recomputation."""
    import csv

    with open(DATA / "oscillator.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    in_file = {name: np.array([float(r[name]) for r in rows]) for name in ("t", "u", "y")}
    with open_source(DATA / "oscillator.csv", required=("u", "y")) as src:
        assert src.signals == ("u", "y")
        got = src.read_all()
    assert np.array_equal(got["y"], in_file["y"]) and np.array_equal(got["u"], in_file["u"])
    want = oscillator_samples()
    assert np.array_equal(got.t_ns, want.t_ns)
    assert np.array_equal(got["u"], want["u"])
    np.testing.assert_allclose(got["y"], want["y"], rtol=4 * np.finfo(float).eps, atol=0)


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


# --- CSV the way real data come -----------------------------------------------------------------

#: The published Silverbox record (Wigren & Schoukens, ECC 2013): header '"V1","V2",', no time column,
#: sampled at 10^7/2^14 Hz.  Read where it lies (``realdata/silverbox/`` beside the project, or the folder
#: FPDD_REALDATA names), never copied into the project.
SILVERBOX_RATE_HZ = 1e7 / 2**14


def _silverbox(name: str = "SNLS80mV.csv.gz") -> Path:
    from tests.realdata import realdata

    return realdata("silverbox", name)


def test_silverbox_as_published_is_read_with_a_rate(tmp_path: Path) -> None:
    import gzip

    from twin.models.records import load_records

    path = _silverbox()
    with gzip.open(path, "rt") as f:
        head = [next(f) for _ in range(3)]
    assert head[0].strip() == '"V1","V2",'  # the trailing empty column is in the file as published
    first = [float(v) for v in head[1].strip().rstrip(",").split(",")]
    # without a rate: refused with one line that says to pass it
    with pytest.raises(DataError, match=r"no time column 't'.*--rate HZ"):
        CsvSource(path, mapping={"V1": ("u", "V"), "V2": ("y", "V")})
    records = load_records(str(path), model="oscillator", mapping={"V1": ("u", "V"), "V2": ("y", "V")},
                           rate_hz=SILVERBOX_RATE_HZ)
    assert len(records) == 1
    rec = records[0]
    assert len(rec) == 131072 and rec.dt == pytest.approx(2**14 / 1e7, rel=1e-9)
    assert [rec["u"][0], rec["y"][0]] == first
    # the sample time as --dt gives the same record; the map may name the unit or not
    with CsvSource(path, mapping={"V1": "u", "V2": "y"}, dt_s=2**14 / 1e7) as src:
        got = src.read_all()
        assert not src.report.lossy
    assert np.array_equal(got["y"], rec["y"]) and got.t_ns[1] == 1_638_400


def test_silverbox_replay_info_and_twin_fit_flags(capsys: pytest.CaptureFixture) -> None:
    from replay import cli

    path = str(_silverbox())
    code = cli.main(["info", path, "--rate", "610.3515625", "--map", "u=V1:V", "--map", "y=V2:V", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    info = json.loads(out)
    assert info["signals"] == ["u", "y"] and info["samples"] == 131072
    assert info["rate_hz"] == pytest.approx(SILVERBOX_RATE_HZ, rel=1e-6)
    code = cli.main(["info", path, "--map", "u=V1:V", "--map", "y=V2:V"])
    _, err = capsys.readouterr()
    assert code != 0 and len(err.strip().splitlines()) == 1 and "--rate HZ" in err and "Traceback" not in err


def test_silverbox_schroeder_record_with_flag_columns() -> None:
    """The archive's second record: header 'Ovld2,Ovld1,V1,V2,' with the overload flags only in the first row.
    Mapped columns are read; the unmapped flag columns (empty in every other row) are not, and the report
    names them."""
    path = _silverbox("Schroeder80mV.csv.gz")
    with CsvSource(path, mapping={"V1": ("u", "V"), "V2": ("y", "V")}, rate_hz=SILVERBOX_RATE_HZ) as src:
        got = src.read_all()
        report = src.report
    assert got.names == ("u", "y") and len(got) > 100_000 and not report.lossy
    assert "column(s) 'Ovld2', 'Ovld1' not read: neither a known signal nor mapped" in str(report.problems[0])
    with CsvSource(path, mapping={"V1": ("u", "V"), "V2": ("y", "V"), "Ovld1": "ovld"},
                   rate_hz=SILVERBOX_RATE_HZ) as src:  # mapped, the flag column is read: its empty fields say so
        assert len(src.read_all()) <= 1 and src.report.skipped["bad_row"] > 100_000


def test_csv_trailing_empty_columns_and_quotes(tmp_path: Path) -> None:
    path = tmp_path / "quoted.csv"
    path.write_text('"t","x",\n0.000,0.001,\n0.001,0.002\n"0.002","0.003",\n0.003,0.004,,\n0.004,0.005,7\n')
    with CsvSource(path) as src:
        assert src.signals == ("x",)
        got = src.read_all()
        report = src.report
    assert got.t_ns.tolist() == [0, 1_000_000, 2_000_000, 3_000_000]
    np.testing.assert_array_equal(got["x"], [0.001, 0.002, 0.003, 0.004])
    assert report.skipped["bad_row"] == 1  # a value in the unnamed column is not a trailing delimiter
    assert "line 6: 3 fields, expected 2" in "\n".join(map(str, report.problems))


def test_csv_without_time_column_takes_a_rate(tmp_path: Path) -> None:
    path = tmp_path / "norate.csv"
    path.write_text("x,pA\n" + "".join(f"{1e-4 * i},{1e6}\n" for i in range(5)) + "oops,1e6\n0.0006,1e6\n")
    with pytest.raises(DataError, match=r"no time column 't' \(s\); .*a file without a time column needs its "
                       r"sample rate: --rate HZ \(or --dt S\)"):
        CsvSource(path)
    with CsvSource(path, rate_hz=2000.0) as src:
        got = src.read_all()
    # a bad row keeps its slot in time: the sample after it is at 6 / 2000 s
    assert got.t_ns.tolist() == [0, 500_000, 1_000_000, 1_500_000, 2_000_000, 3_000_000]
    for bad, match in (({"rate_hz": 1.0}, r"--rate 1.0 Hz: expected a sample rate from 10 Hz to 1e\+07 Hz"),
                       ({"rate_hz": float("nan")}, "expected a sample rate"),
                       ({"dt_s": 0.0}, "expected a sample rate"),
                       ({"rate_hz": 1e3, "dt_s": 1e-3}, "give one")):
        with pytest.raises(DataError, match=match):
            CsvSource(path, **bad)
    timed = tmp_path / "timed.csv"
    timed.write_text("t,x\n0,0\n0.001,0\n")
    with pytest.raises(DataError, match=r"has a time column 't'; a sample rate .* is for a file without one"):
        CsvSource(timed, rate_hz=1000.0)


def test_csv_units_in_the_header_are_read(tmp_path: Path) -> None:
    path = tmp_path / "units.csv"
    path.write_text("t [ms],x_ref[mm],x (mm),pA[bar]\n0,1,2,100\n1,1,2.5,101\n")
    with CsvSource(path) as src:
        assert src.signals == ("x_ref", "x", "pA")
        got = src.read_all()
    assert got.t_ns.tolist() == [0, 1_000_000]
    np.testing.assert_allclose(got["x"], [2e-3, 2.5e-3], rtol=1e-15)
    np.testing.assert_allclose(got["pA"], [100e5, 101e5], rtol=1e-15)
    extra = tmp_path / "extra.csv"
    extra.write_text("t,x,x_ref[furlong]\n0,0.001,1\n0.001,0.002,1\n")
    with CsvSource(extra) as src:
        assert src.signals == ("x", "x_ref[furlong]")
        src.read_all()
        assert not src.report.lossy
        assert "header: column(s) 'x_ref[furlong]' not understood: no known signal" in str(src.report.problems[0])
    wrong = tmp_path / "wrong.csv"
    wrong.write_text("t,x[bar]\n0,1\n")
    with pytest.raises(DataError, match=r"'x\[bar\]'.*bar converts to Pa, but 'x' is in m"):
        CsvSource(wrong)


def test_csv_unit_check_is_dimensional_per_model(tmp_path: Path) -> None:
    from twin.models.records import signal_specs

    path = tmp_path / "volts.csv"
    path.write_text("t,V1,V2\n" + "".join(f"{i / 1000},{0.01 * i},{0.02 * i}\n" for i in range(20)))
    quality = QualityOptions(specs=signal_specs("oscillator"))
    with CsvSource(path, mapping={"V1": ("u", "mV"), "V2": ("y", "V")}, quality=quality) as src:
        got = src.read_all()
    np.testing.assert_allclose(got["u"][1], 1e-5, rtol=1e-12)  # mV converted to V, kept in V
    np.testing.assert_allclose(got["y"][1], 0.02, rtol=1e-12)
    with pytest.raises(DataError, match=r"V converts to V, but 'x' is in m"):
        CsvSource(path, mapping={"V2": ("x", "V")})


def test_csv_foreign_columns_hint_is_right_and_works(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from replay import cli

    path = tmp_path / "foreign.csv"
    path.write_text("time_ms,dem_mm,pos_mm,pa_bar,pb_bar\n"
                    + "".join(f"{i},{0.01 * i},{0.01 * i - 0.001},{100 + i % 3},{90 - i % 3}\n" for i in range(60)))
    with pytest.raises(DataError) as err:
        CsvSource(path)
    msg = str(err.value)
    hint = msg.split("e.g. ", 1)[1].split(";")[0]
    assert hint == ("--map t=time_ms:ms --map x_ref=dem_mm:mm --map x=pos_mm:mm --map pA=pa_bar:bar "
                    "--map pB=pb_bar:bar")
    argv = ["info", str(path), "--json", *hint.split()]
    assert cli.main(argv) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["signals"] == ["x_ref", "x", "pA", "pB"] and info["rate_hz"] == pytest.approx(1000.0)
    # names with spaces and units in brackets: the hint is quoted for a shell and works as typed
    import shlex

    spaced = tmp_path / "spaced.csv"
    spaced.write_text("Zeit [ms],Position (mm)\n" + "".join(f"{i},{0.01 * i}\n" for i in range(60)))
    with pytest.raises(DataError) as err:
        CsvSource(spaced)
    hint = str(err.value).split("e.g. ", 1)[1].split(";")[0]
    assert hint == "--map 't=Zeit [ms]:ms' --map 'x=Position (mm):mm'"
    assert cli.main(["info", str(spaced), "--json", *shlex.split(hint)]) == 0
    assert json.loads(capsys.readouterr().out)["rate_hz"] == pytest.approx(1000.0)
    # a time unit that reads the record at an absurd rate is refused with the unit that fits
    with pytest.raises(DataError, match=r"'time_ms' read in s: .*\(1 Hz\) is not a rig record's rate.*"
                       r"--map t=time_ms:ms"):
        with CsvSource(path, mapping={"time_ms": ("t", "s"), "pos_mm": ("x", "mm")}) as src:
            src.read_all()


def test_csv_header_parser_is_bounded(tmp_path: Path) -> None:
    """A 200 000-column header (once quadratic: 32 000 columns took 17 s) is refused at once, and the message
    does not repeat the header; a line over the limit costs one row, never the rows after it."""
    wide = tmp_path / "wide.csv"
    wide.write_text(",".join("a" * 3 for _ in range(200_000)) + "\n0\n")
    with pytest.raises(LogFormatError) as err:
        CsvSource(wide)
    assert "header has 200000 columns, more than 4096" in str(err.value) and len(str(err.value)) < 300
    dup = tmp_path / "dup.csv"
    dup.write_text("t," + ",".join(["x"] * 4000) + "\n")
    with pytest.raises(LogFormatError) as err:
        CsvSource(dup)
    assert "column(s) x appear more than once" in str(err.value) and len(str(err.value)) < 600
    long = tmp_path / "long.csv"
    long.write_text("t,x\n0.000,0.1\n" + "9" * (2 << 20) + "\n0.002,0.3\n0.003,0.4\n")
    with CsvSource(long) as src:
        got = src.read_all()
        assert src.report.skipped["bad_row"] == 1
    assert got.t_ns.tolist() == [0, 2_000_000, 3_000_000]


def test_csv_last_line_without_line_end_is_not_trusted(tmp_path: Path) -> None:
    path = tmp_path / "cut.csv"
    path.write_text("t,x\n0.000,0.25\n0.001,0.25\n0.002,0.2")  # cut inside the last number
    with CsvSource(path) as src:
        got = src.read_all()
        report = src.report
    assert got["x"].tolist() == [0.25, 0.25] and report.truncated and report.lossy
    assert "line 4: the file ends inside this line (no line end)" in "\n".join(map(str, report.problems))
    crlf = tmp_path / "crlf.csv"
    crlf.write_bytes(b"t,x\r\n# a comment\r\n0.000,0.25\r\n\r\n0.001,0.5\r\n")
    with CsvSource(crlf) as src:
        got = src.read_all()
        assert not src.report.lossy
    assert got["x"].tolist() == [0.25, 0.5]


def test_csv_gzip_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "rig.csv.gz"
    want = _rig(300)
    with open_sink(path) as sink:
        sink.write(want)
    assert path.read_bytes()[:2] == b"\x1f\x8b"  # gzip
    with open_source(path) as src:
        got = src.read_all()
    assert np.array_equal(got.t_ns, want.t_ns) and all(np.array_equal(got[k], want[k]) for k in want.names)


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
        assert set(props) == {"t", "timestamp", "rig", "x", "pA", "display"} and props["timestamp"]["title"] == "time"
        counts = summary.statistics.channel_message_counts
        assert counts[topics[SIGNALS_TOPIC].id] == 1500 and counts[topics[BLOCK_TOPIC].id] == 2
        _, _, msg = next(reader.iter_messages(topics=[SIGNALS_TOPIC]))
        first = json.loads(msg.data)
        assert set(first) == {"t", "timestamp", "rig", "x", "pA", "display"} and first["t"] == msg.log_time * 1e-9
        assert first["rig"] == "layout" and first["display"] == {"x": pytest.approx(first["x"] * 1e3, rel=1e-6),
                                                                 "pA": pytest.approx(first["pA"] * 1e-6, rel=1e-6)}
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


# --- MATLAB and text files; gains and offsets in the column map -------------------------------------------------

def _mat_record(path: Path, **extra) -> dict:
    """A MATLAB v5 file written by scipy: a time vector, two signals in foreign names and units, scalars."""
    import gzip

    import scipy.io

    rng = np.random.default_rng(3)
    n = 500
    data = {"t": (np.arange(n) * 1e-3)[:, None], "pos_mm": rng.normal(0.0, 5.0, (n, 1)),
            "vir": rng.normal(0.0, 1.0, (1, n)), "gain": np.array([[35.15]]), "notes": "bench 3", **extra}
    if str(path).endswith(".gz"):
        import io

        buf = io.BytesIO()
        scipy.io.savemat(buf, data)
        path.write_bytes(gzip.compress(buf.getvalue()))
    else:
        scipy.io.savemat(path, data)
    return {k: np.asarray(v).ravel() for k, v in data.items() if k != "notes"}


@pytest.mark.parametrize("name", ["rec.mat", "rec.mat.gz"])
def test_mat_file_reads_mapped_vectors_with_gain_and_unit(tmp_path, name):
    from twin.models.records import load_records

    path = tmp_path / name
    d = _mat_record(path)
    with open_source(path, mapping={"pos_mm": ("x", "mm"), "vir": ("F", "", "35.15N/V", "-2N")}) as src:
        got = src.read_all()
    assert set(got.names) == {"x", "F"} and len(got) == 500
    np.testing.assert_array_equal(got.t_ns, np.rint(d["t"] * 1e9).astype(np.int64))
    np.testing.assert_allclose(got["x"], d["pos_mm"] * 1e-3, rtol=1e-15)
    np.testing.assert_allclose(got["F"], d["vir"] * 35.15 - 2.0, rtol=1e-15)
    (rec,) = load_records(str(path), model="oscillator", map=["u=vir*35.15N/V", "y=pos_mm:mm"])
    np.testing.assert_allclose(rec["u"], d["vir"] * 35.15, rtol=1e-15)


def test_mat_file_refuses_a_missing_or_non_vector_variable(tmp_path):
    path = tmp_path / "rec.mat"
    _mat_record(path)
    with pytest.raises(DataError, match=r"rec\.mat: variable 'qm' \(--map x=qm\) not in the file; expected a vector"
                                        r".*pos_mm \(500 samples\)"):
        open_source(path, mapping={"qm": "x"})
    with pytest.raises(DataError, match=r"variable 'gain' \(--map x=gain\) is a 1x1 scalar, expected a vector"):
        open_source(path, mapping={"gain": "x"})
    with pytest.raises(DataError, match=r"variable 'notes' \(--map x=notes\) is text, expected a vector"):
        open_source(path, mapping={"notes": "x"})
    with pytest.raises(DataError, match=r"gives N, but 'x' is in m"):
        open_source(path, mapping={"vir": ("x", "", "35.15N/V", "")})
    bad = tmp_path / "bad.mat"
    bad.write_bytes(b"not a MATLAB file at all, just words" * 10)
    with pytest.raises(LogFormatError, match=r"bad\.mat: not a MATLAB \.mat file"):
        open_source(bad)


def test_mat_file_with_a_sample_time_instead_of_a_time_vector(tmp_path):
    import scipy.io

    path = tmp_path / "ts.mat"
    scipy.io.savemat(path, {"y": np.arange(100.0)[:, None] * 1e-3, "u": np.ones((100, 1)), "Ts": np.array([[2e-3]])})
    with open_source(path) as src:
        got = src.read_all()
    np.testing.assert_array_equal(got.t_ns, np.arange(100) * 2_000_000)
    path2 = tmp_path / "none.mat"
    scipy.io.savemat(path2, {"y": np.arange(100.0)[:, None] * 1e-3})
    with pytest.raises(DataError, match=r"none\.mat: no time variable .* give --rate HZ or --dt S"):
        open_source(path2)
    with open_source(path2, rate_hz=500.0) as src:
        assert src.read_all().t_ns[1] == 2_000_000


def test_text_files_tab_header_blank_separated_and_numbered_columns(tmp_path):
    tab = tmp_path / "run.tsv"
    tab.write_text("time\tlabel\tpos\n0.000\ta\t1.5\n0.001\tb\t2.5\n0.002\tc\t3.5\n0.003\td\t4.5\n")
    with open_source(tab, mapping={"time": "t", "pos": ("x", "mm")}) as src:
        got = src.read_all()
    np.testing.assert_allclose(got["x"], [1.5e-3, 2.5e-3, 3.5e-3, 4.5e-3])
    blank = tmp_path / "run.txt"
    blank.write_text("% a comment\nt   u    y\n0.000  1  2\n0.001  2  4\n0.002  3 x\n0.003  4  8\n0.004  5  10\n")
    with open_source(blank, mapping={"u": ("F", "", "2", "+1")}) as src:
        got = src.read_all()
    np.testing.assert_allclose(got["F"], [3.0, 5.0, 9.0, 11.0])  # the row with 'x' skipped and counted
    assert src.report.skipped["bad_row"] == 1
    numbered = tmp_path / "bare.txt"
    numbered.write_text("".join(f"{i * 1e-3:.3f} {i} {2 * i}\n" for i in range(10)))
    with open_source(numbered, mapping={"1": "t", "3": ("x", "mm")}) as src:
        got = src.read_all()
    np.testing.assert_allclose(got["x"], 2e-3 * np.arange(10))


def test_map_grammar_gain_offset_and_its_errors():
    from replay.csvio import parse_map
    from replay.csvio.columns import parse_mapping

    m = parse_map(["u=vir*35.15N/V", "x=pos*0.001+0.2", "pA=p:bar*2", "x_ref=dem:mm-5mm", "t=time:ms"])
    assert m == {"vir": ("u", "", "35.15N/V", ""), "pos": ("x", "", "0.001", "+0.2"),
                 "p": ("pA", "bar", "2", ""), "dem": ("x_ref", "mm", "", "-5mm"), "time": ("t", "ms")}
    from twin.models.records import signal_specs

    n = parse_mapping("f", m, signal_specs("oscillator"))
    assert n["vir"] == ("u", None, pytest.approx(35.15), 0.0)
    assert n["pos"] == ("x", None, 0.001, 0.2)
    assert n["dem"] == ("x_ref", "mm", 1.0, pytest.approx(-0.005))
    with pytest.raises(DataError, match=r"expected a number after '\*'"):
        parse_map(["x=pos*abc"])
    with pytest.raises(DataError, match=r"the time takes a unit"):
        parse_map(["t=time*0.001"])
    with pytest.raises(DataError, match=r"f: --map u=vir\*35.15N/V: gives N, but 'u' is in V"):
        parse_mapping("f", parse_map(["u=vir*35.15N/V"]))  # the rig's u is a valve voltage
    with pytest.raises(DataError, match=r"the offset \+2bar is not in a unit of m"):
        parse_mapping("f", parse_map(["x=pos:mm+2bar"]))


def test_tab_text_whose_last_column_is_empty_on_some_rows(tmp_path):
    """A tab-separated export (as the hydraulic actuator data set's) whose last column is filled only on its first
    rows: a row ending in a tab has an empty last field, not one field fewer."""
    path = tmp_path / "export.txt"
    rows = [f"{i}\t{0.1 * i:.1f}\t" + ("Var_A\t1.5" if i < 2 else "\t") for i in range(6)]
    path.write_text("Time\tPG_1\tF_Names\tF_Values\n" + "\n".join(rows) + "\n")
    with open_source(path, mapping={"Time": ("t", "ms"), "PG_1": ("pA", "bar")}) as src:
        got = src.read_all()
    assert len(got) == 6 and not src.report.skipped
    np.testing.assert_allclose(got["pA"], 1e4 * np.arange(6))
