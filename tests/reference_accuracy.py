"""Monte Carlo accuracy of the batch fit on the independent reference simulator (a measurement, not a test).

    python tests/reference_accuracy.py --seeds 50 [--noise white|coloured] [--json]

Per seed: a 12 s record of the MSP25 (truth drawn 3-20 % off Table 9, P controller
digital at the log's rate reading the noisy x, multisine demand, noise through the
loop), a five-parameter fit from x, pA, pB started 10-40 % off the truth.  Prints,
per parameter: the coverage of the nominal 95 % intervals (HAC and textbook),
the mean z, the RMSE of the relative error, and the RMSE over the mean textbook
standard error (the white-noise Cramer-Rao bound at the estimate).  Also the
paper's table: scenarios A and B on noise-free reference records.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from reference import batch, msp25_spec  # noqa: E402

from twin.estimation.fit import fit  # noqa: E402
from twin.models import get_model  # noqa: E402
from twin.paper.cases import CASES, run_case  # noqa: E402
from twin.record import Record  # noqa: E402

FREE = ("Ffric", "CdAleak", "Cd", "zeta", "wn")


def one(ref, seed):
    rng = np.random.default_rng(1000 + seed)
    start = {k: ref.truth[k] * (1 + rng.choice([-1, 1]) * rng.uniform(0.1, 0.4)) for k in FREE}
    rec = Record(ref.dt, {k: np.asarray(v, float) for k, v in ref.signals.items()}, f"ref{seed}")
    res = fit(get_model("msp25"), rec, FREE, start=start)
    return {k: {"truth": ref.truth[k], "est": res.estimate[k], "std": res.std[k], "std_white": res.std_white[k]}
            for k in FREE} | {"success": res.success}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--noise", choices=("white", "coloured"), default="white")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    noise = "default" if args.noise == "white" else {"x": 2e-6, "pA": 2e4, "pB": 2e4, "tau": 0.02}
    specs = [msp25_spec(500 + s, duration=args.duration, truth="draw", noise=noise) for s in range(args.seeds)]
    print(f"simulating {len(specs)} reference records (cached)...", file=sys.stderr, flush=True)
    refs = batch(specs, workers=2)
    rows = []
    for s, ref in enumerate(refs):
        rows.append(one(ref, s))
        print(f"  seed {s}: fitted", file=sys.stderr, flush=True)
    table = {}
    for k in FREE:
        z = np.array([(r[k]["est"] - r[k]["truth"]) / r[k]["std"] for r in rows])
        zw = np.array([(r[k]["est"] - r[k]["truth"]) / r[k]["std_white"] for r in rows])
        rel = np.array([r[k]["est"] / r[k]["truth"] - 1 for r in rows])
        crb = np.array([r[k]["std_white"] / r[k]["truth"] for r in rows])
        table[k] = {"coverage_hac_pct": float(np.mean(np.abs(z) < 1.96) * 100),
                    "coverage_textbook_pct": float(np.mean(np.abs(zw) < 1.96) * 100),
                    "mean_z": float(z.mean()), "rmse_rel_pct": float(np.sqrt(np.mean(rel ** 2)) * 100),
                    "rmse_over_crb": float(np.sqrt(np.mean(rel ** 2)) / np.mean(crb))}
    paper_ref = batch([msp25_spec(11, duration=10.0, truth="draw", noise=None)])[0]
    paper = []
    for case in CASES:
        if case.model == "msp25":
            rec = Record(paper_ref.dt, {k: np.asarray(v, float) for k, v in paper_ref.signals.items()}, "paper")
            r, _ = run_case(case, record=rec, truth=paper_ref.truth)
            paper.extend({"case": x["case"], "parameter": x["parameter"], "error_pct": x["error_pct"],
                          "paper_error_pct": x["paper_error_pct"]} for x in r)
    out = {"seeds": args.seeds, "noise": args.noise, "duration_s": args.duration,
           "converged": sum(r["success"] for r in rows), "parameters": table, "paper_on_reference": paper}
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{args.seeds} seeds, {args.duration:g} s records, {args.noise} noise through the loop; "
          f"{out['converged']} converged")
    print(f"{'param':<8} {'cover HAC':>10} {'cover txt':>10} {'mean z':>7} {'RMSE %':>8} {'RMSE/CRB':>9}")
    for k, t in table.items():
        print(f"{k:<8} {t['coverage_hac_pct']:>9.0f}% {t['coverage_textbook_pct']:>9.0f}% {t['mean_z']:>7.2f} "
              f"{t['rmse_rel_pct']:>8.3f} {t['rmse_over_crb']:>9.2f}")
    print("\npaper's scenarios on a noise-free reference record:")
    for p in paper:
        print(f"  {p['case']:<14} {p['parameter']:<8} error {p['error_pct']:.3f} %  (paper {p['paper_error_pct']} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
