"""Processes and threads the service starts: a spawned process dies with the service
(:func:`die_with_parent`), a thread can run under cProfile (:func:`profiled`), and a rig's commissioning fit
runs in a process of its own (:class:`FitJob`)."""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import signal
import time
from typing import Any
from collections.abc import Callable

from replay.base import Samples
from twin.service.config import RigConfig


def die_with_parent() -> None:
    """Linux: the kernel kills this worker when the service's process dies (even by SIGKILL)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    parent = mp.parent_process()
    if parent is not None and not parent.is_alive():
        os._exit(1)


def profiled(target: Callable[..., Any], name: str) -> Callable[..., Any]:
    """``target`` under cProfile (CPU time of its thread) when ``FPDD_PROFILE_DIR`` is set: the statistics go
    to ``FPDD_PROFILE_DIR/<name>.prof`` (``python -m benchmarks.service fleet --profile DIR`` reads them)."""
    directory = os.environ.get("FPDD_PROFILE_DIR")
    if not directory:
        return target

    def run(*args: Any) -> Any:
        import cProfile

        prof = cProfile.Profile(time.thread_time)
        try:
            return prof.runcall(target, *args)
        finally:
            prof.dump_stats(os.path.join(directory, f"{name}.{os.getpid()}.prof"))

    return run


def _fit_job(conn, samples: Samples, tracked: tuple[str, ...], params: dict, timing, rig: str, model: str,
             module: str) -> None:
    """A spawned process: the commissioning fit of one rig's window with the rig's own ``model`` (registered here
    from its ``module`` when the service registered it at run time), its outcome sent on ``conn``."""
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from twin.models import REGISTRY, register
    from twin.online.commission import fit_window

    try:
        if model not in REGISTRY:
            register(model, module)
        out = fit_window(samples, tracked, params, timing, rig, model_name=model)
    except Exception as exc:  # noqa: BLE001 - a bug of the fit is a failed commissioning, not a dead rig
        out = (None, f"internal error of the fit {type(exc).__name__}: {exc}")
    conn.send(out)
    conn.close()


class FitJob:
    """A rig's commissioning fit in its own spawned process (the other rigs go on meanwhile), of the rig's own
    model (``model`` in rigs.toml)."""

    def __init__(self, rig: RigConfig, samples: Samples) -> None:
        from twin.models import REGISTRY

        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=False)
        timing = rig.timing
        self.proc = ctx.Process(target=_fit_job, args=(child, samples, tuple(rig.track), dict(rig.params), timing,
                                                       rig.name, rig.model, REGISTRY[rig.model]),
                                name=f"twin-commission-{rig.name}")
        self.proc.start()
        child.close()

    def done(self) -> bool:
        return self._conn.poll() or not self.proc.is_alive()

    def result(self) -> tuple[dict | None, str]:
        try:
            if self._conn.poll(1.0):
                return self._conn.recv()
        except (EOFError, OSError):
            pass
        finally:
            self.proc.join(5.0)
        return None, f"the fit's process ended without a result (exit code {self.proc.exitcode})"

    def cancel(self) -> None:
        if self.proc.is_alive():
            self.proc.terminate()
        self.proc.join(5.0)
        self._conn.close()

