"""Hunting the strong-chirp divergence on the reference simulator (a measurement, not a test).

    python -m tests.chirp_divergence [--seeds 3] [--duration 120] [--variants chirp,saturated,...] [--json]

A healthy rig under a chirp of 0.1-8 Hz at its speed limit, on the analog controller (the product's
``--controller continuous --intersample cubic``), tracked with bands centred on the truth as a commissioning fit
gives them; per record: alarm events, the largest excursion of each tracked parameter from its truth (ratio, after
the 2 s the drift test settles), and
the share of samples on which the consistency guard held the drift test.  Variants (verification seeds 1000...):

* ``chirp``: the reference's chirp (5 mm, 0.1-8 Hz, speed limit 0.25 m/s), truth drawn 3-20 % off Table 9;
* ``fast``: the same to 0.5 m/s (no speed limit below 8 Hz: 5 mm at 8 Hz is 0.25 m/s, so 10 mm);
* ``saturated``: 20 mm to 1 m/s, beyond what the valve delivers (the spool and the flow saturate);
* ``spool_saturation``: the reference chirp on a rig with the catalogue's spool saturation (a stroke limit);
* ``wide_truth``: the reference chirp, truth drawn 20-40 % off Table 9;
* ``noisy``: the reference chirp at 3x the sensor noise (through the loop);
* ``friction_step``: 30 s of the chirp at Table 9, friction 60 -> 150 N at 12 s (an alarm before 12 s is the
  reported failure; bands: the defaults).

``--product``: the same chirp on the product's own simulator (``twin simulate --excitation chirp``: 0.1-8 Hz at a
fixed amplitude, so 5 mm reaches 0.25 m/s at 8 Hz), the rig's values away from Table 9 (:data:`PRODUCT_RIG`),
digital and analog controller, the tracker's RK4 at 2 and 4 substeps: alarm events and the estimates over time.
``--unmodelled``: 20 s of rigs out of the tracker's model (seed 1020: a 60 Hz load-train resonance; 1021: the
position sensor 3 ms late, 2 ms pressure transducers), the noise learnt online and kept at its commissioned level.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(1, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks import add_guard_option, apply_guard  # noqa: E402
from reference import batch, msp25_spec  # noqa: E402

CHIRP = {"kind": "chirp"}
SETTLE_S = 2.0  # the drift test's settling time: excursions are counted after it
VARIANTS: dict[str, dict] = {
    "chirp": {"demand": CHIRP, "truth": "draw"},
    "fast": {"demand": {"kind": "chirp", "amplitude": 10e-3, "v_max": 0.5}, "truth": "draw"},
    "saturated": {"demand": {"kind": "chirp", "amplitude": 20e-3, "v_max": 1.0}, "truth": "draw"},
    "spool_saturation": {"demand": CHIRP, "truth": "draw", "effects": ["spool_saturation"]},
    "wide_truth": {"demand": CHIRP, "truth": "draw", "spread": 0.4},
    "noisy": {"demand": CHIRP, "truth": "draw", "noise": {"x": 6e-6, "pA": 6e4, "pB": 6e4}},
    "friction_step": {"demand": CHIRP, "truth": {"Ffric": 60.0},
                      "time_varying": {"Ffric": {"kind": "step", "t0": 12.0, "before": 60.0, "after": 150.0}}},
}


def run(name: str, seed: int, duration: float) -> dict:
    from track_reference import to_samples

    from test_tracker_reference import NOMINAL_BANDS, _commissioned, _run
    from twin.models.base import Timing
    from twin.online.tracker import OnlineTracker

    kw = dict(VARIANTS[name])
    if name == "friction_step":
        duration = 30.0
    spec = msp25_spec(seed, duration=duration, controller="analog", **kw)
    (ref,) = batch([spec], workers=1)
    tr = OnlineTracker(timing=Timing.parse("continuous", "cubic"))
    bands = NOMINAL_BANDS if name == "friction_step" else _commissioned(ref)
    _, events, outs = _run(to_samples(ref), tr, bands)
    est = np.concatenate([o.estimates for o in outs])
    hold = np.concatenate([o.hold for o in outs])
    status = {}
    for o in outs:
        if o.guard is not None:
            u, c = np.unique(o.guard, return_counts=True)
            for k, v in zip(u, c):
                status[str(k)] = status.get(str(k), 0) + int(v)
    worst = {}
    late = np.arange(est.shape[0]) * ref.dt > SETTLE_S
    for j, p in enumerate(tr.tracked):
        truth = np.asarray(ref.hidden[p], float)[late] if p in ref.hidden else float(ref.truth[p])
        r = est[late, j] / truth
        worst[p] = float(r.max() if r.max() > 1 / r.min() else r.min())
    v = np.diff(np.asarray(ref.signals["x"], float)) / ref.dt
    return {"variant": name, "seed": seed, "duration_s": duration, "peak_speed_m_s": float(np.max(np.abs(v))),
            "events": [(round(e.t_s, 3), e.parameter, e.level) for e in events],
            "worst_ratio": worst, "held_share": float(hold.mean()), "guard": status}


#: the product's own chirp (``twin simulate --excitation chirp --amplitude 5mm --f-lo 0.1 --f-hi 8 --duration 60
#: --set wn=250rad/s,zeta=0.4,Ffric=55N,CdAleak=4mm^2,Cd=0.2``): the rig's parameters away from Table 9
PRODUCT_RIG = {"wn": 250.0, "zeta": 0.4, "Ffric": 55.0, "CdAleak": 4e-6, "Cd": 0.2}


def product(controller: str, amplitude: float = 5e-3, duration: float = 60.0, substeps: int = 2,
            seed: int = 1004) -> dict:
    """The chirp on the product's own simulator (the tracker's own model: no mismatch but the integration),
    tracked as ``twin track --controller ...`` with the rig's values stated and default-width bands around them."""
    from test_tracker_reference import NOMINAL_BANDS, _run
    from twin.models import get_model
    from twin.models.base import Timing
    from twin.models.simulate import default_noise, excite, measure
    from twin.online.baseline import Baseline
    from twin.online.tracker import OnlineTracker

    rig = get_model("msp25")
    ps = rig.params(**PRODUCT_RIG)
    name, xr = excite(rig, duration, 1e-3, "chirp", amplitude, 0, 0.1, 8.0)
    timing = Timing.parse(controller, "cubic" if controller == "continuous" else None)
    rec = measure(rig, ps, name, xr, 1e-3, noise=default_noise(rig), seed=seed, timing=timing)
    tr = OnlineTracker(params=PRODUCT_RIG, timing=timing, substeps=substeps)
    bands = {n: Baseline(ps[n], ps[n] * b.lo / b.value, ps[n] * b.hi / b.value) for n, b in NOMINAL_BANDS.items()}
    _, events, outs = _run(rec.to_samples(), tr, bands)
    est = np.concatenate([o.estimates for o in outs])
    guard = np.concatenate([o.guard for o in outs])
    at = [t for t in (4, 10, 22, 30, 40, 59) if t < duration]
    return {"variant": f"product {controller} {amplitude * 1e3:g} mm substeps {substeps}", "seed": seed,
            "events": [(round(e.t_s, 3), e.parameter, e.level) for e in events],
            "ratio_at_s": {t: {n: round(float(est[int(t / 1e-3), j] / ps[n]), 2) for j, n in enumerate(tr.tracked)}
                           for t in at},
            "guard_at_s": {t: str(guard[int(t / 1e-3)]) for t in at}}


