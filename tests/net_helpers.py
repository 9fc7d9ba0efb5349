"""Loopback networking for the tests: a free TCP port for an explicit Zenoh endpoint, a session connected to it."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from contextlib import contextmanager


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def connected(endpoint: str) -> Iterator:
    """A Zenoh peer session connected to ``endpoint`` (explicit, no scouting)."""
    import zenoh

    from fpdd.zenohconf import zenoh_config

    with zenoh.open(zenoh_config(connect=[endpoint])) as session:
        yield session
