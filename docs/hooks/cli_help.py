"""MkDocs hook: the command-line reference is generated at build time from the real argparse parsers.

A page that holds the line ``<!-- cli-help -->`` gets, in its place, the ``--help`` of ``twin``, of every ``twin``
subcommand (and their own subcommands, such as ``twin keys init``), and of ``replay`` and its subcommands, each
under its own heading. Nothing is copied by hand, so the page cannot drift from the code.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator

MARKER = "<!-- cli-help -->"


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _walk(prog: str, parser: argparse.ArgumentParser, level: int) -> Iterator[str]:
    yield f"{'#' * level} `{prog}`\n"
    yield "```text\n" + parser.format_help().rstrip() + "\n```\n"
    for name, sub in _subparsers(parser).items():
        yield from _walk(f"{prog} {name}", sub, level + 1)


def _twin() -> Iterator[str]:
    from twin import cli

    top = cli.build_parser([])
    yield "## `twin`\n"
    yield "```text\n" + top.format_help().rstrip() + "\n```\n"
    for name in cli.COMMANDS:
        full = cli.build_parser([name])  # only the named subcommand's module adds its arguments
        yield from _walk(f"twin {name}", _subparsers(full)[name], 3)


def _replay() -> Iterator[str]:
    from replay import cli

    yield from _walk("replay", cli.build_parser(), 2)


def generate() -> str:
    """The whole reference: every command's ``--help``, as argparse prints it at 100 columns."""
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        return "\n".join([*_twin(), *_replay()])
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, generate())
