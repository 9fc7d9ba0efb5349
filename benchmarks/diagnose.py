"""Benchmark of ``twin diagnose`` (``python -m benchmarks.diagnose [--json]``; also run by ``python -m benchmarks``).

The whole diagnosis - nominal fit, noise model, catalogue screen, timing test, fits of the promising
extensions, greedy re-test, held-out scoring - of 20 s, 1 kHz MSP25 records (x, pA, pB) against the full
catalogue, on the product's own simulation (a hidden viscous friction, noise added after the loop) and,
when the repository's tests are present, on records of the independent reference simulator
(``tests/reference``: a controller reading the noisy measured displacement; healthy, a hidden viscous
friction, an analog controller).  Target (issue): one effect found in <= 20 s on 2 cores.  The baseline,
measured in the same run on the same record, is one nominal fit (``twin fit`` of the five
phenomenological parameters, 8 starts); the ratio says what the diagnosis costs on top of a fit.  The
numba kernels are compiled (and cached) by a warm-up before the clock starts.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

from twin.estimation.diagnose import diagnose
from twin.estimation.fit import fit
from twin.models import get_model
from twin.models.simulate import default_noise, excite, measure

TARGET_S = 20.0


def _product_record(effects, duration_s: float, seed: int):
    rig = get_model("msp25")
    name, xr = excite(rig, duration_s, 1e-3, seed=seed)
    return measure(rig, rig.params(effects=effects), name, xr, 1e-3, noise=default_noise(rig), seed=seed)


def _reference_records(duration_s: float):
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    tests = os.path.join(root, "tests")
    if not os.path.isfile(os.path.join(tests, "diag_reference.py")):
        return []
    sys.path.insert(0, tests)
    try:
        from diag_reference import reference_record
    except ImportError:
        return []
    out = []
    for label, effects, ctrl, expect in (("reference, healthy", (), "digital", []),
                                         ("reference, one effect", ("viscous_friction",), "digital",
                                          ["viscous_friction"]),
                                         ("reference, analog controller", (), "analog", ["controller_rate"])):
        rec, _ = reference_record(effects, seed=11, duration=duration_s, controller=ctrl)
        out.append((label, rec, expect))
    return out


def run(duration_s: float = 20.0, quick: bool = False) -> dict:
    """Time the diagnosis of ``duration_s`` records; returns rows with seconds, baseline and findings."""
    rig = get_model("msp25")
    diagnose("msp25", _product_record(("viscous_friction",), 2.0, 0))  # compile / load the kernels
    cases = [("product, one effect", _product_record(("viscous_friction",), duration_s, 12), ["viscous_friction"])]
    if not quick:
        cases += _reference_records(duration_s)
    rows: list[dict[str, Any]] = []
    for label, rec, expect in cases:
        t0 = time.perf_counter()
        fit(rig, rec.slice(0, int(0.75 * len(rec))), rig.PHENOMENOLOGICAL, n_starts=8, spread=1.5, max_nfev=80)
        base_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        d = diagnose("msp25", rec)
        elapsed = time.perf_counter() - t0
        rows.append({"case": label, "expected": expect, "causes": d.causes, "unexplained": d.unexplained,
                     "seconds": elapsed, "baseline_fit_s": base_s, "ratio_to_fit": elapsed / base_s,
                     "target_s": TARGET_S, "within_target": elapsed <= TARGET_S,
                     "correct": d.causes == expect and not d.unexplained})
    return {"name": "diagnose", "record_s": duration_s, "rate_hz": 1000.0, "cores": os.cpu_count(),
            "catalogue": len(rig.EFFECTS), "rows": rows,
            "max_seconds": max(r["seconds"] for r in rows), "target_s": TARGET_S}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=20.0, help="record length in s (default 20)")
    ap.add_argument("--quick", action="store_true", help="only the product's one-effect record")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    out = run(args.duration, args.quick)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"twin diagnose, {out['record_s']:g} s at 1 kHz, {out['catalogue']} effects + timing, "
          f"{out['cores']} cores:")
    for r in out["rows"]:
        print(f"  {r['case']:<30} found {'+'.join(r['causes']) or 'nothing':<20}"
              f"{' (unexplained)' if r['unexplained'] else '':<14} {r['seconds']:6.1f} s "
              f"({'within' if r['within_target'] else 'OVER'} {r['target_s']:g} s); nominal fit alone "
              f"{r['baseline_fit_s']:.1f} s, ratio {r['ratio_to_fit']:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
