"""``twin fit --compare``: several candidate models (effect sets) fitted on one record and compared on held-out
data, as MATLAB's ``compare(data, sys1, sys2, ...)``; ``twin fit`` prints the ``present``-style summary."""

from __future__ import annotations

import sys

COMPARE_HELP = ("compare candidate models instead of one fit: a comma-separated list, each candidate "
                "[MODEL:]EFFECT+EFFECT or 'none' (e.g. none,viscous_friction,viscous_friction+laminar_leakage); "
                "each is fitted on the records (their first halves without --validate) and simulated on the "
                "held-out data; Fit %%, held-out RMS, AIC and BIC per candidate, the lowest BIC marked best; "
                "every candidate fits --free (default the phenomenological parameters, less those --set) and its "
                "effects' own parameters, and holds --set and --params values")
VALIDATE_HELP = "held-out records for --compare (default: the second half of each record)"


def add_arguments(p) -> None:
    p.add_argument("--compare", metavar="CANDIDATES", help=COMPARE_HELP)
    p.add_argument("--validate", metavar="FILE", action="append", help=VALIDATE_HELP)


def run_compare(args, model, records, base, timing, lost) -> int:
    """Run ``--compare`` and print the table (text, ``--json``; ``--report DIR``: DIR/compare_report.html)."""
    from replay.options import EXIT_LOSS
    from twin.commands.common import dump, kv, names, progress, source_options
    from twin.estimation.compare import Candidate, compare_models
    from twin.models.records import load_records
    from twin.reports import summary as S

    cands = [Candidate.parse(c, model.name) for c in args.compare.split(",") if c.strip()]
    validation = None
    if args.validate:
        validation = []
        for path in args.validate:
            validation.extend(load_records(path, model=model.name, **source_options(args, path)))
    cmp = compare_models(cands, records, validation, base=base, drive=args.drive, timing=timing,
                         n_starts=args.starts, seed=args.seed, outputs=names(args.outputs) or None,
                         progress=None if args.json else progress(args), free=names(args.free) or None,
                         known=tuple(kv(args.set)))
    report = S.compare_report(cmp, args.report) if args.report else None
    if args.json:
        d = S.compare_json(cmp)
        d["input_lost"] = lost
        if report:
            d["report"] = report
        dump(d)
    else:
        print(S.compare_text(cmp))
        if report:
            print(f"report: {report}", file=sys.stderr)
    return EXIT_LOSS if lost else 0
