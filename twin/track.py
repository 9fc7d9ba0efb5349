"""``twin track LOG``: a recorded log through the online twin, offline and as fast as it goes.

The same :class:`twin.service.RigTwin` as the live service (tracker, drift
test), without Zenoh: estimates, alarms and statuses go to an MCAP file that
Foxglove plots (``/twin/estimate``, ``/twin/alarm``, ``/twin/status``), the
parameter trends with the healthy band to a PNG (like the paper's Fig. 4).
The healthy baseline is the rig configuration's values (the paper's Table 9
for the MSP25) unless ``--config`` or ``--baseline`` says otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from twin.cliutil import dump, kv, load_params_file, names


def track(path: str, rig_name: str = "rig", params: dict | None = None, tracked=None, baseline=None,
          out_dir: str | None = None, dbc: str | None = None, chunk: int = 10000, progress=None):
    """Run a log through a :class:`RigTwin`; returns the twin (alarms, history, stats)."""
    from replay.factory import open_source
    from replay.mcapio import McapSink
    from twin.config import RigConfig, default_baseline
    from twin.models import msp25 as M
    from twin.service import RigTwin

    tracked = tuple(tracked or M.PHENOMENOLOGICAL)
    base = default_baseline("msp25", params, tracked)
    base.update(baseline or {})
    rig = RigConfig(rig_name, "msp25", path, dbc, 0.0, tracked, dict(params or {}), base)
    rec = None
    if out_dir:
        os.makedirs(out_dir, exist_ok=True)
        rec = McapSink(os.path.join(out_dir, f"{rig_name}.twin.mcap"))
    twin = RigTwin(rig, None, rec, estimate_every=50)
    opts = {"dbc": dbc} if dbc else {}
    try:
        with open_source(path, **opts) as src:
            for block in src.chunks(chunk):
                twin.write(block)
                if progress:
                    progress(f"{twin.stats.samples} samples, {twin.stats.alarms} alarm event(s)")
        twin.close()
    finally:
        if rec is not None:
            rec.close()
    return twin


def add_track_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="CSV, MCAP or CAN log (ASC, BLF, candump .log, TRC)")
    p.add_argument("--rig", default="rig", help="rig name in events (default rig)")
    p.add_argument("--track", help="parameters to track (default Ffric,CdAleak,Cd,zeta,wn)")
    p.add_argument("--params", metavar="FILE", help="known parameters (JSON of twin fit/diagnose --save)")
    p.add_argument("--set", help="known parameter values NAME=VALUE,...")
    p.add_argument("--config", metavar="RIG.toml", help="take parameters and baseline of this rig configuration")
    p.add_argument("--dbc", help="DBC for CAN logs (default: the MSP25 DBC)")
    p.add_argument("--out", metavar="DIR", default="fpdd-track", help="MCAP and plot directory (default fpdd-track)")
    p.add_argument("--json", action="store_true", help="print alarms and final estimates as JSON")


def run_track(args) -> int:
    from twin.config import load_config
    from twin.models import get_model
    from twin.plots import parameter_trends

    params = {}
    baseline = None
    tracked = names(args.track) or None
    if args.config:
        cfg = load_config(args.config)
        rig = next((r for r in cfg.rigs if r.name == args.rig), cfg.rigs[0])
        params, baseline, tracked = dict(rig.params), rig.baseline, tracked or rig.track
    if args.params or args.set:
        ps = load_params_file(get_model("msp25"), args.params, kv(args.set))
        params.update(ps.as_dict())
        if ps.effects:
            from twin.errors import ParameterError

            raise ParameterError(f"the tracker follows the nominal rig model; effects {list(ps.effects)} "
                                 "are not tracked (fit them with twin fit instead)")
    say = None if args.json else (lambda m: print("\r" + m, end="", file=sys.stderr, flush=True))
    twin = track(args.log, args.rig, params, tracked, baseline, args.out, args.dbc, progress=say)
    if say:
        print(file=sys.stderr)
    png = parameter_trends(twin, twin.rig.baseline, os.path.join(args.out, "parameter_trends.png"),
                           title=f"Tracked parameters of {args.rig} ({os.path.basename(args.log)})")
    result = {
        "log": args.log, "rig": args.rig, "samples": twin.stats.samples,
        "alarms": [dict(a.to_dict(), t=a.t_s) for a in twin.alarms],
        "final": twin.final_estimates(),
        "status": twin.drift.statuses(),
        "counters": twin.tracker.counters,
        "files": {"mcap": os.path.join(args.out, f"{args.rig}.twin.mcap"), "trends_png": png},
    }
    if args.json:
        dump(result)
        return 0
    for a in twin.alarms:
        print(f"t={a.t_s:9.3f} s {a.level.upper():7s} {a.kind:9s} {a.parameter}: {a.estimate:.4g} +- {a.std:.2g} "
              f"(band {a.band_lo:.4g}..{a.band_hi:.4g})")
    print(f"{twin.stats.samples} samples, {len(twin.alarms)} alarm event(s)")
    for n, d in result["final"].items():
        print(f"  {n:8s} {d['value']:.5g} +- {d['std']:.2g} {d['unit']}  [{result['status'][n]}]")
    print(f"MCAP: {result['files']['mcap']}  plot: {png}", file=sys.stderr)
    return 0
