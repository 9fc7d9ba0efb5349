"""An estimation's linear algebra on one BLAS thread (:func:`one_blas_thread`).

The fit and the diagnosis multiply and decompose tall, narrow matrices: a Jacobian of a record's samples by a
handful of parameters, an autoregression's lagged residuals, the score tests' sensitivities.  Such products are
bound by memory, not arithmetic, so a second BLAS thread gains little even on an idle machine; on a machine whose
cores are shared (a service's workers, a test run beside others) OpenBLAS's threads wait for each other at every
call: the Silverbox's whole estimation part (65 062 samples) took 56.6 s of processor time and 172 s on the clock
with two threads under a load average of 9.6-13.3, and 17.1 s and 53 s with one, verdict and estimates unchanged
(``python -m benchmarks.silverbox --samples 0``, docs/results/speed.md).  The model kernels' own parallel loop over
parameter sets (numba) is untouched: its work per thread is a whole simulation.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

from threadpoolctl import ThreadpoolController

F = TypeVar("F", bound=Callable)

#: the process's BLAS libraries, found once (finding them walks every loaded shared object: 20 ms a call, as
#: much as a window's adequacy test); made at the first estimation, with numpy's and scipy's loaded
_CONTROLLER: ThreadpoolController | None = None
#: numpy's BLAS alone, for the online tracker (which imports no scipy module of its own)
_NUMPY_CONTROLLER: ThreadpoolController | None = None


def _one_thread():
    global _CONTROLLER
    if _CONTROLLER is None:
        import scipy.linalg  # noqa: F401 - scipy's own BLAS loaded before the libraries are listed

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER.limit(limits=1, user_api="blas")


def numpy_one_thread():
    """A context with numpy's BLAS limited to one thread (9 us to enter and leave), without importing scipy.

    The online tracker's Python around its compiled kernel multiplies small matrices; OpenBLAS's threads, woken
    by them, then spin on the other core while the kernel runs: a quarter of the tracker's processor time on a
    20-s record (``perf``: ``blas_thread_server``), time a service's other rigs needed."""
    global _NUMPY_CONTROLLER
    if _NUMPY_CONTROLLER is None:
        _NUMPY_CONTROLLER = ThreadpoolController()
    return _NUMPY_CONTROLLER.limit(limits=1, user_api="blas")


def one_blas_thread(func: F) -> F:
    """Run ``func`` with every loaded BLAS library (numpy's, scipy's) limited to one thread, restored after."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with _one_thread():
            return func(*args, **kwargs)
    return wrapper  # type: ignore[return-value]
