"""Loopback networking for the tests: a free TCP port for an explicit Zenoh endpoint, a session connected to it."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from contextlib import contextmanager


#: ports this process handed out: never handed out twice (a test that asks for two gets two)
_GIVEN: set[int] = set()


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now, chosen by the kernel (so parallel test workers,
    which each ask the kernel, get different ones) and never one this process handed out before."""
    for _ in range(100):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if port not in _GIVEN:
            _GIVEN.add(port)
            return port
    raise RuntimeError("no free TCP port on 127.0.0.1 after 100 tries")


@contextmanager
def connected(endpoint: str) -> Iterator:
    """A Zenoh peer session connected to ``endpoint`` (explicit, no scouting)."""
    import zenoh

    from fpdd.zenohconf import zenoh_config

    with zenoh.open(zenoh_config(connect=[endpoint])) as session:
        yield session
