"""Records of the independent reference simulator (``tests/reference``) for the diagnosis tests and the
confusion table, cached on disk.

Truth drawn off Table 9 per seed (3-20 % away), effects in the reference's own formulation with sizes
drawn per seed (a spool stroke limit as a fraction of the peak command the record reaches), a controller reading the noisy measured displacement (digital at the log's rate unless
said otherwise), white or AR(1) noise.  The cache key is the spec plus a digest of the reference's
sources, so a change of the simulator invalidates it.  Cache directory: ``$FPDD_REF_CACHE``, ``$FPDD_REFCACHE`` or
``<tmp>/fpdd-ref-cache``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import tempfile

import numpy as np

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:  # the reference is imported as tests.reference (its numba cache says so)
    sys.path.insert(0, _ROOT)

from tests.reference import msp25_spec, simulate_msp25  # noqa: E402
from tests.reference.record import Record as RefRecord  # noqa: E402
from twin.record import Record  # noqa: E402

CACHE = (os.environ.get("FPDD_REF_CACHE") or os.environ.get("FPDD_REFCACHE")
         or os.path.join(tempfile.gettempdir(), "fpdd-ref-cache"))
REF_DIR = os.path.join(_ROOT, "tests", "reference")

#: the reference's catalogue effects that the product's catalogue names the same way
IN_CATALOGUE = ("viscous_friction", "stribeck_friction", "laminar_leakage", "spool_deadband", "valve_null_bias",
                "supply_pressure_droop", "specimen_stiffness", "sensor_delay", "entrained_air", "spool_saturation",
                "position_sensor_gain", "pressure_sensor_offset", "supply_line_loss", "pressure_sensor_lag",
                "supply_dynamics")
OUT_OF_CATALOGUE = ("mechanical_resonance", "parameter_drift", "x_transducer_lag")

#: out-of-catalogue errors of the logging chain, applied to the reference's logged signals (the controller reads
#: the position upstream of them): effect -> (parameter, low, high) of the per-seed draw
LOGGED = {
    # a first-order lag of the logged displacement (a logging channel's filter): time constant [s]
    "x_transducer_lag": ("tau", 4e-3, 10e-3),
}


def _source_digest() -> str:
    h = hashlib.sha1()
    for name in sorted(os.listdir(REF_DIR)):
        if name.endswith(".py"):
            with open(os.path.join(REF_DIR, name), "rb") as f:
                h.update(name.encode() + f.read())
    return h.hexdigest()[:12]


#: a spool stroke limit is drawn as this fraction of the largest spool command of the same record without it
#: (a limit the valve command never reaches leaves no trace in the record: it is no effect of that record)
LIMIT_FRACTION = (0.5, 0.8)


def _stroke_limit(seed: int, duration: float, controller: str, tau: float, spec: dict) -> float:
    """A spool stroke limit the record reaches: a drawn fraction of the healthy record's peak command."""
    rec, info = reference_record((), seed=seed, duration=duration, controller=controller, tau=tau, **spec)
    known = info["meta"]["known"]
    peak = float(np.max(np.abs(rec["u"]))) * known["Ke"] * known["Ksp"]
    rng = np.random.default_rng([int(seed), 7919])
    return float(rng.uniform(*LIMIT_FRACTION) * peak)


def _logged(name: str, seed: int, rec: Record, info: dict) -> Record:
    """``rec`` with the logging-chain error ``name`` (``LOGGED``) at a size drawn per seed; the size goes into
    ``info["truth"]``."""
    par, lo, hi = LOGGED[name]
    v = float(np.random.default_rng([int(seed), 104729, sorted(LOGGED).index(name)]).uniform(lo, hi))
    info["truth"][f"{name}.{par}"] = v
    sig = dict(rec.signals)
    a = math.exp(-rec.dt / v)  # x_transducer_lag: exact for a signal held between samples
    x = np.asarray(sig["x"], float)
    y = np.empty_like(x)
    y[0] = x[0]
    for k in range(1, x.size):
        y[k] = a * y[k - 1] + (1.0 - a) * x[k]
    sig["x"] = y
    return Record(rec.dt, sig, rec.name)


def reference_record(effects=(), seed: int = 0, duration: float = 8.0, controller: str = "digital",
                     tau: float = 0.0, **spec) -> tuple[Record, dict]:
    """A reference record as the product reads it, and the truth behind it (``truth``, ``meta``); effects of
    the logging chain (``LOGGED``) are applied to the reference's record of the rest."""
    logged = [e for e in effects if e in LOGGED]
    if logged:
        rec, info = reference_record(tuple(e for e in effects if e not in LOGGED), seed, duration, controller,
                                     tau, **spec)
        info = {"truth": dict(info["truth"]), "meta": info["meta"]}
        for e in logged:
            rec = _logged(e, seed, rec, info)
        return Record(rec.dt, rec.signals, f"reference:{'+'.join(effects)}:{controller}:seed{seed}"), info
    noise = {"tau": float(tau)} if tau else "default"
    eff: list | dict = list(effects)
    if "spool_saturation" in eff:
        eff = {e: {} for e in eff}
        eff["spool_saturation"] = {"xs_max": _stroke_limit(seed, duration, controller, tau, spec)}
    kwargs = dict(seed=int(seed), duration=float(duration), controller=controller, truth="draw",
                  effects=eff, noise=noise, **spec)
    key = hashlib.sha1((json.dumps(kwargs, sort_keys=True, default=str) + _source_digest()).encode()).hexdigest()
    os.makedirs(CACHE, exist_ok=True)
    path = os.path.join(CACHE, f"msp25-{key[:20]}.npz")
    if os.path.exists(path):
        ref = RefRecord.load(path)
    else:
        kw = dict(kwargs)
        kw["effects"] = kw["effects"] if isinstance(kw["effects"], dict) else tuple(kw["effects"])
        ref = simulate_msp25(msp25_spec(**kw))
        ref.save(path)
    label = "+".join(effects) or "healthy"
    sig = {k: np.asarray(v, dtype=float) for k, v in ref.signals.items()}
    return Record(ref.dt, sig, f"reference:{label}:{controller}:seed{seed}"), {"truth": ref.truth, "meta": ref.meta}
