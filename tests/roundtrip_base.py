"""One round-trip test class for every file format (python-can ``logformats_test.py`` style).

Subclass :class:`RoundTripBase` once per format and set ``suffix``; the default
``make_sink`` / ``make_source`` go through :func:`replay.factory.open_sink` /
:func:`~replay.factory.open_source`.  Override the hooks where a format needs it::

    class TestAscRoundTrip(RoundTripBase):
        suffix = ".asc"
        time_tol_ns = 1_000               # the format stores microseconds
        value_atol = {"x": 1e-7, ...}     # scaled integer signals
        reference = DATA / "msp25_short.asc"   # a committed file this reader must read

A subclass whose name starts with ``Test`` is collected by pytest; this base is not.
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar
from collections.abc import Mapping

import numpy as np
import pytest

from fpdd.units import RIG_SIGNALS
from replay.base import Samples, Sink, Source
from replay.factory import open_sink, open_source

DATA = Path(__file__).resolve().parent / "data"
T0_NS = 1_700_000_000_000_000_000


class RoundTripBase:
    """Write samples, read them back, compare.  Hooks: class attributes and ``make_*``."""

    #: file suffix of the format, e.g. ".csv"
    suffix: ClassVar[str] = ""
    #: signals written and expected back
    signals: ClassVar[tuple[str, ...]] = RIG_SIGNALS
    #: sample rate (Hz) and length (s) of the generated record
    rate_hz: ClassVar[float] = 1000.0
    seconds: ClassVar[float] = 2.5
    #: tolerance on times read back (ns) and on values (SI units, per signal; 0 = exact)
    time_tol_ns: ClassVar[int] = 0
    value_atol: ClassVar[Mapping[str, float]] = {}
    #: a committed reference file of this format that must read cleanly, or None
    reference: ClassVar[Path | None] = None

    # -- hooks ------------------------------------------------------------------------------------

    def make_samples(self) -> Samples:
        """A seeded record of plausible rig signals in SI units, epoch times."""
        rng = np.random.default_rng(20240601)
        n = int(round(self.seconds * self.rate_hz))
        t = np.arange(n) / self.rate_hz
        base = {
            "x_ref": 0.02 * np.sin(2 * np.pi * 2.0 * t),
            "u": 3.0 * np.cos(2 * np.pi * 2.0 * t),
            "x": 0.02 * np.sin(2 * np.pi * 2.0 * t - 0.1),
            "pA": 12e6 + 4e6 * np.sin(2 * np.pi * 2.0 * t),
            "pB": 12e6 - 4e6 * np.sin(2 * np.pi * 2.0 * t),
            "F": 5e4 * np.sin(2 * np.pi * 2.0 * t),
            "T_oil": np.full(n, 318.15),
            "pP": np.full(n, 21e6),
        }
        noise = {"x_ref": 0.0, "u": 1e-3, "x": 1e-5, "pA": 1e4, "pB": 1e4, "F": 10.0, "T_oil": 0.05, "pP": 1e4}
        t_ns = T0_NS + np.arange(n, dtype=np.int64) * int(round(1e9 / self.rate_hz))
        return Samples(t_ns, {k: base[k] + noise[k] * rng.standard_normal(n) for k in self.signals})

    def make_sink(self, path: Path) -> Sink:
        return open_sink(path)

    def make_source(self, path: Path) -> Source:
        return open_source(path)

    # -- helpers ----------------------------------------------------------------------------------

    def write(self, tmp_path: Path, samples: Samples, name: str = "rt") -> Path:
        path = tmp_path / f"{name}{self.suffix}"
        with self.make_sink(path) as sink:
            half = len(samples) // 2
            sink.write(samples.slice(0, half))  # two blocks: the sink must append
            sink.write(samples.slice(half, len(samples)))
        return path

    def assert_same(self, got: Samples, want: Samples) -> None:
        assert len(got) == len(want), f"{len(got)} samples read back, {len(want)} written"
        dt = np.abs(got.t_ns - want.t_ns)
        assert dt.max() <= self.time_tol_ns, f"time differs by up to {dt.max()} ns"
        for k in self.signals:
            assert k in got.signals, f"signal {k!r} not read back (got {got.names})"
            np.testing.assert_allclose(got[k], want[k], rtol=0, atol=self.value_atol.get(k, 0.0),
                                       err_msg=f"signal {k!r}")

    # -- tests ------------------------------------------------------------------------------------

    def test_round_trip(self, tmp_path: Path) -> None:
        want = self.make_samples()
        path = self.write(tmp_path, want)
        with self.make_source(path) as src:
            assert set(self.signals) <= set(src.signals)
            got = src.read_all()
            report = src.report
        self.assert_same(got, want)
        assert not report.truncated
        assert not report.skipped, report.summary()
        assert report.gaps == []
        assert report.samples_out == len(want)

    def test_chunks_are_bounded_and_complete(self, tmp_path: Path) -> None:
        want = self.make_samples()
        path = self.write(tmp_path, want)
        with self.make_source(path) as src:
            blocks = list(src.chunks(size=333))
        assert blocks and all(0 < len(b) <= 333 for b in blocks)
        self.assert_same(Samples.concat(blocks), want)

    def test_sample_by_sample(self, tmp_path: Path) -> None:
        want = self.make_samples()
        path = self.write(tmp_path, want)
        with self.make_source(path) as src:
            first = [s for _, s in zip(range(5), src)]
        assert [s.t_ns for s in first] == pytest.approx(want.t_ns[:5].tolist(), abs=self.time_tol_ns)
        for i, s in enumerate(first):
            for k in self.signals:
                assert s.values[k] == pytest.approx(want[k][i], abs=self.value_atol.get(k, 0.0))

    def test_reference_file_reads_cleanly(self) -> None:
        if self.reference is None:
            return  # this format has no committed reference: nothing to check
        with self.make_source(self.reference) as src:
            got = src.read_all()
            assert len(got) > 0
            assert not src.report.truncated
            assert not src.report.skipped, src.report.summary()
        assert np.all(np.diff(got.t_ns) > 0)
