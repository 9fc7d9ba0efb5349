"""Start-up: what a fresh process of the online twin pays before its first sample
(``python -m benchmarks.startup [--repeats 5] [--json]``).

* ``import twin.online.tracker`` in a fresh interpreter (wall time of the import, measured inside it), beside
  ``import numpy`` and ``import numba`` in fresh interpreters of the same run: the floor the tracker stands on;
* a service worker's start-up: from the service's ``Process.start()`` of a spawned worker
  (:func:`twin.service.workers.worker_main`, the function ``twin serve`` spawns, with the service's configuration)
  to the worker ready to run its rigs (its modules imported, its arguments unpickled, its console and stop relay
  up), read on the system-wide monotonic clock; beside it, in the same run, the spawn of a bare interpreter (a
  process that imports nothing of ours) and whether filterpy or scipy.optimize were imported on the way (they
  must not be);
* after it, in the same worker, its first tracker: the rig model's filter kernel loaded from numba's on-disk cache
  and the first samples filtered (compiles instead when the cache is cold; run once to warm it).

Medians of ``--repeats`` runs; the machine's load average is printed beside them: the figures are wall times on a
machine that may be shared.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time


def _fresh_import(statement: str) -> float:
    """Seconds ``statement`` takes in a fresh interpreter (timed inside it)."""
    code = f"import time\nt = time.perf_counter()\n{statement}\nprint(time.perf_counter() - t)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def _bare(conn) -> None:
    conn.send(time.monotonic())
    conn.close()


def _worker_probe(conn, cfg, log_level: int, first_tracker: bool) -> None:
    """The worker as ``twin serve`` spawns it, without rigs: ready when :func:`worker_main` has set up and would
    start its rigs' threads; then (``first_tracker``) the tracker's first block."""
    from twin.service.workers import worker_main

    reader, writer = mp.Pipe(duplex=False)
    writer.close()  # the stop relay sees the end of its pipe at once
    worker_main([], cfg, None, reader, log_level)
    ready = time.monotonic()
    loaded = [m for m in ("filterpy", "scipy.optimize") if m in sys.modules]
    first = None
    if first_tracker:
        from twin.models import DEFAULT_MODEL, get_model
        from twin.models.simulate import default_noise, excite, measure
        from twin.online.tracker import OnlineTracker

        model = get_model(DEFAULT_MODEL)
        name, xr = excite(model, 0.2, 1e-3, seed=1000)
        rec = measure(model, model.params(), name, xr, 1e-3, noise=default_noise(model), seed=1000)
        t0 = time.monotonic()
        OnlineTracker().process(rec.to_samples())
        first = time.monotonic() - t0
    conn.send((ready, loaded, first))
    conn.close()


def _config(directory: str):
    from twin.service.config import parse_config

    log = os.path.join(directory, "rig.mcap")
    open(log, "wb").close()
    return parse_config({
        "zenoh": {"mode": "peer", "listen": ["tcp/127.0.0.1:7447"]},
        "service": {"journal_dir": os.path.join(directory, "journal"), "out_dir": os.path.join(directory, "out"),
                    "workers": 1},
        "rig": [{"name": "rig-1", "source": log, "speed": 1.0}],
    }, os.path.join(directory, "rigs.toml"))


def _spawn(target, *args) -> tuple[float, object]:
    """Seconds from ``start()`` to the child's report on the monotonic clock, and the rest of the report."""
    ctx = mp.get_context("spawn")
    reader, writer = ctx.Pipe(duplex=False)
    p = ctx.Process(target=target, args=(writer, *args))
    t0 = time.monotonic()
    p.start()
    writer.close()
    msg = reader.recv()
    p.join(60.0)
    stamp, rest = (msg, None) if isinstance(msg, float) else (msg[0], msg[1:])
    return stamp - t0, rest


def run(repeats: int = 5) -> dict:
    import logging

    import numpy as np

    med = {}
    runs: dict[str, list[float]] = {"numpy": [], "numba": [], "tracker": [], "bare_spawn": [], "worker": [],
                                     "first_tracker": []}
    loaded: set[str] = set()
    with tempfile.TemporaryDirectory() as d:
        cfg = _config(d)
        _spawn(_worker_probe, cfg, logging.WARNING, True)  # the kernel's cache warm (compiled if it was cold)
        for _ in range(repeats):
            runs["numpy"].append(_fresh_import("import numpy"))
            runs["numba"].append(_fresh_import("import numba"))
            runs["tracker"].append(_fresh_import("import twin.online.tracker"))
            runs["bare_spawn"].append(_spawn(_bare)[0])
            t, rest = _spawn(_worker_probe, cfg, logging.WARNING, True)
            runs["worker"].append(t)
            assert isinstance(rest, tuple)
            loaded |= set(rest[0])
            runs["first_tracker"].append(float(rest[1]))
    med = {k: float(np.median(v)) for k, v in runs.items()}
    return {"seconds": runs, "median": med, "imported_on_the_way": sorted(loaded),
            "tracker_over_numba": med["tracker"] / med["numba"], "worker_over_bare_spawn": med["worker"] /
            med["bare_spawn"], "targets": {"import_tracker<=0.5s": med["tracker"] <= 0.5,
                                           "worker_startup<=0.5s": med["worker"] <= 0.5,
                                           "no_filterpy_no_scipy.optimize": not loaded},
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.startup", description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    r = run(args.repeats)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    m = r["median"]
    print(f"import twin.online.tracker: {m['tracker']:.3f} s (median of {args.repeats}); in the same run import numpy "
          f"{m['numpy']:.3f} s, import numba {m['numba']:.3f} s (tracker / numba {r['tracker_over_numba']:.2f})")
    print(f"worker start-up, spawn to ready: {m['worker']:.3f} s; a bare interpreter's spawn {m['bare_spawn']:.3f} s "
          f"(ratio {r['worker_over_bare_spawn']:.1f}); imported on the way: "
          f"{', '.join(r['imported_on_the_way']) or 'neither filterpy nor scipy.optimize'}")
    print(f"then its first tracker (kernel from the on-disk cache, 200 samples): {m['first_tracker']:.3f} s")
    print("targets:", ", ".join(f"{k} {'OK' if v else 'MISSED'}" for k, v in r["targets"].items()),
          f"(load average {r['load_average_1min']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
