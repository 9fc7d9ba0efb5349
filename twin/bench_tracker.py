"""Tracker speed, side by side in one run (``python -m twin.bench_tracker [--json]``).

The 11-state filter (6 model states + 5 parameters), 1 kHz data, x, pA, pB
measured:

* ours: the compiled UKF (:mod:`twin.ukf`), microseconds per sample and
  real-time factor on one core;
* stock: filterpy's ``UnscentedKalmanFilter`` with a per-sigma-point ``fx``
  written in plain numpy (the same equations, RK4 with the same substeps), on
  fewer samples; the ratio of the two and the largest difference of their
  parameter estimates over the samples both ran;
* fleet: how many 1 kHz rigs this machine tracks in real time, measured by
  filtering rigs in one worker process per core at once (spawned processes)
  and dividing the aggregate samples per second by 1000.

Targets (issue 4): <= 25 us per sample (>= 40x real time), >= 500x the stock
filter, >= 50 rigs on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time

import numpy as np


def _record(duration_s: float, seed: int = 0):
    from twin.models import msp25 as M
    from twin.simulate import default_noise, excite, measure

    name, xr = excite(M.MODEL, duration_s, 1e-3, seed=seed)
    return measure(M.MODEL, M.MODEL.params(), name, xr, 1e-3, noise=default_noise(M.MODEL), seed=seed)


def _stock_filter(tr, rec, n_samples: int):
    """filterpy's UKF with a plain-numpy fx per sigma point; returns (seconds per sample, estimates)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    from twin.bench import _numpy_step

    n = tr.n
    scale = tr.scale
    base = tr.pvec.copy()

    def fx(x, dt, u):
        p = base.copy()
        p[tr.idx] = tr.ref * np.exp(x[6:])
        s = _numpy_step((x[:6] * scale)[None, :], np.array([u]), p[None, :], dt, tr.substeps)[0]
        return np.concatenate([s / scale, x[6:]])

    pts = MerweScaledSigmaPoints(n, alpha=tr.alpha, beta=tr.beta, kappa=tr.kappa)
    f = UnscentedKalmanFilter(dim_x=n, dim_z=3, dt=1e-3, hx=lambda x: x[tr.meas_idx], fx=fx, points=pts)
    f.x = tr.x.copy()
    f.P = tr.P.copy()
    f.Q = tr._q(1e-3)
    f.R = np.diag(tr.R)
    Z = np.stack([rec["x"] / 1e-3, rec["pA"] / 1e6, rec["pB"] / 1e6], axis=1)
    est = np.empty((n_samples, len(tr.tracked)))
    f.sigmas_f = pts.sigma_points(f.x, f.P)
    t0 = time.perf_counter()
    for k in range(n_samples):
        if k > 0:
            f.predict(u=rec["u"][k - 1])
        f.update(Z[k])
        est[k] = tr.ref * np.exp(f.x[6:])
    return (time.perf_counter() - t0) / n_samples, est


def _worker(args):
    duration_s, rigs, seed = args
    from twin.tracker import OnlineTracker

    rec = _record(duration_s, seed)
    s = rec.to_samples()
    OnlineTracker(excite=(0.0, 0.0, 0.0)).process(s.slice(0, 50))  # compile/load outside the clock
    t0 = time.perf_counter()
    for _ in range(rigs):
        OnlineTracker().process(s)
    return rigs * len(s), time.perf_counter() - t0


def run(quick: bool = False) -> dict:
    from twin.tracker import OnlineTracker

    duration = 10.0 if quick else 20.0
    rec = _record(duration)
    s = rec.to_samples()
    tr = OnlineTracker(excite=(0.0, 0.0, 0.0), gate_p=1e-300)
    tr.process(s.slice(0, 20))  # compile
    tr = OnlineTracker(excite=(0.0, 0.0, 0.0), gate_p=1e-300)
    t0 = time.perf_counter()
    out = tr.process(s)
    ours = (time.perf_counter() - t0) / len(s)
    n_stock = 100 if quick else 300
    fresh = OnlineTracker(excite=(0.0, 0.0, 0.0), gate_p=1e-300)
    stock, est_stock = _stock_filter(fresh, rec, n_stock)
    diff = float(np.max(np.abs(est_stock / out.estimates[:n_stock] - 1.0)))
    # fleet: one worker per core, each filtering rigs back to back
    cores = os.cpu_count() or 1
    rigs_each = 2 if quick else 4
    ctx = mp.get_context("spawn")
    with ctx.Pool(cores) as pool:
        res = pool.map(_worker, [(duration, rigs_each, 10 + i) for i in range(cores)])
    samples = sum(r[0] for r in res)
    wall = max(r[1] for r in res)
    rigs_rt = samples / wall / 1000.0
    return {
        "ours_us_per_sample": ours * 1e6, "ours_realtime_factor": 1e-3 / ours,
        "stock_us_per_sample": stock * 1e6, "stock_realtime_factor": 1e-3 / stock,
        "speedup_vs_stock": stock / ours, "max_rel_estimate_difference": diff, "stock_samples": n_stock,
        "fleet_cores": cores, "fleet_rigs_realtime_1kHz": rigs_rt,
        "targets": {"us_per_sample<=25": ours * 1e6 <= 25.0, "speedup>=500": stock / ours >= 500,
                    "rigs>=50": rigs_rt >= 50},
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m twin.bench_tracker", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter records")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    r = run(args.quick)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(f"ours : {r['ours_us_per_sample']:8.1f} us/sample  {r['ours_realtime_factor']:8.1f}x real time")
    print(f"stock: {r['stock_us_per_sample']:8.1f} us/sample  {r['stock_realtime_factor']:8.3f}x real time "
          f"(filterpy UKF, numpy fx per sigma point, {r['stock_samples']} samples)")
    print(f"ratio: {r['speedup_vs_stock']:.0f}x; largest relative difference of the estimates: "
          f"{r['max_rel_estimate_difference']:.2e}")
    print(f"fleet: {r['fleet_rigs_realtime_1kHz']:.0f} rigs at 1 kHz in real time on {r['fleet_cores']} cores")
    print("targets:", ", ".join(f"{k} {'OK' if v else 'MISSED'}" for k, v in r["targets"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
