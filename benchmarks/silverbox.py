"""The Silverbox benchmark measured (``python -m benchmarks.silverbox [--samples N] [--scale S] [--json]``).

Reads the published ``SNLS80mV.csv.gz`` where the data set is kept (``FPDD_REALDATA``, default
``../shared/realdata`` beside the project; never copied into it), diagnoses the oscillator on the first
``--samples`` samples of the official estimation part (multisine, samples 40 650-127 400, its first 75 %)
with mass, damping and stiffness free from the default starts, and prints the simulation error (RMS, mV) of
the nominal (linear) and the extended model on the official test splits: the multisine test (the last 25 %
of the multisine part) and the arrow (samples 100-40 575; its first 32 000 stay within the estimation
part's amplitude).  Each test split is simulated from the start of its own part (the multisine part, or the
record's start for the arrow) and scored on the split.  ``--scale`` multiplies both voltages (the verdict
must not change).
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from twin.estimation.diagnose import diagnose
from twin.estimation.fit import initial_from_data
from twin.models import get_model
from twin.record import Record

DT = 2.0 ** 14 / 1e7
MULTISINE = (40650, 127400)
ARROW = (100, 40575)
NO_EXTRAPOLATION = 32000


def read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with gzip.open(path, "rt") as f:
        f.readline()
        a = np.loadtxt(f, delimiter=",", usecols=(0, 1))
    return a[:, 0], a[:, 1]


def rms_mv(model, state, u, y, score: slice, scale: float) -> float:
    rec = Record(DT, {"u": u, "y": y})
    P = model.vector(state.params)[None, :]
    S0 = model.initial_state(P, initial_from_data(model, rec, state.params))
    sim = model.simulate_batch(P, "u", u, DT, S0, None, state.timing)
    e = (sim.outputs["y"][0] - y)[score]
    return 1e3 * float(np.sqrt(np.mean(e * e))) / scale


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], prog="python -m benchmarks.silverbox")
    ap.add_argument("--samples", type=int, default=8192, help="estimation samples the diagnosis sees (default 8192; "
                    "0: all 65 062)")
    ap.add_argument("--scale", type=float, default=1.0, help="multiply both voltages by this factor")
    ap.add_argument("--json", action="store_true", help="machine output (SI: volts as V, time in s)")
    args = ap.parse_args(argv)
    root = Path(os.environ.get("FPDD_REALDATA", Path(__file__).resolve().parents[1].parent / "shared" / "realdata"))
    path = root / "silverbox" / "SNLS80mV.csv.gz"
    if not path.is_file():
        print(f"{path}: not found; set FPDD_REALDATA to the folder holding silverbox/SNLS80mV.csv.gz", file=sys.stderr)
        return 2
    u, y = read(path)
    u, y = args.scale * u, args.scale * y
    a, b = MULTISINE
    mu, my = u[a:b], y[a:b]
    n_est = int(len(mu) * 0.75)
    n = args.samples or n_est
    model = get_model("oscillator")
    t0, c0 = time.perf_counter(), time.process_time()
    d = diagnose(model, Record(DT, {"u": mu[:n], "y": my[:n]}, "silverbox"), free=("m", "d", "k"), seed=1000)
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    rows = {}
    for label, st in (("linear", d.nominal), ("extended", d.final)):
        rows[label] = {
            "multisine_test_rms_V": rms_mv(model, st, mu, my, slice(n_est, None), args.scale) * 1e-3,
            "arrow_full_rms_V": rms_mv(model, st, u[: ARROW[1]], y[: ARROW[1]], slice(ARROW[0], None),
                                       args.scale) * 1e-3,
            "arrow_no_extrapolation_rms_V": rms_mv(model, st, u[: ARROW[0] + NO_EXTRAPOLATION],
                                                   y[: ARROW[0] + NO_EXTRAPOLATION], slice(ARROW[0], None),
                                                   args.scale) * 1e-3,
        }
    out = {"samples": n, "scale": args.scale, "verdict": d.verdict(), "causes": d.causes,
           "effects": {c: {k: v["value"] for k, v in d.effect_params(c).items()} for c in d.causes},
           "nominal": {k: d.nominal.params[k] for k in ("m", "d", "k")}, "rms": rows, "time_s": elapsed,
           "cpu_time_s": cpu, "load_average_1min": load}
    if args.json:
        print(json.dumps(out, indent=1, default=str))
        return 0
    print(f"diagnosis on {n} samples x{args.scale:g}: {d.verdict()}, causes {', '.join(d.causes) or 'none'} "
          f"({elapsed:.1f} s on the clock, {cpu:.1f} s of processor time, load average {load:.2f})")
    for c, v in out["effects"].items():
        print(f"  {c}: " + ", ".join(f"{k}={x:.6g}" for k, x in v.items()))
    print(f"{'RMS [mV], original units':<28} {'multisine test':>15} {'arrow (full)':>13} {'arrow (no extrap.)':>19}")
    for label, r in rows.items():
        print(f"{label:<28} {1e3 * r['multisine_test_rms_V']:15.3f} {1e3 * r['arrow_full_rms_V']:13.3f} "
              f"{1e3 * r['arrow_no_extrapolation_rms_V']:19.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
