"""The ``replay`` command: inspect, convert, play and record rig logs.

::

    replay --version
    replay info LOG [--json] [--dbc FILE] [--map NAME=COLUMN[:UNIT] ...] [--topic TOPIC]
    replay convert IN OUT [--dbc FILE] [--map NAME=COLUMN[:UNIT] ...] [--topic TOPIC] [--json]
    replay [-q] play LOG --to can --channel can://INTERFACE/CHANNEL | --to zenoh [--key K] [--speed 1.0]
    replay record can://INTERFACE/CHANNEL|zenoh://KEY --out FILE [--duration S] [--limit N]

``info`` reads the whole log through the quality gate and prints its signals, sample
count, duration (s), mean rate (Hz) and median step (s), per-signal ranges (display units:
x in mm, pressures in MPa, u in V, T_oil in K; ``--json``: SI with ``"unit"`` beside), gaps,
counts of skipped records and the first problems, plus format-specific facts (MCAP
topics).  An MCAP file without rig samples (e.g. a twin output with ``/twin/estimate``,
``/twin/status``, ``/twin/alarm``) is described by its topics, message counts and time
span.  ``convert`` writes what the reader kept to any format of :mod:`replay.formats`.
``play`` is :mod:`replay.play`, ``record`` :mod:`replay.record`.  ``--json`` prints
one JSON object on stdout for another program (progress goes to stderr).

``--map NAME=COLUMN[:UNIT]`` (CSV input, repeatable) says which column holds signal
``NAME`` and in which unit, e.g. ``--map x=pos_mm:mm --map t=time:ms``; the parser is
:func:`replay.csvio.parse_map`, for every command that reads a record.

Exit status: 0 ok; 1 the input or output could not be used (one line on stderr naming
the file, the record or field, and what was expected); 2 bad command line; 3 the
command completed but input was lost on the way (damaged or dropped records: the
line ``replay: warning: ... input lost (...)`` on stderr says what and where).
Nothing already read is lost on an error: outputs are closed with what they got.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any
from collections.abc import Sequence

from replay import formats
from replay.options import add_input_options, loss_warning, source_options
from fpdd.errors import TwinError


try:
    from replay import play as _play
except ModuleNotFoundError as exc:  # replay.play is written separately; only its absence is tolerated
    if exc.name != "replay.play":
        raise
    _play = None  # type: ignore[assignment]  # the optional-module idiom


def version() -> str:
    from importlib import metadata

    try:
        return metadata.version("fpdd-twin")
    except metadata.PackageNotFoundError:  # running from a source tree
        return "0+unknown"


def info(path: str, **options: Any) -> dict[str, Any]:
    """Read ``path`` completely and return what ``replay info`` prints (units: s, Hz, SI)."""
    import numpy as np

    from replay.factory import open_source

    if formats.suffix_of(path) == ".mcap" and "topic" not in options:
        from replay.factory import check_readable
        from replay.mcapio import inspect

        check_readable(path)
        d = inspect(path)
        if d["samples_topic"] is None:  # no rig samples: a twin output or another writer's file
            span = (d["t_last_ns"] - d["t_first_ns"]) * 1e-9 if d["t_first_ns"] is not None else 0.0
            return {"file": path, "kind": "messages", "samples": 0, "signals": [], "duration_s": span,
                    "format": {k: d[k] for k in ("format", "summary", "topics", "samples_topic")},
                    "messages": d["messages"], "t_first_ns": d["t_first_ns"], "t_last_ns": d["t_last_ns"],
                    "report": d["report"], "summary": f"{path}: MCAP without rig samples (no /rig/signals or "
                    f"/rig/signals_block): {d['messages']} messages on {len(d['topics'])} topic(s)"}
    with open_source(path, **options) as src:
        n = 0
        t_first: int | None = None
        t_last: int | None = None
        ranges: dict[str, list[float]] = {}
        steps: list[float] = []
        jitter = 0.0  # the largest step's distance from a whole number of periods (twin.record.grid_steps)
        for block in src.chunks():
            if not len(block):
                continue
            if t_first is None:
                t_first = int(block.t_ns[0])
            if len(block) > 1 and len(steps) < 64:
                steps.append(float(np.median(np.diff(block.t_ns))))
            if len(block) > 1 and steps:
                dts = np.diff(block.t_ns).astype(np.float64)
                per = float(np.median(steps))
                jitter = max(jitter, float(np.max(np.abs(dts - np.maximum(np.rint(dts / per), 1.0) * per))))
            t_last = int(block.t_ns[-1])
            n += len(block)
            for k, v in block.signals.items():
                fin = v[np.isfinite(v)]
                if not fin.size:
                    continue
                lo, hi = float(fin.min()), float(fin.max())
                r = ranges.setdefault(k, [lo, hi])
                r[0], r[1] = min(r[0], lo), max(r[1], hi)
        # n > 0: both are set
        duration = (t_last - t_first) * 1e-9 if n and t_first is not None and t_last is not None else 0.0
        out: dict[str, Any] = {
            "file": path,
            "kind": "samples",
            "signals": list(src.signals),
            "samples": n,
            "t_first_ns": t_first,
            "t_last_ns": t_last,
            "duration_s": duration,
            "rate_hz": (n - 1) / duration if duration > 0 else None,
            "median_step_s": float(np.median(steps)) * 1e-9 if steps else None,
            "jitter_s": jitter * 1e-9,
            "ranges": {k: {"min": v[0], "max": v[1], "unit": _si_unit(k)} for k, v in ranges.items()},
            "report": src.report.to_dict(),
            "summary": src.report.summary(),
        }
        describe = getattr(src, "describe", None)
        if callable(describe):
            out["format"] = describe()
        return out


def _si_unit(name: str) -> str:
    """The SI unit a signal is read in (its :class:`~fpdd.units.SignalSpec`; ``""`` when unknown)."""
    from fpdd.units import SIGNAL_UNITS

    return SIGNAL_UNITS.get(name, "")


def _shown_range(r: dict[str, Any]) -> str:
    """``[lo, hi] unit`` of one signal's range, in its display unit (SI with its unit when none is known)."""
    from fpdd.units import display

    unit, factor = display(r.get("unit") or "")
    lo, hi = (r[k] * factor for k in ("min", "max"))
    return f"[{lo:.6g}, {hi:.6g}] {unit}".rstrip()


