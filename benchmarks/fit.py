"""Benchmarks, measured side by side in one run (``python -m benchmarks [--json] [--quick]``).

Rows, each with a baseline measured in the same process:

* MSP25 right-hand side for a batch of 23 states (a UKF's sigma points):
  compiled kernel vs the same equations in plain, batch-vectorised numpy;
* one RK4 sample step (3 substeps) of 23 states: compiled vs numpy;
* a 10 s, 1 kHz closed-loop simulation;
* the advanced two-parameter fit (zeta and CdAleak from x alone, noisy);
* all of ``twin paper`` and the oscillator cases alone;
* then the tracker, diagnosis and ingest benchmarks of the other packages,
  when present (``benchmarks.tracker``, ``benchmarks.diagnose``, ``benchmarks.replay``).

Targets (issue 2): the two-parameter fit <= 5 s (the paper: ~15 min), the
oscillator cases <= 1 s together.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time

import numpy as np

from twin.models import msp25 as M


def _numpy_deriv(S, u, P):
    """The nominal MSP25 equations in plain numpy over a batch (the baseline)."""
    xs, vs, pA, pB, x, v = S.T
    rho, A, V0, dpl = P[:, M.I_RHO], P[:, M.I_A], P[:, M.I_V0], P[:, M.I_DPL]
    wn, pP, pT = P[:, M.I_WN], P[:, M.I_PP], P[:, M.I_PT]

    def sq(dp):
        return dp / np.sqrt(np.sqrt(dp * dp + dpl * dpl))

    dvs = wn * wn * (P[:, M.I_KE] * P[:, M.I_KSP] * u - xs) - 2.0 * P[:, M.I_ZETA] * wn * vs
    g = P[:, M.I_CD] * P[:, M.I_B] * np.sqrt(2.0 / rho)
    pos = xs >= 0
    o = np.abs(xs)
    qPA = np.where(pos, g * o * sq(pP - pA), 0.0)
    qBT = np.where(pos, g * o * sq(pB - pT), 0.0)
    qAT = np.where(pos, 0.0, g * o * sq(pA - pT))
    qPB = np.where(pos, 0.0, g * o * sq(pP - pB))
    qAB = P[:, M.I_CDALEAK] * np.sqrt(2.0 / rho) * sq(pA - pB)
    dpA = P[:, M.I_BULK] * (qPA - qAT - qAB - A * v) / (V0 + A * x)
    dpB = P[:, M.I_BULK] * (qPB - qBT + qAB + A * v) / (V0 - A * x)
    dv = ((pA - pB) * A - P[:, M.I_FFRIC] * np.tanh(v / P[:, M.I_VREF]) - P[:, M.I_FEXT]) / P[:, M.I_M]
    return np.stack([vs, dvs, dpA, dpB, v, dv], axis=1)


def _numpy_step(S, u, P, dt, nsub):
    h = dt / nsub
    for _ in range(nsub):
        k1 = _numpy_deriv(S, u, P)
        k2 = _numpy_deriv(S + 0.5 * h * k1, u, P)
        k3 = _numpy_deriv(S + 0.5 * h * k2, u, P)
        k4 = _numpy_deriv(S + h * k3, u, P)
        S = S + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return S


def _time(fn, min_time=0.2, max_reps=100000) -> float:
    """Seconds per call: best of 3 batches, each at least ``min_time`` long."""
    fn()
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        el = time.perf_counter() - t0
        if el >= min_time or n >= max_reps:
            break
        n *= 4
    best = el / n
    for _ in range(2):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, (time.perf_counter() - t0) / n)
    return best


def _sigma_batch(K=23, seed=0):
    rng = np.random.default_rng(seed)
    p = M.MODEL.vector(M.MODEL.params())
    P = np.repeat(p[None], K, axis=0)
    S = np.zeros((K, 6))
    S[:, 0] = rng.normal(0, 1e-4, K)
    S[:, 1] = rng.normal(0, 1e-2, K)
    S[:, 2] = 14e6 + rng.normal(0, 1e5, K)
    S[:, 3] = 14e6 + rng.normal(0, 1e5, K)
    S[:, 4] = rng.normal(0, 1e-3, K)
    S[:, 5] = rng.normal(0, 1e-2, K)
    return S, rng.normal(0, 0.5, K), P


def bench_core(quick: bool = False) -> list[dict]:
    from twin.estimation.fit import fit
    from twin.paper.cases import CASES, run_all
    from twin.models.simulate import default_noise, excite, measure

    rows = []
    S, U, P = _sigma_batch()
    np.testing.assert_allclose(M.rhs_batch(S, U, P), _numpy_deriv(S, U, P), rtol=1e-9, atol=1e-6)
    t_nb = _time(lambda: M.rhs_batch(S, U, P))
    t_np = _time(lambda: _numpy_deriv(S, U, P))
    rows.append({"name": "msp25 rhs, batch of 23", "unit": "us", "value": t_nb * 1e6,
                 "baseline": "plain numpy, batch-vectorised", "baseline_value": t_np * 1e6, "ratio": t_np / t_nb})
    t_nb = _time(lambda: M.step_batch(S, U, P, 1e-3, 3))
    t_np = _time(lambda: _numpy_step(S, U, P, 1e-3, 3))
    rows.append({"name": "RK4 sample step (3 substeps), 23 states", "unit": "us", "value": t_nb * 1e6,
                 "baseline": "plain numpy", "baseline_value": t_np * 1e6, "ratio": t_np / t_nb})
    name, xr = excite(M.MODEL, 10.0, 1e-3)
    ps = M.MODEL.params()
    t_sim = _time(lambda: M.MODEL.simulate(ps, name, xr, 1e-3), min_time=0.3)
    rows.append({"name": "10 s closed-loop simulation at 1 kHz", "unit": "ms", "value": t_sim * 1e3,
                 "baseline": "real time", "baseline_value": 10e3, "ratio": 10.0 / t_sim})
    rec = measure(M.MODEL, ps, name, xr, 1e-3, noise=default_noise(M.MODEL), seed=1)
    t0 = time.perf_counter()
    res = fit(M.MODEL, rec, ("zeta", "CdAleak"), start={"zeta": 0.6, "CdAleak": 3 * 3.2863e-9}, outputs=("x",))
    t_fit = time.perf_counter() - t0
    rows.append({"name": "advanced two-parameter fit (zeta, CdAleak; x only, noisy, 8 starts)", "unit": "s",
                 "value": t_fit, "baseline": "paper (MATLAB, 2010)", "baseline_value": 15 * 60.0,
                 "ratio": 15 * 60.0 / t_fit, "target": "<= 5 s", "ok": t_fit <= 5.0,
                 "estimate": res.estimate})
    rows.append(_five_parameter_command())
    osc = [c for c in CASES if c.model == "oscillator"]
    _, t_osc = run_all(False, cases=osc)
    rows.append({"name": "oscillator cases A-D together", "unit": "s", "value": t_osc,
                 "baseline": "paper ('a couple of seconds' each)", "baseline_value": 2.0 * len(osc),
                 "ratio": 2.0 * len(osc) / t_osc, "target": "<= 1 s", "ok": t_osc <= 1.0})
    if not quick:
        _, t_all = run_all(False)
        rows.append({"name": "all of twin paper (13 fits)", "unit": "s", "value": t_all,
                     "baseline": "paper (~15 min per rig case)", "baseline_value": 15 * 60.0 * 6,
                     "ratio": 15 * 60.0 * 6 / t_all})
    return rows


#: the user's rig of issue 20 for ``twin simulate`` / ``twin fit``: two areas, the filtered PID, a warming oil logged
USER_RIG_SET = "AB=960mm^2,V0B=300cm^3,KP=300,KI=2000,KD=0.6,Tf=1ms"
USER_RIG_SIM = ["--set", USER_RIG_SET, "--temperature", "40degC:60degC", "--temperature-rate", "10Hz"]


def user_rig_command(repeats: int = 3) -> dict:
    """The 40 s five-parameter ``twin fit`` command on the user's rig (:data:`USER_RIG_SIM`, T_oil read sample by
    sample) against the same command on the paper's rig, interleaved, medians of wall time."""
    plain, user = [], []
    for _ in range(repeats):
        plain.append(_five_parameter_command()["value"])
        user.append(_five_parameter_command(USER_RIG_SIM, ["--set", USER_RIG_SET])["value"])
    m_plain, m_user = float(np.median(plain)), float(np.median(user))
    return {"name": "five-parameter fit, 40 s record, user's rig (two areas, filtered PID, T_oil logged): whole "
                    "twin fit command", "unit": "s", "value": m_user, "runs": user,
            "baseline": f"the paper's rig, same command, same run ({m_plain:.2f} s)", "baseline_value": m_plain,
            "baseline_runs": plain, "ratio": m_user / m_plain, "target": "<= 5 s", "ok": m_user <= 5.0}


