"""The ``replay`` command: inspect, convert and play rig logs.

::

    replay info LOG [--json] [--dbc FILE] [--map COL=SIGNAL[:UNIT] ...] [--topic TOPIC]
    replay convert IN OUT [--dbc FILE] [--map COL=SIGNAL[:UNIT] ...] [--topic TOPIC] [--json]
    replay play LOG --to can|zenoh [--speed 1.0]     (from replay.play, when installed)

``info`` reads the whole log through the quality gate and prints its signals, sample
count, duration (s), mean rate (Hz) and median step (s), per-signal ranges (SI), gaps,
counts of skipped records and the first problems, plus format-specific facts (MCAP
topics) from the source's ``describe()`` when it has one.  ``convert`` writes what the
reader kept to any format :func:`replay.factory.open_sink` knows.  ``--json`` prints one
JSON object on stdout for another program.  Exit status: 0 ok, 1 the input could not
be used (the message names file and record), 2 bad command line.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from replay.factory import CAN_LOG_SUFFIXES, open_sink, open_source
from twin.errors import TwinError

try:
    from replay import play as _play
except ModuleNotFoundError as exc:  # replay.play is written separately; only its absence is tolerated
    if exc.name != "replay.play":
        raise
    _play = None


def _parse_map(items: Sequence[str]) -> dict[str, str | tuple[str, str]]:
    """``["pos_mm=x:mm", "p=pA"]`` -> ``{"pos_mm": ("x", "mm"), "p": "pA"}``."""
    out: dict[str, str | tuple[str, str]] = {}
    for item in items:
        column, sep, target = item.partition("=")
        if not sep or not column or not target:
            raise argparse.ArgumentTypeError(f"--map {item!r}: expected COLUMN=SIGNAL or COLUMN=SIGNAL:UNIT")
        name, colon, unit = target.partition(":")
        out[column] = (name, unit) if colon else name
    return out


def _source_options(args: argparse.Namespace, path: str) -> dict[str, Any]:
    """Constructor options for the input's source; each option only where its format takes it."""
    suffix = Path(path).suffix.lower()
    options: dict[str, Any] = {}
    if args.dbc:
        if suffix not in CAN_LOG_SUFFIXES:
            raise argparse.ArgumentTypeError(f"--dbc applies to CAN logs ({', '.join(CAN_LOG_SUFFIXES)}), "
                                             f"not to {path}")
        options["dbc"] = args.dbc
    if args.map:
        if suffix != ".csv":
            raise argparse.ArgumentTypeError(f"--map applies to CSV input, not to {path}")
        options["mapping"] = _parse_map(args.map)
    if args.topic:
        if suffix != ".mcap":
            raise argparse.ArgumentTypeError(f"--topic applies to MCAP input, not to {path}")
        options["topic"] = args.topic
    return options


def _add_input_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dbc", metavar="FILE", help="DBC file for CAN logs (default: the MSP25 DBC shipped)")
    p.add_argument("--map", metavar="COL=SIGNAL[:UNIT]", action="append", default=[],
                   help="CSV input: rename a column and convert its unit, e.g. pos_mm=x:mm (repeatable)")
    p.add_argument("--topic", metavar="TOPIC", help="MCAP input: the samples topic (default: "
                   "/rig/signals_block if present, else /rig/signals)")


