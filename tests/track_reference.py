"""Records of the independent reference simulator (``tests.reference``) for the tracker's tests and figures.

Named scenarios (healthy with nominal, 2x and coloured noise; analog and 5 kHz
digital controllers; friction steps, valve wn decay, worn seal; the user's rig:
the demands ``chirp`` (on the analog controller), ``sweep``, ``blocks``, ``road``,
pressures at 500 Hz with CAN-jittered stamps ``can_rate``, warming oil ``warming``) built from
``tests.reference.msp25_spec`` and cached on disk (the simulator takes about
0.8 s per simulated second): ``$FPDD_REF_CACHE`` or
``~/.cache/fpdd-twin/reference``, one ``.npz`` per spec digest.  Nothing here
imports the product except :func:`to_samples`, which turns a record into the
product's :class:`replay.base.Samples` and the product's timing flag.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
for _p in (HERE, os.path.dirname(HERE)):  # the simulator is the top-level package ``reference`` (as in conftest)
    if _p not in sys.path:
        sys.path.insert(0, _p)

from reference import Record, msp25_spec, simulate_msp25  # noqa: E402
from reference.tables import MSP25_FREE  # noqa: E402

TWO_PI = 2.0 * math.pi
WN = MSP25_FREE["wn"]
LEAK = MSP25_FREE["CdAleak"]


#: the user's rigs (known values): a single-rod cylinder (area ratio 0.5) at KP 300 V/m, and an industrial PID whose
#: derivative is filtered with the time constant ``PID_TF``
SINGLE_ROD = {"AB": 960e-6, "V0B": 300e-6, "KP": 300.0}
PID = {"KP": 300.0, "KI": 2000.0, "KD": 0.6}
PID_TF = 1e-3
#: what the tracker is told of each user's-rig scenario (as its rigs.toml would say; it tracks from the logged u)
RIG_PARAMS = {"single_rod": SINGLE_ROD, "pid_filtered": {**PID, "Tf": PID_TF}}

#: healthy scenarios named by their demand kind (tests.reference.msp25.DEMAND_KINDS)
DEMANDS = ("chirp", "sweep", "blocks", "road")


def cache_dir() -> str:
    d = os.environ.get("FPDD_REF_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "fpdd-twin", "reference")
    os.makedirs(d, exist_ok=True)
    return d


def scenario(name: str, seed: int = 0, duration: float = 30.0) -> dict[str, Any]:
    """Keyword arguments of :func:`msp25_spec` for a named scenario, plus the product's timing flag.

    Healthy records draw their truth within +-20 % of Table 9 (the tracker,
    started at Table 9, starts away from it); fault records start at Table 9 so
    the default bands hold.
    """
    kw: dict[str, Any] = {"seed": seed, "duration": duration}
    controller = "digital"
    if name.startswith("healthy") or name in ("analog", "digital5k"):
        kw["truth"] = "draw"
    if name == "healthy":
        pass
    elif name == "healthy_2x":
        kw["noise"] = {"x": 4e-6, "pA": 4e4, "pB": 4e4}
    elif name == "healthy_ar1":
        kw["noise"] = {"x": 3e-6, "pA": 2e4, "pB": 2e4, "tau": 0.02}
    elif name == "analog":
        kw["controller"] = "analog"
        controller = "continuous"
    elif name == "digital5k":
        kw["rate_hz"] = 5000.0
        controller = "digital:5000"
    elif name == "friction_step":  # 60 -> 150 N at 12 s
        kw["truth"] = {"Ffric": 60.0}
        kw["time_varying"] = {"Ffric": {"kind": "step", "t0": 12.0, "before": 60.0, "after": 150.0}}
    elif name == "friction_step_small":  # 60 -> 90 N at 12 s
        kw["truth"] = {"Ffric": 60.0}
        kw["time_varying"] = {"Ffric": {"kind": "step", "t0": 12.0, "before": 60.0, "after": 90.0}}
    elif name == "wn_decay":  # 43 -> 30 Hz, linear over 20 s from 5 s
        kw["time_varying"] = {"wn": {"kind": "ramp", "t0": 5.0, "t1": 25.0, "start": WN, "end": TWO_PI * 30.0}}
    elif name == "worn_seal":  # leakage x1 -> x30, linear over 20 s from 5 s
        kw["time_varying"] = {"CdAleak": {"kind": "ramp", "t0": 5.0, "t1": 25.0, "start": LEAK, "end": 30 * LEAK}}
    elif name in DEMANDS:  # the test engineer's demands, healthy; the chirp on the analog controller
        kw["truth"] = "draw"
        kw["demand"] = {"kind": name}
        if name == "chirp":
            kw["controller"] = "analog"
            controller = "continuous"
    elif name == "can_rate":  # pressures at 500 Hz as the DBC logs them, time stamps with CAN jitter
        kw["truth"] = "draw"
        kw["signal_rates"] = {"pA": 500.0, "pB": 500.0}
        kw["time_jitter_s"] = 150e-6
    elif name == "single_rod":  # a single-rod cylinder (area ratio 0.5), the paper's demand, KP 300 V/m
        kw["truth"] = "draw"
        kw["known"] = dict(SINGLE_ROD)
    elif name == "pid_filtered":  # an industrial PID with a 1 ms derivative filter
        kw["truth"] = "draw"
        kw["known"] = dict(PID)
        kw["pid"] = {"Tf": PID_TF}
    elif name == "warming":  # oil 40 -> 60 C over 10 min: bulk modulus -12 %, leakage +15 %
        kw["truth"] = "draw"
        kw["temperature"] = {"T": {"kind": "ramp", "t0": 0.0, "t1": 600.0, "start": 313.15, "end": 333.15},
                             "b_visc": math.log(1.15) / 20.0}
        kw["signal_rates"] = {"T_oil": 10.0}
    else:
        raise ValueError(f"unknown scenario {name!r}")
    return {"spec": kw, "controller": controller}


def _digest(kw: dict) -> str:
    return hashlib.sha1(json.dumps(kw, sort_keys=True, default=str).encode()).hexdigest()[:16]


def record(name: str, seed: int = 0, duration: float = 30.0) -> tuple[Record, str]:
    """(reference record, the product's ``--controller`` value) of a scenario, from the cache if there."""
    sc = scenario(name, seed, duration)
    path = os.path.join(cache_dir(), f"{name}-{seed}-{duration:g}-{_digest(sc['spec'])}.npz")
    if os.path.exists(path):
        return Record.load(path), sc["controller"]
    rec = simulate_msp25(msp25_spec(**sc["spec"]))
    rec.save(path)
    return rec, sc["controller"]


def to_samples(rec: Record, t0_ns: int = 1_700_000_000_000_000_000):
    """The record as the product's :class:`replay.base.Samples` (ns timestamps, SI signals)."""
    from replay.base import Samples

    t_ns = t0_ns + np.round(rec.t * 1e9).astype(np.int64)
    return Samples(t_ns, {k: np.asarray(v, float) for k, v in rec.signals.items()})


def truth_at(rec: Record, name: str) -> np.ndarray:
    """True value of a free parameter at every log instant (time-varying or constant)."""
    if name in rec.hidden:
        return np.asarray(rec.hidden[name], float)
    return np.full(rec.t.size, float(rec.truth[name]))


def build(jobs: list[tuple[str, int, float]], workers: int = 1) -> None:
    """Fill the cache for ``jobs`` (name, seed, duration), in ``workers`` processes."""
    if workers <= 1:
        for j in jobs:
            record(*j)
        return
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(workers) as pool:
        pool.starmap(record, jobs)


#: the records the CI tests use (name, seed, duration)
CI_RECORDS = [
    ("healthy", 1, 30.0), ("healthy_2x", 2, 30.0), ("healthy_ar1", 3, 30.0), ("analog", 4, 30.0),
    ("digital5k", 5, 30.0), ("friction_step", 6, 20.0), ("wn_decay", 7, 20.0), ("worn_seal", 8, 20.0),
]

if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="fill the reference-record cache")
    ap.add_argument("--ci", action="store_true")
    ap.add_argument("--long", type=float, default=0.0, help="also healthy records of this many seconds each")
    ap.add_argument("--workers", type=int, default=1)
    a = ap.parse_args()
    jobs = list(CI_RECORDS) if a.ci else []
    if a.long:
        jobs += [(n, 100 + i, a.long) for i, n in enumerate(("healthy", "healthy_2x", "healthy_ar1", "analog",
                                                              "digital5k", "healthy"))]
    build(jobs, a.workers)
