"""What every ``replay`` command that reads a record shares: its input options (``--dbc``, ``--map``,
``--rate``/``--dt``, ``--topic``) and the loss warning with its exit status."""

from __future__ import annotations

import argparse
import math
import re
import sys
from typing import Any

from replay import formats
from fpdd.errors import TwinError

#: Exit status of a command that completed but lost input on the way.
EXIT_LOSS = 3


def source_options(args: argparse.Namespace, path: str) -> dict[str, Any]:
    """Constructor options for the input's source; each option only where its format takes it.

    Raises :class:`argparse.ArgumentTypeError` for an option its input does not take and
    :class:`~fpdd.errors.DataError` for a malformed ``--map``.
    """
    from replay.csvio import parse_map

    suffix = formats.suffix_of(path)
    options: dict[str, Any] = {}
    if getattr(args, "dbc", None):
        if suffix not in formats.CAN_LOG_SUFFIXES:
            raise argparse.ArgumentTypeError(f"--dbc applies to CAN logs ({', '.join(formats.CAN_LOG_SUFFIXES)}), "
                                             f"not to {path}")
        options["dbc"] = args.dbc
    if getattr(args, "map", None):
        if not formats.takes_map(path):
            raise argparse.ArgumentTypeError(f"--map applies to CSV input, text and MATLAB files and CAN logs "
                                             f"(the DBC's signals), not to {path} (its signals are named)")
        try:
            options["mapping"] = parse_map(args.map)
        except TwinError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    options.update(rate_options(args, path))
    if getattr(args, "topic", None):
        if suffix != ".mcap":
            raise argparse.ArgumentTypeError(f"--topic applies to MCAP input, not to {path}")
        options["topic"] = args.topic
    return options


def rate_options(args: argparse.Namespace, path: str) -> dict[str, float]:
    """``rate_hz`` / ``dt_s`` of a CSV without a time column, from ``--rate`` / ``--dt`` (checked by the reader).

    Raises :class:`argparse.ArgumentTypeError` when both are given or the input is not a CSV.
    """
    rate, dt = getattr(args, "rate", None), getattr(args, "dt", None)
    if rate is None and dt is None:
        return {}
    if rate is not None and dt is not None:
        raise argparse.ArgumentTypeError("--rate and --dt say the same thing: give one")
    if not formats.takes_rate(path):
        raise argparse.ArgumentTypeError(f"--rate/--dt apply to CSV, text or MATLAB input without a time column, "
                                         f"not to {path}")
    return {"rate_hz": float(rate)} if rate is not None else {"dt_s": float(dt or 0.0)}


_RATE_UNITS = {"hz": 1.0, "khz": 1e3}
_DT_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9}


def _with_unit(text: str, units: dict[str, float], what: str, default: str) -> float:
    """A positive finite number, optionally followed by one of ``units`` (``"1.6384ms"``)."""
    m = re.fullmatch(r"\s*([-+0-9.eE]+|[a-zA-Z]+)\s*([a-zA-Zµ]*)\s*", text)
    try:
        value = float(m.group(1)) if m else float("nan")
    except ValueError:
        value = float("nan")
    unit = (m.group(2) if m else "").lower() or default
    if not (math.isfinite(value) and value > 0) or unit not in units:
        raise argparse.ArgumentTypeError(f"{text!r}: expected {what} > 0, optionally with a unit "
                                         f"({', '.join(units)}), e.g. 610.35{default.replace('hz', 'Hz')}")
    return value * units[unit]


def rate_hz(text: str) -> float:
    """``--rate``: a sample rate in Hz (``610.35``, ``1kHz``)."""
    return _with_unit(text, _RATE_UNITS, "a sample rate", "hz")


def dt_s(text: str) -> float:
    """``--dt``: a sample time in s (``0.0016384``, ``1.6384ms``)."""
    return _with_unit(text, _DT_UNITS, "a sample time", "s")


def add_rate_options(p: argparse.ArgumentParser) -> None:
    """``--rate HZ`` / ``--dt S``: the sample rate of a CSV that has no time column."""
    p.add_argument("--rate", metavar="HZ", type=rate_hz, default=None,
                   help="CSV, text or MATLAB input without a time column: its sample rate (Hz, or with a unit: "
                        "1kHz); row i is at i/HZ s, e.g. --rate 610.3515625")
    p.add_argument("--dt", metavar="S", type=dt_s, default=None,
                   help="CSV, text or MATLAB input without a time column: its sample time (s, or with a unit: "
                        "1ms), instead of --rate")


#: ``--map``'s help, the one text of every command that reads a record.
MAP_HELP = ("signal NAME is COLUMN (a CSV or text column, a MATLAB variable, a CAN signal of the DBC) in UNIT "
            "(converted to SI), times GAIN plus OFFSET (each a number, optionally with a unit; a gain in A/B reads "
            "the column in B and gives A; units checked against the signal's), e.g. x=pos_mm:mm, t=time:ms, "
            "u=vir*35.15N/V, x=pos*0.001+0.2, x=MyPosSignal:mm (repeatable)")


def add_input_options(p: argparse.ArgumentParser) -> None:
    """``--dbc``, ``--map``, ``--rate``/``--dt``, ``--topic``: the options of a command that reads a record."""
    p.add_argument("--dbc", metavar="FILE", help="DBC file for CAN logs (default: the MSP25 DBC shipped)")
    p.add_argument("--map", metavar="NAME=COLUMN[:UNIT][*GAIN][+OFFSET]", action="append", default=[],
                   help=MAP_HELP)
    add_rate_options(p)
    p.add_argument("--topic", metavar="TOPIC", help="MCAP input: the samples topic (default: "
                   "/rig/signals_block if present, else /rig/signals)")


def loss_warning(report: dict[str, Any] | None) -> int:
    """Print the loss line of a read report (``ReadReport.to_dict()``); EXIT_LOSS if input was lost."""
    if not report or not report.get("lossy"):
        return 0
    print(f"replay: warning: {report['loss_line']}", file=sys.stderr)
    return EXIT_LOSS


def plain_text(doc: str | None) -> str:
    """A docstring as a command's help shows it: reStructuredText markup removed (````x```` and
    ``:role:`x``` become ``x``; a ``.. directive::`` line and a lone ``::`` are dropped)."""
    import re

    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", doc or "")
    text = re.sub(r"``([^`]+)``", r"\1", text)
    text = re.sub(r"(?m)^\s*\.\. [a-z-]+::.*\n", "", text)
    text = re.sub(r"(?m)^(\s*)::\s*$", "", text)
    return re.sub(r"(\S)::(\s*)$", r"\1:\2", text, flags=re.M)
