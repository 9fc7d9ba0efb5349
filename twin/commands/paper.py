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
    p.add_argument("--case", metavar="NAME,...", help="only these cases, e.g. osc-A,rig-A-wn (default: all)")
    p.add_argument("--plot", metavar="DIR", help="write the comparison plot (PNG) to DIR")
    p.add_argument("--report", metavar="DIR", help="write DIR/paper_report.html: the cases, our errors beside "
                   "the paper's (one self-contained file)")
    add_timing_arguments(p)
    p.add_argument("--json", action="store_true")


def table(rows: list[dict]) -> str:
    """The cases for a person: each parameter in its display unit (``twin params``), the unit in a column."""
    from twin.reports.units import Shown, fmt

    out = [f"{'case':<14} {'param':<8} {'true':>12} {'estimate':>14} {'std':>10} {'unit':<6} {'error %':>10} "
           f"{'paper est':>11} {'paper err %':>11} {'time s':>7}"]
    for r in rows:
        sh = Shown(r["parameter"], r.get("model"), r.get("unit"))
        pe = "-" if r["paper_estimate"] is None else fmt(sh(r["paper_estimate"]), 6)
        unit = "" if sh.unit in ("1", "") else sh.unit
        out.append(f"{r['case']:<14} {r['parameter']:<8} {fmt(sh(r['true']), 6):>12} {fmt(sh(r['estimate']), 8):>14} "
                   f"{fmt(sh(r['std']), 3):>10} {unit:<6} {r['error_pct']:>10.2e} {pe:>11} "
                   f"{r['paper_error_pct']:>11.4g} {r['fit_time_s']:>7.2f}")
    return "\n".join(out)


def run(args) -> int:
    from twin.paper.cases import CASES, run_all

    cases = None
    if args.case:
        known = {c.case for c in CASES}
        wanted = [n.strip() for n in args.case.split(",") if n.strip()]
        unknown = [n for n in wanted if n not in known]
        if unknown:
            from fpdd.errors import ParameterError

            raise ParameterError(f"--case: no case {', '.join(unknown)} (the cases: {', '.join(sorted(known))})")
        cases = [c for c in CASES if c.case in wanted]
    rows, elapsed = run_all(noisy=args.noise, seed=args.seed, progress=None if args.json else _progress(args),
                            timing=timing_of(args), **({"cases": cases} if cases else {}))
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
    print(table(rows))
    worse = [r for r in rows if round(r["error_pct"], 4) > r["paper_error_pct"] or r["error_pct"] > 0.01]
    if args.noise:
        outside = [r for r in rows if r["z"] > 3]
        print(f"\nwith sensor noise (x: 2 um): {len(rows) - len(outside)}/{len(rows)} estimates within 3 std of the truth")
    else:
        print(f"\nnoise-free: {len(rows) - len(worse)}/{len(rows)} errors at most the paper's (to its printed 4 decimals) and at most 0.01 %")
    print(f"all cases in {elapsed:.2f} s (the paper: minutes per case)")
    return 0
