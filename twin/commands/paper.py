"""``twin paper``: regenerate the paper's cases: our estimates beside the paper's."""

from __future__ import annotations

import sys

from twin.commands.common import add_timing_arguments, timing_of
from twin.commands.common import dump as _dump
from twin.commands.common import progress as _progress

HELP = "regenerate the paper's cases: our estimates beside the paper's"


def add_arguments(p) -> None:
    p.add_argument("--noise", action="store_true", help="with realistic sensor noise (x: 2 um, y: 1 um)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--plot", metavar="DIR", help="write the comparison plot (PNG) to DIR")
    p.add_argument("--report", metavar="DIR", help="write DIR/paper_report.html: the cases, our errors beside "
                   "the paper's (one self-contained file)")
    add_timing_arguments(p)
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from twin.estimation.paper import format_rows, run_all

    rows, elapsed = run_all(noisy=args.noise, seed=args.seed, progress=None if args.json else _progress(args),
                            timing=timing_of(args))
    if args.plot:
        from twin.reports.plots import paper_table

        p = paper_table(rows, args.plot)
        if not args.json:
            print(f"plot: {p}", file=sys.stderr)
    if args.report:
        from twin.reports import paper_report

        p = paper_report(rows, args.report, elapsed_s=elapsed)
        if not args.json:
            print(f"report: {p}", file=sys.stderr)
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
