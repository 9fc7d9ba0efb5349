"""The project's one Zenoh configuration: endpoints checked, a JSON5 file honoured, flags that override the
file only when given, sessions opened with a one-line error naming the endpoint.

Every Zenoh user of both packages (live sources and sinks, ``replay play``/``record``, the twin's bus, the
service, ``twin alarms``/``top``) builds its configuration here.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zenoh

from fpdd.errors import ConfigError, SourceError


#: link protocols of Zenoh 1.x endpoints; those before ``unixsock-stream`` need ``HOST:PORT``
ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")
_ENDPOINT_RE = re.compile(r"^(?P<proto>[A-Za-z][A-Za-z0-9-]*)/(?P<addr>[^?#]+)(?P<rest>[?#].*)?$")


def check_endpoint(endpoint: Any, where: str, *, listen: bool = False) -> str:
    """``endpoint`` if it is a Zenoh endpoint ``PROTOCOL/HOST:PORT``, else a one-line ConfigError.

    :param where: what names the value in the message (file and key, or a CLI option).
    :param listen: a listening endpoint may use port 0 (any free port).
    """
    example = "expected PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447"
    if not isinstance(endpoint, str):
        raise ConfigError(f"{where}: {endpoint!r} is not an endpoint string ({example})")
    m = _ENDPOINT_RE.match(endpoint)
    if m is None:
        raise ConfigError(f"{where}: {endpoint!r} is not an endpoint ({example})")
    proto, addr = m.group("proto"), m.group("addr")
    if proto not in ENDPOINT_PROTOCOLS:
        raise ConfigError(f"{where}: {endpoint!r}: unknown protocol {proto!r} "
                          f"(one of {', '.join(ENDPOINT_PROTOCOLS)})")
    if proto in ("tcp", "udp", "tls", "quic", "ws"):
        host, sep, port = addr.rpartition(":")
        if not sep or not host or host in ("[", "[]"):
            raise ConfigError(f"{where}: {endpoint!r} has no HOST:PORT ({example})")
        if not port.isdigit() or not (0 if listen else 1) <= int(port) <= 65535:
            raise ConfigError(f"{where}: {endpoint!r}: port {port!r} is not in "
                              f"{0 if listen else 1}..65535 ({example})")
    return endpoint


def zenoh_config(
    mode: str | None = None,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool | None = None,
    *,
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """The project's one Zenoh configuration builder.

    Without ``config_file``: a session in ``mode`` (default ``peer``) with
    exactly these endpoints and multicast scouting off unless asked for.
    With ``config_file`` (JSON5: TLS, access control, ...): the file as it is,
    and only what the caller gives explicitly overrides it: ``mode`` when not
    ``None``, ``listen``/``connect`` when non-empty, ``multicast_scouting``
    when not ``None``. A default never overrides the file.

    :raises ConfigError: an unknown mode, a client asked to listen, an endpoint
        that is not ``PROTOCOL/HOST:PORT``, or a file Zenoh cannot read (named).
    """
    if mode is not None and mode not in ("peer", "client", "router"):
        raise ConfigError(f"mode: {mode!r} is not one of ['peer', 'client', 'router']")
    for e in listen:
        check_endpoint(e, "listen", listen=True)
    for e in connect:
        check_endpoint(e, "connect")
    if config_file:
        path = Path(config_file)
        if not path.is_file():
            what = "is a directory" if path.is_dir() else "does not exist"
            raise ConfigError(f"{config_file}: cannot read the Zenoh configuration: {what}")
        try:
            config = zenoh.Config.from_file(str(path))
        except (zenoh.ZError, ValueError) as exc:
            raise ConfigError(f"{config_file}: invalid Zenoh configuration: {zenoh_text(exc)}") from exc
    else:
        config = zenoh.Config()
        mode = mode or "peer"
        multicast_scouting = bool(multicast_scouting)
    effective = mode or json.loads(config.get_json("mode") or '"peer"') or "peer"
    if effective == "client" and listen:
        raise ConfigError(f"listen: a client cannot listen (got {list(listen)!r}); use mode 'peer'")
    try:
        if mode is not None:
            config.insert_json5("mode", json.dumps(mode))
        if listen or not config_file:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect or not config_file:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if multicast_scouting is not None:
            config.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    except zenoh.ZError as exc:
        where = f"{config_file}: " if config_file else ""
        raise ConfigError(f"{where}invalid Zenoh configuration: {zenoh_text(exc)}") from exc
    return config


def config_endpoints(config: zenoh.Config) -> tuple[list[str], list[str]]:
    """``(listen, connect)`` endpoints of a Zenoh configuration (for messages)."""
    try:
        mode = json.loads(config.get_json("mode")) or "peer"
    except (zenoh.ZError, ValueError):
        mode = "peer"

    def endpoints(key: str) -> list[str]:
        try:
            value = json.loads(config.get_json(key))
        except (zenoh.ZError, ValueError):
            return []
        if isinstance(value, dict):  # per-mode endpoints: {"router": [...], "peer": [...], "client": [...]}
            value = value.get(mode) or []
        return [str(e) for e in value or []]

    return endpoints("listen/endpoints"), endpoints("connect/endpoints")


_RUST_LOCATION = re.compile(r"\s*at /\S+?\.rs:\d+\.?")


def zenoh_text(exc: BaseException) -> str:
    """A Zenoh (Rust) error message without its source locations, on one line."""
    text = _RUST_LOCATION.sub("", str(exc)).replace("\n", " ").strip()
    return re.sub(r"\s+", " ", text).strip(" .[]")


def open_session(config: zenoh.Config, who: str = "twin") -> zenoh.Session:
    """``zenoh.open(config)``; a failure becomes one line naming the endpoint and the cause.

    :raises SourceError: a listen endpoint in use or not local, a router
        unreachable, a host name that does not resolve, a certificate missing.
    """
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise SourceError(f"{who}: {describe_open_error(config, exc)}") from None


def describe_open_error(config: zenoh.Config, exc: BaseException) -> str:
    text = zenoh_text(exc)
    listen, connect = config_endpoints(config)
    m = re.search(r"bound to (\S+?):? ", text)
    if "Address already in use" in text:
        ep = m.group(1) if m else ", ".join(listen)
        return f"cannot listen on {ep}: the address is already in use (another twin serve or zenohd?)"
    if "Cannot assign requested address" in text or "not available" in text:
        ep = m.group(1) if m else ", ".join(listen)
        return f"cannot listen on {ep}: not an address of this host"
    if "Unable to connect to any of" in text:
        return (f"cannot reach {', '.join(connect) or 'any Zenoh router'}: nothing answers there "
                "(is the router or the twin running, and the address right?)")
    if "lookup address" in text or "Name or service not known" in text:
        return f"cannot resolve the host name of {', '.join(listen + connect)}: {text}"
    return f"cannot open a Zenoh session (listen {listen or 'none'}, connect {connect or 'none'}): {text}"
