"""The ``twin`` command: models, simulation, fitting, the paper's cases, tracking, the service.

Every subcommand has ``--help``; those whose output another program reads have
``--json`` (JSON on stdout, progress and messages on stderr).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from typing import Sequence

from twin.cliutil import dump as _dump
from twin.cliutil import finite_or_none
from twin.cliutil import kv as _kv
from twin.cliutil import load_params_file
from twin.cliutil import names as _names
from twin.cliutil import progress as _progress
from twin.cliutil import add_timing_arguments, timing_of
from twin.errors import TwinError


# --- params -------------------------------------------------------------------------------
def cmd_params(args) -> int:
    from twin.models import get_model

    model = get_model(args.model)
    ps = model.params(effects=_names(args.effects))
    if args.json:
        _dump({"model": model.name, "params": [dict(s.to_dict(), value=v) for s, v in zip(ps.specs, ps.values)],
               "effects": {n: {"description": e.description, "signature": e.signature,
                               "params": list(e.names)} for n, e in model.EFFECTS.items()}})
        return 0
    print(ps.table())
    print("\neffects (switch on with --effects NAME,...):")
    for n, e in model.EFFECTS.items():
        print(f"  {n:<22} {e.description}  [{', '.join(e.names)}]")
    return 0


# --- simulate -----------------------------------------------------------------------------
def cmd_simulate(args) -> int:
    from replay.factory import open_sink
    from twin.models import get_model
    from twin.simulate import default_noise, excite, measure

    model = get_model(args.model)
    ps = model.params(effects=_names(args.effects), **_kv(args.set))
    name, drive = excite(model, args.duration, args.dt, args.excitation, args.amplitude, args.seed,
                         args.f_lo, args.f_hi)
    noise = {} if args.noise == "none" else default_noise(model)
    noise.update(_kv(args.noise_levels))
    timing = timing_of(args)
    rec = measure(model, ps, name, drive, args.dt, noise=noise, quantisation=_kv(args.quantisation),
                  seed=args.seed, name=args.output, timing=timing)
    with open_sink(args.output) as sink:
        sink.write(rec.to_samples())
    info = {"output": args.output, "model": model.name, "samples": len(rec), "dt": args.dt,
            "signals": list(rec.signals), "params": ps.as_dict(), "effects": list(ps.effects), "noise": noise,
            "timing": timing.to_dict()}
    if args.json:
        _dump(info)
    else:
        print(f"wrote {len(rec)} samples of {', '.join(rec.signals)} to {args.output}", file=sys.stderr)
    return 0


# --- fit ----------------------------------------------------------------------------------
def cmd_fit(args) -> int:
    from twin.fit import fit
    from twin.models import get_model
    from twin.record import load_records

    model = get_model(args.model)
    records = []
    for path in args.data:
        records.extend(load_records(path, model=model.name))
    base, saved_timing = load_params_file(model, args.params, _kv(args.set), _names(args.effects),
                                          with_timing=True)
    timing = timing_of(args, saved_timing)
    free = _names(args.free) or model.PHENOMENOLOGICAL
    outputs = _names(args.outputs) or None
    res = fit(model, records, free, base=base, start=_kv(args.start), outputs=outputs,
              noise=_kv(args.noise_levels), drive=args.drive, estimate_init=_names(args.estimate_init),
              n_starts=args.starts, seed=args.seed, progress=None if args.json else _progress(args),
              timing=timing)
    plots = []
    if args.plot:
        from twin.plots import fit_convergence

        plots = fit_convergence(res, records, model, args.plot)
    if args.save:
        with open(args.save, "w") as f:
            json.dump(finite_or_none({"model": model.name, "effects": list(res.params.effects),
                                      "params": res.params.as_dict(), "std": res.std, "timing": res.timing,
                                      "noise": {o: float(np.sqrt(res.mse[o])) for o in res.outputs}}),
                      f, indent=2, allow_nan=False)
    if args.json:
        d = res.to_dict()
        d["plots"] = plots
        d["records"] = [r.name for r in records]
        _dump(d)
    else:
        print(res.table())
        for p in plots:
            print(f"plot: {p}", file=sys.stderr)
    return 0


# --- paper --------------------------------------------------------------------------------
def cmd_paper(args) -> int:
    from twin.paper import format_rows, run_all

    rows, elapsed = run_all(noisy=args.noise, seed=args.seed, progress=None if args.json else _progress(args),
                            timing=timing_of(args))
    if args.plot:
        from twin.plots import paper_table

        p = paper_table(rows, args.plot)
        if not args.json:
            print(f"plot: {p}", file=sys.stderr)
    if args.json:
        _dump(rows)
        return 0
    print(format_rows(rows))
    worse = [r for r in rows if round(r["error_pct"], 4) > r["paper_error_pct"] or r["error_pct"] > 0.01]
    if args.noise:
        outside = [r for r in rows if r["z"] > 3]
        print(f"\nwith sensor noise (x: 2 um): {len(rows) - len(outside)}/{len(rows)} estimates within 3 std of the truth")
    else:
        print(f"\nnoise-free: {len(rows) - len(worse)}/{len(rows)} errors at most the paper's (to its printed 4 decimals) and at most 0.01 %")
    print(f"all cases in {elapsed:.2f} s (the paper: minutes per case)")
    return 0


# --- the subcommands other modules bring --------------------------------------------------
def _lazy(module: str, add: str, run: str):
    """Subcommand whose arguments and runner live in ``module`` (imported on use)."""
    import importlib

    mod = importlib.import_module(module)
    return getattr(mod, add), getattr(mod, run)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fpdd-twin")
    except PackageNotFoundError:  # running from a source tree that was not installed
        from twin import __version__

        return __version__


def _common() -> argparse.ArgumentParser:
    """Flags every subcommand accepts too (before or after its name)."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                        help="no progress messages on stderr")
    return common


