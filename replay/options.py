"""What every ``replay`` command that reads a record shares: its input options (``--dbc``, ``--map``,
``--topic``) and the loss warning with its exit status."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from replay import formats
from replay.errors import TwinError

#: Exit status of a command that completed but lost input on the way.
EXIT_LOSS = 3


def source_options(args: argparse.Namespace, path: str) -> dict[str, Any]:
    """Constructor options for the input's source; each option only where its format takes it.

    Raises :class:`argparse.ArgumentTypeError` for an option its input does not take and
    :class:`~twin.errors.DataError` for a malformed ``--map``.
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
        if suffix != ".csv":
            raise argparse.ArgumentTypeError(f"--map applies to CSV input, not to {path}")
        try:
            options["mapping"] = parse_map(args.map)
        except TwinError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    if getattr(args, "topic", None):
        if suffix != ".mcap":
            raise argparse.ArgumentTypeError(f"--topic applies to MCAP input, not to {path}")
        options["topic"] = args.topic
    return options


def add_input_options(p: argparse.ArgumentParser) -> None:
    """``--dbc``, ``--map``, ``--topic``: the options of a command that reads a record."""
    p.add_argument("--dbc", metavar="FILE", help="DBC file for CAN logs (default: the MSP25 DBC shipped)")
    p.add_argument("--map", metavar="NAME=COLUMN[:UNIT]", action="append", default=[],
                   help="CSV input: signal NAME is in column COLUMN, in UNIT (converted to SI), e.g. x=pos_mm:mm, "
                        "t=time:ms (repeatable)")
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
