"""How the programs leave the process."""

from __future__ import annotations

import sys
from typing import Any


def exit_process(rc: int) -> None:
    """Leave a program with ``rc``, without the interpreter's finalization once Zenoh was loaded.

    Zenoh's own (Rust) threads may still call into Python while the interpreter shuts down; such a thread is
    unwound by ``pthread_exit`` through Rust frames and the process aborts (SIGABRT, "FATAL: exception not
    rethrown") after everything was already closed, checkpointed and summarized. The programs close what they
    own before they return their code; what is left is flushing, done here."""
    if "zenoh" not in sys.modules:
        sys.exit(rc)
    import logging
    import os

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can reach the reader
            pass
    os._exit(rc)


#: How often a long-running process gives its C heap's free pages back to the system [s].
TRIM_EVERY_S = 60.0

_malloc_trim: Any = None


def trim_heap() -> bool:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim(0)``); ``False`` where there is none.

    A service that runs for months allocates and frees arrays of many sizes on several threads (the filter's
    blocks, the window re-fits, the bus's messages); glibc keeps what was freed inside its arenas. One rig's twin
    fed a 10-min log as fast as it goes: Python's allocations flat (``tracemalloc``, 0.9 MiB throughout), the
    resident size +2.1 MiB in 4 min of record, and flat when trimmed each minute. (The 30-min service soak's slow
    growth, about 0.13 MiB a minute per rig, is not this: the same with and without the trim; see
    docs/results/speed.md.) A trim takes a few milliseconds and holds no Python lock."""
    global _malloc_trim
    if _malloc_trim is None:
        import ctypes
        import ctypes.util

        try:
            fn = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
            fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
            _malloc_trim = fn
        except (OSError, AttributeError):  # not glibc: nothing to trim this way
            _malloc_trim = False
    if not _malloc_trim:
        return False
    _malloc_trim(0)
    return True
