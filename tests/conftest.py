"""Shared fixtures: records of the independent reference simulator (``tests/reference``), and a Zenoh peer on
loopback (``endpoint``, ``hub``) that the bus tests' sessions connect to.

Records are cached on disk (``$FPDD_REFCACHE``; the tests default it to ``~/.cache/fpdd-twin/refcache``, or under
``$XDG_CACHE_HOME``: outside the clone, so a fresh clone or a CI run on the same machine finds the records an
earlier run simulated) under a hash of their full spec and of the simulator's source (a changed simulator never
reads an old record), so a session generates each one once; misses of one call are simulated in two worker
processes.  Parallel test workers (pytest-xdist) share the cache (files are renamed into
place) and each test gets its own port (:func:`net_helpers.free_port`) and temporary directory.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence

import pytest

if not os.environ.get("FPDD_REFCACHE"):  # before any record is read; worker processes inherit it
    os.environ["FPDD_REFCACHE"] = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(
        os.path.expanduser("~"), ".cache"), "fpdd-twin", "refcache")

from reference import Record, batch, msp25_spec, oscillator_spec  # noqa: F401, E402  (re-exported for tests)


def get_records(specs: Sequence[dict], workers: int = 2) -> list[Record]:
    """Records of ``specs`` (from ``msp25_spec`` / ``oscillator_spec``), through the disk cache."""
    return batch(specs, workers=workers)


@pytest.fixture(scope="session")
def reference_records():
    """The function ``get_records(specs) -> list[Record]`` (cached)."""
    return get_records


@pytest.fixture
def endpoint() -> str:
    """An explicit loopback endpoint on a free port (scouting stays off in every session's configuration)."""
    from net_helpers import free_port

    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def hub(endpoint: str) -> Iterator:
    """The listening peer every other session connects to (a plain peer: it stands in for a site router)."""
    import zenoh

    from fpdd.zenohconf import zenoh_config

    with zenoh.open(zenoh_config(listen=[endpoint])) as session:
        yield session