def _t(t_ns: int | None) -> str:
    return "-" if t_ns is None else f"{t_ns * 1e-9:.6f} s"


def _print_info(d: dict[str, Any]) -> None:
    print(d["summary"])
    rep = d["report"]
    if d.get("kind") == "messages":
        print(f"messages: {d['messages']}  time span: {d['duration_s']:.6f} s "
              f"(t = {_t(d['t_first_ns'])} .. {_t(d['t_last_ns'])})")
        for t in d["format"]["topics"]:
            print(f"topic {t['topic']}: schema {t['schema'] or '-'}, {t['encoding']}, {t['messages']} messages, "
                  f"t = {_t(t['t_first_ns'])} .. {_t(t['t_last_ns'])}")
        for p in rep["problems"][:20]:
            print(f"  {p}")
        return
    print(f"signals: {', '.join(d['signals'])}")
    rate = f"{d['rate_hz']:.6g} Hz" if d["rate_hz"] else "n/a"
    step = f"{d['median_step_s']:.6g} s" if d["median_step_s"] else "n/a"
    print(f"samples: {d['samples']}  duration: {d['duration_s']:.6f} s  mean rate: {rate}  median step: {step}")
    if d.get("jitter_s"):
        print(f"time stamps: jitter up to {d['jitter_s'] * 1e6:.4g} us, read on the grid of the median step")
    for k, r in d["ranges"].items():
        print(f"  {k:>8}: {_shown_range(r)}")
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
    """Copy every sample the reader keeps from ``src_path`` to ``dst_path``; return the read report.

    The output is opened after the input (a bad input creates no file) and closed with
    what it got if the read fails part way.
    """
    from replay.factory import open_sink, open_source

    with open_source(src_path, **options) as src:
        with open_sink(dst_path) as sink:
            for block in src.chunks():
                sink.write(block)
        return {"input": src.report.to_dict(), "summary": src.report.summary(), "output": dst_path}