def jit_note(command: str) -> str | None:
    """A line to show before the first run compiles the models (numba caches them for later runs)."""
    import glob
    import os

    if command in ("params", "alarms"):
        return None
    here = os.path.join(os.path.dirname(__file__), "models", "__pycache__")
    if glob.glob(os.path.join(here, "msp25.*.nbi")):
        return None
    return ("twin: first run: compiling the models (about a minute, once; later runs load them from the "
            "cache)")


def build_parser() -> argparse.ArgumentParser:
    common = _common()
    ap = argparse.ArgumentParser(prog="twin", description=__doc__.split("\n")[0], parents=[common])
    ap.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add = sub.add_parser

    def add_parser(name, **kw):
        return _add(name, parents=[common], **kw)

    sub.add_parser = add_parser  # type: ignore[method-assign]

    p = sub.add_parser("params", help="list a model's parameters, units, bounds and effects")
    p.add_argument("--model", default="msp25", choices=("msp25", "oscillator"))
    p.add_argument("--effects", help="comma-separated effects to switch on")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_params)

    p = sub.add_parser("simulate", help="simulate an identification experiment and write CSV or MCAP")
    p.add_argument("--model", default="msp25", choices=("msp25", "oscillator"))
    p.add_argument("-o", "--output", required=True, help="output file (.csv or .mcap)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds (default 10)")
    p.add_argument("--dt", type=float, default=1e-3, help="sample time in s (default 1e-3)")
    p.add_argument("--excitation", default=None, choices=("multisine", "chirp", "steps"))
    p.add_argument("--amplitude", type=float, default=None, help="peak of the drive (m for x_ref, N for force)")
    p.add_argument("--f-lo", type=float, default=None, help="lowest frequency in Hz")
    p.add_argument("--f-hi", type=float, default=None, help="highest frequency in Hz")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", help="parameter values NAME=VALUE,..., with a unit or SI (e.g. wn=43Hz,CdAleak=3.3mm^2)")
    p.add_argument("--effects", help="comma-separated effects to switch on")
    p.add_argument("--noise", choices=("default", "none"), default="default",
                   help="sensor noise: x 2 um, pressures 20 kPa (default) or none")
    p.add_argument("--noise-levels", help="override noise std per signal, NAME=STD,...")
    p.add_argument("--quantisation", help="LSB per signal, NAME=LSB,...")
    add_timing_arguments(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("fit", help="fit free parameters to measured records (output error)")
    p.add_argument("data", nargs="+", help="records (CSV, MCAP, CAN logs); parameters are shared")
    p.add_argument("--model", default="msp25", choices=("msp25", "oscillator"))
    p.add_argument("--free", help="free parameters (default: the phenomenological ones)")
    p.add_argument("--outputs", help="outputs fitted, e.g. x or x,pA,pB (default: all present)")
    p.add_argument("--params", metavar="FILE", help="parameter set (JSON of twin fit/diagnose --save)")
    p.add_argument("--set", help="known parameter values NAME=VALUE,..., with a unit or SI (e.g. Fext=15kN)")
    p.add_argument("--start", help="start values of free parameters NAME=VALUE,..., with a unit or SI (e.g. wn=40Hz)")
    p.add_argument("--effects", help="effects to switch on by name")
    p.add_argument("--drive", default="auto", choices=("auto", "x_ref", "u"),
                   help="closed loop from x_ref or open loop from u (default: x_ref if logged)")
    p.add_argument("--estimate-init", help="initial-state quantities to estimate per record, e.g. x0,dp0 "
                   "(the initial state is read off the first samples in any case)")
    p.add_argument("--noise-levels", help="noise std per output used as residual weights, NAME=STD,...")
    p.add_argument("--starts", type=int, default=8, help="multi-start candidates screened (default 8)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--plot", metavar="DIR", help="write convergence plots (PNG) to DIR")
    p.add_argument("--save", metavar="FILE", help="save the fitted parameter set as JSON")
    add_timing_arguments(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("paper", help="regenerate the paper's cases: our estimates beside the paper's")
    p.add_argument("--noise", action="store_true", help="with realistic sensor noise (x: 2 um, y: 1 um)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--plot", metavar="DIR", help="write the comparison plot (PNG) to DIR")
    add_timing_arguments(p)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_paper)

    for name, module, add_name, run_name, help_ in (
        ("track", "twin.track", "add_track_arguments", "run_track",
         "replay a log through the tracker: estimates, alarms, trend plot"),
        ("diagnose", "twin.diagnose", "add_diagnose_arguments", "run_diagnose",
         "show what the simulation gets wrong, name the cause, measure the gain"),
        ("alarms", "twin.bus", "add_alarms_arguments", "run_alarms_cli",
         "print drift alarms as they come, history first"),
        ("serve", "twin.service", "add_serve_arguments", "run_serve", "run the online twin for one or more rigs"),
        ("demo", "twin.demo", "add_demo_arguments", "run_demo",
         "end-to-end demo: simulate a wearing rig, track it, alarm over Zenoh"),
    ):
        add, run = _lazy(module, add_name, run_name)
        p = sub.add_parser(name, help=help_)
        add(p)
        p.set_defaults(func=run)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not hasattr(args, "quiet"):
        args.quiet = False
    note = None if args.quiet else jit_note(args.command)
    if note:
        print(note, file=sys.stderr, flush=True)
    try:
        return int(args.func(args) or 0)
    except TwinError as exc:
        print(f"twin {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader went away (``twin params | head``): not an error of ours
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