def _five_parameter_command(sim_args=(), fit_args=()) -> dict:
    """The issue's speed target: all five parameters from a 40 s, 1 kHz record, the whole ``twin fit``
    command (a fresh process: start-up, reading the CSV, the fit, the table) beside the fit alone."""
    import os
    import subprocess
    import tempfile

    from twin.estimation.fit import fit
    from twin.models.records import load_records

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "rig40.csv")
        subprocess.run([sys.executable, "-m", "twin.cli", "-q", "simulate", "-o", path, "--duration", "40",
                        "--seed", "3", *sim_args], check=True)
        start = "Ffric=70N,CdAleak=0.005mm^2,Cd=0.25,zeta=0.45,wn=37Hz"
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "twin.cli", "-q", "fit", path, "--start", start, "--json", *fit_args],
                       check=True, stdout=subprocess.DEVNULL)
        t_cmd = time.perf_counter() - t0
        if sim_args:
            return {"value": t_cmd}
        recs = load_records(path, model="msp25")
        t0 = time.perf_counter()
        fit(M.MODEL, recs, M.PHENOMENOLOGICAL, start={"Ffric": 70.0, "CdAleak": 5e-9, "Cd": 0.25, "zeta": 0.45,
                                                      "wn": 2 * np.pi * 37})
        t_fit = time.perf_counter() - t0
    return {"name": "five-parameter fit, 40 s record: whole twin fit command", "unit": "s", "value": t_cmd,
            "baseline": f"the fit alone in this process ({t_fit:.2f} s)", "baseline_value": t_fit,
            "ratio": t_fit / t_cmd, "target": "<= 5 s", "ok": t_cmd <= 5.0}


