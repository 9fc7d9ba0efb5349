"""``twin diagnose DATA``: what the simulation gets wrong, the named cause, the gain (library: :mod:`twin.estimation.diagnose`)."""

from __future__ import annotations

import argparse
import sys

from fpdd import jsonio
from twin.models import DEFAULT_MODEL, MODELS
from replay.options import EXIT_LOSS
from twin.commands.common import add_map_argument, add_timing_arguments, dump, loss_lines, source_options, timing_of
from twin.commands.common import kv as _kv
from twin.commands.common import names as _names


def add_arguments(p: argparse.ArgumentParser) -> None:
    from twin.commands.common import EXIT_HELP

    p.epilog = EXIT_HELP
    p.add_argument("data", nargs="+", help="records (CSV, MCAP, CAN logs); parameters are shared")
    p.add_argument("--model", default=DEFAULT_MODEL, choices=MODELS)
    p.add_argument("--outputs", help="outputs used, e.g. x or x,pA,pB (default: all present)")
    p.add_argument("--free", help="nominal free parameters (default: the phenomenological ones)")
    p.add_argument("--set", help="known parameter values NAME=VALUE,...")
    p.add_argument("--effects", help="effects known to be present (switched on, not screened)")
    p.add_argument("--candidates", help="restrict the screened catalogue to these effects")
    p.add_argument("--drive", default="auto", choices=("auto", "x_ref", "u"))
    p.add_argument("--noise-levels", help="noise std per output used as residual weights, NAME=STD,...")
    p.add_argument("--holdout", type=float, default=0.25, help="held-out tail of each record (default 0.25)")
    p.add_argument("--alpha", type=float, default=None,
                   help="family-wise significance level of the tests (default: twin.estimation.diagnose.ALPHA, 1e-3)")
    p.add_argument("--max-effects", type=int, default=3, help="most effects named (default 3)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save", metavar="FILE", help="save the extended parameter set (JSON for twin fit / tracker)")
    p.add_argument("--report", metavar="DIR", help="write plots (PNG), diagnosis.json and extended_params.json")
    p.add_argument("--no-timing-test", action="store_true",
                   help="do not test other loop timings (the controller_rate candidate); a timing stated by "
                        "--controller or --intersample is not tested either")
    add_timing_arguments(p)
    add_map_argument(p)
    p.add_argument("--json", action="store_true", help="print the diagnosis as JSON")


def run(args) -> int:
    from twin.models import get_model
    from twin.models.base import DEFAULT_TIMING
    from twin.record import Record
    from twin.models.records import load_records

    model = get_model(args.model)
    records: list[Record] = []
    reports: list = []
    for path in args.data:  # read (and refused) before the diagnosis's libraries are imported
        records.extend(load_records(path, model=model.name, reports=reports, **source_options(args, path)))
    from twin.estimation.diagnose import ALPHA, diagnose

    lost = loss_lines("diagnose", reports)
    base = model.params(effects=_names(args.effects), **_kv(args.set))
    # without --free: the phenomenological parameters less those --set holds (the oscillator's k=0 stays 0)
    free = _names(args.free) or tuple(n for n in model.PHENOMENOLOGICAL if n not in _kv(args.set))
    if not free:
        from fpdd.errors import ParameterError

        raise ParameterError(f"--set holds every nominal free parameter of {model.name} "
                             f"({', '.join(model.PHENOMENOLOGICAL)}): name those to fit with --free")
    quiet = getattr(args, "quiet", False)
    progress = None if quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    diag = diagnose(model, records, outputs=_names(args.outputs) or None, free=free,
                    base=base, candidates=_names(args.candidates) or None, holdout=args.holdout,
                    alpha=ALPHA if args.alpha is None else args.alpha, max_effects=args.max_effects,
                    noise=_kv(args.noise_levels),
                    drive=args.drive, seed=args.seed, progress=progress, timing=timing_of(args, DEFAULT_TIMING),
                    # a timing the user stated is the rig's: not renamed
                    test_timing=not (args.no_timing_test or args.controller is not None
                                     or args.intersample is not None))
    if args.report:
        from twin.reports.diagnose import write_diagnosis

        html = write_diagnosis(diag, args.report)
        if not args.json:
            print(f"report: {html}", file=sys.stderr)
    if args.save:
        jsonio.write(args.save, diag.extended_params())
    if args.json:
        dump({**diag.to_dict(), "input_lost": lost})
    else:
        print(diag.text())
        for line in lost:
            print(f"input lost: {line}")
    return EXIT_LOSS if lost else 0
