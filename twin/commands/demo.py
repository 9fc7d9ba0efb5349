"""``twin demo``: the end-to-end main job on an embedded default, nothing to install beyond the package.

1. Simulate an MSP25 rig (the paper's Table 9) running a multisine test for
   150 s while its piston seal wears: after 30 s of healthy running the
   cross-piston leakage ``CdAleak`` grows geometrically, 6-fold by the end, so
   that it leaves its healthy band (3x) at 104 s; sensors with realistic noise.
   The wear is slow enough for the early warning to speak first: the forecast
   needs 30 s to settle and a minute of trend.
2. Log it to MCAP, as a rig's recorder would.
3. Start the service on an in-process Zenoh peer (loopback, explicit endpoint,
   multicast scouting off) and replay the log through it in real time or
   faster (``--speed``).
4. A subscriber on a second Zenoh session prints the alarms as they arrive
   (history first, then live).
5. Write the report: parameter trends with the healthy band and the alarms
   (PNG, like the paper's Fig. 4), an HTML page, the twin's MCAP (estimates,
   alarms, statuses, forecasts, the alarms' lines and the decimated signals)
   and the Foxglove layout of the rig (``foxglove-layout.json``) that plots it.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import threading
import time
from typing import TYPE_CHECKING

from twin.online.events import format_alarm

if TYPE_CHECKING:
    from twin.service.rig import RigTwin


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_record(duration_s: float, seed: int, factor: float, t_start: float, t_end: float, shape: str = "exp"):
    from twin.models import DEFAULT_MODEL, get_model
    from twin.models.scenario import Drift, simulate_wear
    from fpdd.units import NOMINAL_NOISE
    from twin.models.simulate import excite

    model = get_model(DEFAULT_MODEL)
    name, xr = excite(model, duration_s, 1e-3, seed=seed)
    drift = Drift("CdAleak", factor, t_start, t_end, shape)
    noise = {k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}
    rec, P = simulate_wear(model.params(), xr, 1e-3, [drift], noise=noise, seed=seed, name="demo-rig")
    return rec, P, drift

def run(out_dir: str = "fpdd-demo", duration_s: float = 150.0, speed: float = 20.0, seed: int = 0,
        factor: float = 6.0, t_start: float = 30.0, t_end: float = 150.0, rig_name: str = "msp25-demo",
        say=print, shape: str = "exp") -> dict:
    import zenoh

    from replay.mcapio import McapSink
    from twin.service.subscriber import AlarmSubscriber
    from fpdd.zenohconf import zenoh_config
    from twin.online.baseline import default_baseline
    from twin.service.config import RigConfig, ServiceConfig
    from twin.models import DEFAULT_MODEL, get_model
    from twin.service.serve import serve

    os.makedirs(out_dir, exist_ok=True)
    t0 = time.perf_counter()
    grows = "grows geometrically" if shape == "exp" else {"ramp": "ramps", "step": "steps"}.get(shape, shape)
    say(f"1/5 simulating {duration_s:.0f} s of an MSP25 at 1 kHz; CdAleak {grows} x{factor:g} "
        f"from t={t_start:g} s to {t_end:g} s")
    rec, P, drift = make_record(duration_s, seed, factor, t_start, t_end, shape)
    from twin.online.tracker import OnlineTracker

    OnlineTracker().process(rec.to_samples().slice(0, 10))  # compile (or load) the filter before the clock runs
    log_path = os.path.join(out_dir, "rig.mcap")
    with McapSink(log_path, rig=rig_name) as sink:
        sink.write(rec.to_samples())
    say(f"2/5 logged {len(rec)} samples to {log_path}")

    baseline = default_baseline(DEFAULT_MODEL)
    rig = RigConfig(name=rig_name, model=DEFAULT_MODEL, source=log_path, dbc=None, speed=speed,
                    track=tuple(get_model(DEFAULT_MODEL).PHENOMENOLOGICAL), params={}, baseline=baseline)
    cfg = ServiceConfig(path="<demo>", zenoh_mode="peer", listen=(), connect=(),
                        journal_dir=os.path.join(out_dir, "journal"), out_dir=out_dir, estimate_every=50,
                        rigs=(rig,))
    journal = os.path.join(cfg.journal_dir, f"{rig_name}.alarms.jsonl")
    if os.path.exists(journal):  # a fresh demo starts a fresh journal
        os.remove(journal)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    received: list = []
    sub_done = threading.Event()
    service_done = threading.Event()
    say(f"3/5 service on a Zenoh peer at {endpoint}; replaying at {speed:g}x real time")
    with zenoh.open(zenoh_config("peer", listen=[endpoint])) as srv_session, \
            zenoh.open(zenoh_config("peer", connect=[endpoint])) as sub_session:

        def subscriber():
            with AlarmSubscriber(sub_session, rig=rig_name) as sub:
                while not (service_done.is_set() and len(received) >= expected[0]):
                    try:
                        ev = sub.recv(timeout=0.2)
                    except TimeoutError:
                        continue
                    received.append(ev)
                    say(f"   subscriber: {format_alarm(ev, wall_clock=False)}")
            sub_done.set()

        expected = [10 ** 9]
        th = threading.Thread(target=subscriber, name="alarm-subscriber", daemon=True)
        th.start()
        twins: dict[str, RigTwin] = {}
        stats = serve(cfg, session=srv_session, twins=twins)
        twin = twins[rig_name]
        expected[0] = len(twin.alarms)
        service_done.set()
        sub_done.wait(timeout=15.0)
    alarms = twin.alarms
    say(f"4/5 service done: {stats[rig_name].samples} samples, {len(alarms)} alarm event(s); "
        f"the subscriber received {len(received)}")
    paths = report(out_dir, rec, P, twin, drift, baseline)
    say(f"5/5 report: {paths['html']}")
    t_cross = drift.crossing(get_model(DEFAULT_MODEL).NOMINAL["CdAleak"], baseline["CdAleak"].lo, baseline["CdAleak"].hi, rec.t_s)
    from twin.online.events.forecast import FORECAST_UNITS

    first = next((a for a in alarms if a.parameter == "CdAleak" and a.level == "alarm"), None)
    early = next((a for a in alarms if a.parameter == "CdAleak" and a.level == "early"), None)
    forecast = next((f for f in twin.forecasts if f.parameter == "CdAleak"), None)
    summary = {
        "rig": rig_name, "samples": stats[rig_name].samples, "duration_s": duration_s, "speed": speed,
        "truth": {"parameter": "CdAleak", "factor": factor, "t_start_s": t_start, "t_end_s": t_end,
                  "crosses_band_at_s": t_cross},
        "alarms": [a.to_dict() for a in alarms],
        "received_by_subscriber": len(received),
        "first_alarm_s": first.t_s if first else None,
        "detection_delay_s": (first.t_s - t_cross) if (first and t_cross is not None) else None,
        "first_forecast": {**forecast.to_dict(), "units": {k: u for k, u in FORECAST_UNITS.items()
                                                           if k in forecast.to_dict()}}
        if forecast is not None else None,
        "early_warning_s": early.t_s if early else None,
        "forecasts": len(twin.forecasts),
        "false_alarms": [a.parameter for a in alarms if a.parameter != "CdAleak" and a.level != "ok"],
        "final": twin.final_estimates(),
        "service_us_per_sample": 1e6 * stats[rig_name].busy_s / max(stats[rig_name].samples, 1),
        "wall_s": time.perf_counter() - t0,
        "files": paths,
    }
    return summary

def report(out_dir, rec, P, twin, drift, baseline) -> dict:
    from twin.reports import simple as html_report
    from twin.reports.plots import parameter_trends

    png = parameter_trends(twin, baseline, os.path.join(out_dir, "parameter_trends.png"), rec.t_s, P,
                           title="Tracked parameters of the wearing rig (cf. paper Fig. 4)")
    from datetime import UTC, datetime

    from twin.reports.units import Shown, fmt

    def shown(name: str, unit: str | None = None) -> Shown:  # a person reads display units (wn in Hz, mm²)
        return Shown(name, twin.rig.model, unit)

    def when(a) -> str:
        if a.wall_ns is None:
            return ""
        return datetime.fromtimestamp(a.wall_ns / 1e9, tz=UTC).isoformat(timespec="seconds").replace("+00:00", "Z")

    rows = [{"seq": a.seq, "raised (UTC)": when(a), "t [s]": round(a.t_s, 3), "parameter": a.parameter,
             "level": a.level, "kind": a.kind, "estimate": fmt(shown(a.parameter)(a.estimate), 4),
             "std": fmt(shown(a.parameter)(a.std), 2),
             "band": f"{fmt(shown(a.parameter)(a.band_lo), 4)} .. {fmt(shown(a.parameter)(a.band_hi), 4)}",
             "unit": shown(a.parameter).unit_text}
            for a in twin.alarms]
    final = [{"parameter": n, "estimate": fmt(shown(n, d["unit"])(d["value"]), 5),
              "std": fmt(shown(n, d["unit"])(d["std"]), 2), "unit": shown(n, d["unit"]).unit_text}
             for n, d in twin.final_estimates().items()]
    html = html_report.write(os.path.join(out_dir, "report.html"), "fpdd-twin demo: a wearing MSP25 rig", [
        ("Scenario", f"<p>Cross-piston leakage CdAleak grows x{drift.factor:g} "
                     f"({'geometrically' if drift.shape == 'exp' else drift.shape}) from t = {drift.t_start:g} s "
                     f"to {drift.t_end:g} s; sensors: x 2 µm, pA/pB 20 kPa noise; 1 kHz.</p>"),
        ("Alarms (as journaled and published over Zenoh)", html_report.table(rows)),
        ("Parameter trends", html_report.image(png, "estimates ±2σ, truth dashed, healthy band shaded")),
        ("Final estimates", html_report.table(final)),
    ])
    from twin.service.live_view.layout import write_layout

    layout = write_layout(os.path.join(out_dir, "foxglove-layout.json"), rig=twin.rig.name, model=twin.rig.model)
    return {"html": html, "trends_png": png, "rig_mcap": os.path.join(out_dir, "rig.mcap"),
            "twin_mcap": os.path.join(out_dir, f"{twin.rig.name}.twin.mcap"), "foxglove_layout": layout}

def add_demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="fpdd-demo", help="report directory (default fpdd-demo)")
    p.add_argument("--duration", type=float, default=150.0,
                   help="simulated seconds (default 150: the wear starts at 30 s, leaves the band at 104 s)")
    p.add_argument("--speed", type=float, default=20.0, help="replay speed, x real time (default 20; 0 = as fast as possible)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")

def run_demo(args) -> int:
    say = (lambda m: print(m, file=sys.stderr, flush=True)) if args.json else print
    summary = run(args.out, args.duration, args.speed, args.seed, say=say)
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
        return 0
    from twin.online.tracker import fmt_estimate

    print("\nfinal estimates:")
    for n, d in summary["final"].items():
        print("  " + fmt_estimate(n, d["value"], d["std"]))
    if summary["early_warning_s"] is not None:
        fc = summary["first_forecast"]

        def at(v) -> str:
            return "never" if v is None else f"{v:.0f}"
        print(f"early warning at t = {summary['early_warning_s']:.2f} s: CdAleak forecast to leave its band at "
              f"t = {at(fc['t_exit'])} s (90 % interval {at(fc['t_exit_lo'])} .. {at(fc['t_exit_hi'])} s)")
    if summary["detection_delay_s"] is not None:
        print(f"CdAleak left its healthy band at t = {summary['truth']['crosses_band_at_s']:.2f} s; "
              f"alarm at t = {summary['first_alarm_s']:.2f} s ({summary['detection_delay_s']:.2f} s later)")
    print(f"false alarms: {summary['false_alarms'] or 'none'}; service busy {summary['service_us_per_sample']:.1f} "
          "us per sample (filter, drift test, publishing); "
          f"demo took {summary['wall_s']:.1f} s")
    print(f"report: {summary['files']['html']}; in Foxglove: {summary['files']['twin_mcap']} with the layout "
          f"{summary['files']['foxglove_layout']}")
    return 0
