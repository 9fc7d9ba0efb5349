"""Reprs a person reads in a REPL: one line each, the key facts, never the arrays."""

from __future__ import annotations

import numpy as np

from replay.base import ReadReport, Samples
from twin.record import Record

MAX_LEN = 200  # one line of a terminal, roughly


def one_line(obj: object) -> str:
    text = repr(obj)
    assert "\n" not in text and len(text) <= MAX_LEN, (len(text), text)
    assert "array(" not in text  # no array printed
    return text


def rig_record(n: int = 3000, dt: float = 1e-3, name: str = "rig-a run 3") -> Record:
    rng = np.random.default_rng(7)
    return Record(dt, {"x_ref": rng.normal(0, 1e-3, n), "u": rng.normal(0, 1, n), "x": rng.normal(0, 1e-3, n),
                       "pA": rng.normal(5e6, 1e4, n), "pB": rng.normal(5e6, 1e4, n), "aux_7": rng.normal(0, 1, n)},
                  name=name)


def test_record_repr_names_the_count_duration_step_and_signals_with_units() -> None:
    rec = rig_record()
    text = one_line(rec)
    assert text.startswith("Record('rig-a run 3', ")
    assert f"{len(rec)} samples" in text and "3 s at dt 1 ms" in text
    assert text.endswith(": x_ref [m], u [V], x [m], pA [Pa], pB [Pa], aux_7)")  # a signal of no known unit: bare


def test_record_repr_stays_one_line_with_many_signals_and_a_long_name() -> None:
    rng = np.random.default_rng(8)
    rec = Record(1e-4, {f"can_signal_{i:02d}": rng.normal(size=500) for i in range(30)},
                 name="/data/hall2/rig-b/2026-11-30/" + "very_long_log_name_" * 5 + ".blf[0:500]")
    text = one_line(rec)
    assert "500 samples" in text and "0.05 s at dt 0.1 ms" in text
    shown = [f"can_signal_{i:02d}" for i in range(30) if f"can_signal_{i:02d}" in text]
    assert shown == [f"can_signal_{i:02d}" for i in range(len(shown))] and len(shown) >= 5
    assert text.endswith(f", ... {30 - len(shown)} more)")
    assert ".blf[0:500]'" in text  # the end of the name says which piece of which file


def test_samples_repr_names_the_count_span_step_and_signals_with_units() -> None:
    rec = rig_record()
    samples = rec.to_samples()
    text = one_line(samples)
    assert text == ("Samples(3000 samples over 2.999 s, dt 1 ms: x_ref [m], u [V], x [m], pA [Pa], pB [Pa], aux_7)")
    rng = np.random.default_rng(9)
    t_ns = np.cumsum(rng.integers(900_000, 1_100_000, 400))  # a logger's jittered clock
    jittered = one_line(Samples(t_ns, {"x": rng.normal(size=400), "T_oil": rng.normal(300, 1, 400)}))
    assert jittered.startswith("Samples(400 samples over ") and ", dt ~" in jittered and "T_oil [K]" in jittered
    thirds = one_line(Record(1e-3 / 3, {"x": np.zeros(30)}).to_samples())  # ns rounding is no jitter
    assert "dt 0.3333 ms" in thirds
    assert one_line(Samples.empty(("x", "pA"))) == "Samples(0 samples: x [m], pA [Pa])"


def test_read_report_repr_counts_and_keeps_the_problems_out_of_the_line() -> None:
    report = ReadReport("rig-b.asc", records_read=12_000, samples_out=11_000)
    for i in range(120):
        report.skip("bad_dlc", f"line {100 + i}", "a frame of 7 bytes where the DBC declares 8")
    text = one_line(report)
    assert text.startswith("ReadReport(rig-b.asc: 12000 records read, 11000 samples out; ")
    assert "bad_dlc=120" in text and f"{report.max_problems} problem(s) kept" in text


def test_a_tracked_block_prints_its_size_and_last_status_not_its_arrays() -> None:
    from twin.online.tracker import OnlineTracker

    rec = rig_record(n=500)
    block = OnlineTracker(dt=1e-3).process(rec.to_samples())
    text = one_line(block)
    assert text.startswith("TrackBlock(500 samples over 0.499 s, 5 parameters, outputs x, pA, pB; last status ")
