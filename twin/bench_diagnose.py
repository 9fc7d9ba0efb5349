"""Benchmark of ``twin diagnose`` (``python -m twin.bench_diagnose [--json]``; also run by ``twin.bench``).

The whole diagnosis - nominal fit, catalogue screen, fits of the promising
extensions, greedy re-test, held-out scoring - of a 20 s, 1 kHz MSP25 record
(x, pA, pB with noise x: 2 um, pressures: 20 kPa) against the full catalogue
of ten effects, in three situations: a healthy rig, one hidden effect, and two
hidden effects that are only recognisable together (a Stribeck friction and a
displacement sensor delay).  Target (issue 5): <= 60 s each on 2 cores.  The
numba kernels are compiled (and cached) by a warm-up diagnosis of a short
record before the clock starts.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from twin.diagnose import diagnose
from twin.models import get_model
from twin.simulate import default_noise, excite, measure

TARGET_S = 60.0
CASES = (("healthy", ()), ("one effect", ("viscous_friction",)),
         ("two effects", ("stribeck_friction", "sensor_delay")))


def _record(effects, duration_s: float, seed: int):
    rig = get_model("msp25")
    name, xr = excite(rig, duration_s, 1e-3, seed=seed)
    return measure(rig, rig.params(effects=effects), name, xr, 1e-3, noise=default_noise(rig), seed=seed)


def run(duration_s: float = 20.0, quick: bool = False) -> dict:
    """Time the diagnosis of ``duration_s`` rig records; returns rows with seconds and findings.

    ``quick`` times only the two-effect case (the slowest).
    """
    diagnose("msp25", _record(("viscous_friction",), 2.0, 0))  # compile / load the kernels
    rows = []
    for i, (label, effects) in enumerate(CASES):
        if quick and len(effects) < 2:
            continue
        rec = _record(effects, duration_s, 11 + i)
        t0 = time.perf_counter()
        d = diagnose("msp25", rec)
        elapsed = time.perf_counter() - t0
        rows.append({"case": label, "hidden": list(effects), "causes": d.causes, "unexplained": d.unexplained,
                     "seconds": elapsed, "target_s": TARGET_S, "within_target": elapsed <= TARGET_S,
                     "correct": sorted(d.causes) == sorted(effects) and not d.unexplained})
    return {"name": "diagnose", "record_s": duration_s, "rate_hz": 1000.0, "cores": os.cpu_count(),
            "catalogue": len(get_model("msp25").EFFECTS), "rows": rows,
            "max_seconds": max(r["seconds"] for r in rows), "target_s": TARGET_S}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=20.0, help="record length in s (default 20)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    out = run(args.duration)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"twin diagnose, {out['record_s']:g} s at 1 kHz, {out['catalogue']} effects, {out['cores']} cores:")
    for r in out["rows"]:
        print(f"  {r['case']:<12} hidden {'+'.join(r['hidden']) or 'none':<32} found "
              f"{'+'.join(r['causes']) or 'none':<32} {r['seconds']:6.1f} s "
              f"({'within' if r['within_target'] else 'OVER'} {r['target_s']:g} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
