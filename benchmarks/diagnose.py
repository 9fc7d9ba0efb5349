"""Benchmark of ``twin diagnose`` (``python -m benchmarks.diagnose [--json] [--against REV]``; also run by
``python -m benchmarks``).

The whole diagnosis - nominal fit, noise model, catalogue screen, timing test, fits of the promising
extensions, greedy re-test, held-out scoring - of 20 s, 1 kHz MSP25 records (x, pA, pB) against the full
catalogue, on the product's own simulation (a hidden viscous friction, noise added after the loop) and,
when the repository's tests are present, on records of the independent reference simulator
(``tests/reference``: a controller reading the noisy measured displacement; healthy, a hidden viscous
friction, an analog controller), and the EMPS axis (real data, 24.8 s, the oscillator with m and d free) when
``realdata/emps`` is beside the project.  Target: at most 10 s of CPU (``time.process_time``: every thread of
the process) per 20 s record for the whole diagnosis.  Baselines measured in the same run on the same records:
one nominal fit (``twin fit`` of the phenomenological parameters, 8 starts), and with ``--against REV`` the
diagnosis of the project at git revision ``REV`` (its ``twin``, ``fpdd`` and ``replay`` extracted to a temporary
folder and run in a subprocess on the same records).  The numba kernels are compiled (and cached) by a warm-up
before the clock starts.
"""

from __future__ import annotations

import argparse
import gzip
import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from typing import Any

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:  # appended: the sources of --against REV, first on PYTHONPATH, stay first
    sys.path.append(ROOT)

from twin.estimation.diagnose import diagnose  # noqa: E402
from twin.estimation.fit import fit  # noqa: E402
from twin.models import get_model  # noqa: E402
from twin.models.simulate import default_noise, excite, measure  # noqa: E402
from twin.record import Record  # noqa: E402

TARGET_CPU_S = 10.0
#: the EMPS force per controller volt (N/V) and where the record is kept
EMPS_GTAU = 35.15
EMPS_PATH = os.path.join(os.path.dirname(ROOT), "shared", "realdata", "emps", "DATA_EMPS.mat.gz")


def _product_record(effects, duration_s: float, seed: int):
    rig = get_model("msp25")
    name, xr = excite(rig, duration_s, 1e-3, seed=seed)
    return measure(rig, rig.params(effects=effects), name, xr, 1e-3, noise=default_noise(rig), seed=seed)


def _reference_records(duration_s: float):
    tests = os.path.join(ROOT, "tests")
    if not os.path.isfile(os.path.join(tests, "diag_reference.py")):
        return []
    sys.path.insert(0, tests)
    try:
        from diag_reference import reference_record
    except ImportError:
        return []
    out: list[tuple] = []
    for label, effects, ctrl, expect in (("reference, healthy", (), "digital", []),
                                         ("reference, one effect", ("viscous_friction",), "digital",
                                          ["viscous_friction"]),
                                         ("reference, analog controller", (), "analog", ["controller_rate"])):
        rec, _ = reference_record(effects, seed=11, duration=duration_s, controller=ctrl)
        out.append((label, "msp25", rec, expect, {}))
    return out


def _emps_case():
    path = os.environ.get("FPDD_EMPS", EMPS_PATH)
    if not os.path.isfile(path):
        return []
    import numpy as np
    import scipy.io

    with gzip.open(path) as f:
        mat = scipy.io.loadmat(io.BytesIO(f.read()))
    t = mat["t"].ravel()
    rec = Record(float(np.median(np.diff(t))), {"u": EMPS_GTAU * mat["vir"].ravel(), "y": mat["qm"].ravel()}, "EMPS")
    osc = get_model("oscillator")
    opts = {"free": ("m", "d"), "base": osc.params().update({"k": osc.params().spec("k").lo})}
    return [("EMPS (real, 24.8 s)", "oscillator", rec, ["input_offset", "coulomb_friction"], opts)]


def _cases(duration_s: float, quick: bool, only: list[str] | None = None):
    cases: list[tuple] = [("product, one effect", "msp25", _product_record(("viscous_friction",), duration_s, 12),
              ["viscous_friction"], {})]
    if not quick:
        cases += _reference_records(duration_s) + _emps_case()
    if only:
        cases = [c for c in cases if any(o.lower() in c[0].lower() for o in only)]
    return cases


def _time_diagnoses(cases) -> list[dict]:
    import twin

    diagnose("msp25", _product_record(("viscous_friction",), 2.0, 0))  # compile / load the kernels
    out = []
    for label, model, rec, expect, opts in cases:
        if model == "oscillator":
            diagnose(model, rec.slice(0, 2000), **opts)
        t0, c0 = time.perf_counter(), time.process_time()
        d = diagnose(model, rec, **opts)
        out.append({"case": label, "seconds": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                    "causes": d.causes, "unexplained": d.unexplained,
                    "correct": sorted(d.causes) == sorted(expect), "sources": os.path.dirname(twin.__file__)})
    return out