class _Version(argparse.Action):
    """``--version``, looked up only when asked (``--help`` stays fast)."""

    def __call__(self, parser, namespace, values, option_string=None):  # noqa: D102
        parser.exit(message=f"{parser.prog} (fpdd-twin) {version()}\n")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors naming the command (exit status 2)."""

    def error(self, message: str):  # noqa: D102
        self.exit(2, f"{self.prog}: error: {message}\n(see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="replay", description="Read, convert, play and record rig signal logs "
                     "(CSV, MCAP, CAN logs, live CAN and Zenoh) as one stream of samples in SI units.",
                     epilog="exit status: 0 ok, 1 unusable input or output, 2 bad command line, "
                            "3 completed but input was lost (see the warning line)")
    parser.add_argument("--version", action=_Version, nargs=0, help="show the version and exit")
    parser.add_argument("-q", "--quiet", dest="quiet_all", action="store_true",
                        help="no progress on stderr (any command; also after it: replay play LOG -q ...)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    logs = ", ".join(formats.FILE_SUFFIXES)
    p = sub.add_parser("info", help="signals, duration, rates, gaps and bad records of a log",
                       description="Read a log through the quality checks and summarise it; an MCAP file without "
                                   "rig samples (a twin output) is summarised by its topics.")
    p.add_argument("log", metavar="LOG", help=f"log file ({logs})")
    add_input_options(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p = sub.add_parser("convert", help="convert a log to another format",
                       description="Read IN through the quality checks and write the kept samples to OUT; "
                                   "the formats come from the suffixes.")
    p.add_argument("input", metavar="IN", help=f"input log ({logs})")
    p.add_argument("output", metavar="OUT", help=f"output file ({logs})")
    add_input_options(p)
    p.add_argument("--json", action="store_true", help="print the read report as one JSON object")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    if _play is not None:
        _play.register(sub)
    from replay import record as _record

    _record.register(sub)
    return parser


def _run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if getattr(args, "quiet_all", False):
        args.quiet = True
    if args.command not in ("info", "convert"):
        return int(args.func(args) or 0)
    try:
        options = source_options(args, args.log if args.command == "info" else args.input)
    except argparse.ArgumentTypeError as exc:
        parser.error(str(exc))
    if args.command == "info":
        d = info(args.log, **options)
        if args.json:
            print(json.dumps(d, indent=1))
        else:
            _print_info(d)
        return loss_warning(d["report"])
    d = convert(args.input, args.output, **options)
    if args.json:
        print(json.dumps(d, indent=1))
    else:
        print(d["summary"])
        print(f"written: {args.output}")
    return loss_warning(d["input"])


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        rc = _run(parser, args)
        sys.stdout.flush()  # a closed pipe is found here, not in the interpreter's last flush
        return rc
    except TwinError as exc:
        print(f"replay: error: {exc}", file=sys.stderr)
    except KeyboardInterrupt:
        print("replay: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (``replay info LOG | head``): not an error of ours
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing more to flush at exit
        return 0
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"replay: error: {where}{exc.strerror or exc}", file=sys.stderr)
    except MemoryError:
        print("replay: error: out of memory", file=sys.stderr)
    except Exception as exc:  # noqa: BLE001 - one line, never a traceback, for a command line user
        print(f"replay: error: unexpected {type(exc).__name__}: {exc} (a bug: please report it with the command "
              "line)", file=sys.stderr)
    return 1


def entry() -> None:
    """The ``replay`` program: :func:`main`, then out of the process (:func:`fpdd.process.exit_process`)."""
    from fpdd.process import exit_process

    exit_process(main())


if __name__ == "__main__":
    entry()
