"""``twin track LOG``: a recorded log through the online twin, offline (library: :mod:`twin.service.track`)."""

from __future__ import annotations

import argparse
import os
import sys

from replay.options import EXIT_LOSS
from twin.commands.common import (add_map_argument, add_timing_arguments, dump, kv, loss_lines, names, source_options,
                                  timing_of)
from twin.models import DEFAULT_MODEL, MODELS, trackable_models


def add_arguments(p: argparse.ArgumentParser) -> None:
    from twin.commands.common import EXIT_HELP

    p.epilog = EXIT_HELP
    p.add_argument("log", help="CSV, MCAP or CAN log (ASC, BLF, candump .log, TRC)")
    p.add_argument("--rig", default="rig", help="rig name in events (default rig)")
    p.add_argument("--model", choices=MODELS, default=None,
                   help=f"the rig model to track (default the --config rig's, the --params fit's, else "
                        f"{DEFAULT_MODEL})")
    p.add_argument("--track", help="parameters to track (default the model's phenomenological ones, e.g. "
                                   "Ffric,CdAleak,Cd,zeta,wn)")
    p.add_argument("--params", metavar="FIT.json",
                   help="commissioning fit (JSON of twin fit --save): known values, healthy bands around the fitted "
                        "ones, sensor noise, loop timing")
    p.add_argument("--noise-levels", metavar="x=2um,pA=20kPa,...",
                   help="sensor noise standard deviations per output, with their units; default the fit's, else "
                        "x=2um,pA=20kPa,pB=20kPa (the filter goes on learning them online)")
    p.add_argument("--set", help="known parameter values NAME=VALUE,...")
    p.add_argument("--config", metavar="RIG.toml", help="take parameters and baseline of this rig configuration")
    p.add_argument("--dbc", help="DBC for CAN logs (default: the DBC shipped with replay)")
    p.add_argument("--out", metavar="DIR", default="fpdd-track", help="MCAP and plot directory (default fpdd-track)")
    p.add_argument("--json", action="store_true", help="print alarms, forecasts and final estimates as JSON")
    p.add_argument("--forecast-horizon", type=float, metavar="S",
                   help="early warning horizon in seconds: an 'early' alarm when a parameter is forecast to leave its "
                        "band within S s with probability 0.9 (default the rig's forecast_horizon_s, else 3600)")
    p.add_argument("--maintenance", action="append", default=[], metavar="P[,P2]@SECONDS[:NOTE]",
                   help="a maintenance recorded in the log: the forecasts of P (and P2) start afresh at SECONDS from "
                        "the start of the record, e.g. CdAleak@1800:seal replaced (repeatable)")
    p.add_argument("--confirm", action="store_true",
                   help="raise a warning or alarm only when a batch re-fit of the recent window (twin fit's output-error "
                        "fit with its HAC standard errors and adequacy test) confirms it at a stated level; a window "
                        "that cannot test a parameter says not_testable (about 6x the CPU of the filter alone)")
    add_timing_arguments(p)
    add_map_argument(p)


def parse_maintenance(text: str, tracked) -> tuple[float, list[str], str]:
    """``P[,P2]@SECONDS[:NOTE]`` -> ``(seconds, [P, P2], note)``; ParameterError naming the option."""
    import math
    import re

    from fpdd.errors import ParameterError

    m = re.fullmatch(r"\s*([A-Za-z_][A-Za-z0-9_]*(?:\s*,\s*[A-Za-z_][A-Za-z0-9_]*)*)\s*@\s*([^:]+?)\s*(?::(.*))?",
                     text)
    t = None
    if m:
        try:
            t = float(m.group(2))
        except ValueError:
            t = None
    if m is None or t is None or not (math.isfinite(t) and t >= 0):
        raise ParameterError(f"--maintenance: expected PARAMETER[,PARAMETER]@SECONDS[:NOTE] with SECONDS >= 0 from "
                             f"the start of the record, got {text!r}")
    ps = [p.strip() for p in m.group(1).split(",")]
    bad = [p for p in ps if p not in tracked]
    if bad:
        raise ParameterError(f"--maintenance: {', '.join(map(repr, bad))} not tracked (tracked: {', '.join(tracked)})")
    return t, ps, (m.group(3) or "").strip()


