"""Ingest throughput of the replay readers, side by side, same run, same machine.

    python -m benchmarks.replay [--seconds 3600] [--baseline-seconds 600] [--json] [--no-can]

Writes a seeded record of the five rig signals at 1 kHz (default one hour, 3.6 M
samples) to a temporary directory as MCAP and as CSV, then measures in samples/s:

* MCAP write (:class:`~replay.mcapio.McapSink`: per-sample JSON + block topic);
* MCAP read through :class:`~replay.mcapio.McapSource` (block topic, the default);
* MCAP read of the per-sample JSON topic through ``McapSource`` (batched ``json.loads``);
* baseline: ``mcap`` reader + one ``json.loads`` per message (the naive path);
* CSV write and read (:class:`~replay.csvio.CsvSource`), baseline ``csv.reader`` row by row;
* the CAN rows of ``benchmarks.can.run()`` when that module is installed
  (frames/s, against a per-frame ``cantools`` decode loop).

The per-sample paths and baselines are slow (tens of seconds per hour of data), so they
run over the first ``--baseline-seconds`` of the same files; rates are per sample, so
the ratios stay comparable.  Ratio = rate / baseline rate of the same format.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np
from mcap.reader import make_reader

from fpdd.units import RIG_SIGNALS
from replay.base import Samples
from replay.csvio import CsvSink, CsvSource
from replay.mcapio import SIGNALS_TOPIC, McapSink, McapSource


def record(seconds: float, rate_hz: float = 1000.0, seed: int = 0) -> Samples:
    """A seeded rig record in SI units (sine demand, tracking rod, chamber pressures)."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate_hz))
    t = np.arange(n) / rate_hz
    s = np.sin(2 * np.pi * 1.0 * t)
    cols = {
        "x_ref": 0.02 * s,
        "u": 2.0 * np.cos(2 * np.pi * t) + 0.01 * rng.standard_normal(n),
        "x": 0.02 * s + 1e-5 * rng.standard_normal(n),
        "pA": 12e6 + 4e6 * s + 1e4 * rng.standard_normal(n),
        "pB": 12e6 - 4e6 * s + 1e4 * rng.standard_normal(n),
    }
    return Samples(np.arange(n, dtype=np.int64) * int(round(1e9 / rate_hz)), {k: cols[k] for k in RIG_SIGNALS})


def _timed(f: Callable[[], int]) -> tuple[int, float]:
    t = time.perf_counter()
    n = f()
    return n, time.perf_counter() - t


def _naive_mcap(path: Path, end_ns: int) -> int:
    cols: dict[str, list[float]] = {k: [] for k in RIG_SIGNALS}
    times: list[int] = []
    with open(path, "rb") as f:
        for _s, _c, msg in make_reader(f, validate_crcs=True).iter_messages(
                topics=[SIGNALS_TOPIC], ending_before=end_ns):
            d = json.loads(msg.data)
            times.append(msg.log_time)
            for k in RIG_SIGNALS:
                cols[k].append(d[k])
    Samples(np.array(times), {k: np.array(v) for k, v in cols.items()})
    return len(times)


def _naive_csv(path: Path, rows: int) -> int:
    out: list[list[float]] = []
    with open(path, newline="") as f:
        reader = csv.reader(f)
        next(reader)
        for i, row in enumerate(reader):
            if i >= rows:
                break
            out.append([float(v) for v in row])
    np.array(out)
    return len(out)


def _read(src_factory: Callable[[], Any]) -> int:
    with src_factory() as src:
        return sum(len(b) for b in src.chunks())


