"""Tracker speed and accuracy, measured in one run (``python -m benchmarks.tracker [--json] [--accuracy]``).

Speed: the 14-state filter (6 model states + 5 parameters + 3 sensor-noise
states), 1 kHz data, x, pA, pB measured, with the consistency guard, sensor
checks and online noise learning on (the production settings):

* ours: the compiled UKF (:mod:`twin.online.ukf`), microseconds per sample (CPU time
  of this process, and wall time) and real-time factor on one core;
* stock: filterpy's ``UnscentedKalmanFilter`` with a per-sigma-point ``fx``
  written in plain numpy (the same equations, RK4 with the same substeps), on
  fewer samples; the ratio of the two, measured in the same run;
* fleet: how many 1 kHz rigs this machine tracks in real time, measured by
  filtering rigs in one worker process per core at once (spawned processes)
  and dividing the aggregate samples per second by 1000 (wall clock: other
  work on the machine lowers it); beside it the same from the workers' CPU
  time, what the cores would hold were they the filter's alone.

Targets: <= 20 us per sample on one core, >= 100 rigs at 1 kHz on 2 cores.

Before/after (always, and alone with ``--against-before``): the kernel as it was before the model interface
(``twin/online/ukf.py`` of git revision :data:`BEFORE_REV`, read with ``git show`` from the repository this
benchmark runs in: 47 positional arrays, the rig model built in) timed against the current
per-model kernel on the same record, interleaved, ``--repeats`` times each (medians, CPU time), with the
largest relative difference of their estimates: a ratio measured in the same run on a shared, noisy machine.
Target (issue 20): the current kernel <= 12 us per sample.  ``--models``: the kernel alone of every registered
model the online twin runs, interleaved, each against the default rig's (target: the oscillator's at least 5x
faster).  ``--new-models``: the tracker on the user's rig
(:data:`USER_RIG`: two areas, the filtered PID, a warming oil logged as ``T_oil``) against the paper's rig, same
excitation, interleaved, medians.

Accuracy (``--accuracy``, needs the repository's ``tests/reference``
simulator; records are cached, see ``tests/track_reference.py``): false
alarms per hour on the long healthy reference records (nominal, 2x and
coloured noise, analog and 5 kHz digital controllers with the matching
timing; bands centred on the drawn truth), the coverage of each parameter's
95 % interval there (the published one and the filter's own; sampled once a second after 20 s), and the detection
delays of a friction step, a valve wn decay and a worn seal over several seeds.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time

import numpy as np

#: the last revision whose filter kernel took 47 positional arrays with the MSP25 built in (before the model
#: interface): the baseline of the before/after timing
BEFORE_REV = "2c8e44e"


def _kernel_at(rev: str):
    """``twin/online/ukf.py`` as it was at git revision ``rev``, imported as a module of its own (its source is
    written to a temporary folder, so numba caches its compiled code there)."""
    import importlib.util
    import subprocess
    import tempfile

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    src = subprocess.run(["git", "show", f"{rev}:twin/online/ukf.py"], cwd=root, capture_output=True, text=True)
    if src.returncode != 0:
        raise SystemExit(f"benchmarks.tracker: the kernel of revision {rev} is needed as the baseline and git "
                         f"could not read it ({src.stderr.strip() or 'git show failed'}); run from a git clone")
    folder = os.path.join(tempfile.gettempdir(), "twin_bench_kernels")
    os.makedirs(folder, exist_ok=True)
    name = "ukf_" + "".join(c if c.isalnum() else "_" for c in rev)
    path = os.path.join(folder, name + ".py")
    try:
        with open(path) as f:
            same = f.read() == src.stdout
    except OSError:
        same = False
    if not same:  # rewritten only when it differs: numba's cache of it stays valid from run to run
        with open(path, "w") as f:
            f.write(src.stdout)
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # importable by its name: numba's cached code refers to its module by name
    spec.loader.exec_module(mod)
    return mod


#: the user's rig (issue 20's new models): a single-rod cylinder, the industrial PID with its filtered derivative,
#: and an oil warming 40 -> 60 degC over the record, logged as T_oil at 10 Hz (held on the 1 kHz grid)
USER_RIG = {"AB": 960e-6, "V0B": 300e-6, "KP": 300.0, "KI": 2000.0, "KD": 0.6, "Tf": 1e-3}


def _record(duration_s: float, seed: int = 0, user_rig: bool = False):
    from twin.models import DEFAULT_MODEL, get_model
    from twin.models.simulate import default_noise, excite, measure, ramp

    model = get_model(DEFAULT_MODEL)
    name, xr = excite(model, duration_s, 1e-3, seed=seed)
    if not user_rig:
        return measure(model, model.params(), name, xr, 1e-3, noise=default_noise(model), seed=seed)
    return measure(model, model.params((), **USER_RIG), name, xr, 1e-3, noise=default_noise(model), seed=seed,
                   exogenous={"T_oil": ramp(313.15, 333.15, xr.size)}, exogenous_every=100)


def new_models(repeats: int = 3, duration: float = 20.0) -> dict:
    """The tracker on the user's rig (:data:`USER_RIG`: two areas, the filtered PID, a logged warming oil) against
    the same tracker on the paper's rig, same excitation, interleaved; CPU us per sample (medians)."""
    from twin.online.tracker import OnlineTracker

    recs = {"paper_rig": (_record(duration).to_samples(), {}),
            "user_rig": (_record(duration, user_rig=True).to_samples(), USER_RIG)}
    for s, known in recs.values():
        OnlineTracker(params=known).process(s.slice(0, 20))  # compile / load outside the clock
    times: dict[str, list[float]] = {k: [] for k in recs}
    for _ in range(repeats):
        for key, (s, known) in recs.items():
            tr = OnlineTracker(params=known)
            c0 = time.process_time()
            tr.process(s)
            times[key].append((time.process_time() - c0) / len(s) * 1e6)
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"cpu_us_per_sample": times, "median": med, "ratio_user_over_paper": med["user_rig"] / med["paper_rig"],
            "target_user_rig<=12us": med["user_rig"] <= 12.0,
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