def _read(path: str, opts: dict, reports: list, model: str):
    """Blocks of the log; its signals checked first against ``model`` (:func:`twin.models.records.check_signals`,
    naming the models whose signals the log has when it is not ``model``'s), its read report kept.  The log is
    opened and checked here, before the tracker is imported; its blocks are read as they are iterated."""
    from fpdd.errors import DataError
    from replay.factory import open_source
    from twin.models.records import check_source, reader_options

    try:
        src = open_source(path, **reader_options(path, model, opts))
    except DataError as exc:  # e.g. a force in N where the model's drive is a voltage: whose record is it?
        other = _model_of_record(path, opts, model)
        if other is None:
            raise
        raise DataError(f"{exc}; it reads as a record of the {other} model, not of the {model} model: "
                        f"--model {other}") from None
    try:
        check_source(path, src, model, suggest=True)
    except BaseException:
        src.close()
        raise
    return _blocks(src, reports)


def _blocks(src, reports: list):
    with src:
        try:
            yield from src.chunks(10000)
        finally:  # the report of the reading itself (a CAN log's reader starts a fresh one for each reading)
            reports.append(src.report)


def _model_of_record(path: str, opts: dict, model: str) -> str | None:
    """The first other trackable model whose signals the log at ``path`` has, read with that model's table."""
    from fpdd.errors import DataError
    from replay.factory import open_source
    from twin.models.records import check_source, reader_options

    for other in trackable_models():
        if other == model:
            continue
        try:
            with open_source(path, **reader_options(path, other, opts)) as src:
                check_source(path, src, other)
        except DataError:
            continue
        return other
    return None


