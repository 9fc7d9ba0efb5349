"""``twin alarms``: drift alarms as they come, history first (library: :mod:`twin.service.bus`).

With ``--keys DIR`` (a trust store of ``<rig>.pub`` files, :mod:`twin.service.signing`) every
alarm of a rig with a key is verified: each printed line says ``verified``; a forged one is
not printed, a ``forged: ...`` line goes to stderr instead. Alarms of rigs without a key are
printed marked ``unverified`` (refused with ``--require-signed``). Two history queryables that
disagree are reported as ``conflict: ...`` on stderr and never merged. ``--json`` adds
``"verification"`` to each alarm object. An alarm of an earlier epoch of the rig's numbering (one
recorded off the bus in another campaign and put again), or a number received live before, is not
printed: a ``replayed: ...`` line goes to stderr (:class:`twin.service.subscriber.AlarmSubscriber`).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from datetime import datetime
from pathlib import Path

import zenoh

from fpdd.argtypes import non_negative_seconds, positive_int, positive_seconds
from fpdd import jsonio
from fpdd.errors import ConfigError, SourceError
from twin.online.events import format_alarm
from twin.service.bus import RigKeys
from twin.service.queries import live_twins
from twin.service.subscriber import AlarmSubscriber
from fpdd.zenohconf import check_endpoint, config_endpoints, open_session, zenoh_config

_DURATION_RE = re.compile(r"^(\d+(?:\.\d+)?)\s*(ms|s|m|h|d)$")
_UNIT_S = {"ms": 1e-3, "s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}


def parse_since(text: str, *, now_ns: int | None = None) -> int:
    """Parse ``--since``: an ISO 8601 time, a duration back from now, or integer ns.

    ``"2025-03-01T08:00:00+01:00"`` (naive times are local), ``"90s"``,
    ``"15m"``, ``"2h"``, ``"1d"``, ``"500ms"``, or ``"1740812400000000000"``
    (``t_ns`` as in the events). Durations count back from the wall clock, so
    they are meaningful for live rigs, not for replays of old logs.

    :returns: ``t_ns`` [ns].
    :raises ValueError: none of these forms.
    """
    text = text.strip()
    if text.isdigit():
        return int(text)
    match = _DURATION_RE.match(text)
    if match:
        now = time.time_ns() if now_ns is None else now_ns
        return max(0, now - int(float(match.group(1)) * _UNIT_S[match.group(2)] * 1e9))
    try:
        moment = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(
            f"--since: {text!r} is not an ISO 8601 time, a duration like 15m/2h/1d, or integer ns"
        ) from None
    if moment.tzinfo is None:
        moment = moment.astimezone()
    return int(round(moment.timestamp() * 1e9))


class Since(int):
    """A parsed ``--since`` (the int is ns): ``kind`` ``"wall"`` (a duration back from now or an ISO time: when
    the alarm was raised, ``wall_ns``, or its ``t_ns`` when not known), ``"t_ns"`` (integer ns: the record's
    time) or ``"t_s"`` (``t=SECONDS``: seconds from the start of the record, in :attr:`t_s`)."""

    kind: str = "wall"
    t_s: float = 0.0

    def keeps(self, event) -> bool:
        """Whether ``event`` (an AlarmEvent) is at or after this time."""
        if self.kind == "t_s":
            return event.t_s >= self.t_s
        if self.kind == "t_ns":
            return event.t_ns >= self
        return (event.wall_ns if event.wall_ns is not None else event.t_ns) >= self


def _since_argument(text: str) -> int:
    t = text.strip()
    if t.startswith("t="):  # record time from its start: t=90, t=90s, t=15m
        rest = t[2:].strip()
        match = _DURATION_RE.match(rest)
        try:
            t_s = float(match.group(1)) * _UNIT_S[match.group(2)] if match else float(rest)
        except ValueError:
            raise argparse.ArgumentTypeError(f"--since: {text!r}: t= takes seconds from the start of the record, "
                                             "e.g. t=90 or t=15m") from None
        since = Since(int(t_s * 1e9))
        since.kind, since.t_s = "t_s", t_s
        return since
    try:
        since = Since(parse_since(t))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    since.kind = "t_ns" if t.isdigit() else "wall"
    return since


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the options of ``twin alarms`` to ``parser`` (a sub-command parser)."""
    parser.add_argument("--rig", default="*", help="rig id, or '*' for every rig (default)")
    parser.add_argument(
        "--since", type=_since_argument, metavar="T",
        help="alarms from time T: raised in the last 15m/2h/1d or since an ISO 8601 time (wall clock, as "
        "printed first on each line); t=SECONDS from the start of the record (t=90, t=15m); or the record's t_ns",
    )
    parser.add_argument(
        "--since-seq", type=positive_int, metavar="N", help="history from sequence number N (per rig)"
    )
    parser.add_argument(
        "--no-history", action="store_true", help="live alarms only, do not fetch the history first"
    )
    parser.add_argument(
        "--connect", "--zenoh-connect", dest="connect", action="append", default=[], metavar="ENDPOINT",
        help="Zenoh endpoint to connect to, e.g. tls/router.site:7447 (repeatable; --zenoh-connect too, as in replay); "
        "without it or --zenoh-config, peers are discovered by multicast scouting",
    )
    parser.add_argument(
        "--mode", choices=("peer", "client"), default=None,
        help="Zenoh session mode (default: the --zenoh-config file's, else peer)",
    )
    parser.add_argument(
        "--zenoh-config", type=Path, metavar="FILE",
        help="Zenoh JSON5 configuration (TLS, credentials), e.g. deploy/twin-peer.json5",
    )
    parser.add_argument(
        "--keys", type=Path, metavar="DIR",
        help="trust store: a directory of <rig>.pub public keys (twin keys init); alarms of those rigs are "
        "verified and forged ones refused (reported on stderr)",
    )
    parser.add_argument(
        "--require-signed", action="store_true",
        help="refuse alarms of rigs without a key in --keys too (default: print them marked unverified)",
    )
    parser.add_argument("--json", action="store_true",
                        help="print one AlarmEvent JSON object per line, with \"verification\": verified|unverified")
    parser.add_argument("--count", type=positive_int, metavar="N", help="exit after N alarms")
    parser.add_argument(
        "--for", "--timeout", dest="timeout", type=positive_seconds, metavar="S",
        help="exit after S seconds (default: run until stopped; as twin top --for, --timeout too)"
    )
    parser.add_argument(
        "--wait", type=non_negative_seconds, default=10.0, metavar="S",
        help="give up (exit status 2) when no twin of --rig is reachable within S seconds "
        "(default 10; 0: wait for ever)",
    )
    return parser


