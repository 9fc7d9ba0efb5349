"""Make the small reference files of tests/data with the project's own writers.

    python tests/data/make_reference.py

writes ``reference.csv`` and ``reference.mcap`` (0.2 s of the five rig signals at
1 kHz, SI units) and ``oscillator.csv`` (the oscillator contract ``t, u, y``).  The
samples come from :func:`reference_samples` / :func:`oscillator_samples` (seeded), so a
test can compare what it reads with what was written.  Rerun only when the layout of
a format changes on purpose, and commit the outputs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fpdd.units import RIG_SIGNALS
from replay.base import Samples
from replay.csvio import CsvSink
from replay.mcapio import McapSink

HERE = Path(__file__).resolve().parent
T0_NS = 1_700_000_000_000_000_000  # an epoch time, so that absolute times are exercised


def reference_samples(n: int = 200, rate_hz: float = 1000.0, seed: int = 3) -> Samples:
    """Plausible rig signals: a 5 Hz sine demand, a tracking rod, chamber pressures (SI)."""
    rng = np.random.default_rng(seed)
    t_ns = T0_NS + np.arange(n, dtype=np.int64) * int(round(1e9 / rate_hz))
    t = np.arange(n) / rate_hz
    x_ref = 0.01 * np.sin(2 * np.pi * 5.0 * t)
    x = x_ref + 1e-5 * rng.standard_normal(n)
    u = 2.0 * np.cos(2 * np.pi * 5.0 * t) + 0.01 * rng.standard_normal(n)
    pA = 10e6 + 3e6 * np.sin(2 * np.pi * 5.0 * t) + 2e4 * rng.standard_normal(n)
    pB = 10e6 - 3e6 * np.sin(2 * np.pi * 5.0 * t) + 2e4 * rng.standard_normal(n)
    cols = dict(x_ref=x_ref, u=u, x=x, pA=pA, pB=pB)
    return Samples(t_ns, {k: cols[k] for k in RIG_SIGNALS})


def oscillator_samples(n: int = 100, rate_hz: float = 100.0, seed: int = 4) -> Samples:
    """The oscillator contract: input ``u`` (V) and displacement ``y`` (m), time from 0."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    u = np.where(t >= 0.1, 1.0, 0.0)
    y = 0.5 * (1 - np.exp(-t / 0.2)) * u + 1e-4 * rng.standard_normal(n)
    return Samples(np.arange(n, dtype=np.int64) * int(round(1e9 / rate_hz)), {"u": u, "y": y})


def main() -> None:
    with CsvSink(HERE / "reference.csv") as sink:
        sink.write(reference_samples())
    with McapSink(HERE / "reference.mcap") as sink:
        sink.write(reference_samples())
    with CsvSink(HERE / "oscillator.csv") as sink:
        sink.write(oscillator_samples())


if __name__ == "__main__":
    main()
