"""Five-parameter fits of the user's rig on the independent reference simulator (a measurement, not a test).

    python -m tests.user_rig_accuracy --seeds 3 [--duration 12] [--diagnose] [--track-s 300] [--json]

Cases, per verification seed (1000 + i; truth drawn 3-20 % off Table 9, noise through the loop, starts 10-40 %
off the truth):

* ``single_rod``: a single-rod cylinder (AB = A / 2, V0B = 300 cm^3), P controller at KP 300 V/m (at the
  paper's 400 V/m the loop of this cylinder is unstable for 6 of 40 truth draws: the retracting stroke's flow
  gain is sqrt(2) times the paper rig's); fitted with its geometry stated (``AB``, ``V0B``); the symmetric model
  refuses the record (counted);
* ``pid_filtered``: KP 300 V/m, KI 2000 V/(m s), KD 0.6 V s/m, derivative filter 1 ms; fitted with the
  controller stated;
* ``pid_jitter``: the same rig logged with time stamps late by 0-150 us (CAN arbitration), read through the
  product's record cutting (one rule: stamps on the nominal grid);
* ``pid_tf_unstated``: the ``pid_filtered`` records fitted without the derivative filter stated (``Tf = 0``):
  what the filter is worth.

* ``can_rate``: the PID rig with its pressures logged at 500 Hz as the DBC logs them (held onto the 1 kHz grid
  of x) and time stamps 0-150 us late;
* ``chirp``, ``sweep``, ``blocks``, ``road``: the paper's rig under the test engineer's demands (a chirp of
  0.1-8 Hz and a logarithmic sweep of 0.2-15 Hz at 5 mm up to the speed limit 0.25 m/s, block loading, a
  road-load profile; :mod:`tests.reference.signals`);
* ``warming_oil``: the paper's rig whose oil warms 40 -> 60 degC over the first 12 s, ``T_oil`` logged at 10 Hz
  (held onto the grid) and read by the fit sample by sample; ``warming_oil_unlogged``: the same records fitted
  without ``T_oil`` (the bias a constant temperature leaves).

Prints per case and parameter: the largest |z| (error over the fit's standard error) and the largest relative
error over the seeds, and per case how many fits converged (``conv``) and how many passed the fit's adequacy
test (``adeq``: no "the model does not represent this record" warning).  ``--diagnose``: the healthy diagnosis of each record too (names nothing, not
"unexplained").  ``--track-s S``: healthy tracking of each tracking case for S seconds (bands centred on the
truth, as a commissioning fit gives them; alarm events counted, and the early warning's forecasts and early alarms
on the same estimates), and a worn seal and a friction rise on the CAN-rate rig, alarmed on their own parameter.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(1, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the project (tests.*)

from benchmarks import add_guard_option, apply_guard  # noqa: E402
from reference import batch, msp25_spec  # noqa: E402
from track_reference import PID, RIG_PARAMS, SINGLE_ROD  # noqa: E402

from replay.base import Samples  # noqa: E402
from fpdd.errors import DataError  # noqa: E402
from twin.estimation.fit_checked import fit  # noqa: E402
from twin.models import get_model  # noqa: E402
from twin.record import Record, records_from_samples  # noqa: E402

FREE = ("Ffric", "CdAleak", "Cd", "zeta", "wn")
#: an oil warming 40 -> 60 degC over the first 12 s (bulk modulus -12 %, leakage x1.82 at b_visc 0.03/K)
WARMING = {"kind": "ramp", "t0": 0.0, "t1": 12.0, "start": 313.15, "end": 333.15}
CASES = {
    "single_rod": ({"known": SINGLE_ROD}, SINGLE_ROD),
    "pid_filtered": ({"known": PID, "pid": {"Tf": 1e-3}}, {**PID, "Tf": 1e-3}),
    "pid_jitter": ({"known": PID, "pid": {"Tf": 1e-3}, "time_jitter_s": 150e-6}, {**PID, "Tf": 1e-3}),
    "pid_tf_unstated": ({"known": PID, "pid": {"Tf": 1e-3}}, PID),
    "can_rate": ({"known": PID, "pid": {"Tf": 1e-3}, "signal_rates": {"pA": 500.0, "pB": 500.0},
                  "time_jitter_s": 150e-6}, {**PID, "Tf": 1e-3}),
    **{k: ({"demand": {"kind": k}}, {}) for k in ("chirp", "sweep", "blocks", "road")},
    "warming_oil": ({"temperature": {"T": WARMING}, "signal_rates": {"T_oil": 10.0}}, {}),
    "warming_oil_unlogged": ({"temperature": {"T": WARMING}, "signal_rates": {"T_oil": 10.0}}, {}),
}


def product_record(ref, name: str) -> Record:
    """The record as the product reads it: through its time-stamp rule when the stamps jitter."""
    sig = {k: np.asarray(v, float) for k, v in ref.signals.items() if not (k == "T_oil" and name.startswith(
        "warming_oil_unlogged"))}
    if ref.meta.get("time_jitter_s", 0.0) > 0.0:
        (rec,) = records_from_samples(Samples(np.round(ref.t * 1e9).astype(np.int64), sig), name)
        return rec
    return Record(ref.dt, sig, name)


def one(case: str, ref, seed: int) -> dict:
    rig = get_model("msp25")
    rng = np.random.default_rng(seed)
    start = {k: ref.truth[k] * (1 + rng.choice([-1, 1]) * rng.uniform(0.1, 0.4)) for k in FREE}
    rec = product_record(ref, f"{case}{seed}")
    row: dict = {"seed": seed}
    if case == "single_rod":
        try:
            fit(rig, rec, FREE, start=start)
            row["refused_symmetric"] = False
        except DataError:
            row["refused_symmetric"] = True
    res = fit(rig, rec, FREE, base=rig.params(**CASES[case][1]), start=start)
    row["success"] = bool(res.success)
    row["adequate"] = bool(res.adequacy.get("adequate", True))  # the fit's adequacy test: no warning
    for k in FREE:
        row[k] = {"truth": ref.truth[k], "est": res.estimate[k], "std": res.std[k],
                  "z": (res.estimate[k] - ref.truth[k]) / res.std[k], "rel_pct": 100 * (res.estimate[k] / ref.truth[k] - 1)}
    return row


def diagnosed(case: str, ref, seed: int) -> dict:
    from twin.estimation.diagnose import diagnose

    rig = get_model("msp25")
    d = diagnose(rig, product_record(ref, f"{case}{seed}"), base=rig.params(**CASES[case][1]))
    return {"seed": seed, "causes": list(d.causes), "unexplained": bool(d.unexplained)}


#: healthy tracking: scenario of tests/track_reference.py -> the product's known parameters
TRACK_CASES = {"chirp": {}, "sweep": {}, "blocks": {}, "road": {}, "can_rate": {}, **RIG_PARAMS}
#: faults on the CAN-rate rig: scenario -> (parameter that must alarm, alone)
TRACK_FAULTS = {"worn_seal": "CdAleak", "friction_step": "Ffric"}


def tracked(name: str, seed: int, duration: float, fault: str | None = None) -> dict:
    """Run the tracker over one reference record: alarm events (time, parameter, level)."""
    from track_reference import scenario, to_samples

    from test_tracker_reference import NOMINAL_BANDS, _commissioned, _run
    from twin.models.base import Timing
    from twin.online.tracker import OnlineTracker

    sc = scenario(fault or name, seed, duration)
    kw = dict(sc["spec"])
    if fault:  # the fault on the CAN-rate rig: pressures at 500 Hz, time stamps 0-150 us late
        kw.update(signal_rates={"pA": 500.0, "pB": 500.0}, time_jitter_s=150e-6)
    (ref,) = batch([msp25_spec(**kw)], workers=1)
    timing = Timing.parse(sc["controller"], "cubic" if sc["controller"] == "continuous" else None)
    tr = OnlineTracker(params=TRACK_CASES.get(name) or None, timing=timing,
                       **({"start": {"Ffric": 40.0, "zeta": 0.33}} if fault else {}))
    from twin.online.forecast import ForecastMonitor

    samples = to_samples(ref)
    base = NOMINAL_BANDS if fault else _commissioned(ref)
    _, events, outs = _run(samples, tr, base)
    # the early warning on the same estimates, as the service feeds it
    fm, early, n_fc = ForecastMonitor("ref", base), [], 0
    t0 = int(samples.t_ns[0])
    for out in outs:
        ev, fcs = fm.update_block(tr.tracked, out.t_ns, (out.t_ns - t0) * 1e-9, out.estimates, out.log_std,
                                  out.frozen, out.hold, out.held_log_std)
        early += [(round(e.t_s, 3), e.parameter, e.kind) for e in ev]
        n_fc += len(fcs)
    return {"scenario": fault or name, "seed": seed, "duration_s": duration,
            "events": [(round(e.t_s, 3), e.parameter, e.level) for e in events], "early": early, "forecasts": n_fc}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--diagnose", type=int, default=0, metavar="N",
                    help="also the healthy diagnosis of the first N seeds' records of every case")
    ap.add_argument("--track-s", type=float, default=0.0,
                    help="also healthy tracking of this many seconds per tracking case, and the faults")
    ap.add_argument("--warming", action="store_true",
                    help="also 10 min of a healthy rig whose oil warms from 40 to 60 C (bulk modulus -12 %%, "
                         "leakage +15 %%; T_oil logged at 10 Hz): alarm events counted")
    ap.add_argument("--json", action="store_true")
    add_guard_option(ap)
    args = ap.parse_args(argv)
    bad = apply_guard(args.guard)
    if bad:
        print(bad, file=sys.stderr)
        return 2
    cases = [c for c in args.cases.split(",") if c]
    for c in cases:
        if c not in CASES:
            print(f"--cases: unknown case {c!r}; known: {', '.join(CASES)}", file=sys.stderr)
            return 2
    specs = [(c, 1000 + i, msp25_spec(1000 + i, duration=args.duration, truth="draw", **CASES[c][0]))
             for c in cases for i in range(args.seeds)]
    print(f"simulating {len(specs)} reference records (cached)...", file=sys.stderr, flush=True)
    refs = batch([s for _, _, s in specs], workers=2)
    rows: dict[str, list] = {c: [] for c in cases}
    for (c, seed, _), ref in zip(specs, refs):
        rows[c].append(one(c, ref, seed))
        print(f"  {c} seed {seed}: fitted", file=sys.stderr, flush=True)
    out: dict = {"seeds": args.seeds, "duration_s": args.duration, "cases": {}}
    if args.diagnose:
        out["diagnosis"] = {}
        for (c, seed, _), ref in zip(specs, refs):
            if seed >= 1000 + args.diagnose:
                continue
            out["diagnosis"].setdefault(c, []).append(diagnosed(c, ref, seed))
            print(f"  {c} seed {seed}: diagnosed", file=sys.stderr, flush=True)
    if args.track_s > 0:
        print("tracking...", file=sys.stderr, flush=True)
        out["tracking"] = [tracked(n, 1000 + i, args.track_s) for i, n in enumerate(TRACK_CASES)]
        out["faults"] = [tracked("can_rate", 1100 + i, 20.0, fault=f) for i, f in enumerate(TRACK_FAULTS)]
    if args.warming:
        out.setdefault("tracking", []).append(tracked("warming", 1200, 600.0))
    for c, rs in rows.items():
        d = {"converged": sum(r["success"] for r in rs), "adequate": sum(r["adequate"] for r in rs),
             "max_abs_z": {k: max(abs(r[k]["z"]) for r in rs) for k in FREE},
             "max_abs_rel_pct": {k: max(abs(r[k]["rel_pct"]) for r in rs) for k in FREE}, "rows": rs}
        if c == "single_rod":
            d["refused_by_symmetric_model"] = sum(r["refused_symmetric"] for r in rs)
        out["cases"][c] = d
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{args.seeds} seeds (1000...), {args.duration:g} s records; per parameter: max |z| / max |error| %")
    print(f"{'case':<14} {'conv':>4} {'adeq':>4} " + " ".join(f"{k:>16}" for k in FREE))
    for c, d in out["cases"].items():
        cells = " ".join(f"{d['max_abs_z'][k]:>6.2f} / {d['max_abs_rel_pct'][k]:>6.2f}%" for k in FREE)
        print(f"{c:<14} {d['converged']:>4} {d['adequate']:>4} {cells}")
        if "refused_by_symmetric_model" in d:
            print(f"{'':<14} the symmetric model refused {d['refused_by_symmetric_model']} of {args.seeds}")
    for c, rs in out.get("diagnosis", {}).items():
        named = sum(bool(r["causes"]) for r in rs)
        unexp = sum(r["unexplained"] for r in rs)
        print(f"diagnosis {c:<14} named something: {named} of {len(rs)}; unexplained: {unexp} of {len(rs)}")
    for r in out.get("tracking", []):
        print(f"tracking {r['scenario']:<10} {r['duration_s']:g} s: {len(r['events'])} alarm event(s) {r['events']}; "
              f"{r['forecasts']} forecasts, early alarm events {r['early']}")
    for r, (f, p) in zip(out.get("faults", []), TRACK_FAULTS.items()):
        ok = bool(r["events"]) and {e[1] for e in r["events"]} == {p}
        print(f"fault {f:<14} on the CAN-rate rig: {'alarmed on ' + p + ' alone' if ok else 'NOT as expected'} "
              f"{r['events'][:4]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