def _stock_filter(tr, rec, n_samples: int):
    """filterpy's UKF with a plain-numpy fx per sigma point; returns (seconds per sample, estimates)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    from twin.online import ukf
    from benchmarks.fit import _numpy_step

    n, nm = tr.n, tr.nmod
    scale = tr.scale
    base = tr.pvec.copy()
    a = tr.ch[:, ukf.H_A].copy()

    def fx(x, dt, u):
        p = base.copy()
        p[tr.idx] = tr.values_of(x[6:nm])
        s = _numpy_step((x[:6] * scale)[None, :], np.array([u]), p[None, :], dt, tr.substeps)[0]
        return np.concatenate([s / scale, x[6:nm], a * x[nm:]])

    pts = MerweScaledSigmaPoints(n, alpha=tr.alpha, beta=tr.beta, kappa=tr.kappa)
    f = UnscentedKalmanFilter(dim_x=n, dim_z=3, dt=1e-3, hx=lambda x: x[tr.meas_idx] + x[nm:], fx=fx, points=pts)
    f.x = tr.x.copy()
    f.P = tr.P.copy()
    tr.dt = 1e-3
    f.Q = tr.process_noise(1e-3)
    f.R = np.diag(tr.R_floor)
    Z = np.stack([rec["x"] / 1e-3, rec["pA"] / 1e6, rec["pB"] / 1e6], axis=1)
    est = np.empty((n_samples, len(tr.tracked)))
    f.sigmas_f = pts.sigma_points(f.x, f.P)
    t0 = time.perf_counter()
    for k in range(n_samples):
        if k > 0:
            f.predict(u=rec["u"][k - 1])
        f.update(Z[k])
        est[k] = tr.values_of(f.x[6:nm])
    return (time.perf_counter() - t0) / n_samples, est


def _worker(args):
    duration_s, rigs, seed = args
    from twin.online.tracker import OnlineTracker

    rec = _record(duration_s, seed)
    s = rec.to_samples()
    OnlineTracker().process(s.slice(0, 50))  # compile/load outside the clock
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(rigs):
        OnlineTracker().process(s)
    return rigs * len(s), time.perf_counter() - t0, time.process_time() - c0


def run(quick: bool = False) -> dict:
    from twin.online.tracker import OnlineTracker

    duration = 10.0 if quick else 20.0
    rec = _record(duration)
    s = rec.to_samples()
    OnlineTracker().process(s.slice(0, 20))  # compile
    tr = OnlineTracker()
    c0, t0 = time.process_time(), time.perf_counter()
    tr.process(s)
    ours_cpu = (time.process_time() - c0) / len(s)
    ours = (time.perf_counter() - t0) / len(s)
    n_stock = 100 if quick else 300
    c0 = time.process_time()
    stock, est_stock = _stock_filter(OnlineTracker(excite=(0.0, 0.0, 0.0), gate_p=1e-300, adapt_noise=False), rec,
                                     n_stock)
    stock_cpu = (time.process_time() - c0) / n_stock
    plain = OnlineTracker(excite=(0.0, 0.0, 0.0), gate_p=1e-300, adapt_noise=False)
    out = plain.process(s.slice(0, n_stock))
    diff = float(np.max(np.abs(est_stock / out.estimates - 1.0)))
    cores = os.cpu_count() or 1
    rigs_each = 2 if quick else 4
    ctx = mp.get_context("spawn")
    with ctx.Pool(cores) as pool:
        res = pool.map(_worker, [(duration, rigs_each, 10 + i) for i in range(cores)])
    samples = sum(r[0] for r in res)
    wall = max(r[1] for r in res)
    rigs_rt = samples / wall / 1000.0
    rigs_cpu = sum(r[0] / r[2] for r in res) / 1000.0  # each worker on a core of its own
    return {
        "ours_us_per_sample": ours * 1e6, "ours_cpu_us_per_sample": ours_cpu * 1e6,
        "ours_realtime_factor": 1e-3 / ours,
        "stock_us_per_sample": stock * 1e6, "stock_cpu_us_per_sample": stock_cpu * 1e6,
        "stock_realtime_factor": 1e-3 / stock,
        "speedup_vs_stock": stock / ours, "speedup_vs_stock_cpu": stock_cpu / ours_cpu,
        "max_rel_estimate_difference": diff, "stock_samples": n_stock,
        "fleet_cores": cores, "fleet_rigs_realtime_1kHz": rigs_rt, "fleet_rigs_1kHz_by_cpu_time": rigs_cpu,
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "targets": {"cpu_us_per_sample<=20": ours_cpu * 1e6 <= 20.0, "rigs>=100": rigs_rt >= 100},
    }


def _before_tracker_class():
    """An :class:`~twin.online.tracker.OnlineTracker` whose compiled call is the kernel of
    revision :data:`BEFORE_REV` (the same filter before the model interface), given the arrays it took."""
    old = _kernel_at(BEFORE_REV)
    from twin.online import ukf
    from twin.online.tracker import OnlineTracker

    class BeforeTracker(OnlineTracker):
        def _run_kernel(self, block, closed, ticks, mode, out):
            g = self.guard_settings
            stroke, (pmin, pmax) = self.ranges["x"][1], self.ranges["pA"]
            cfg = np.array([float(g[k]) for k in ukf.CFG_NAMES if k != "warm_s"]
                           + [stroke, pmin, pmax, float(g["warm_s"])])
            setup = self._setup()
            return old.run_kernel(
                self.x, self.P, self.fs, self.ch, self.x_ck, self.P_ck, block.U, block.XREF, block.Z, block.DT,
                self.meas_idx, closed, ticks, mode, self.dt, self.pvec, self.idx, self.lo_log, self.width,
                self.scale, self.substeps, self.q_state, setup.q_param, self.prior_model, self.Wm, self.Wc,
                self.lam, self.floor, self.gate, self.max_gated, self.chan, self.excite_thresh, self.tau_excite,
                self.fb_col, cfg, *out)

    return BeforeTracker


def against_before(repeats: int = 3, duration: float = 20.0) -> dict:
    """The current kernel against the one before the model interface, same record, interleaved; CPU us per sample
    (medians) and the largest relative difference of the estimates."""
    from twin.online.tracker import OnlineTracker

    Before = _before_tracker_class()
    s = _record(duration).to_samples()
    kinds = {"current": OnlineTracker, "before": Before}
    for cls in kinds.values():
        cls().process(s.slice(0, 20))  # compile / load outside the clock
    times: dict[str, list[float]] = {k: [] for k in kinds}
    est = {}
    for _ in range(repeats):
        for key, cls in kinds.items():
            tr = cls()
            c0 = time.process_time()
            out = tr.process(s)
            times[key].append((time.process_time() - c0) / len(s) * 1e6)
            est[key] = out.estimates
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"cpu_us_per_sample": times, "median": med, "speedup": med["before"] / med["current"],
            "max_rel_estimate_difference": float(np.max(np.abs(est["current"] / est["before"] - 1.0))),
            "target_current<=12us": med["current"] <= 12.0,
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


# --- accuracy on the reference simulator --------------------------------------------------------
LONG_HEALTHY = [("healthy", 100), ("healthy_2x", 101), ("healthy_ar1", 102), ("analog", 103), ("digital5k", 104),
                ("healthy", 105)]
FAULT_SEEDS = (6, 16, 26)


def _reference():
    tests = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    import track_reference as ref  # the repository's independent simulator, through its cache

    return ref


def _track_reference(rec, controller, base, chunk=5000):
    from twin.online.drift import DriftMonitor
    from twin.models.base import Timing
    from twin.online.tracker import OnlineTracker

    ref = _reference()
    s = ref.to_samples(rec)
    tr = OnlineTracker(timing=Timing.parse(controller))
    dm = DriftMonitor("ref", base)
    events, est, std, tstd = [], [], [], []
    t0 = int(s.t_ns[0])
    for i in range(0, len(s), chunk):
        out = tr.process(s.slice(i, i + chunk))
        events += dm.update_block(tr.tracked, out.t_ns, (out.t_ns - t0) * 1e-9, out.estimates, out.log_std,
                                  out.frozen, out.hold, out.guard)
        est.append(out.estimates[::1000])
        std.append(out.interval_stds[::1000])
        tstd.append(out.stds[::1000])
    return tr, events, np.concatenate(est), np.concatenate(std), np.concatenate(tstd)


def accuracy(duration: float = 600.0, fault_duration: float = 20.0) -> dict:
    from twin.models import DEFAULT_MODEL
    from twin.online.baseline import Baseline, default_baseline

    ref = _reference()
    nominal = default_baseline(DEFAULT_MODEL)
    out: dict = {"healthy": [], "faults": {}}
    hours = 0.0
    n_alarms = 0
    hits: dict[str, list] = {}
    hits_tracking: dict[str, list] = {}
    for name, seed in LONG_HEALTHY:
        rec, controller = ref.record(name, seed, duration)
        base = {n: Baseline(float(rec.truth[n]), float(rec.truth[n]) * b.lo / b.value,
                            float(rec.truth[n]) * b.hi / b.value) for n, b in nominal.items()}
        tr, events, est, std, tstd = _track_reference(rec, controller, base)
        raised = [e for e in events if e.kind in ("raised", "escalated")]
        hours += duration / 3600.0
        n_alarms += len(raised)
        t = np.arange(est.shape[0])  # one per second
        keep = t >= 20
        cover = {}
        for j, n in enumerate(tr.tracked):
            z = (est[keep, j] - float(rec.truth[n])) / std[keep, j]
            inside = np.abs(z) <= 1.96
            hits.setdefault(n, []).append(inside)
            hits_tracking.setdefault(n, []).append(np.abs(est[keep, j] - float(rec.truth[n])) <= 1.96 * tstd[keep, j])
            cover[n] = float(np.mean(inside))
        out["healthy"].append({"record": name, "seed": seed, "controller": controller, "seconds": duration,
                               "events": len(raised), "coverage95": cover,
                               "noise": {o: round(v["std"] / v["nominal"], 3) for o, v in tr.noise_levels().items()},
                               "ar1": {o: round(v["ar1"], 3) for o, v in tr.noise_levels().items()}})
    out["false_alarms_per_hour"] = n_alarms / hours
    out["healthy_hours"] = hours
    out["coverage95"] = {n: float(np.mean(np.concatenate(v))) for n, v in hits.items()}
    out["coverage95_tracking_std"] = {n: float(np.mean(np.concatenate(v))) for n, v in hits_tracking.items()}
    for name, param in (("friction_step", "Ffric"), ("friction_step_small", "Ffric"), ("wn_decay", "wn"),
                        ("worn_seal", "CdAleak")):
        delays, wrong = [], 0
        for seed in FAULT_SEEDS:
            rec, controller = ref.record(name, seed, fault_duration)
            tr, events, _, _, _ = _track_reference(rec, controller, nominal)
            b = nominal[param]
            v = ref.truth_at(rec, param)
            out_idx = np.flatnonzero((v < b.lo) | (v > b.hi))
            t_cross = float(rec.t[out_idx[0]]) if out_idx.size else None
            alarms = [e for e in events if e.level == "alarm" and e.parameter == param]
            wrong += len({e.parameter for e in events} - {param})
            delays.append(alarms[0].t_s - t_cross if (alarms and t_cross is not None) else None)
        out["faults"][name] = {"parameter": param, "delays_s": delays, "wrong_parameter_events": wrong}
    return out


def _print_before(a: dict) -> None:
    for k, v in a["cpu_us_per_sample"].items():
        print(f"{k:>8s} kernel: median {a['median'][k]:6.2f} us/sample CPU (runs: {', '.join(f'{t:.2f}' for t in v)})")
    print(f"current / before: {1.0 / a['speedup']:.3f} (speed-up {a['speedup']:.2f}x); largest relative difference of "
          f"the estimates {a['max_rel_estimate_difference']:.1e}; current <= 12 us/sample: "
          f"{'OK' if a['target_current<=12us'] else 'MISSED'} (load average {a['load_average_1min']})")


def models_kernel(repeats: int = 5, duration: float = 20.0) -> dict:
    """The compiled kernel alone (CPU time of its calls, :func:`twin.online.ukf.kernel_for`) of every registered
    model the online twin runs, each on its own default excitation and noise, interleaved ``repeats`` times;
    medians in us per sample and each model's speed-up over the default rig's kernel in the same run (target: the
    oscillator's at least 5x)."""
    from twin.models import DEFAULT_MODEL, MODELS, get_model
    from twin.models.simulate import default_noise, excite, measure
    from twin.online import ukf
    from twin.online.tracker import OnlineTracker

    spent = [0.0]
    kernel_for = ukf.kernel_for

    def timed(model):
        run = kernel_for(model)

        def call(*a):
            c0 = time.process_time()
            try:
                return run(*a)
            finally:
                spent[0] += time.process_time() - c0
        return call

    recs = {}
    for name in MODELS:
        m = get_model(name)
        if m.FILTER is None:
            continue
        kind, xr = excite(m, duration, 1e-3, seed=0)
        recs[name] = measure(m, m.params(), kind, xr, 1e-3, noise=default_noise(m), seed=0).to_samples()
    times: dict[str, list[float]] = {k: [] for k in recs}
    ukf.kernel_for = timed
    try:
        for name, s in recs.items():
            OnlineTracker(model=name).process(s.slice(0, 20))  # compile / load outside the clock
        for _ in range(repeats):
            for name, s in recs.items():
                spent[0] = 0.0
                OnlineTracker(model=name).process(s)
                times[name].append(spent[0] / len(s) * 1e6)
    finally:
        ukf.kernel_for = kernel_for
    med = {k: float(np.median(v)) for k, v in times.items()}
    base = med[DEFAULT_MODEL]
    return {"cpu_us_per_sample": times, "median": med, "speedup_over_default": {k: base / v for k, v in med.items()},
            "default_model": DEFAULT_MODEL, "states": {k: OnlineTracker(model=k).n for k in recs},
            "target_oscillator>=5x": base / med["oscillator"] >= 5.0 if "oscillator" in med else None,
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


#: one tree's kernels, run from that tree (``PYTHONPATH``): every registered model's kernel alone on its default
#: record (fastest of ``REPEATS`` calls on one captured block, after a warm-up), and its estimates at the end
_KERNEL_WORKER = """
import json, sys, time
import numpy as np
from twin.models import MODELS, get_model
from twin.models.simulate import default_noise, excite, measure
from twin.online import ukf
from twin.online.tracker import OnlineTracker
repeats, duration = int(sys.argv[1]), float(sys.argv[2])
out = {}
for name in MODELS:
    m = get_model(name)
    if m.FILTER is None:
        continue
    kind, xr = excite(m, duration, 1e-3, seed=0)
    s = measure(m, m.params(), kind, xr, 1e-3, noise=default_noise(m), seed=0).to_samples()
    tr = OnlineTracker(model=name)
    got = {}
    run_kernel = tr._run_kernel

    def grab(block, closed, ticks, mode, o):
        got["call"] = (tr._setup(), tuple(a.copy() for a in (tr.x, tr.P, tr.fs, tr.ch, tr.x_ck, tr.P_ck)), block,
                       closed, ticks, mode, o)
        return run_kernel(block, closed, ticks, mode, o)

    tr._run_kernel = grab
    est = tr.process(s).estimates[-1]
    setup, carry, block, closed, ticks, mode, o = got["call"]
    run = ukf.kernel_for(m)
    times = []
    for _ in range(repeats):
        c = ukf.Carry(*(a.copy() for a in carry))
        t0 = time.process_time()
        run(setup, c, block, closed, ticks, mode, o)
        times.append((time.process_time() - t0) / len(s) * 1e6)
    out[name] = {"fastest": min(times), "median": float(np.median(times)), "estimates": [float(v) for v in est]}
print(json.dumps(out))
"""


def models_against(baseline: str, rounds: int = 3, repeats: int = 15, duration: float = 20.0) -> dict:
    """Every registered model's kernel alone, this tree against the tree of the git revision ``baseline``, each in
    its own fresh process (the two trees cannot share one), ``rounds`` interleaved pairs (a warm-up pair first: a
    fresh tree compiles its kernels); per round the fastest of ``repeats`` calls on the same captured block
    (:data:`_KERNEL_WORKER`); medians over the rounds, and the largest relative difference of the estimates at the
    end of each model's record (0: the same numbers)."""
    import subprocess
    import tempfile

    from benchmarks.startup import _export

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory() as d:
        trees = {"now": root, "baseline": _export(baseline, os.path.join(d, "baseline"))}
        worker = os.path.join(d, "kernels.py")
        with open(worker, "w") as f:
            f.write(_KERNEL_WORKER)

        def once(tree: str, n: int) -> dict:
            p = subprocess.run([sys.executable, worker, str(n), str(duration)], cwd=tree, capture_output=True,
                               text=True, env=dict(os.environ, PYTHONPATH=tree))
            if p.returncode != 0:
                raise RuntimeError(f"the kernels of {tree} failed: {p.stderr.strip().splitlines()[-1:]}")
            return json.loads(p.stdout)

        for tree in trees.values():
            once(tree, 1)
        runs: dict[str, list[dict]] = {k: [] for k in trees}
        for _ in range(rounds):
            for which, tree in trees.items():
                runs[which].append(once(tree, repeats))
    models = sorted(set(runs["now"][0]) & set(runs["baseline"][0]))
    out: dict = {"baseline": baseline, "rounds": rounds, "repeats": repeats, "models": {},
                 "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}
    for name in models:
        now = float(np.median([r[name]["fastest"] for r in runs["now"]]))
        base = float(np.median([r[name]["fastest"] for r in runs["baseline"]]))
        a = np.array(runs["now"][-1][name]["estimates"])
        b = np.array(runs["baseline"][-1][name]["estimates"])
        rel = float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300))) if a.shape == b.shape else float("inf")
        out["models"][name] = {"now_us": now, "baseline_us": base, "speedup": base / now,
                               "now_runs": [r[name]["fastest"] for r in runs["now"]],
                               "baseline_runs": [r[name]["fastest"] for r in runs["baseline"]],
                               "max_rel_estimate_difference": rel}
    return out


