"""CAN logs: round trips per format, reference files, decode against cantools, bad input.

The round trips subclass the project's one round-trip class
(:class:`roundtrip_base.RoundTripBase`, python-can's ``logformats_test.py``
pattern) once per format, mixed with the CAN-specific checks of :class:`CanChecks`
(DBC rates, uniform grid, committed reference values).
"""

from __future__ import annotations

import random
from pathlib import Path

import cantools
import numpy as np
import pytest

from fpdd.units import RIG_SIGNALS
from replay.base import Samples
from benchmarks.can import msp25_samples
from replay.can.logs import CanLogSink, CanLogSource
from replay.can.codec import DEFAULT_DBC, VectorCodec, load_dbc
from fpdd.errors import DataError, LogFormatError, SourceError

from roundtrip_base import RoundTripBase

DATA = Path(__file__).parent / "data"
T0_S = 1_700_000_000.0
#: one LSB of each signal in SI units (the quantisation of the DBC)
LSB = {"x": 1e-7, "x_ref": 1e-7, "u": 5e-4, "pA": 1e3, "pB": 1e3, "pP": 1e3, "T_oil": 0.1}


def _close(a: np.ndarray, b: np.ndarray, name: str) -> None:
    np.testing.assert_array_less(np.abs(a - b), LSB[name] * 0.5 + 1e-12 * np.abs(b) + 1e-15, err_msg=name)


# --- round trip through one base class ------------------------------------------------------------