def run(seconds: float = 3600.0, baseline_seconds: float = 600.0, can: bool = True) -> dict[str, Any]:
    """Measure every row; returns ``{"rows": [...], "can": {...} or None}``."""
    data = record(seconds)
    n = len(data)
    base_s = min(baseline_seconds, seconds)
    base_end_ns = int(round(base_s * 1e9))
    rows: list[dict[str, Any]] = []

    def row(name: str, samples: int, secs: float, baseline: str | None) -> None:
        rows.append({"name": name, "samples": samples, "seconds": secs,
                     "samples_per_s": samples / secs, "baseline": baseline})

    with tempfile.TemporaryDirectory() as d:
        mcap_path = Path(d) / "hour.mcap"
        csv_path = Path(d) / "hour.csv"

        def write_mcap() -> int:
            with McapSink(mcap_path) as sink:
                sink.write(data)
            return n

        def write_csv() -> int:
            with CsvSink(csv_path) as sink:
                for a in range(0, n, 65536):
                    sink.write(data.slice(a, a + 65536))
            return n

        row("mcap write (json + block)", *_timed(write_mcap), None)
        row("mcap read naive json.loads", *_timed(lambda: _naive_mcap(mcap_path, base_end_ns)), None)
        row("mcap read McapSource block topic", *_timed(lambda: _read(lambda: McapSource(mcap_path))),
            "mcap read naive json.loads")
        row("mcap read McapSource /rig/signals", *_timed(lambda: _read(
            lambda: McapSource(mcap_path, topic=SIGNALS_TOPIC, end_ns=base_end_ns))),
            "mcap read naive json.loads")
        row("csv write", *_timed(write_csv), None)
        row("csv read naive csv.reader", *_timed(lambda: _naive_csv(csv_path, int(round(base_s * 1000)))), None)
        row("csv read CsvSource", *_timed(lambda: _read(lambda: CsvSource(csv_path))), "csv read naive csv.reader")
        mcap_mb = mcap_path.stat().st_size / 1e6
        csv_mb = csv_path.stat().st_size / 1e6

    rate = {r["name"]: r["samples_per_s"] for r in rows}
    for r in rows:
        r["ratio"] = r["samples_per_s"] / rate[r["baseline"]] if r["baseline"] else None
        r["x_real_time"] = r["samples_per_s"] / 1000.0
    can_res = None
    if can:
        try:
            from benchmarks import can as bench_can
        except ModuleNotFoundError as exc:
            if exc.name != "benchmarks.can":
                raise
        else:
            can_res = bench_can.run()
    return {"record_seconds": seconds, "samples": n, "baseline_seconds": base_s,
            "mcap_mb": mcap_mb, "csv_mb": csv_mb, "rows": rows, "can": can_res}


def _print(res: dict[str, Any]) -> None:
    print(f"record: {res['record_seconds']:.0f} s at 1 kHz = {res['samples']} samples "
          f"(MCAP {res['mcap_mb']:.0f} MB, CSV {res['csv_mb']:.0f} MB); "
          f"per-sample paths and baselines over the first {res['baseline_seconds']:.0f} s")
    print(f"{'path':<38} {'samples':>10} {'time s':>8} {'samples/s':>12} {'x real time':>11} {'ratio':>7}")
    for r in res["rows"]:
        ratio = f"{r['ratio']:.1f}x" if r["ratio"] else "base" if any(
            o["baseline"] == r["name"] for o in res["rows"]) else ""
        print(f"{r['name']:<38} {r['samples']:>10} {r['seconds']:>8.2f} {r['samples_per_s']:>12.0f} "
              f"{r['x_real_time']:>11.0f} {ratio:>7}")
    can_res = res["can"]
    if can_res:
        print(f"{'CAN decode + align (vectorised)':<38} {can_res['frames']:>10} frames "
              f"{can_res['vectorised_frames_per_s']:>12.0f} frames/s {can_res['ratio']:>6.1f}x")
        print(f"{'CAN per-frame cantools (baseline)':<38} {can_res['frames']:>10} frames "
              f"{can_res['cantools_frames_per_s']:>12.0f} frames/s {'base':>7}")
        for fmt, r in can_res.get("file_read_frames_per_s", {}).items():
            print(f"{'CAN log read ' + fmt:<38} {'':>10}        {r:>12.0f} frames/s")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=3600.0, help="record length in s at 1 kHz (default 3600)")
    ap.add_argument("--baseline-seconds", type=float, default=600.0,
                    help="length in s read by the slow per-sample paths and baselines (default 600)")
    ap.add_argument("--no-can", action="store_true", help="skip the CAN rows")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    res = run(args.seconds, args.baseline_seconds, can=not args.no_can)
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        _print(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
