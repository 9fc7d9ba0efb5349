"""``twin warm``: compile every model's kernels once, so the first real command loads them from the cache.

numba compiles a model's functions and the tracker's kernel on their first use and keeps the machine code on
disk (beside the modules, or in numba's per-user cache where the package directory is not writable); the first
``twin track`` or ``twin serve`` after an install otherwise spends a minute compiling before it reads its input.
``twin warm`` runs each model's own paths on a short simulated record, in this process, exactly as the commands
run them: ``twin simulate``, ``twin track`` (a model the online twin runs; the step compiles the forecast's fits
too, which a short record never reaches) and ``twin fit``. Run it once after installing or upgrading, as the user
the service runs as (its cache is that user's where the package directory is not writable); a second run finds
everything compiled and takes seconds.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
import time

from twin.commands.common import dump as _dump
from twin.models import MODELS

#: seconds of the record each model's paths run on: long enough for the tracker's and the fit's every stage
RECORD_S = 2.0


def add_arguments(p) -> None:
    p.add_argument("--model", action="append", choices=MODELS, metavar="NAME",
                   help=f"a model to warm (repeatable; default: every registered one: {', '.join(MODELS)})")
    p.add_argument("--json", action="store_true", help="each model's steps and their CPU seconds as JSON")


def _step(argv: list[str]) -> float:
    """One ``twin`` command in this process, its output kept out of ours; the CPU seconds it took."""
    from fpdd.errors import TwinError
    from twin.cli import main

    out, err = io.StringIO(), io.StringIO()
    t0 = time.process_time()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([*argv, "--quiet"])
    if rc != 0:
        last = (err.getvalue().strip().splitlines() or [f"exit code {rc}"])[-1]
        raise TwinError(f"{argv[0]}: {last}")
    return time.process_time() - t0


def run(args) -> int:
    from fpdd.errors import TwinError
    from twin.models import get_model
    from twin.online.forecast import compile_kernels as compile_forecast

    models = args.model or list(MODELS)
    say = (lambda m: None) if args.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    rows = []
    with tempfile.TemporaryDirectory(prefix="twin-warm-") as tmp:
        for name in models:
            model = get_model(name)
            rec = os.path.join(tmp, f"{name}.csv")
            steps: dict[str, float] = {}
            plan = [("simulate", ["simulate", "--model", name, "--duration", f"{RECORD_S:g}", "--seed", "1",
                                  "-o", rec])]
            if model.TRACKABLE:
                plan.append(("track", ["track", rec, "--model", name]))
            plan.append(("fit", ["fit", rec, "--model", name, "--starts", "2"]))
            for step, argv in plan:
                say(f"twin warm: {name}: {step}...")
                try:
                    steps[step] = _step(argv)
                    if step == "track":  # the forecast's fits: a 2-s record has no history to fit them on
                        t0 = time.process_time()
                        compile_forecast()
                        steps[step] += time.process_time() - t0
                except TwinError as exc:
                    raise TwinError(f"model {name}: {exc}") from None
            rows.append({"model": name, "cpu_s": steps, "total_cpu_s": sum(steps.values())})
            say(f"twin warm: {name}: " + ", ".join(f"{k} {v:.1f} s" for k, v in steps.items()) + " of CPU")
    if args.json:
        _dump({"models": rows})
    else:
        for r in rows:
            print(f"{r['model']:<12} {r['total_cpu_s']:6.1f} s of CPU  ("
                  + ", ".join(f"{k} {v:.1f}" for k, v in r["cpu_s"].items()) + ")")
    return 0
