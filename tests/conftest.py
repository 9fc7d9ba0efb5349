"""Shared fixtures: records of the independent reference simulator (``tests/reference``).

Records are cached on disk (``$FPDD_REFCACHE``, default ``tests/.refcache/``) under a
hash of their full spec, so a session generates each one once; misses of one call are
simulated in two worker processes.
"""

from __future__ import annotations

from collections.abc import Sequence

import pytest

from reference import Record, batch, msp25_spec, oscillator_spec  # noqa: F401  (re-exported for tests)


def get_records(specs: Sequence[dict], workers: int = 2) -> list[Record]:
    """Records of ``specs`` (from ``msp25_spec`` / ``oscillator_spec``), through the disk cache."""
    return batch(specs, workers=workers)


@pytest.fixture(scope="session")
def reference_records():
    """The function ``get_records(specs) -> list[Record]`` (cached)."""
    return get_records
