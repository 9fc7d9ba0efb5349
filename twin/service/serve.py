"""Run a service configuration: every rig of ``rigs.toml`` (in threads or worker processes, :mod:`twin.service.fleet`)
on one Zenoh session, until their logs end or the service is told to stop."""

from __future__ import annotations

import threading
from collections.abc import Callable

from fpdd.errors import TwinError
from twin.online.events import AlarmEvent
from twin.service.config import ServiceConfig
from twin.service.rig import RigStats, RigTwin


def serve(cfg: ServiceConfig, stop: threading.Event | None = None,
          on_alarm: Callable[[AlarmEvent], None] | None = None, session=None,
          twins: dict[str, RigTwin] | None = None, *, summaries: dict | None = None) -> dict[str, RigStats]:
    """Run every rig of ``cfg`` until their logs end or ``stop`` is set; returns per-rig stats.

    A live rig runs until ``stop``. ``session``: an open Zenoh session to use
    (default: open one from ``cfg`` and ``ZENOH_CONFIG``); ``twins``: a dict
    that receives each rig's :class:`RigTwin` (rigs then run in threads of this
    process); ``summaries``: a dict that receives each rig's
    :class:`twin.service.outcome.RigSummary`, failures included.

    :raises ConfigError: the configuration cannot run (journal directory, a log missing).
    :raises SourceError: the Zenoh session cannot be opened (one line naming the endpoint).
    :raises TwinError: a rig failed (``rig NAME failed: cause``) after the others stopped.
    """
    from twin.service.fleet import Fleet, check_journal_dir, check_sources

    stop = stop or threading.Event()
    check_journal_dir(cfg)
    check_sources(cfg)
    own_session = session is None
    if own_session:
        session = open_service_session(cfg)
    try:
        if cfg.failover is not None:  # rigs shared with other services (twin.service.failover)
            from twin.service.failover import serve_failover

            result = serve_failover(cfg, session, stop, on_alarm)
        else:
            result = Fleet(cfg, session, stop, on_alarm=on_alarm, keep=twins).run()
    finally:
        if own_session:
            session.close()
    if summaries is not None:
        summaries.update(result)
    failed = [s for s in result.values() if s.state == "failed"]
    if failed:
        raise TwinError("; ".join(f"rig {s.rig} failed: {s.message}" for s in failed))
    return {name: s.stats for name, s in result.items()}


def zenoh_settings(cfg: ServiceConfig):
    """The service's Zenoh configuration: ``ZENOH_CONFIG`` (if set), then what ``[zenoh]`` gives explicitly."""
    import os

    from fpdd.zenohconf import zenoh_config
    from fpdd.errors import ConfigError

    file = os.environ.get("ZENOH_CONFIG") or None
    try:
        conf = zenoh_config(cfg.zenoh_mode, cfg.listen, cfg.connect, None, config_file=file)
        if cfg.failover is not None:  # a host silent this long is dead: its rigs' tokens go (twin.service.ownership)
            conf.insert_json5("transport/link/tx/lease", str(int(cfg.failover.lease_s * 1000)))
        return conf
    except ConfigError as exc:
        text = str(exc)
        raise ConfigError(f"ZENOH_CONFIG={text}" if file and text.startswith(file) else f"{cfg.path}: zenoh: {text}") \
            from None


def open_service_session(cfg: ServiceConfig):
    from fpdd.zenohconf import open_session

    return open_session(zenoh_settings(cfg), "twin serve")
