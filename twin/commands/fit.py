"""``twin fit``: fit free parameters to measured records (output error)."""

from __future__ import annotations

import sys

from twin.models import DEFAULT_MODEL, MODELS
from replay.options import EXIT_LOSS
from twin.commands.common import (add_map_argument, add_timing_arguments, load_params_file, loss_lines,
                                  source_options, timing_of)
from twin.commands.common import dump as _dump
from twin.commands.common import kv as _kv
from twin.commands.common import names as _names
from twin.commands.common import progress as _progress

HELP = "fit free parameters to measured records (output error)"


def add_arguments(p) -> None:
    from twin.commands.common import EXIT_HELP

    p.epilog = EXIT_HELP
    p.add_argument("data", nargs="+", help="records (CSV, MCAP, CAN logs); parameters are shared")
    p.add_argument("--model", default=DEFAULT_MODEL, choices=MODELS)
    p.add_argument("--free", help="free parameters, exactly these (default: the phenomenological ones and the "
                   "own parameters of the effects --effects switches on, less those --set holds)")
    p.add_argument("--outputs", help="outputs fitted, e.g. x or x,pA,pB (default: all present)")
    p.add_argument("--params", metavar="FILE", help="parameter set (JSON of twin fit/diagnose --save)")
    p.add_argument("--set", help="known parameter values NAME=VALUE,..., with a unit or SI (e.g. Fext=15kN)")
    p.add_argument("--start", help="start values of free parameters NAME=VALUE,..., with a unit or SI (e.g. wn=40Hz)")
    p.add_argument("--effects", help="effects to switch on by name; their own parameters are fitted too unless "
                   "--set holds them or --free lists the free parameters")
    p.add_argument("--drive", default="auto", choices=("auto", "x_ref", "u"),
                   help="closed loop from x_ref or open loop from u (default: x_ref if logged)")
    p.add_argument("--estimate-init", help="initial-state quantities to estimate per record, e.g. x0,dp0 "
                   "(the initial state is read off the first samples in any case)")
    p.add_argument("--noise-levels", help="noise std per output used as residual weights, NAME=STD,...")
    p.add_argument("--starts", type=int, default=8, help="multi-start candidates screened (default 8)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--plot", metavar="DIR", help="write convergence plots (PNG) to DIR")
    p.add_argument("--report", metavar="DIR", help="write DIR/fit_report.html: compare, resid, parameters, "
                   "correlation, loop timing (one self-contained file)")
    p.add_argument("--save", metavar="FILE", help="save the fitted parameter set as JSON")
    p.add_argument("--no-adequacy", action="store_true",
                   help="skip the adequacy test of the fitted model (by default a model that does not represent "
                   "the record is said so, with the failed test: its prediction errors follow the drive, stay "
                   "predictable, or grow on the record's tail)")
    add_timing_arguments(p)
    add_map_argument(p)
    from twin.commands.compare import add_arguments as add_compare_arguments

    add_compare_arguments(p)
    p.add_argument("--json", action="store_true")


def free_names(model, free: tuple[str, ...], known, effects: tuple[str, ...]) -> tuple[str, ...]:
    """The parameters ``twin fit`` frees: ``free`` (``--free``) exactly as listed when given; else the model's
    phenomenological parameters and the own parameters of ``effects`` (``--effects``: an effect switched on is
    fitted, as ``--compare`` fits its candidates'), less those ``known`` holds (``--set``; a spring held at 0
    stays 0).  A ``--params`` file's effects keep their saved values unless named here."""
    if free:
        return free
    own = tuple(n for e in effects if e in model.EFFECTS for n in model.EFFECTS[e].names)
    return tuple(dict.fromkeys(n for n in (*model.PHENOMENOLOGICAL, *own) if n not in known))


def run(args) -> int:
    from twin.models import get_model
    from twin.models.records import load_records

    model = get_model(args.model)
    records = []
    reports: list = []
    for path in args.data:  # read (and refused) before the fit's libraries are imported
        records.extend(load_records(path, model=model.name, reports=reports, **source_options(args, path)))
    from twin.estimation.fit_checked import fit

    lost = loss_lines("fit", reports)
    base, saved_timing = load_params_file(model, args.params, _kv(args.set), _names(args.effects),
                                          with_timing=True)
    timing = timing_of(args, saved_timing)
    free = free_names(model, _names(args.free), _kv(args.set), _names(args.effects))
    outputs = _names(args.outputs) or None
    if args.compare:
        from twin.commands.compare import run_compare

        return run_compare(args, model, records, base, timing, lost)
    res = fit(model, records, free, base=base, start=_kv(args.start), outputs=outputs,
              noise=_kv(args.noise_levels), drive=args.drive, estimate_init=_names(args.estimate_init),
              n_starts=args.starts, seed=args.seed, progress=None if args.json else _progress(args),
              timing=timing, adequacy=not args.no_adequacy)
    plots = []
    if args.plot:
        from twin.reports.plots import fit_convergence

        plots = fit_convergence(res, records, model, args.plot)
    report = None
    if args.report:
        from twin.reports import fit_report

        report = fit_report(res, records, model, args.report)
    if args.save:
        res.save(args.save, map=getattr(args, "map", None))
    from twin.reports import summary as _summary

    summary = _summary.summarize(res, records, drive=args.drive)
    if args.json:
        d = res.to_dict()
        d["summary"] = summary
        d["plots"] = plots
        d["records"] = [r.name for r in records]
        d["input_lost"] = lost
        if report:
            d["report"] = report
        _dump(d)
    else:
        print(res.table())
        print(_summary.text(summary))
        for line in lost:
            print(f"input lost: {line}")
        for p in plots:
            print(f"plot: {p}", file=sys.stderr)
        if report:
            print(f"report: {report}", file=sys.stderr)
    return EXIT_LOSS if lost else 0