def wait_for_twin(session: zenoh.Session, rig: str, wait_s: float, where: str) -> list[str]:
    """The rigs whose twin is alive, waiting up to ``wait_s``; SourceError naming ``where`` if none."""
    deadline = time.monotonic() + wait_s
    while True:
        remaining = deadline - time.monotonic()
        rigs = live_twins(session, rig, timeout=max(0.2, min(1.0, remaining)))
        if rigs:
            return rigs
        if time.monotonic() >= deadline:
            raise SourceError(f"no twin reachable through {where} within {wait_s:g} s "
                              f"(no liveliness token on {RigKeys(rig).twin})")


def run(args: argparse.Namespace) -> int:
    """``twin alarms``: print alarms as they come, the history first.

    :param args: parsed by a parser set up with :func:`add_arguments`.
    :returns: exit status: 0, or 1 when ``--count`` alarms did not arrive within ``--timeout``.
        Forgeries and conflicts are reported on stderr and do not change the status.
    :raises ConfigError: a bad option or Zenoh file (one line naming it).
    :raises SourceError: the session cannot be opened, or no twin is reachable within ``--wait``.
    """
    from twin.service.signing import TrustStore

    if args.require_signed and args.keys is None:
        raise ConfigError("--require-signed: needs --keys DIR (the rigs' public keys)")
    trust = TrustStore(args.keys) if args.keys is not None else None
    scouting = True if not args.connect and args.zenoh_config is None else None
    for e in args.connect:
        check_endpoint(e, "--connect")
    config = zenoh_config(
        mode=args.mode,
        connect=args.connect,
        multicast_scouting=scouting,
        config_file=args.zenoh_config,
    )
    _, connect = config_endpoints(config)
    where = ", ".join(connect) if connect else "multicast scouting"
    deadline = None if args.timeout is None else time.monotonic() + args.timeout
    printed = 0
    session = open_session(config, "twin alarms")
    with session:
        if args.wait > 0:
            wait_for_twin(session, args.rig, args.wait, where)
        with AlarmSubscriber(
            session,
            rig=args.rig,
            since_seq=args.since_seq,
            since_t_ns=args.since if getattr(args.since, "kind", "t_ns") == "t_ns" else None,
            history=not args.no_history,
            trust=trust,
            require_signed=args.require_signed,
            on_report=lambda _kind, line: print(line, file=sys.stderr, flush=True),
        ) as subscriber:
            reported = 0
            while args.count is None or printed < args.count:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    break
                try:
                    event = subscriber.recv(timeout=remaining)
                except TimeoutError:
                    break
                for rig, first, last in subscriber.missed[reported:]:
                    print(f"warning: {rig} alarms seq {first}..{last} lost and not in history", file=sys.stderr)
                reported = len(subscriber.missed)
                if args.since is not None and isinstance(args.since, Since) and not args.since.keeps(event):
                    continue
                checked = subscriber.verification.get((event.rig, event.seq), "unverified")
                if args.json:
                    line = jsonio.dumps({**event.to_dict(), "verification": checked}, indent=None, sort_keys=True)
                else:
                    line = f"{format_alarm(event)} [{checked}]"
                print(line, flush=True)
                printed += 1
    return 1 if args.count is not None and printed < args.count else 0
