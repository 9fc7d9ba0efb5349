"""``twin serve --config RIG.toml``: the online twin for every rig of a configuration, until told to stop
(library: :mod:`twin.service.serve`)."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import threading

from replay.options import EXIT_LOSS
from fpdd.errors import TwinError
from twin.online.events import AlarmEvent, format_alarm
from twin.service.config import ServiceConfig, load_config, with_commission_s


def add_arguments(p: argparse.ArgumentParser) -> None:
    from twin.commands.common import EXIT_HELP

    p.epilog = EXIT_HELP
    p.add_argument("--config", required=True, metavar="RIG.toml",
                   help="rig configuration (every key: the documentation site's rigs.toml page, "
                        "docs/reference/rigs-toml.md; a [failover] table shares its rigs with other services, one "
                        "runs each: docs/guide/failover.md)")
    p.add_argument("--json", action="store_true", help="print per-rig statistics as JSON at the end (input_lost: "
                   "what a replayed log's reader lost, \"\" when nothing)")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"),
                   help="console messages from this level up (default info)")
    p.add_argument("--foxglove", type=int, metavar="PORT", help="also serve a live view to Foxglove on "
                   "ws://HOST:PORT (0: any free port), rig signals included; a layout whose rig is the first "
                   "rig served is written to the journal directory")
    p.add_argument("--foxglove-signals-hz", type=float, default=50.0, metavar="HZ",
                   help="with --foxglove: rig signal samples shown per second and rig (default 50)")
    p.add_argument("--foxglove-host", default="127.0.0.1", help="address of the Foxglove server (default loopback)")
    p.add_argument("--commission-s", type=float, metavar="SECONDS",
                   help="commission every rig without commission/commission_s on its first SECONDS in service "
                        "(as commission_s in rigs.toml; a commissioning saved by an earlier run is reused)")


def startup_line(cfg: ServiceConfig, workers: int) -> str:
    from fpdd.zenohconf import config_endpoints
    from twin.service.serve import zenoh_settings

    from twin.service.checkpoints import journal_path

    conf = zenoh_settings(cfg)
    import json as _json

    mode = _json.loads(conf.get_json("mode") or '"peer"')
    listen, connect = config_endpoints(conf)
    rigs = ", ".join(f"{r.name} <- {r.source}" for r in cfg.rigs)
    where = "in this process" if workers == 0 else f"over {workers} worker process(es)"
    return (f"{len(cfg.rigs)} rig(s) {where}: {rigs}; zenoh {mode}, listen {listen or 'none'}, "
            f"connect {connect or 'none'}; journal {journal_path(cfg, '<rig>').parent}/<rig>.db")


def run(args) -> int:
    from twin.service.console import install

    console = install(getattr(logging, args.log_level.upper()))  # a stuck console never stalls the service
    try:
        return _run(args, console)
    finally:
        console.close()


def _run(args, console) -> int:
    import json
    import signal

    from twin.service.serve import open_service_session, serve

    from twin.service.fleet import Fleet, check_journal_dir, check_sources

    cfg = with_commission_s(load_config(args.config), getattr(args, "commission_s", None))
    if args.foxglove is not None:  # the runners put their rig's signals on the bus for the view
        cfg = dataclasses.replace(cfg, signals_hz=max(0.0, args.foxglove_signals_hz))
    check_journal_dir(cfg)
    check_sources(cfg)
    stop = threading.Event()

    def on_signal(signum, frame) -> None:  # noqa: ARG001
        if not stop.is_set():
            console.line(f"twin serve: {signal.Signals(signum).name} received, stopping (checkpointing every rig)")
        stop.set()

    def show(ev: AlarmEvent) -> None:
        console.line(f"twin serve: {format_alarm(ev, wall_clock=False)}")

    session = open_service_session(cfg)
    summaries: dict = {}
    view = None
    # installed once the session is open, restored in the finally below (a session that cannot open, a port in
    # use, leaves a caller's handlers as they were)
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        if args.foxglove is not None:
            from twin.service.live_view import LiveView

            from pathlib import Path

            from twin.service.live_view import write_layout

            view = LiveView(args.foxglove_host, args.foxglove, bands={r.name: r.baseline for r in cfg.rigs},
                            model=cfg.rigs[0].model, signal_rate_hz=max(0.0, args.foxglove_signals_hz))
            view.follow(session)  # every rig's estimate, status, alarm and signals as published, workers included
            layout = write_layout(str(Path(cfg.journal_dir) / "foxglove-layout.json"), rig=cfg.rigs[0].name,
                                  model=cfg.rigs[0].model)
            console.line(f"twin serve: Foxglove live view on ws://{args.foxglove_host}:{view.port} "
                         f"(layout for rig {cfg.rigs[0].name}: {layout})")
        workers = Fleet(cfg, session, stop).worker_count
        console.line(f"twin serve: {startup_line(cfg, workers)}")
        error = None
        try:
            stats = serve(cfg, stop, on_alarm=show, session=session, summaries=summaries)
        except TwinError as exc:
            error, stats = exc, {k: v.stats for k, v in summaries.items()}
    finally:
        if view is not None:
            view.close()
        session.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    lost = {}
    for name in (r.name for r in cfg.rigs):
        if name in summaries:
            console.line(f"twin serve: summary {summaries[name].line()}")
            if summaries[name].input_lost:
                lost[name] = summaries[name].input_lost
    for name, line in lost.items():
        console.line(f"twin serve: warning: rig {name}: {line}")
    if args.json:
        print(json.dumps({k: {**dataclasses.asdict(v), "input_lost": lost.get(k, "")} for k, v in stats.items()},
                         indent=2))
    if error is not None:
        raise error
    return EXIT_LOSS if lost else 0
