"""Asking the running twins over Zenoh: their latest estimates, statuses and forecasts (plain ``get`` on the
latest-value queryables of :class:`twin.service.bus.TwinPublisher`) and which twins are alive."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import Any

import zenoh

from fpdd.errors import ConfigError, DataError
from twin.online.events import EstimateEvent, StatusEvent, validate
from twin.service.bus import RigKeys

__all__ = ["fetch_forecasts", "fetch_latest", "live_twins"]

log = logging.getLogger(__name__)


def fetch_forecasts(session: zenoh.Session, rig: str = "*", *, timeout: float = 5.0) -> list[dict[str, Any]]:
    """The latest forecast message of each matching running twin (a plain ``get`` on ``fpdd/<rig>/forecast``),
    sorted by rig; a reply that does not follow :data:`twin.online.events.forecast.FORECAST_SCHEMA` is left out (logged).
    """
    from twin.online.events.forecast import FORECAST_SCHEMA

    out = []
    for reply in session.get(RigKeys(rig).forecast, target=zenoh.QueryTarget.ALL, timeout=timeout):
        if reply.ok is None:
            continue
        try:
            d = json.loads(reply.ok.payload.to_string())
            validate(d, FORECAST_SCHEMA, "forecast")
        except (DataError, ValueError) as exc:
            log.warning("%s: rejected forecast reply: %s", reply.ok.key_expr, exc)
            continue
        out.append(d)
    return sorted(out, key=lambda d: d["rig"])


def fetch_latest(
    session: zenoh.Session,
    what: str,
    rig: str = "*",
    *,
    timeout: float = 5.0,
) -> list[EstimateEvent | StatusEvent]:
    """The latest estimate or status of each matching running twin (a plain ``get``).

    :param what: ``"estimate"`` or ``"status"``.
    :param rig: a rig id or ``"*"``.
    :param timeout: how long to wait for replies [s].
    :returns: one event per twin that has published one, sorted by rig.
    """
    keys = RigKeys(rig)
    parse: Callable[[Any], EstimateEvent | StatusEvent]
    if what == "estimate":
        key, parse = keys.estimate, EstimateEvent.from_dict
    elif what == "status":
        key, parse = keys.status, StatusEvent.from_dict
    else:
        raise ConfigError(f"what: {what!r} is not one of ['estimate', 'status']")
    events = []
    for reply in session.get(key, target=zenoh.QueryTarget.ALL, timeout=timeout):
        if reply.ok is not None:
            events.append(parse(json.loads(reply.ok.payload.to_string())))
    return sorted(events, key=lambda e: e.rig)


def live_twins(session: zenoh.Session, rig: str = "*", *, timeout: float = 5.0) -> list[str]:
    """The rigs whose twin is currently alive (liveliness tokens ``fpdd/<rig>/twin``), sorted."""
    rigs = set()
    for reply in session.liveliness().get(RigKeys(rig).twin, timeout=timeout):
        if reply.ok is not None:
            rigs.add(RigKeys.rig_of(reply.ok.key_expr))
    return sorted(rigs)