class CanChecks(RoundTripBase):
    """CAN logs in the shared round trip, plus checks only CAN logs need."""

    time_tol_ns = 0  # microsecond timestamps, start times on whole seconds: exact
    #: half an LSB of each DBC signal (quantisation), plus float rounding
    value_atol = {k: LSB[k] * 0.5 * (1 + 1e-6) for k in LSB}

    def make_sink(self, path: Path) -> CanLogSink:
        return CanLogSink(path, decimate=False)  # every signal on every sample: exact round trip

    def make_source(self, path: Path) -> CanLogSource:
        return CanLogSource(path, signals=self.signals)

    @pytest.fixture
    def samples(self) -> Samples:
        return msp25_samples(0.5, seed=7)

    def test_round_trip_at_dbc_rates(self, tmp_path, samples):
        """Pressures at 500 Hz, status at 10 Hz: held values are those of the last frame sent."""
        p = tmp_path / f"rates{self.suffix}"
        with CanLogSink(p) as sink:
            sink.write(samples)
        with CanLogSource(p) as src:
            back = src.read_all()
        np.testing.assert_array_equal(back.t_ns, samples.t_ns)
        held_p = samples["pA"][(np.arange(len(samples)) // 2) * 2]
        _close(back["pA"], held_p, "pA")
        held_t = samples["T_oil"][(np.arange(len(samples)) // 100) * 100]
        _close(back["T_oil"], held_t, "T_oil")
        _close(back["x"], samples["x"], "x")

    def test_uniform_grid(self, tmp_path, samples):
        p = tmp_path / f"grid{self.suffix}"
        with CanLogSink(p) as sink:
            sink.write(samples)
        with CanLogSource(p, grid_hz=500.0) as src:
            back = src.read_all()
        assert np.all(np.diff(back.t_ns) == 2_000_000)
        _close(back["x"], samples["x"][::2][: len(back)], "x")

    def test_committed_reference(self):
        """The project's writer output committed in tests/data reads back to the seeded signals."""
        ref = msp25_samples(0.05, seed=0)
        with CanLogSource(DATA / f"msp25_short{self.suffix}") as src:
            back = src.read_all()
            assert src.report.skipped == {}, src.report.summary()
        assert len(back) == len(ref)
        np.testing.assert_array_equal(back.t_ns - back.t_ns[0], ref.t_ns - ref.t_ns[0])
        _close(back["x"], ref["x"], "x")
        _close(back["u"], ref["u"], "u")


class TestASC(CanChecks):
    suffix = ".asc"
    reference = DATA / "msp25_short.asc"


class TestBLF(CanChecks):
    suffix = ".blf"
    reference = DATA / "msp25_short.blf"


class TestCandump(CanChecks):
    suffix = ".log"
    reference = DATA / "msp25_short.log"


class TestTRC(CanChecks):
    suffix = ".trc"
    reference = DATA / "msp25_short.trc"


def test_round_trip_signals_are_the_rig_signals():
    assert CanChecks.signals == RIG_SIGNALS


# --- the reference recorded with python-can's own tools ------------------------------------------

@pytest.mark.parametrize("name", ["msp25_pycan_reference.log", "msp25_pycan_reference.asc"])
def test_python_can_reference(name):
    """Logged by can.Logger from a virtual bus (tests/data/make_can_reference.py): known values."""
    with CanLogSource(DATA / name) as src:
        s = src.read_all()
        rep = src.report
    k = np.arange(200)
    assert len(s) == 200
    np.testing.assert_array_equal(s.t_ns - s.t_ns[0], k * 1_000_000)
    np.testing.assert_allclose(s["x"], 10e-6 * k, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s["x_ref"], 12e-6 * k, rtol=0, atol=1e-12)
    # u is sent 100 us after x in the same cycle: the same-cycle window puts it on sample k
    np.testing.assert_allclose(s["u"], 5e-3 * k, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s["pA"], (10000 + 10 * (k // 2) * 2) * 1e3)
    np.testing.assert_allclose(s["T_oil"], 45.0 + 273.15)
    assert rep.skipped == {"unknown_id 0x7FF": 1}
    assert "frame 129" in str(rep.problems[0]) and "0x7FF" in str(rep.problems[0]) and name in str(rep.problems[0])


# --- decode against cantools, bit for bit ---------------------------------------------------------

def _random_frames(rng, n):
    return rng.integers(0, 256, size=(n, 8), dtype=np.uint8)


def test_msp25_decode_matches_cantools_bit_exact():
    rng = np.random.default_rng(1)
    codec = VectorCodec()
    db = load_dbc()
    for msg in db.messages:
        data = _random_frames(rng, 500)
        ours = codec.decode_raw(msg.frame_id, data)
        for i in range(len(data)):
            ref = msg.decode(bytes(data[i, : msg.length]), decode_choices=False)
            for name, v in ref.items():
                assert ours[name][i] == float(v), (msg.name, name, i, ours[name][i], v)


def _random_database(seed: int) -> cantools.database.can.Database:
    """Messages with random Intel/Motorola, signed/unsigned, float and odd-sized signals."""
    from cantools.database.can import Message, Signal

    rnd = random.Random(seed)
    messages = []
    for m in range(12):
        signals, used = [], set()
        for j in range(rnd.randint(1, 6)):
            big = rnd.random() < 0.5
            is_float = rnd.random() < 0.15
            length = rnd.choice([32, 64]) if is_float else rnd.randint(1, 64)
            for _ in range(200):
                if big:
                    start = rnd.randint(0, 63)
                    byte, bit = divmod(start, 8)
                    msb = (7 - byte) * 8 + bit
                    ok = msb - length + 1 >= 0
                    # bits as byte * 8 + bit-in-byte, the numbering of Intel signals
                    bits = {(7 - b // 8) * 8 + b % 8 for b in range(msb - length + 1, msb + 1)}
                else:
                    start = rnd.randint(0, 64 - length)
                    bits = set(range(start, start + length))
                    ok = True
                if ok and not bits & used:
                    used |= bits
                    scale = 1 if rnd.random() < 0.3 else rnd.choice([0.1, 0.25, 0.001, 3.7, 1e-6])
                    offset = 0 if rnd.random() < 0.5 else rnd.choice([-40, 273.15, 0.5, -1000])
                    if is_float:
                        scale, offset = 1, 0
                    conv = cantools.database.conversion.BaseConversion.factory(scale, offset, is_float=is_float)
                    signals.append(Signal(f"s{j}", start, length, "big_endian" if big else "little_endian",
                                          is_signed=(rnd.random() < 0.5) and not is_float, conversion=conv))
                    break
        messages.append(Message(0x200 + m, f"M{m}", 8, signals))
    return cantools.database.can.Database(messages)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_layouts_decode_matches_cantools_bit_exact(seed):
    db = _random_database(seed)
    codec = VectorCodec(db)
    rng = np.random.default_rng(seed)
    for msg in db.messages:
        data = _random_frames(rng, 200)
        ours = codec.decode_raw(msg.frame_id, data)
        for i in range(len(data)):
            ref = msg.decode(bytes(data[i]), decode_choices=False)
            for name, v in ref.items():
                a, b = ours[name][i], float(v)
                assert a == b or (np.isnan(a) and np.isnan(b)), (msg.name, name, i, a, b)


def test_encode_matches_cantools_bit_exact():
    rng = np.random.default_rng(3)
    codec = VectorCodec()
    db = load_dbc()
    for msg in db.messages:
        n = 300
        vals = {}
        for s in msg.signals:
            lo, hi = s.minimum, s.maximum
            raw = rng.integers(round((lo - s.offset) / s.scale), round((hi - s.offset) / s.scale) + 1, n)
            vals[s.name] = raw * s.scale + s.offset
        ours = codec.encode(msg.frame_id, vals)
        for i in range(n):
            ref = msg.encode({k: float(v[i]) for k, v in vals.items()}, strict=True)
            assert bytes(ours[i, : msg.length]) == ref, (msg.name, i)


# --- bad input ------------------------------------------------------------------------------------

def _line(t: float, fid: int, data: bytes) -> str:
    return f"({t:.6f}) can0 {fid:03X}#{data.hex().upper()}\n"


def _good_lines(cycles: int, start: int = 0, t0: float = T0_S, skip_pressure: range = range(0)) -> list[str]:
    """candump lines of MSP25 traffic encoded with cantools (independent of our encoder)."""
    db = load_dbc()
    pos, valve = db.get_message_by_name("MSP25_Position"), db.get_message_by_name("MSP25_Valve")
    pres, hpu = db.get_message_by_name("MSP25_Pressure"), db.get_message_by_name("HPU_Status")
    out = []
    for k in range(start, start + cycles):
        t = t0 + k * 1e-3
        out.append(_line(t, 0x100, pos.encode({"x": float(k), "x_ref": 0.0})))
        out.append(_line(t + 1e-4, 0x101, valve.encode({"u": 0.0, "RollCnt": k % 256, "CtrlMode": 1})))
        if k % 2 == 0 and k not in skip_pressure:
            out.append(_line(t + 2e-4, 0x120, pres.encode({"pA": 1000, "pB": 2000, "RollCnt": (k // 2) % 256})))
        if k % 100 == 0:
            out.append(_line(t + 3e-4, 0x3A0, hpu.encode({"pP": 21000, "T_oil": 40.0, "HPU_State": 3,
                                                          "RollCnt": (k // 100) % 16})))
    return out


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("".join(lines))
    return path


def _read(path: Path, **kw):
    with CanLogSource(path, **kw) as src:
        s = src.read_all()
        return s, src.report


def test_clean_file_has_empty_report(tmp_path):
    s, rep = _read(_write(tmp_path / "ok.log", _good_lines(300)))
    assert len(s) == 300 and rep.skipped == {} and rep.gaps == [] and not rep.truncated
    np.testing.assert_allclose(s["x"], np.arange(300) * 1e-6)


def test_unknown_id_counted_skipped_and_named(tmp_path):
    lines = _good_lines(300)

    def t_of(i: int) -> float:
        return float(lines[i - 1][1:].split(")")[0]) + 5e-5

    lines.insert(10, _line(t_of(10), 0x7AB, b"\x01\x02"))
    lines.insert(20, _line(t_of(20), 0x7AB, b"\x01\x02"))
    lines.insert(30, f"({t_of(30):.6f}) can0 18FF0001#0102\n")
    p = _write(tmp_path / "unk.log", lines)
    s, rep = _read(p)
    assert len(s) == 300
    assert rep.skipped["unknown_id 0x7AB"] == 2 and rep.skipped["unknown_id 0x18FF0001x"] == 1
    msg = str(rep.problems[0])
    assert str(p) in msg and "frame 10 " in msg and "0x7AB" in msg and "not in the DBC" in msg


def test_wrong_dlc(tmp_path):
    lines = _good_lines(100)
    i = next(j for j, ln in enumerate(lines) if " 120#" in ln and j > 20)
    lines[i] = lines[i].split("#")[0] + "#0102\n"  # pressure frame with 1 byte... 2 bytes
    s, rep = _read(_write(tmp_path / "dlc.log", lines))
    assert rep.skipped["wrong_dlc"] == 1 and len(s) == 100
    msg = str(rep.problems[0])
    assert f"frame {i} " in msg and "0x120" in msg and "DLC 2, expected 5" in msg


def test_frame_that_fails_to_decode(tmp_path):
    lines = _good_lines(100)
    i = next(j for j, ln in enumerate(lines) if " 100#" in ln and j > 40)
    lines[i] = lines[i].split("#")[0] + "#FFFFFF7F00000000\n"  # x = 2^31-1 raw, beyond the DBC range
    s, rep = _read(_write(tmp_path / "dec.log", lines))
    assert rep.skipped["decode_error"] == 1
    assert "signal x = 2.14748e+08 um outside the DBC range [-500000, 500000]" in str(rep.problems[0])
    assert len(s) == 99  # that control cycle has no x: no grid instant


def test_error_and_remote_frames(tmp_path):
    lines = _good_lines(50)
    lines.insert(5, "(%.6f) can0 20000080#0000000000000000\n" % (T0_S + 0.0012))  # error frame
    lines.insert(9, "(%.6f) can0 120#R\n" % (T0_S + 0.0021))  # remote frame of a DBC id
    s, rep = _read(_write(tmp_path / "err.log", lines))
    assert rep.skipped["decode_error"] == 2 and len(s) == 50
    text = " ".join(str(p) for p in rep.problems)
    assert "error frame" in text and "remote frame" in text


def test_time_going_backwards_and_repeating(tmp_path):
    lines = _good_lines(100)
    lines.insert(40, _line(T0_S + 0.001, 0x101, b"\x00\x00\x05\x01"))  # back in time
    lines.insert(60, lines[59])  # the same frame again: repeated timestamp for that id
    s, rep = _read(_write(tmp_path / "back.log", lines))
    assert rep.skipped["time_backwards"] == 1 and rep.skipped["time_repeated"] == 1
    assert np.all(np.diff(s.t_ns) > 0) and len(s) == 100
    assert any("goes back to 1700000000.001000 s" in str(p) and "frame 40 " in str(p) for p in rep.problems)


def test_counter_gap_reported(tmp_path):
    lines = [ln for ln in _good_lines(100) if not (" 101#" in ln and ln.startswith("(1700000000.0301"))]
    s, rep = _read(_write(tmp_path / "cnt.log", lines))
    assert rep.skipped["counter_gap"] == 1
    assert any("rolling counter RollCnt jumps 29 -> 31, expected 30: 1 frame(s) lost" in str(p) for p in rep.problems)
    assert np.isfinite(s["u"]).all()  # one lost frame is within the max age


def test_stale_signal_set_to_nan_and_reported(tmp_path):
    lines = _good_lines(200, skip_pressure=range(100, 120))  # 20 ms without pressures
    s, rep = _read(_write(tmp_path / "stale.log", lines))
    stale = np.isnan(s["pA"])
    assert stale.any() and np.isnan(s["pB"][stale]).all()
    assert rep.skipped["stale pA"] == stale.sum()
    # max age 2.5 * 2 ms: samples more than 5 ms after the last pressure frame (t=98.2 ms) are NaN
    t_ms = (s.t_ns - s.t_ns[0]) / 1e6
    np.testing.assert_array_equal(t_ms[stale], np.arange(104, 120))
    assert any("pA, pB stale" in str(p) and "max age 5 ms" in str(p) for p in rep.problems)


def test_gap_in_master_reported_not_interpolated(tmp_path):
    lines = _good_lines(100) + _good_lines(100, start=150)
    s, rep = _read(_write(tmp_path / "gap.log", lines))
    assert len(s) == 200
    assert rep.gaps == [(int(T0_S * 1e9) + 99_000_000, int(T0_S * 1e9) + 150_000_000)]


def test_warmup_until_every_signal_seen(tmp_path):
    lines = _good_lines(300)
    i = next(j for j, ln in enumerate(lines) if " 3A0#" in ln)
    del lines[i]  # first HPU status lost: T_oil and pP first seen at 100 ms
    s, rep = _read(_write(tmp_path / "warm.log", lines), signals=("x", "u", "pA", "pB", "T_oil", "pP"))
    assert len(s) == 200 and rep.skipped["warmup"] == 100
    assert np.isfinite(s["T_oil"]).all()


def test_missing_required_signal(tmp_path):
    p = _write(tmp_path / "m.log", _good_lines(50))
    with pytest.raises(DataError, match="signal 'F' is in no message"):
        CanLogSource(p, signals=("x", "F"))


def test_truncated_candump_keeps_prefix(tmp_path):
    text = "".join(_good_lines(200))
    p = tmp_path / "cut.log"
    p.write_text(text[: len(text) // 2 - 7])
    s, rep = _read(p)
    assert rep.truncated and 90 <= len(s) <= 101
    assert any("truncated" in str(p_) for p_ in rep.problems)


def test_truncated_asc_and_blf_keep_prefix(tmp_path):
    samples = msp25_samples(1.0, seed=1)
    for suf in (".asc", ".blf"):
        full = tmp_path / f"full{suf}"
        with CanLogSink(full) as sink:
            sink.write(samples)
        raw = full.read_bytes()
        cut = tmp_path / f"cut{suf}"
        cut.write_bytes(raw[: len(raw) * 6 // 10])
        s, rep = _read(cut)
        assert rep.truncated, suf
        assert 200 < len(s) < 1000, (suf, len(s))
        _close(s["x"], samples["x"][: len(s)], "x")
        assert any("kept" in str(p) for p in rep.problems), rep.problems


def test_unreadable_and_unknown_inputs(tmp_path):
    with pytest.raises(SourceError, match="not found"):
        CanLogSource(tmp_path / "none.log")
    with pytest.raises(LogFormatError, match="unknown CAN log format .suffix '.xyz'.; known: .asc, .blf, .log, .trc"):
        CanLogSource(_write(tmp_path / "a.xyz", ["x"]))
    bad = tmp_path / "bad.blf"
    bad.write_bytes(b"NOT A BLF FILE AT ALL" * 10)
    with pytest.raises(LogFormatError, match="bad.blf"):
        CanLogSource(bad)
    with pytest.raises(LogFormatError, match="no CAN frames"):
        CanLogSource(_write(tmp_path / "empty.log", ["\n"]))
    with pytest.raises(SourceError, match="DBC file not found"):
        VectorCodec(tmp_path / "no.dbc")


def test_sink_refuses_unrepresentable_values(tmp_path):
    s = msp25_samples(0.01)
    s.signals["x"][3] = 0.9  # m: beyond 32 bits of 0.1 um
    with pytest.raises(DataError, match="signal 'x' row 3: value 900000 um outside the DBC range"):
        with CanLogSink(tmp_path / "o.log") as sink:
            sink.write(s)
    part = Samples(s.t_ns, {"x": s["x"]})
    with pytest.raises(DataError, match="needs x, x_ref"):
        with CanLogSink(tmp_path / "p.log") as sink:
            sink.write(part)


def test_dbc_is_documented_and_loads():
    db = load_dbc(DEFAULT_DBC)
    assert {m.name: m.cycle_time for m in db.messages} == {
        "MSP25_Position": 1, "MSP25_Valve": 1, "MSP25_Pressure": 2, "HPU_Status": 100}
    assert VectorCodec().rig_signals == ("x_ref", "u", "x", "pA", "pB", "T_oil", "pP")


def test_required_signal_missing_from_log(tmp_path):
    s = msp25_samples(0.05)
    part = Samples(s.t_ns, {k: s[k] for k in ("x", "x_ref", "u")})
    p = tmp_path / "xu.log"
    with CanLogSink(p) as sink:
        sink.write(part)
    with CanLogSource(p) as src:
        assert src.signals == ("x_ref", "u", "x")
    with pytest.raises(DataError, match="required signal\\(s\\) 'pA' missing"):
        CanLogSource(p, required=("x", "pA"))


def test_many_unknown_ids_are_named_up_to_a_limit(tmp_path):
    lines = _good_lines(100)
    for j in range(30):
        lines.insert(2 + j, _line(T0_S + 1e-4 + 1e-6 * (j + 1), 0x600 + j, b"\x00"))
    s, rep = _read(_write(tmp_path / "flood.log", lines))
    assert len(s) == 100
    named = [k for k in rep.skipped if k.startswith("unknown_id 0x")]
    assert len(named) == 20 and rep.skipped["unknown_id other"] == 10


# --- your own DBC: its signal names mapped with --map ----------------------------------------------------------

def _foreign_dbc(path: Path, *, units: bool = True) -> Path:
    """A DBC of another vendor's names, written by cantools: the MSP25's resolutions (0.1 um, 0.5 mV, 1 kPa) in
    other units and scales (mm, mV, bar), the position's unit left out where ``units`` is False."""
    from cantools.database.can import Database, Message, Signal

    def sig(name, start, length, scale, unit, signed=True, lo=None, hi=None):
        return Signal(name, start, length, is_signed=signed, conversion=cantools.database.conversion.BaseConversion
                      .factory(scale=scale, offset=0.0), minimum=lo, maximum=hi, unit=unit)

    msgs = [
        Message(0x210, "AxisPosition", 8, [sig("MyPosSignal", 0, 32, 1e-4, "mm" if units else ""),
                                           sig("MyDemand", 32, 32, 1e-4, "mm")], cycle_time=1),
        Message(0x211, "ServoValve", 2, [sig("ValveCmd", 0, 16, 0.5, "mV")], cycle_time=1),
        Message(0x220, "Chambers", 4, [sig("ChamberA", 0, 16, 0.01, "bar", signed=False),
                                       sig("ChamberB", 16, 16, 0.01, "bar", signed=False)], cycle_time=1),
    ]
    path.write_text(Database(msgs).as_dbc_string())
    return path


FOREIGN_MAP = ["--map", "x=MyPosSignal:mm", "--map", "x_ref=MyDemand", "--map", "u=ValveCmd",
               "--map", "pA=ChamberA", "--map", "pB=ChamberB"]


def _foreign_log(path: Path, dbc: Path, samples: Samples) -> Path:
    """``samples`` (SI) as frames of the foreign DBC, encoded by cantools, written by python-can's own writer."""
    import can

    db = cantools.database.load_file(str(dbc))
    values = {"AxisPosition": {"MyPosSignal": samples["x"] * 1e3, "MyDemand": samples["x_ref"] * 1e3},
              "ServoValve": {"ValveCmd": samples["u"] * 1e3},
              "Chambers": {"ChamberA": samples["pA"] * 1e-5, "ChamberB": samples["pB"] * 1e-5}}
    with can.Logger(str(path)) as writer:
        for i, t_ns in enumerate(samples.t_ns):
            for k, (name, sigs) in enumerate(values.items()):
                msg = db.get_message_by_name(name)
                data = msg.encode({s: float(v[i]) for s, v in sigs.items()}, scaling=True, strict=False)
                writer.on_message_received(can.Message(timestamp=t_ns * 1e-9 + 1e-4 * k, arbitration_id=msg.frame_id,
                                                       is_extended_id=False, data=data))
    return path


def _reference_samples() -> Samples:
    from replay.csvio import CsvSource

    with CsvSource(DATA / "reference.csv") as src:
        return src.read_all()


def test_own_dbc_signals_mapped_as_csv_columns(tmp_path, capsys):
    """A DBC with other names and units (cantools) and a BLF log (python-can's writer): ``replay info --map``
    reads it to the same numbers as the record it was made from, to the DBC's resolution."""
    import json

    from replay import cli as replay_cli

    samples = _reference_samples()
    dbc = _foreign_dbc(tmp_path / "vendor.dbc", units=False)
    log = _foreign_log(tmp_path / "vendor.blf", dbc, samples)
    assert replay_cli.main(["info", str(log), "--dbc", str(dbc), *FOREIGN_MAP, "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert set(info["signals"]) == {"x", "x_ref", "u", "pA", "pB"}
    src = CanLogSource(log, dbc=VectorCodec(dbc, mapping={"MyPosSignal": ("x", "mm"), "MyDemand": "x_ref",
                                                          "ValveCmd": "u", "ChamberA": "pA", "ChamberB": "pB"}))
    got = src.read_all()
    assert len(got) == len(samples)
    for name in ("x", "x_ref", "u", "pA", "pB"):
        _close(got[name], samples[name], name)


def test_own_dbc_without_map_names_what_was_looked_for(tmp_path, capsys):
    """Without --map the error says what was looked for and what the DBC has (not an empty list); a mapped
    signal the DBC lacks is named with the DBC's signals; a signal without a unit is refused with the map
    that gives it one."""
    from replay import cli as replay_cli

    dbc = _foreign_dbc(tmp_path / "vendor.dbc", units=False)
    log = _foreign_log(tmp_path / "vendor.asc", dbc, _reference_samples().slice(0, 50))
    assert replay_cli.main(["info", str(log), "--dbc", str(dbc)]) != 0
    err = capsys.readouterr().err
    assert "()" not in err and "looked for CAN signals named as a rig signal" in err
    assert "MyPosSignal (no unit, in AxisPosition)" in err and "--map x=MyPosSignal:mm" in err
    assert replay_cli.main(["info", str(log), "--dbc", str(dbc), "--map", "x=MyPos"]) != 0
    err = capsys.readouterr().err
    assert "no signal 'MyPos' in the DBC; its signals: ChamberA, ChamberB, MyDemand, MyPosSignal, ValveCmd" in err
    assert replay_cli.main(["info", str(log), "--dbc", str(dbc), "--map", "x=MyPosSignal"]) != 0
    err = capsys.readouterr().err
    assert "signal 'MyPosSignal' (-> x) has unit ''" in err and "--map x=MyPosSignal:UNIT" in err
    assert replay_cli.main(["info", str(log), "--dbc", str(dbc), "--map", "x=MyPosSignal:bar"]) != 0
    assert "but 'x' is in m" in capsys.readouterr().err
    assert len(err.strip().splitlines()) <= 2  # one line (and argparse's pointer to --help)
    # twin's commands take --dbc too; a record mapped without a drive says what its DBC has
    from twin import cli as twin_cli

    assert twin_cli.main(["fit", str(log), "--dbc", str(dbc), "--map", "pA=ChamberA", "-q"]) == 2
    err = capsys.readouterr().err
    assert "missing a drive" in err and "MyPosSignal (no unit, in AxisPosition)" in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_twin_track_reads_own_dbc_through_map(tmp_path, capsys):
    """``twin track LOG --dbc VENDOR.dbc --map x=MyPosSignal:mm ...`` tracks the very numbers the shipped MSP25
    DBC gives for the same record: the same resolutions decode to the same values, so the same estimates."""
    import json

    from twin import cli as twin_cli

    samples = _reference_samples()
    dbc = _foreign_dbc(tmp_path / "vendor.dbc")
    ours = _foreign_log(tmp_path / "vendor.blf", dbc, samples)
    shipped = tmp_path / "msp25.blf"
    with CanLogSink(shipped, decimate=False) as sink:
        sink.write(samples)
    runs = []
    for log, extra in ((ours, ["--dbc", str(dbc), *FOREIGN_MAP]), (shipped, [])):
        assert twin_cli.main(["track", str(log), *extra, "--out", str(tmp_path / log.stem), "--json", "-q"]) == 0
        runs.append(json.loads(capsys.readouterr().out))
    assert runs[0]["samples"] == runs[1]["samples"] == len(samples)
    for name, d in runs[1]["final"].items():
        assert runs[0]["final"][name]["value"] == pytest.approx(d["value"], rel=1e-9), name


def test_live_bus_takes_the_same_map(tmp_path):
    """``can://`` with your own DBC: the same --map (rigs.toml ``map``) names its signals."""
    from replay.factory import open_source

    dbc = _foreign_dbc(tmp_path / "vendor.dbc")
    with open_source("can://virtual/own_dbc_map", dbc=str(dbc), timeout_s=0.1,
                     mapping={"MyPosSignal": ("x", "mm"), "ValveCmd": "u", "ChamberA": ("pA", "bar")}) as src:
        assert src.codec.rig_signals == ("u", "x", "pA")
        assert src.codec.message_of("x").name == "AxisPosition"