#: the paper's hard case as a command: zeta and CdAleak from x alone, an analog controller, starts at zeta 0.6 and
#: CdAleak x3 (the nominal CdAleak is 3.2863e-9 m^2)
HARD_FIT = ["--free", "zeta,CdAleak", "--outputs", "x", "--controller", "continuous", "--start",
            "zeta=0.6,CdAleak=0.0098589mm^2", "--json"]


def _command_cpu(tree: str, argv: list[str], threads: int | None = None) -> tuple[float, float, dict]:
    """CPU seconds (user + system) and wall seconds of ``python -m twin.cli ARGV`` run from ``tree``, its JSON;
    ``threads``: numba's threads (``NUMBA_NUM_THREADS``; default numba's, one per core)."""
    import os
    import subprocess

    env = dict(os.environ, PYTHONPATH=tree)
    if threads:
        env["NUMBA_NUM_THREADS"] = str(threads)
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "twin.cli", *argv], cwd=tree, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.DEVNULL)
    out = p.stdout.read() if p.stdout else b""
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    if status != 0:
        raise RuntimeError(f"twin {' '.join(argv)} (from {tree}) exited with status {status}")
    return ru.ru_utime + ru.ru_stime, wall, json.loads(out)


def hard_fit_command(repeats: int = 3, baseline: str | None = None, duration: float = 40.0,
                     threads: int | None = None) -> dict:
    """The whole ``twin fit`` command on the paper's hard case (:data:`HARD_FIT`, a ``duration`` s record of the
    product's simulator, analog controller, default noise, seed 3), CPU and wall medians of ``repeats`` runs; with
    ``baseline`` the same command from that git revision's tree, interleaved in the same run (one warm-up run each
    first: the numba cache of a fresh tree compiles).  ``threads=1`` makes the CPU time the work alone: the
    batched simulations' parallel loop otherwise adds its threads' waiting, which varies with the machine's load."""
    import os
    import subprocess
    import tempfile

    from benchmarks.startup import _export

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "hard.csv")
        subprocess.run([sys.executable, "-m", "twin.cli", "-q", "simulate", "-o", path, "--duration", str(duration),
                        "--seed", "3", "--controller", "continuous"], check=True, capture_output=True)
        trees = {"now": root}
        if baseline:
            trees["baseline"] = _export(baseline, os.path.join(d, "baseline"))
        argv = ["-q", "fit", path, *HARD_FIT]
        runs: dict[str, list[tuple[float, float]]] = {k: [] for k in trees}
        est: dict[str, dict] = {}
        for tree in trees.values():
            _command_cpu(tree, argv, threads)
        for _ in range(repeats):
            for which, tree in trees.items():
                cpu, wall, res = _command_cpu(tree, argv, threads)
                runs[which].append((cpu, wall))
                est[which] = {p: v["value"] for p, v in res["params"].items()} | {"nfev": res.get("nfev"),
                                                                                   "adequate": res["adequacy"].get(
                                                                                       "adequate")}
    out: dict = {"name": f"hard two-parameter fit, {duration:g} s record, analog controller: whole twin fit command",
                 "repeats": repeats, "baseline": baseline, "estimates": est, "numba_threads": threads,
                 "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}
    for which, rs in runs.items():
        out[which] = {"cpu_s": float(np.median([r[0] for r in rs])), "wall_s": float(np.median([r[1] for r in rs])),
                      "cpu_runs": [r[0] for r in rs]}
    if baseline:
        out["cpu_ratio"] = out["baseline"]["cpu_s"] / out["now"]["cpu_s"]
    return out


def _others(quick: bool) -> list[dict]:
    rows = []
    for mod in ("benchmarks.tracker", "benchmarks.diagnose", "benchmarks.replay", "benchmarks.failover"):
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise
            continue
        if hasattr(m, "run"):
            out = m.run(quick=quick) if "quick" in m.run.__code__.co_varnames else m.run()
            rows.append({"name": mod, "result": out})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    ap.add_argument("--quick", action="store_true", help="skip the longest rows")
    ap.add_argument("--core-only", action="store_true", help="only the model and fit rows")
    ap.add_argument("--user-rig", type=int, default=0, metavar="N",
                    help="only the 40 s five-parameter twin fit command on the user's rig against the paper's, "
                         "N interleaved runs each")
    ap.add_argument("--hard-command", type=int, default=0, metavar="N",
                    help="only the whole twin fit command on the paper's hard case (40 s, analog controller), N runs")
    ap.add_argument("--baseline", metavar="REV", help="with --hard-command: the same command from this git "
                    "revision's tree too, interleaved in the same run")
    ap.add_argument("--numba-threads", type=int, metavar="N",
                    help="with --hard-command: numba's threads in the commands (1: CPU time without the waiting)")
    args = ap.parse_args(argv)
    if args.hard_command:
        h = hard_fit_command(args.hard_command, args.baseline, threads=args.numba_threads)
        if args.json:
            print(json.dumps(h, indent=2))
            return 0
        line = f"{h['name']}: {h['now']['cpu_s']:.2f} s CPU ({h['now']['wall_s']:.2f} s wall)"
        if args.baseline:
            b = h["baseline"]
            line += (f"; the tree of {args.baseline} in the same run {b['cpu_s']:.2f} s CPU ({b['wall_s']:.2f} s "
                     f"wall): {h['cpu_ratio']:.2f}x")
        runs = "; runs " + ", ".join(f"{c:.2f}" for c in h["now"]["cpu_runs"])
        if args.baseline:
            runs += " against " + ", ".join(f"{c:.2f}" for c in h["baseline"]["cpu_runs"])
        print(line + f"; median of {h['repeats']}{runs} s CPU; numba threads {h['numba_threads'] or 'default'}; "
              f"load average {h['load_average_1min']:.1f}")
        print("estimates:", json.dumps(h["estimates"]))
        return 0
    if args.user_rig:
        r = user_rig_command(args.user_rig)
        if args.json:
            print(json.dumps(r, indent=2))
        else:
            print(f"{r['name']}: {r['value']:.2f} s (runs {', '.join(f'{v:.2f}' for v in r['runs'])}); "
                  f"{r['baseline']} (runs {', '.join(f'{v:.2f}' for v in r['baseline_runs'])}); ratio "
                  f"{r['ratio']:.2f}; target {r['target']}: {'met' if r['ok'] else 'MISSED'}")
        return 0
    print("compiling and warming up ...", file=sys.stderr)
    rows = bench_core(args.quick)
    extra = [] if args.core_only else _others(args.quick)
    if args.json:
        print(json.dumps({"core": rows, "other": extra}, indent=2, default=str))
        return 0
    print(f"{'benchmark':<66} {'ours':>12} {'baseline':>14} {'ratio':>9}  baseline is")
    for r in rows:
        flag = "" if "ok" not in r else ("  OK" if r["ok"] else f"  MISSES {r['target']}")
        print(f"{r['name']:<66} {r['value']:>9.3g} {r['unit']:<2} {r['baseline_value']:>11.4g} {r['unit']:<2} "
              f"{r['ratio']:>8.1f}x  {r['baseline']}{flag}")
    for r in extra:
        print(f"\n{r['name']}:")
        print(json.dumps(r["result"], indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
