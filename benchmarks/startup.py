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

Per command (``--commands``): ``twin --help`` and ``twin CMD --help`` for every command, and for the commands that
read an input file (``fit``, ``track``, ``diagnose`` a 1 s record, ``serve`` its rigs.toml; ``simulate`` until it opens
its output; ``params`` the whole command) the start-up to the moment the process opens that file (an audit hook on
``open`` in the fresh interpreter), as the process's CPU time and wall time from the parent's launch, and which heavy
modules (numba, scipy, the diagnosis) were imported by then.  With ``--baseline REV`` the same commands run in the same
run from the tree of ``REV`` (``git archive``, first on ``PYTHONPATH``), their ratio printed beside.

Medians of ``--repeats`` runs; the machine's load average is printed beside them: the figures are wall times on a
machine that may be shared (the CPU times are less sensitive to the load).
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


#: the modules a command should not pay for unless it runs them
HEAVY = ("numba", "scipy", "scipy.optimize", "scipy.stats", "scipy.signal", "twin.estimation.diagnose", "matplotlib",
         "pint")

#: runs in a fresh interpreter: ``sys.argv[1]`` the file whose opening ends the start-up ('' for none: the command's
#: end), ``sys.argv[2]`` the heavy modules looked for, the rest the command line; prints ``cpu_s wall_end heavy,modules`` on stderr's last line
_PROBE = r"""
import os, sys, time
target = os.path.abspath(sys.argv[1]) if sys.argv[1] else None
HEAVY = sys.argv[2].split(",")

def _report():
    heavy = ",".join(m for m in HEAVY if m in sys.modules)
    sys.stderr.write(f"\nSTARTUP {time.process_time():.6f} {time.time():.6f} {heavy or '-'}\n")
    sys.stderr.flush()

def _hook(event, args):
    if event == "open" and target is not None and isinstance(args[0], (str, bytes)):
        path = os.fsdecode(args[0])
        if os.path.abspath(path) == target:
            _report()
            os._exit(0)

sys.addaudithook(_hook)
import twin.cli
try:
    rc = twin.cli.main(sys.argv[3:])
except SystemExit as exc:
    rc = exc.code
_report()
os._exit(0)
"""


def _command_once(tree: str, target: str, argv: list[str], env: dict) -> tuple[float, float, list[str]]:
    """CPU seconds of the fresh process to ``target``'s opening (or its end), wall seconds from the launch, the heavy
    modules imported by then."""
    t0 = time.time()
    out = subprocess.run([sys.executable, "-c", _PROBE, target, ",".join(HEAVY), *argv], cwd=tree, env=env, capture_output=True,
                         text=True, timeout=600)
    line = [ln for ln in out.stderr.splitlines() if ln.startswith("STARTUP ")]
    if not line:
        raise RuntimeError(f"twin {' '.join(argv)}: no start-up report; stderr: {out.stderr[-2000:]}")
    _, cpu, wall_end, heavy = line[-1].split()
    return float(cpu), float(wall_end) - t0, ([] if heavy == "-" else heavy.split(","))


def _export(rev: str, into: str) -> str:
    """The tree of ``rev`` unpacked into ``into`` (its numba cache builds there on first use)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    os.makedirs(into, exist_ok=True)
    archive = subprocess.run(["git", "-C", root, "archive", rev], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", into], input=archive, check=True)
    return into


def _command_cases(d: str) -> list[tuple[str, str, list[str]]]:
    """(label, file whose opening ends the start-up, argv) for every command."""
    from twin.cli import COMMANDS

    rec = os.path.join(d, "rec1.csv")
    if not os.path.exists(rec):
        subprocess.run([sys.executable, "-m", "twin.cli", "-q", "simulate", "-o", rec, "--duration", "1"], check=True,
                       capture_output=True)
    cfg = os.path.join(d, "rigs.toml")
    with open(cfg, "w") as f:
        f.write(f'[service]\njournal_dir = "{d}/journal"\n\n[[rig]]\nname = "rig-1"\nsource = "{rec}"\n')
    cases = [("twin --help", "", ["--help"])]
    cases += [(f"twin {c} --help", "", [c, "--help"]) for c in COMMANDS]
    cases += [("twin fit REC (to reading it)", rec, ["-q", "fit", rec]),
              ("twin track REC (to reading it)", rec, ["-q", "track", rec, "--out", os.path.join(d, "t")]),
              ("twin diagnose REC (to reading it)", rec, ["-q", "diagnose", rec]),
              ("twin serve --config (to reading it)", cfg, ["-q", "serve", "--config", cfg]),
              ("twin simulate 1 s (to its output: simulated first)", os.path.join(d, "sim.csv"),
               ["-q", "simulate", "-o", os.path.join(d, "sim.csv"), "--duration", "1"]),
              ("twin params (whole command)", "", ["params"])]
    return cases


def run_commands(repeats: int = 3, baseline: str | None = None) -> dict:
    """Start-up per command (medians of ``repeats``), beside the same commands of ``baseline``'s tree."""
    import numpy as np

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as d:
        trees = {"now": root}
        if baseline:
            trees["baseline"] = _export(baseline, os.path.join(d, "baseline"))
        work = os.path.join(d, "work")
        os.makedirs(work)
        cases = _command_cases(work)
        rows = []
        for label, target, argv in cases:
            row: dict = {"command": label}
            for which, tree in trees.items():
                env = dict(os.environ, PYTHONPATH=tree)
                runs = [_command_once(tree, target, argv, env) for _ in range(repeats + 1)][1:]  # first: warm-up
                row[which] = {"cpu_s": float(np.median([r[0] for r in runs])),
                              "wall_s": float(np.median([r[1] for r in runs])), "heavy": runs[-1][2]}
            if "baseline" in row:
                row["cpu_ratio"] = row["baseline"]["cpu_s"] / row["now"]["cpu_s"]
            rows.append(row)
    return {"commands": rows, "baseline": baseline, "repeats": repeats,
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


def print_commands(r: dict) -> None:
    base = r["baseline"]
    print(f"start-up per command, CPU s (wall s from launch), median of {r['repeats']}"
          + (f"; baseline: the tree of {base} in the same run" if base else "")
          + f" (load average {r['load_average_1min']}):")
    for row in r["commands"]:
        now = row["now"]
        line = (f"  {row['command']:<40} {now['cpu_s']:6.3f} ({now['wall_s']:6.3f})  "
                f"heavy: {','.join(now['heavy']) or '-':<36}")
        if "baseline" in row:
            b = row["baseline"]
            line += f" | baseline {b['cpu_s']:6.3f} ({b['wall_s']:6.3f}) {row['cpu_ratio']:5.1f}x"
            line += f"  heavy: {','.join(b['heavy']) or '-'}"
        print(line)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.startup", description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--commands", action="store_true",
                    help="only the start-up of every twin command (to reading its input), not the worker's")
    ap.add_argument("--baseline", metavar="REV",
                    help="with --commands: also run the commands from the tree of this git revision, same run")
    args = ap.parse_args(argv)
    if args.commands:
        rc = run_commands(args.repeats, args.baseline)
        if args.json:
            print(json.dumps(rc, indent=2))
        else:
            print_commands(rc)
        return 0
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
