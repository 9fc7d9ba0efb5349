"""``one_blas_thread`` limits every BLAS library an estimation uses, scipy's included, even when the first
limited call comes before anything imported scipy (the controller that lists the libraries is made once per
process: made too early, it had left scipy's OpenBLAS on its threads, and a diagnosis took 6-13 % more CPU)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import json, sys
    import numpy as np
    assert "scipy" not in sys.modules
    from twin.estimation.threads import one_blas_thread

    @one_blas_thread
    def first():
        return None

    @one_blas_thread
    def later():
        import scipy.linalg  # noqa: F401
        from threadpoolctl import threadpool_info
        return [(i["filepath"].rsplit("/", 1)[-1], i["num_threads"]) for i in threadpool_info()
                if i["user_api"] == "blas"]

    first()
    print(json.dumps(later()))
""")


def test_one_blas_thread_limits_scipys_blas_when_the_first_call_precedes_scipy() -> None:
    done = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "2"})  # two threads unless limited
    assert done.returncode == 0, done.stderr[-2000:]
    libs = json.loads(done.stdout)
    assert len(libs) >= 2, libs  # numpy's and scipy's own OpenBLAS
    assert all(n == 1 for _, n in libs), libs


TRACKER = textwrap.dedent("""
    import json
    import numpy as np
    from threadpoolctl import threadpool_info
    from replay.base import Samples
    from twin.online.tracker import OnlineTracker

    def numpy_blas():
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    seen = []
    tr = OnlineTracker(dt=1e-3)
    inner = tr._process
    def spy(samples):
        seen.append(numpy_blas())
        return inner(samples)
    tr._process = spy
    t = np.arange(50, dtype=np.int64) * 1_000_000
    tr.process(Samples(t, {"u": np.zeros(50), "x": np.zeros(50), "pA": np.full(50, 14e6), "pB": np.full(50, 14e6)}))
    print(json.dumps({"during": seen, "after": numpy_blas()}))
""")


def test_the_tracker_filters_with_numpys_blas_on_one_thread_and_gives_it_back() -> None:
    """OpenBLAS's threads, woken by the Python around the kernel, spin on the other core while the kernel runs:
    the tracker holds numpy's BLAS at one thread while it filters a block, and restores it after."""
    done = subprocess.run([sys.executable, "-c", TRACKER], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "2"})
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout)
    assert got["during"] and all(n == [1] * len(n) for n in got["during"]), got
    assert got["after"] and max(got["after"]) == 2, got
