"""Command line: write one reference record to CSV (``python -m tests.reference --help``)."""

from __future__ import annotations

import argparse
import json
import sys
import time

from .cache import get_record
from .msp25 import CONTROLLERS, msp25_spec
from .oscillator import oscillator_spec
from .tables import MSP25_EFFECTS, OSC_EFFECTS


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.reference",
                                 description="Simulate one record of the independent reference simulator "
                                             "and write it as CSV (t,x_ref,u,x,pA,pB or t,u,y; SI).")
    ap.add_argument("output", help="CSV file to write")
    ap.add_argument("--model", choices=("msp25", "oscillator"), default="msp25")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=20.0, help="seconds (default 20)")
    ap.add_argument("--log-rate", type=float, default=1000.0, help="log rate [Hz] (default 1000)")
    ap.add_argument("--controller", choices=CONTROLLERS[:2], default="digital", help="msp25 only")
    ap.add_argument("--rate", type=float, default=None, help="digital controller rate [Hz] (default: log rate)")
    ap.add_argument("--intersample", choices=("analytic", "zoh", "foh", "cubic"), default=None,
                    help="demand (msp25) or force (oscillator) between samples (default analytic)")
    ap.add_argument("--amplitude", type=float, default=None, help="multisine peak (m for msp25, N for oscillator)")
    ap.add_argument("--Fext", type=float, default=0.0, help="constant external force [N] (msp25)")
    ap.add_argument("--effects", default="", help="comma-separated effect names; sizes drawn from the seed. "
                    f"msp25: {', '.join(MSP25_EFFECTS)}; oscillator: {', '.join(OSC_EFFECTS)}")
    ap.add_argument("--draw-truth", action="store_true", help="free parameters drawn off the defaults")
    ap.add_argument("--no-noise", action="store_true")
    ap.add_argument("--no-cache", action="store_true", help="simulate even if cached; do not store")
    args = ap.parse_args(argv)
    effects = [e for e in args.effects.split(",") if e]
    truth = "draw" if args.draw_truth else None
    noise = None if args.no_noise else "default"
    if args.model == "msp25":
        demand = {} if args.amplitude is None else {"amplitude": args.amplitude}
        spec = msp25_spec(args.seed, duration=args.duration, log_rate_hz=args.log_rate, controller=args.controller,
                          rate_hz=args.rate, intersample=args.intersample, demand=demand, Fext=args.Fext,
                          effects=effects, truth=truth, noise=noise)
    else:
        force = {} if args.amplitude is None else {"amplitude": args.amplitude}
        spec = oscillator_spec(args.seed, duration=args.duration, log_rate_hz=args.log_rate,
                               intersample=args.intersample or "analytic", force=force, effects=effects,
                               truth=truth, noise=noise)
    t0 = time.perf_counter()
    rec = get_record(spec, cache=not args.no_cache)
    wall = time.perf_counter() - t0
    rec.to_csv(args.output)
    info = {"output": args.output, "samples": int(rec.t.size), "wall_s": round(wall, 3),
            "simulation_s": round(rec.meta["elapsed_s"], 3), "truth": rec.truth}
    json.dump(info, sys.stdout, indent=1, default=str)
    sys.stdout.write("\n")
    return 0
