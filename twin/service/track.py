"""``twin track LOG``: a recorded log through the online twin, offline and as fast as it goes.

The same :class:`twin.service.rig.RigTwin` as the live service (tracker, drift
test), without Zenoh: estimates, alarms and statuses go to an MCAP file that
Foxglove plots (``/twin/estimate``, ``/twin/alarm``, ``/twin/status``), the
parameter trends with the healthy band to a PNG (like the paper's Fig. 4).
The healthy baseline is the rig configuration's values (the paper's Table 9
for the MSP25) unless ``--config`` or ``--baseline`` says otherwise.

Offline there is no journal, so :class:`SequenceNumbers` stands in for the
service's publisher and numbers the alarm events 1, 2, 3, ... as the journal
would: the ``/twin/alarm`` messages carry the same ``seq`` field as on the bus
(``seq = 0`` means "never journaled" and is not a valid payload).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterable
from types import SimpleNamespace

from twin.commands.common import add_map_argument, add_timing_arguments, dump, kv, names, source_options, timing_of
from twin.online.events import format_alarm


class SequenceNumbers:
    """The publisher interface of :class:`twin.service.rig.RigTwin` without a bus: numbers alarms 1, 2, 3, ..."""

    def __init__(self) -> None:
        self.seq = 0

    def publish_alarm(self, ev):
        self.seq += 1
        return ev.with_seq(self.seq)

    def publish_estimate(self, ev):
        return ev

    def publish_status(self, ev):
        return ev


def _mapped(path: str, opts: dict):
    """Blocks of a CSV read with a column mapping (``--map``)."""
    from replay.factory import open_source

    with open_source(path, **opts) as src:
        yield from src.chunks(10000)


def _blocks(source, chunk: int, dbc: str | None):
    """Blocks of :class:`replay.base.Samples` from a path, a Record, Samples or an iterable of them."""
    from replay.base import Samples
    from replay.factory import open_source
    from twin.record import Record

    if isinstance(source, (str, os.PathLike)):
        opts = {"dbc": dbc} if dbc else {}
        with open_source(os.fspath(source), **opts) as src:
            yield from src.chunks(chunk)
        return
    items = [source] if isinstance(source, (Record, Samples)) else source
    if not isinstance(items, Iterable):
        from twin.errors import DataError

        raise DataError(f"track reads a log path, a Record, Samples or an iterable of them, "
                        f"not {type(source).__name__}")
    for item in items:
        s = item.to_samples() if isinstance(item, Record) else item
        for i in range(0, len(s), chunk):
            yield s.slice(i, i + chunk)


def track(source, rig_name: str = "rig", params: dict | None = None, tracked=None, baseline=None,
          out_dir: str | None = None, dbc: str | None = None, chunk: int = 10000, progress=None,
          estimate_every: int = 50, noise: dict | None = None, timing=None, commission=None):
    """Run ``source`` through a :class:`RigTwin` (tracker and drift test); returns the twin.

    ``source``: a log path (any format :func:`replay.factory.open_source` reads), a
    :class:`twin.record.Record`, :class:`replay.base.Samples`, or an iterable of
    them in time order (a stream of blocks).  ``params``: known parameters that
    differ from the nominal MSP25; ``tracked``: parameter names (default all five
    phenomenological ones); ``baseline``: ``{name: twin.service.config.Baseline}``
    overriding the default bands; ``noise``: sensor noise standard deviations
    per output (SI); ``timing``: the loop's :class:`~twin.models.base.Timing`;
    ``commission``: a :class:`twin.online.commission.Commission` (or the path of a
    ``twin fit --save`` file): known values, healthy bands around the fitted
    values, noise and timing.  With ``out_dir`` the estimates, alarms and
    statuses go to ``OUT_DIR/RIG.twin.mcap``, an estimate every ``estimate_every``
    samples.  The twin holds the results:
    ``alarms`` (events with ``t_s`` from the start of the record),
    ``final_estimates()``, ``history_arrays()``, ``drift.statuses()``,
    ``tracker.counters``.
    """
    from replay.mcapio import McapSink
    from twin.service.config import RigConfig, default_baseline
    from twin.models import msp25 as M
    from twin.service.rig import RigTwin

    from twin.online.commission import Commission, load_fit, tracker_for

    tracked = tuple(tracked or M.PHENOMENOLOGICAL)
    if isinstance(commission, (str, os.PathLike)):
        commission = load_fit(os.fspath(commission))
    base = default_baseline("msp25", params, tracked)
    if isinstance(commission, Commission):
        base.update(commission.baseline(tracked))
    base.update(baseline or {})
    where = os.fspath(source) if isinstance(source, (str, os.PathLike)) else f"<{type(source).__name__}>"
    rig = RigConfig(rig_name, "msp25", where, dbc, 0.0, tracked, dict(params or {}), base)
    rec = None
    if out_dir:
        os.makedirs(out_dir, exist_ok=True)
        rec = McapSink(os.path.join(out_dir, f"{rig_name}.twin.mcap"))
    every = max(1, int(estimate_every))
    twin = RigTwin(rig, SequenceNumbers(), rec, estimate_every=every)
    if noise or timing is not None or commission is not None:
        # the rig configuration plus what the command line adds
        r = SimpleNamespace(model="msp25", params=dict(params or {}), track=tracked,
                            noise=dict(noise or {}), timing=timing, commission=commission)
        twin.tracker = tracker_for(r)
    try:
        for block in _blocks(source, chunk, dbc):
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
    p.add_argument("--params", metavar="FIT.json",
                   help="commissioning fit (JSON of twin fit --save): known values, healthy bands around the fitted "
                        "ones, sensor noise, loop timing")
    p.add_argument("--noise-levels", metavar="x=2e-6,pA=2e4,...",
                   help="sensor noise standard deviations (SI) per output; default the fit's, else "
                        "x=2e-6,pA=2e4,pB=2e4 (the filter goes on learning them online)")
    p.add_argument("--set", help="known parameter values NAME=VALUE,...")
    p.add_argument("--config", metavar="RIG.toml", help="take parameters and baseline of this rig configuration")
    p.add_argument("--dbc", help="DBC for CAN logs (default: the MSP25 DBC)")
    p.add_argument("--out", metavar="DIR", default="fpdd-track", help="MCAP and plot directory (default fpdd-track)")
    p.add_argument("--json", action="store_true", help="print alarms and final estimates as JSON")
    add_timing_arguments(p)
    add_map_argument(p)


def _check_rig_log(path: str) -> None:
    """A CSV of the oscillator (columns u, y, no x) is not a rig log: say so before reading it."""
    if not str(path).lower().endswith(".csv"):
        return
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            header = [c.strip() for c in f.readline().split(",")]
    except OSError:
        return  # the reader names the problem
    if "y" in header and not {"x", "pA", "pB"} & set(header):
        from twin.errors import DataError

        raise DataError(f"{path}: columns {', '.join(header)} are the oscillator's; the tracker follows the msp25 "
                        "rig model (it needs u or x_ref and at least one of x, pA, pB)")


def run_track(args) -> int:
    from twin.service.config import load_config
    from twin.models import get_model
    from twin.reports.plots import parameter_trends

    _check_rig_log(args.log)
    params = {}
    baseline = None
    tracked = names(args.track) or None
    if args.config:
        cfg = load_config(args.config)
        rig = next((r for r in cfg.rigs if r.name == args.rig), cfg.rigs[0])
        params, baseline, tracked = dict(rig.params), rig.baseline, tracked or rig.track
    commission = None
    if args.params:
        from twin.online.commission import load_fit, tracker_params

        commission = load_fit(args.params)
        tracker_params(commission, tracked or get_model("msp25").PHENOMENOLOGICAL)  # refuses effects
    if args.set:
        model = get_model("msp25")
        over = kv(args.set)
        model.params((), **over)  # checks names and ranges
        params.update(over)
    noise = kv(args.noise_levels) if args.noise_levels else None
    if noise:
        bad = [k for k in noise if k not in ("x", "pA", "pB")]
        if bad or any(not v > 0 for v in noise.values()):
            from twin.errors import ParameterError

            raise ParameterError(f"--noise-levels: expected positive standard deviations of x, pA, pB (SI), got "
                                 f"{args.noise_levels!r}")
    timing = timing_of(args) if (args.controller or args.intersample) else None
    say = None if args.json else (lambda m: print("\r" + m, end="", file=sys.stderr, flush=True))
    log = args.log
    if getattr(args, "map", None):
        log = _mapped(args.log, source_options(args, args.log))
    twin = track(log, args.rig, params, tracked, baseline, args.out, args.dbc, progress=say, noise=noise,
                 timing=timing, commission=commission)
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
        "consistency": twin.drift.guard,
        "sensors": twin.tracker.sensor_status(),
        "noise": twin.tracker.noise_levels(),
        "timing": twin.tracker.timing.label,
        "files": {"mcap": os.path.join(args.out, f"{args.rig}.twin.mcap"), "trends_png": png},
    }
    from twin.reports import track_report

    result["files"]["report"] = track_report(twin, args.out, log=args.log)
    if args.json:
        dump(result)
        return 0
    for a in twin.alarms:
        print(format_alarm(a, wall_clock=False))
    print(f"{twin.stats.samples} samples, {len(twin.alarms)} alarm event(s); timing {result['timing']}")
    note = ", ".join(f"{o} {s}" for o, s in result["sensors"].items() if s != "ok")
    if note:
        print(f"  sensors: {note}")
    if result["consistency"] != "consistent":
        print(f"  filter not consistent with the data at the end: {result['consistency']}")
    specs = twin.tracker.ps
    for n, d in result["final"].items():  # display units (JSON above stays SI)
        show = specs.spec(n).show
        value, std = float(f"{d['value']:.5g}"), float(f"{d['std']:.2g}")
        print(f"  {n:8s} {show(value)} +- {show(std)}  [{result['status'][n]}]")
    print(f"MCAP: {result['files']['mcap']}  plot: {png}", file=sys.stderr)
    return 0
