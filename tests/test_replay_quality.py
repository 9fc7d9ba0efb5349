"""The quality gate every reader shares: NaN, time order, gaps, ranges and units."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fpdd.units import SIGNALS, to_si
from replay.base import ReadReport, Samples
from replay.csvio import CsvSource
from replay.quality import QualityGate, QualityOptions, require_signals, unit_hint
from fpdd.errors import DataError

MS = 1_000_000


def _gate(**options) -> QualityGate:
    return QualityGate(ReadReport("rig.csv"), QualityOptions(**options))


def _block(t_ms, **signals) -> Samples:
    return Samples(np.asarray(t_ms, dtype=np.int64) * MS, {k: np.asarray(v, float) for k, v in signals.items()})


def test_nan_and_inf_are_dropped_counted_and_named() -> None:
    gate = _gate()
    out = gate.apply(_block([0, 1, 2, 3, 4], x=[0.0, np.nan, 0.1, np.inf, 0.2], u=[0, 0, -np.inf, 0, 0]),
                     labels=[10, 11, 12, 13, 14], label="line")
    assert out.t_ns.tolist() == [0, 4 * MS]
    rep = gate.report
    assert rep.skipped == {"nan": 1, "inf": 2}
    text = [str(p) for p in rep.problems]
    assert "rig.csv: line 11: signal 'x' is nan, expected a finite value" in text
    assert "rig.csv: line 13: signal 'x' is inf, expected a finite value" in text
    assert "rig.csv: line 12: signal 'u' is -inf, expected a finite value" in text
    assert rep.samples_out == 2


def test_time_backwards_and_repeating_are_dropped_across_blocks() -> None:
    gate = _gate()
    a = gate.apply(_block([0, 1, 2, 2, 3], x=[0.0] * 5))
    b = gate.apply(_block([1, 3, 4, 5], x=[0.0] * 4))  # 1 goes back, 3 repeats the last of block a
    assert a.t_ns.tolist() == [0, MS, 2 * MS, 3 * MS]
    assert b.t_ns.tolist() == [4 * MS, 5 * MS]
    assert gate.report.skipped == {"time_repeated": 2, "time_backwards": 1}
    assert any("goes backwards (latest time so far 3000000 ns)" in str(p) for p in gate.report.problems)


def test_gaps_are_reported_not_filled() -> None:
    gate = _gate(max_gap_s=0.005)
    out = gate.apply(_block([0, 1, 2, 10, 11], x=[0.0] * 5))
    out2 = gate.apply(_block([30, 31], x=[0.0] * 2))
    assert len(out) + len(out2) == 7  # nothing added
    assert gate.report.gaps == [(2 * MS, 10 * MS), (11 * MS, 30 * MS)]


def test_gap_threshold_is_estimated_from_the_first_steps() -> None:
    gate = _gate()
    t = np.concatenate([np.arange(20), np.arange(20) + 100])
    for chunk in np.array_split(t, 8):  # the estimate waits for enough steps, then looks back
        gate.apply(_block(chunk, x=np.zeros(chunk.size)))
    assert gate.max_gap_ns == 5 * MS
    assert gate.report.gaps == [(19 * MS, 100 * MS)]


def test_missing_required_signal_names_file_signal_and_what_it_has() -> None:
    with pytest.raises(DataError, match=r"rig.mcap: required signal\(s\) 'pB' missing; the file has 'x', 'pA'"):
        require_signals("rig.mcap", ("x", "pA"), ("x", "pB"))


def test_missing_required_signal_in_a_csv(tmp_path: Path) -> None:
    path = tmp_path / "rig.csv"
    path.write_text("t,x,pA\n0,0,1e6\n")
    with pytest.raises(DataError, match=r"rig.csv: required signal\(s\) 'pB' missing; the file has 'x', 'pA'"):
        CsvSource(path, required=("x", "pA", "pB"))


def _pressure_bar(n: int = 500, seed: int = 5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 120.0 + 80.0 * np.sin(np.linspace(0, 6, n)) + rng.standard_normal(n)


def test_pressure_in_bar_where_pa_expected(tmp_path: Path) -> None:
    path = tmp_path / "bar.csv"
    p = _pressure_bar()
    t = np.arange(p.size) * 1e-3
    path.write_text("t,pA\n" + "".join(f"{a!r},{b!r}\n" for a, b in zip(t.tolist(), p.tolist())))
    with CsvSource(path) as src:
        with pytest.raises(DataError) as info:
            src.read_all()
    msg = str(info.value)
    assert str(path) in msg and "'pA'" in msg and "expected Pa" in msg
    assert f"observed range [{p.min():.6g}, {p.max():.6g}]" in msg
    assert "look like bar" in msg


def test_pressure_in_mpa_out_of_range_hint() -> None:
    # MPa values of a 0..35 MPa signal are 0..35 "Pa": implausibly small
    gate = _gate()
    v = np.linspace(1.0, 35.0, 200)
    with pytest.raises(DataError, match=r"'pB'.*MPa"):
        gate.apply(_block(np.arange(200), pB=v))


def test_displacement_in_mm_where_m_expected() -> None:
    gate = _gate()
    x = 80.0 * np.sin(np.linspace(0, 6, 300))  # +-80 mm
    with pytest.raises(DataError, match=r"rig.csv: signal 'x': observed range \[-79.9\d*, 79.9\d*\].*expected .* in m; "
                                        r"the values look like mm"):
        gate.apply(_block(np.arange(300), x=x))


def test_temperature_in_degc_where_k_expected() -> None:
    with pytest.raises(DataError, match=r"'T_oil'.*look like degC"):
        _gate().apply(_block(np.arange(50), T_oil=np.full(50, 45.0)))


def test_isolated_out_of_range_glitch_is_skipped_not_raised() -> None:
    gate = _gate()
    x = np.full(2000, 0.01)
    x[700] = 3.0e38  # an ADC fault value
    out = gate.apply(_block(np.arange(2000), x=x), labels=np.arange(2000) + 2, label="line")
    assert len(out) == 1999
    assert gate.report.skipped == {"out_of_range": 1}
    assert "rig.csv: line 702: signal 'x' = 3e+38 m outside [-0.5, 0.5] m" in [str(p) for p in gate.report.problems]


def test_range_check_can_be_turned_off() -> None:
    out = _gate(check_range=False).apply(_block(np.arange(10), x=np.full(10, 80.0)))
    assert len(out) == 10


def test_units_and_hint_helpers() -> None:
    np.testing.assert_allclose(to_si(np.array([1.0, 2.0]), "bar"), [1e5, 2e5])
    np.testing.assert_allclose(to_si(np.array([0.0]), "degC"), [273.15])
    np.testing.assert_allclose(to_si(np.array([1.0]), "psi"), [6894.757293168361])
    assert "mm" in unit_hint(SIGNALS["x"], -100.0, 100.0)
    assert unit_hint(SIGNALS["x"], -1e9, 1e9) == ""
    with pytest.raises(DataError, match="unknown unit 'inch'"):
        to_si(np.zeros(1), "inch")


def test_options_are_validated() -> None:
    with pytest.raises(ValueError, match=r"max_gap_s \(=0\) must be > 0 s"):
        QualityOptions(max_gap_s=0)