def info(path: str, **options: Any) -> dict[str, Any]:
    """Read ``path`` completely and return what ``replay info`` prints (units: s, Hz, SI)."""
    with open_source(path, **options) as src:
        n = 0
        t_first = t_last = None
        ranges: dict[str, list[float]] = {}
        steps: list[float] = []
        for block in src.chunks():
            if not len(block):
                continue
            if t_first is None:
                t_first = int(block.t_ns[0])
            if len(block) > 1 and len(steps) < 64:
                steps.append(float(np.median(np.diff(block.t_ns))))
            t_last = int(block.t_ns[-1])
            n += len(block)
            for k, v in block.signals.items():
                lo, hi = float(v.min()), float(v.max())
                r = ranges.setdefault(k, [lo, hi])
                r[0], r[1] = min(r[0], lo), max(r[1], hi)
        duration = (t_last - t_first) * 1e-9 if n else 0.0
        out: dict[str, Any] = {
            "file": path,
            "signals": list(src.signals),
            "samples": n,
            "t_first_ns": t_first,
            "t_last_ns": t_last,
            "duration_s": duration,
            "rate_hz": (n - 1) / duration if duration > 0 else None,
            "median_step_s": float(np.median(steps)) * 1e-9 if steps else None,
            "ranges": {k: {"min": v[0], "max": v[1]} for k, v in ranges.items()},
            "report": src.report.to_dict(),
            "summary": src.report.summary(),
        }
        describe = getattr(src, "describe", None)
        if callable(describe):
            out["format"] = describe()
        return out


def _print_info(d: dict[str, Any]) -> None:
    print(d["summary"])
    print(f"signals: {', '.join(d['signals'])}")
    rate = f"{d['rate_hz']:.6g} Hz" if d["rate_hz"] else "n/a"
    step = f"{d['median_step_s']:.6g} s" if d["median_step_s"] else "n/a"
    print(f"samples: {d['samples']}  duration: {d['duration_s']:.6f} s  mean rate: {rate}  median step: {step}")
    for k, r in d["ranges"].items():
        print(f"  {k:>8}: [{r['min']:.6g}, {r['max']:.6g}]")
    rep = d["report"]
    print(f"gaps: {len(rep['gaps_ns'])}")
    for a, b in rep["gaps_ns"][:10]:
        print(f"  {a * 1e-9:.6f} s -> {b * 1e-9:.6f} s ({(b - a) * 1e-9:.6g} s)")
    if rep["skipped"]:
        print("skipped: " + ", ".join(f"{k}={v}" for k, v in sorted(rep["skipped"].items())))
    for p in rep["problems"][:20]:
        print(f"  {p}")
    fmt = d.get("format")
    if fmt:
        for t in fmt.get("topics", []):
            print(f"topic {t['topic']}: schema {t['schema'] or '-'}, {t['encoding']}, {t['messages']} messages")


def convert(src_path: str, dst_path: str, **options: Any) -> dict[str, Any]:
    """Copy every sample the reader keeps from ``src_path`` to ``dst_path``; return the read report."""
    with open_source(src_path, **options) as src:
        with open_sink(dst_path) as sink:
            for block in src.chunks():
                sink.write(block)
        return {"input": src.report.to_dict(), "summary": src.report.summary(), "output": dst_path}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="replay", description="Read, convert and play rig signal logs "
                                     "(CSV, MCAP, CAN logs) as one stream of samples in SI units.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sub.add_parser("info", help="signals, duration, rates, gaps and bad records of a log",
                       description="Read a log through the quality checks and summarise it.")
    p.add_argument("log", metavar="LOG", help="log file (.csv, .mcap, .asc, .blf, .log, .trc)")
    _add_input_options(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p = sub.add_parser("convert", help="convert a log to another format",
                       description="Read IN through the quality checks and write the kept samples to OUT; "
                                   "the formats come from the suffixes.")
    p.add_argument("input", metavar="IN", help="input log")
    p.add_argument("output", metavar="OUT", help="output file (.csv, .mcap or a CAN log suffix)")
    _add_input_options(p)
    p.add_argument("--json", action="store_true", help="print the read report as one JSON object")
    if _play is not None:
        _play.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command not in ("info", "convert"):
        return int(args.func(args) or 0)
    try:
        options = _source_options(args, args.log if args.command == "info" else args.input)
    except argparse.ArgumentTypeError as exc:
        parser.error(str(exc))
    try:
        if args.command == "info":
            d = info(args.log, **options)
            if args.json:
                print(json.dumps(d, indent=1))
            else:
                _print_info(d)
        else:
            d = convert(args.input, args.output, **options)
            if args.json:
                print(json.dumps(d, indent=1))
            else:
                print(d["summary"])
                print(f"written: {args.output}")
    except TwinError as exc:
        print(f"replay: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
