"""How the programs leave the process."""

from __future__ import annotations

import sys


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
