"""Commissioning on a window that starts mid-motion (``python -m benchmarks.commission_start``).

A service started on a rig that is already running gathers its commissioning window from wherever the rig is.
For each seed of the independent reference simulator (``tests/reference``; truth drawn 20 % around Table 9,
default multisine demand, noise through the loop), a window of ``--window`` seconds is cut at each start of
``--starts`` and fitted as the service fits it (:func:`twin.online.commission.fit_window`), with the window's
first ``BURN_S`` counted and not. Printed: per start and burn-in, how many windows were refused and, of the
accepted fits, how many parameters lie more than 3 standard errors from their truth (rms of the z-scores).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from benchmarks.campaign_draw import reference

TRACKED = ("Ffric", "CdAleak", "Cd", "zeta", "wn")


def _spec(seed: int, duration: float) -> dict:
    return reference().msp25_spec(seed, duration=duration, truth="draw")


def _one(job: tuple[int, float, float, float, float]) -> dict:
    seed, start, burn, window, duration = job
    from replay.base import Samples
    from twin.online.commission import fit_window

    (rec,) = reference().batch([_spec(seed, duration)], workers=1)
    i0 = int(round(start / rec.dt))
    i1 = i0 + int(round(window / rec.dt))
    t_ns = np.round(rec.t[i0:i1] * 1e9).astype(np.int64)
    doc, why = fit_window(Samples(t_ns, {k: np.asarray(v, float)[i0:i1] for k, v in rec.signals.items()}),
                          TRACKED, burn_s=burn)
    z = None if doc is None else {k: (doc["params"][k]["value"] - rec.truth[k]) / doc["params"][k]["std"]
                                  for k in TRACKED}
    return {"seed": seed, "start": start, "burn": burn, "z": z, "refused": why}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.commission_start", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0-19", help="seed range A-B of the reference simulator (default 0-19)")
    ap.add_argument("--starts", default="0,3.37,7.61", help="window starts [s], comma-separated")
    ap.add_argument("--window", type=float, default=12.0, help="window length [s] (default 12)")
    ap.add_argument("--duration", type=float, default=30.0, help="record length [s] (default 30)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true", help="one JSON object per fit instead of the table")
    args = ap.parse_args(argv)
    from twin.online.commission import BURN_S

    lo, hi = (int(v) for v in args.seeds.split("-"))
    starts = [float(s) for s in args.starts.split(",")]
    duration = max(args.duration, max(starts) + args.window)
    seeds = list(range(lo, hi + 1))
    reference().batch([_spec(s, duration) for s in seeds], workers=args.workers)  # cached for the workers
    jobs = [(s, st, b, args.window, duration) for s in seeds for st in starts for b in (0.0, BURN_S)]
    with ProcessPoolExecutor(args.workers) as ex:
        rows = []
        for i, r in enumerate(ex.map(_one, jobs), 1):
            rows.append(r)
            if args.json:
                print(json.dumps(r), flush=True)
            else:
                print(f"\r{i}/{len(jobs)} fits", end="", file=sys.stderr, flush=True)
    if args.json:
        return 0
    print(file=sys.stderr)
    print(f"{'start s':>8} {'burn s':>6} {'refused':>8}  " + "  ".join(f"{k:>14}" for k in TRACKED))
    for st in starts:
        for b in (0.0, BURN_S):
            rr = [r for r in rows if r["start"] == st and r["burn"] == b]
            ok = [r["z"] for r in rr if r["z"] is not None]
            cells = []
            for k in TRACKED:
                z = np.array([o[k] for o in ok])
                off = int(np.sum(np.abs(z) > 3))
                rms = math.sqrt(float(np.mean(np.clip(z, -50, 50) ** 2))) if z.size else math.nan
                cells.append(f"{off:>3}/{z.size:<3} rms {rms:4.2f}")
            print(f"{st:8.2f} {b:6.2f} {len(rr) - len(ok):>3}/{len(rr):<4}  " + "  ".join(cells))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