#: rigs the tracker's model cannot represent (``--unmodelled``): seed -> effects (sizes explicit)
UNMODELLED = {1020: {"mechanical_resonance": {"f": 60.0, "m2": 30.0, "zeta2": 0.02}},
              1021: {"sensor_delay": {"delay": 3e-3}, "pressure_sensor_lag": {"tau": 2e-3}}}


def unmodelled(seed: int, adapt: bool) -> dict:
    """20 s of a healthy drawn rig with effects out of the tracker's model (:data:`UNMODELLED`), tracked with the
    noise learnt online (``adapt``) or kept at its commissioned level: alarm events, the share of samples the
    guard held after 2 s, the learnt noise (x nominal, AR(1)) and the final estimates over the truth."""
    from track_reference import to_samples

    from test_tracker_reference import _commissioned, _run
    from twin.online.tracker import OnlineTracker

    (ref,) = batch([msp25_spec(seed, duration=20.0, truth="draw", effects=UNMODELLED[seed])], workers=1)
    tr = OnlineTracker(guard={"adapt": 1.0 if adapt else 0.0})
    _, events, outs = _run(to_samples(ref), tr, _commissioned(ref))
    guard = np.concatenate([o.guard for o in outs])
    late = np.arange(guard.size) * ref.dt > SETTLE_S
    est = outs[-1].estimates[-1]
    return {"variant": f"unmodelled {'+'.join(UNMODELLED[seed])}, noise {'learnt' if adapt else 'kept'}",
            "seed": seed, "events": [(round(e.t_s, 3), e.parameter, e.level) for e in events],
            "held_share": float((guard[late] != "consistent").mean()),
            "noise": {o: (round(v["std"] / v["nominal"], 2), round(v["ar1"], 2)) for o, v in tr.noise_levels().items()},
            "final_ratio": {n: round(float(est[j] / ref.truth[n]), 3) for j, n in enumerate(tr.tracked)}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first", type=int, default=1000)
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--product", action="store_true",
                    help="the product's own chirp instead (digital and analog controller, 5 and 20 mm; tracker "
                         "substeps 2 and 4)")
    ap.add_argument("--json", action="store_true")
    add_guard_option(ap)
    ap.add_argument("--unmodelled", action="store_true",
                    help="rigs out of the tracker's model instead (a load-train resonance; late sensors), the noise "
                         "learnt and kept")
    args = ap.parse_args(argv)
    bad = apply_guard(args.guard)
    if bad:
        print(bad, file=sys.stderr)
        return 2
    rows = []
    if args.unmodelled:
        for seed in UNMODELLED:
            for adapt in (True, False):
                r = unmodelled(seed, adapt)
                rows.append(r)
                if not args.json:
                    print(f"{r['variant']} seed {seed}: {len(r['events'])} alarm event(s) {r['events'][:4]}; held "
                          f"{100 * r['held_share']:.1f} %; noise {r['noise']}; final {r['final_ratio']}", flush=True)
        if args.json:
            print(json.dumps(rows, indent=2))
        return 0
    if args.product:
        for ctrl, amp, sub in (("digital", 5e-3, 2), ("digital", 5e-3, 4), ("continuous", 5e-3, 2),
                               ("continuous", 20e-3, 2)):
            r = product(ctrl, amp, args.duration, sub)
            rows.append(r)
            if not args.json:
                print(f"{r['variant']}: {len(r['events'])} alarm event(s) {r['events'][:4]}", flush=True)
                for t, v in r["ratio_at_s"].items():
                    print(f"   {t:>3} s estimate/truth " + " ".join(f"{k} {x:.2f}" for k, x in v.items())
                          + f"  {r['guard_at_s'][t]}", flush=True)
        if args.json:
            print(json.dumps(rows, indent=2))
        return 0
    for name in [v for v in args.variants.split(",") if v]:
        if name not in VARIANTS:
            print(f"--variants: unknown {name!r}; known: {', '.join(VARIANTS)}", file=sys.stderr)
            return 2
        for i in range(args.seeds):
            r = run(name, args.first + i, args.duration)
            rows.append(r)
            if args.json:
                continue
            w = " ".join(f"{k} x{v:.3g}" for k, v in r["worst_ratio"].items())
            print(f"{name:<17} seed {r['seed']} {r['duration_s']:g} s peak {r['peak_speed_m_s']:.3f} m/s: "
                  f"{len(r['events'])} alarm event(s) {r['events'][:4]}; held {100 * r['held_share']:.1f} %; "
                  f"worst {w}", flush=True)
    if args.json:
        print(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
