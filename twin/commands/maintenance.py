"""``twin maintenance``: record a maintenance event of a running rig (library: :mod:`twin.service.maintenance`).

The service records it in the rig's maintenance log (beside its alarm journal, kept across restarts) and the
rig's twin starts the forecasts of the named parameters afresh: their history no longer predicts their future
(a standing ``early`` alarm returns). The drift test's healthy band is kept.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fpdd.argtypes import positive_seconds


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", required=True, help="the rig's id, as in rigs.toml")
    p.add_argument("--parameter", action="append", required=True, metavar="NAME",
                   help="a tracked parameter that was serviced, e.g. CdAleak (repeatable)")
    p.add_argument("--note", default="", help="what was done, one line (kept with the event)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable); without --connect "
                   "or --zenoh-config, the service is found by multicast scouting")
    p.add_argument("--mode", choices=("peer", "client"), default=None,
                   help="Zenoh session mode (default: the --zenoh-config file's, else peer)")
    p.add_argument("--zenoh-config", type=Path, metavar="FILE", help="Zenoh JSON5 configuration (TLS, credentials)")
    p.add_argument("--timeout", type=positive_seconds, default=10.0, metavar="S",
                   help="give up (exit status 2) when no twin of the rig answers within S seconds (default 10)")
    p.add_argument("--json", action="store_true", help="print the event as recorded, as JSON")


def run(args) -> int:
    from fpdd.zenohconf import check_endpoint, config_endpoints, open_session, zenoh_config
    from fpdd.errors import SourceError
    from twin.service.bus import _check_rig
    from twin.service.maintenance import send_maintenance

    _check_rig(args.rig, wildcard=False)
    for e in args.connect:
        check_endpoint(e, "--connect")
    scouting = True if not args.connect and args.zenoh_config is None else None
    config = zenoh_config(mode=args.mode, connect=args.connect, multicast_scouting=scouting,
                          config_file=args.zenoh_config)
    _, connect = config_endpoints(config)
    where = ", ".join(connect) if connect else "multicast scouting"
    session = open_session(config, "twin maintenance")
    try:
        ev = send_maintenance(session, args.rig, args.parameter, args.note, timeout=args.timeout)
    except SourceError as exc:
        raise SourceError(f"{exc} (via {where})") from None
    finally:
        session.close()
    if args.json:
        print(json.dumps(ev))
    else:
        note = f" ({ev['note']})" if ev.get("note") else ""
        print(f"rig {ev['rig']}: maintenance #{ev['seq']} recorded: {', '.join(ev['parameters'])}{note}; "
              "their forecasts start afresh")
    sys.stdout.flush()
    return 0