def _against(rev: str, duration_s: float, quick: bool, only: list[str] | None = None) -> list[dict] | str:
    """The same cases diagnosed by the project at ``rev`` (a subprocess with its sources first on the path)."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            blob = subprocess.run(["git", "-C", ROOT, "archive", rev, "twin", "fpdd", "replay"], check=True,
                                  capture_output=True).stdout
        except (subprocess.CalledProcessError, OSError) as e:
            return f"git archive {rev} failed: {e}"
        with tarfile.open(fileobj=io.BytesIO(blob)) as tf:
            tf.extractall(tmp, filter="data")
        env = dict(os.environ, PYTHONPATH=tmp + os.pathsep + os.environ.get("PYTHONPATH", ""))
        cmd = [sys.executable, os.path.abspath(__file__), "--cases-only", "--duration", str(duration_s)]
        if quick:
            cmd.append("--quick")
        for o in only or ():
            cmd += ["--case", o]
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tmp)
        if p.returncode != 0:
            return f"the diagnosis at {rev} failed: {p.stderr.strip().splitlines()[-1:] or p.returncode}"
        rows = json.loads(p.stdout)
        if any(not r["sources"].startswith(tmp) for r in rows):
            return f"the diagnosis at {rev} ran the checkout's sources, not the revision's"
        return rows


def run(duration_s: float = 20.0, quick: bool = False, against: str | None = None,
        only: list[str] | None = None) -> dict:
    """Time the diagnosis of ``duration_s`` records; rows with CPU and wall seconds, baselines and findings."""
    cases = _cases(duration_s, quick, only)
    rows: list[dict[str, Any]] = _time_diagnoses(cases)
    for row, (_label, model, rec, expect, opts) in zip(rows, cases):
        m = get_model(model)
        c0 = time.process_time()
        fit(m, rec.slice(0, int(0.75 * len(rec))), opts.get("free") or m.PHENOMENOLOGICAL, base=opts.get("base"),
            n_starts=8, spread=1.5, max_nfev=80)
        row.update({"expected": expect, "baseline_fit_cpu_s": time.process_time() - c0,
                    "target_cpu_s": TARGET_CPU_S * len(rec) * rec.dt / 20.0})
        row["within_target"] = row["cpu_s"] <= row["target_cpu_s"]
        row["ratio_to_fit"] = row["cpu_s"] / row["baseline_fit_cpu_s"]
    old = _against(against, duration_s, quick, only) if against else None
    if isinstance(old, list):
        for row, o in zip(rows, old):
            row["against"] = {"rev": against, "cpu_s": o["cpu_s"], "seconds": o["seconds"], "causes": o["causes"],
                              "correct": o["correct"]}
            row["speedup"] = o["cpu_s"] / row["cpu_s"]
    return {"name": "diagnose", "record_s": duration_s, "rate_hz": 1000.0, "cores": os.cpu_count(),
            "catalogue": len(get_model("msp25").EFFECTS), "rows": rows, "against_error": old if isinstance(old, str)
            else None, "max_cpu_s": max(r["cpu_s"] for r in rows), "target_cpu_s": TARGET_CPU_S}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=20.0, help="record length in s (default 20)")
    ap.add_argument("--quick", action="store_true", help="only the product's one-effect record")
    ap.add_argument("--against", metavar="REV", help="also time the diagnosis of git revision REV on the same records")
    ap.add_argument("--case", action="append", metavar="TEXT", help="only the cases whose label contains TEXT")
    ap.add_argument("--cases-only", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.cases_only:  # the subprocess of --against: the diagnoses alone, as JSON
        print(json.dumps(_time_diagnoses(_cases(args.duration, args.quick, args.case))))
        return 0
    out = run(args.duration, args.quick, args.against, args.case)
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"twin diagnose, {out['record_s']:g} s at 1 kHz, {out['catalogue']} effects + timing, "
          f"{out['cores']} cores, CPU seconds (every thread):")
    for r in out["rows"]:
        old = r.get("against")
        was = (f"; at {old['rev']}: {old['cpu_s']:.1f} s CPU, found {'+'.join(old['causes']) or 'nothing'} "
               f"(x{r['speedup']:.2f})") if old else ""
        print(f"  {r['case']:<30} found {'+'.join(r['causes']) or 'nothing':<34}"
              f"{' (unexplained)' if r['unexplained'] else '':<14} {r['cpu_s']:6.1f} s CPU "
              f"({'within' if r['within_target'] else 'OVER'} {r['target_cpu_s']:.1f} s), {r['seconds']:.1f} s wall; "
              f"nominal fit alone {r['baseline_fit_cpu_s']:.1f} s CPU{was}")
    if out["against_error"]:
        print(f"  (no comparison: {out['against_error']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
