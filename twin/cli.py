"""The ``twin`` command: models, simulation, fitting, the paper's cases, tracking, the service.

Every subcommand has ``--help``; those whose output another program reads have
``--json`` (JSON on stdout, progress and messages on stderr).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from fpdd.errors import TwinError

#: subcommand -> (module, function adding its arguments, function running it, one-line help).  Only the
#: module of the subcommand being run is imported: ``twin --help`` imports none of them.
COMMANDS: dict[str, tuple[str, str, str, str]] = {
    "params": ("twin.commands.params", "add_arguments", "run",
               "list a model's parameters, units, bounds and effects"),
    "simulate": ("twin.commands.simulate", "add_arguments", "run",
                 "simulate an identification experiment and write CSV or MCAP"),
    "fit": ("twin.commands.fit", "add_arguments", "run", "fit free parameters to measured records (output error)"),
    "paper": ("twin.commands.paper", "add_arguments", "run",
              "regenerate the paper's cases: our estimates beside the paper's"),
    "track": ("twin.commands.track", "add_arguments", "run",
              "replay a log through the tracker: estimates, alarms, trend plot"),
    "diagnose": ("twin.commands.diagnose", "add_arguments", "run",
                 "show what the simulation gets wrong, name the cause, measure the gain"),
    "alarms": ("twin.commands.alarms", "add_arguments", "run", "print drift alarms as they come, history first"),
    "keys": ("twin.commands.keys", "add_arguments", "run", "make a rig's alarm-signing key pair (Ed25519)"),
    "serve": ("twin.commands.serve", "add_arguments", "run", "run the online twin for one or more rigs"),
    "demo": ("twin.commands.demo", "add_demo_arguments", "run_demo",
             "end-to-end demo: simulate a wearing rig, track it, alarm over Zenoh"),
    "top": ("twin.commands.top", "add_top_arguments", "run_top",
            "live terminal view of the running twins: estimates, statuses, last alarms"),
    "maintenance": ("twin.commands.maintenance", "add_arguments", "run",
                    "record a rig's maintenance: the named parameters' forecasts start afresh"),
    "warm": ("twin.commands.warm", "add_arguments", "run",
             "compile every model's kernels once (after an install), so the first command loads them"),
}


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

    if command in ("params", "alarms", "top", "keys", "maintenance"):
        return None
    here = os.path.join(os.path.dirname(__file__), "models", "__pycache__")
    if glob.glob(os.path.join(here, "*.nbi")):
        return None
    return ("twin: first run: compiling the models (about half a minute, once; later runs load them from the "
            "cache)")


def _chosen(argv: Sequence[str]) -> str | None:
    """The subcommand named in ``argv`` (the first word that is one), if any."""
    for a in argv:
        if a in COMMANDS:
            return a
    return None


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the subcommand named in ``argv`` gets its arguments (its module is imported)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    chosen = _chosen(argv)
    common = _common()
    ap = argparse.ArgumentParser(prog="twin", description=__doc__.split("\n")[0].replace("``", ""), parents=[common])
    ap.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, add, run, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_, parents=[common])
        if name == chosen:
            mod = importlib.import_module(module)
            getattr(mod, add)(p)
            p.set_defaults(func=getattr(mod, run))
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv).parse_args(argv)
    if not hasattr(args, "quiet"):
        args.quiet = False
    note = None if args.quiet else jit_note(args.command)
    if note:
        print(note, file=sys.stderr, flush=True)
    try:
        rc = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe is found here, not in the interpreter's last flush
        return rc
    except TwinError as exc:
        print(f"twin {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader went away (``twin params | head``): not an error of ours
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


def entry() -> None:
    """The ``twin`` program: :func:`main`, then out of the process (:func:`fpdd.process.exit_process`)."""
    from fpdd.process import exit_process

    exit_process(main())


if __name__ == "__main__":
    entry()