def confirm_cost(duration: float = 60.0) -> dict:
    """The tracker alone against the tracker with its alarms confirmed by window re-fits
    (:class:`twin.online.confirm.ConfirmedDrift`: scheduled every period, triggered by the drift test) on the same
    record, CPU time per sample, in the same run."""
    from twin.online.baseline import default_baseline
    from twin.online.confirm import PERIOD_S, WINDOW_S, track_confirmed
    from twin.online.tracker import OnlineTracker

    s = _record(duration).to_samples()
    OnlineTracker().process(s.slice(0, 2000))  # compiled before timing
    t0 = time.process_time()
    tr = OnlineTracker()
    for i in range(0, len(s), 1000):
        tr.process(s.slice(i, min(len(s), i + 1000)))
    alone = (time.process_time() - t0) / len(s) * 1e6
    t0 = time.process_time()
    cd, _ = track_confirmed(s, OnlineTracker(), default_baseline("msp25"))
    both = (time.process_time() - t0) / len(s) * 1e6
    return {"seconds": duration, "window_s": WINDOW_S, "period_s": PERIOD_S, "refits": cd.n_fits,
            "tracker_cpu_us_per_sample": alone, "confirmed_cpu_us_per_sample": both,
            "cpu_s_per_refit": (both - alone) * len(s) * 1e-6 / max(cd.n_fits, 1), "ratio": both / alone,
            "load_average_1min": round(os.getloadavg()[0], 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.tracker", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="shorter records")
    ap.add_argument("--accuracy", action="store_true", help="false alarms, coverage and delays on the reference "
                                                            "simulator's records (long; cached)")
    ap.add_argument("--seconds", type=float, default=600.0, help="length of each healthy record (--accuracy)")
    ap.add_argument("--against-before", action="store_true",
                    help="only time the current kernel against the one before the model interface")
    ap.add_argument("--new-models", action="store_true",
                    help="only time the tracker on the user's rig (two areas, filtered PID, logged warming oil) "
                         "against the paper's rig")
    ap.add_argument("--models", action="store_true",
                    help="only the kernel of every registered model, each against the default rig's kernel")
    ap.add_argument("--baseline", metavar="REV", help="with --models: every model's kernel from this git "
                    "revision's tree too, in fresh processes interleaved with this tree's, estimates compared")
    ap.add_argument("--repeats", type=int, default=3, help="interleaved runs of each kernel (before/after)")
    ap.add_argument("--confirm", action="store_true",
                    help="only the cost of confirming alarms by window re-fits, against the tracker alone")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.confirm:
        c = confirm_cost(20.0 if args.quick else 60.0)
        if args.json:
            print(json.dumps(c, indent=2))
            return 0
        print(f"tracker alone {c['tracker_cpu_us_per_sample']:.1f} us/sample CPU; with confirmed alarms "
              f"({c['refits']} re-fits of {c['window_s']:g} s windows, scheduled every {c['period_s']:g} s, in "
              f"{c['seconds']:g} s) {c['confirmed_cpu_us_per_sample']:.1f} us/sample: ratio {c['ratio']:.1f}, "
              f"{c['cpu_s_per_refit']:.2f} s CPU per re-fit (load average {c['load_average_1min']})")
        return 0
    if args.models and args.baseline:
        mb = models_against(args.baseline, rounds=args.repeats)
        if args.json:
            print(json.dumps(mb, indent=2))
            return 0
        for k, v in mb["models"].items():
            print(f"{k:12s} kernel {v['now_us']:6.2f} us/sample CPU, {args.baseline} {v['baseline_us']:6.2f} "
                  f"(medians of {mb['rounds']} interleaved rounds, each the fastest of {mb['repeats']} calls): "
                  f"{v['speedup']:.2f}x; largest relative difference of the estimates {v['max_rel_estimate_difference']:.1e}")
        print(f"(load average {mb['load_average_1min']})")
        return 0
    if args.baseline:
        print("--baseline: only with --models", file=sys.stderr)
        return 2
    if args.models:
        mk = models_kernel(max(args.repeats, 5), 10.0 if args.quick else 20.0)
        if args.json:
            print(json.dumps(mk, indent=2))
            return 0
        for k, v in mk["median"].items():
            print(f"{k:12s} kernel {v:6.2f} us/sample CPU (median of {len(mk['cpu_us_per_sample'][k])}), "
                  f"{mk['states'][k]} filter states, {mk['speedup_over_default'][k]:.2f}x the {mk['default_model']} "
                  "kernel's speed")
        print(f"target: the oscillator's kernel at least 5x the {mk['default_model']}'s: "
              f"{'met' if mk['target_oscillator>=5x'] else 'MISSED'} (load average {mk['load_average_1min']})")
        return 0
    if args.new_models:
        nm = new_models(args.repeats, 10.0 if args.quick else 20.0)
        if args.json:
            print(json.dumps(nm, indent=2))
            return 0
        print(f"user's rig (two areas, filtered PID, T_oil logged): {nm['median']['user_rig']:.2f} us/sample CPU "
              f"(median of {args.repeats}); paper's rig in the same run: {nm['median']['paper_rig']:.2f}; ratio "
              f"{nm['ratio_user_over_paper']:.2f}; target <= 12 us: "
              f"{'met' if nm['target_user_rig<=12us'] else 'MISSED'} (load average {nm['load_average_1min']})")
        return 0
    if args.against_before:
        a = against_before(args.repeats, 10.0 if args.quick else 20.0)
        if args.json:
            print(json.dumps(a, indent=2))
            return 0
        _print_before(a)
        return 0
    if args.accuracy:
        r = accuracy(args.seconds)
        if args.json:
            print(json.dumps(r, indent=2))
            return 0
        print(f"false alarms: {r['false_alarms_per_hour']:.2f} per hour over {r['healthy_hours']:.2f} h of healthy "
              "records")
        for h in r["healthy"]:
            print(f"  {h['record']:12s} seed {h['seed']:3d} ({h['controller']}): {h['events']} event(s); noise x "
                  f"{h['noise']}, AR(1) {h['ar1']}")
        print("coverage of the published 95 % intervals: "
              + ", ".join(f"{n} {v:.1%}" for n, v in r["coverage95"].items()))
        print("  (of +-1.96 of the filter's own std, wider by its random walk: "
              + ", ".join(f"{n} {v:.1%}" for n, v in r["coverage95_tracking_std"].items()) + ")")
        for name, f in r["faults"].items():
            d = ", ".join("missed" if x is None else f"{x:.2f} s" for x in f["delays_s"])
            print(f"{name:20s} {f['parameter']:8s} delays {d}; events on other parameters: "
                  f"{f['wrong_parameter_events']}")
        return 0
    r = run(args.quick)
    r["before_after"] = against_before(args.repeats, 10.0 if args.quick else 20.0)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    _print_before(r["before_after"])
    print(f"ours : {r['ours_cpu_us_per_sample']:8.1f} us/sample CPU ({r['ours_us_per_sample']:.1f} wall), "
          f"{r['ours_realtime_factor']:8.1f}x real time (guard, sensor checks, noise learning on)")
    print(f"stock: {r['stock_cpu_us_per_sample']:8.1f} us/sample CPU ({r['stock_us_per_sample']:.1f} wall), "
          f"{r['stock_realtime_factor']:8.3f}x real time (filterpy UKF, numpy fx per sigma point, "
          f"{r['stock_samples']} samples)")
    print(f"ratio: {r['speedup_vs_stock_cpu']:.0f}x (CPU), {r['speedup_vs_stock']:.0f}x (wall); largest relative "
          f"difference of the estimates: {r['max_rel_estimate_difference']:.2e}")
    print(f"fleet: {r['fleet_rigs_realtime_1kHz']:.0f} rigs at 1 kHz in real time on {r['fleet_cores']} cores "
          f"(wall clock, load average {r['load_average_1min']}); {r['fleet_rigs_1kHz_by_cpu_time']:.0f} by the "
          "workers' CPU time (cores of their own)")
    print("targets:", ", ".join(f"{k} {'OK' if v else 'MISSED'}" for k, v in r["targets"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