def run(args) -> int:
    from twin.service.config import load_config
    from twin.models import get_model
    from twin.reports.plots import parameter_trends

    horizon = getattr(args, "forecast_horizon", None)
    if horizon is not None and not (horizon > 0 and horizon < float("inf")):
        from fpdd.errors import ParameterError

        raise ParameterError(f"--forecast-horizon: expected a positive number of seconds, got {horizon!r}")
    params = {}
    baseline = None
    tracked = names(args.track) or None
    model_name = args.model
    if args.config:
        cfg = load_config(args.config)
        rig = next((r for r in cfg.rigs if r.name == args.rig), cfg.rigs[0])
        params, baseline, tracked = dict(rig.params), rig.baseline, tracked or rig.track
        horizon = horizon if horizon is not None else rig.forecast_horizon_s
        model_name = model_name or rig.model
    commission = None
    if args.params:
        from twin.online.commission import load_fit, tracker_params

        commission = load_fit(args.params)
        if model_name is not None and commission.model != model_name:
            from fpdd.errors import ConfigError

            raise ConfigError(f"{args.params}: a fit of the {commission.model} model; tracking the {model_name} "
                              "model")
        model_name = commission.model
        tracker_params(commission, tracked or get_model(model_name).PHENOMENOLOGICAL)  # checks the fit's effects
        for w in commission.warnings:  # the bands are centred on this fit: what it warned of, said again
            print(f"WARNING ({args.params}, the fit the bands are centred on): {w}", file=sys.stderr)
    model_name = model_name or DEFAULT_MODEL
    model = get_model(model_name)
    if args.set:
        over = kv(args.set)
        model.params(commission.effects if commission is not None else (), **over)  # checks names and ranges
        params.update(over)
        held = [n for n in model.PHENOMENOLOGICAL if over.get(n) == 0]
        if tracked is None and held:  # held at exactly 0 by --set (a free mass's spring): held, not tracked
            tracked = tuple(n for n in model.PHENOMENOLOGICAL if n not in held) or None
    noise = kv(args.noise_levels) if args.noise_levels else None
    if noise:
        measured = tuple(model.FILTER.measures) if model.FILTER is not None else model.OUTPUTS
        bad = [k for k in noise if k not in measured]
        if bad or any(not v > 0 for v in noise.values()):
            from fpdd.errors import ParameterError

            raise ParameterError(f"--noise-levels: expected positive standard deviations of {', '.join(measured)} (e.g. x=2um,pA=20kPa), got "
                                 f"{args.noise_levels!r}")
    timing = timing_of(args) if (args.controller or args.intersample) else None
    say = None if args.json else (lambda m: print("\r" + m, end="", file=sys.stderr, flush=True))
    opts = source_options(args, args.log)
    if args.dbc:
        opts["dbc"] = args.dbc
    reports: list = []
    maint = [parse_maintenance(m, tracked or model.PHENOMENOLOGICAL) for m in args.maintenance]
    blocks = _read(args.log, opts, reports, model_name)  # opened and checked before the tracker is imported
    from twin.online.events import format_alarm
    from twin.service.track import track

    twin = track(blocks, args.rig, params, tracked, baseline, args.out,
                 progress=say, noise=noise, timing=timing, commission=commission, forecast_horizon_s=horizon,
                 maintenance=maint, model=model_name, confirm=args.confirm)
    if say:
        print(file=sys.stderr)
    if twin.stats.samples == 0:
        from fpdd.errors import DataError

        raise DataError(f"{args.log}: no usable samples ({reports[0].summary() if reports else 'nothing read'})")
    lost = loss_lines("track", reports)
    png = parameter_trends(twin, twin.rig.baseline, os.path.join(args.out, "parameter_trends.png"),
                           title=f"Tracked parameters of {args.rig} ({os.path.basename(args.log)})")
    result = {
        "log": args.log, "rig": args.rig, "model": model_name, "samples": twin.stats.samples,
        "alarms": [dict(a.to_dict(), t=a.t_s) for a in twin.alarms],
        "forecasts": [f.to_dict() for f in sorted(twin.forecasts, key=lambda f: (f.t, f.parameter))],
        "forecast_horizon_s": twin.forecast.horizon_s,
        "maintenance": [{"parameters": ps, "t": t, "note": note} for t, ps, note in maint],
        "commission_warnings": list(commission.warnings) if commission is not None else [],
        "final": twin.final_estimates(),
        "status": (twin.confirm or twin.drift).statuses(),
        "counters": twin.tracker.counters,
        "consistency": (twin.confirm or twin.drift).guard,
        "sensors": twin.sensor_status(),
        "noise": {o: dict(v, unit=model.signal_unit(o)) for o, v in twin.tracker.noise_levels().items()},
        "timing": twin.tracker.timing.label,
        "files": {"mcap": os.path.join(args.out, f"{args.rig}.twin.mcap"), "trends_png": png},
        "input_lost": lost,
    }
    from twin.reports import track_report

    result["files"]["report"] = track_report(twin, args.out, log=args.log)
    if args.json:
        dump(result)
        return EXIT_LOSS if lost else 0
    for a in twin.alarms:
        print(format_alarm(a, wall_clock=False))
    print(f"{twin.stats.samples} samples, {len(twin.alarms)} alarm event(s); timing {result['timing']}")
    note = ", ".join(f"{o} {s}" for o, s in result["sensors"].items() if s != "ok")
    if note:
        print(f"  sensors: {note}")
    if result["consistency"] != "consistent":
        print(f"  filter not consistent with the data at the end: {result['consistency']}")
    from twin.reports.units import Shown

    specs = twin.tracker.ps
    for n, d in result["final"].items():  # display units, rounded after the conversion (JSON above stays SI)
        sh = Shown(n, spec=specs.spec(n))
        print(f"  {n:8s} {sh.text(d['value'], 5)} +- {sh.text(d['std'], 2)}  [{result['status'][n]}]")
    from twin.online.events.forecast import describe

    for n, f in twin.forecast.latest().items():
        print(f"  {n:8s} leaves its band {describe(f)} (at {f.t:.0f} s of record; P(within "
              f"{twin.forecast.horizon_s:g} s) = {f.p_within_horizon:.2f})")
    for line in lost:
        print(f"  input lost: {line}")
    print(f"report: {result['files']['report']}", file=sys.stderr)
    print(f"MCAP: {result['files']['mcap']}  plot: {png}", file=sys.stderr)
    return EXIT_LOSS if lost else 0
