"""Demands made of parts, step demands, and sensors that drift: the reference simulator's own formulation.

* ``steps``: a staircase of levels drawn uniformly in ``[-A, A]`` (seeded), each held a dwell drawn in
  ``[dwell_lo, dwell_hi]`` s, the moves between them raised cosines no faster than the rig's speed limit
  (a move of ``h`` takes ``max(rise_s, pi |h| / (2 v_max))``: a raised cosine's peak speed is
  ``pi h / (2 T)``).
* ``sequence``: parts of any demand kind one after the other (``parts``: ``{"kind", "seconds", ...}``, each
  part's own settings over its kind's defaults, each drawn from its own seed), the whole starting at
  ``onset_s`` (the demand's offset before it), each part faded out over ``fade_s`` at its end (the parts'
  own ramps fade them in).

Both are evaluated on a grid of ``grid_hz`` and stored as a not-a-knot cubic spline table (the simulator's
``cubic`` signal), which the right-hand side and the controllers read at any instant.

Sensor drift (``sensor_drift`` of a spec): per logged sensor ``x``, ``pA``, ``pB`` an ``offset`` (SI), a
``gain`` (1) and an extra white ``noise`` standard deviation (SI), each a number or a time variation
(``{"kind": "step", "t0", "after"}``, ``{"kind": "ramp", "t0", "t1", "end"}``, ``{"kind": "exp", "t0", "tau",
"end"}``; from 0, 1 and 0).  The reading is ``gain(t) (value + noise) + offset(t) + extra(t) w`` with ``w``
a seeded standard normal sequence of its own.  The position sensor is the one the controller reads, so its
drift moves the rod (digital controllers only: the analog controller's reading is inside the ODE).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import numba as nb
import numpy as np

from .signals import sig_eval

SENSORS = ("x", "pA", "pB")
DRIFT_DEFAULT = {"offset": 0.0, "gain": 1.0, "noise": 0.0}
STEPS_DEFAULT = {"kind": "steps", "amplitude": 5e-3, "v_max": 0.25, "dwell_lo": 0.5, "dwell_hi": 2.0,
                 "rise_s": 0.02, "offset": 0.0, "intersample": "analytic"}
SEQUENCE_DEFAULT = {"kind": "sequence", "parts": [], "onset_s": 0.0, "fade_s": 0.2, "grid_hz": 2000.0,
                    "offset": 0.0, "intersample": "analytic"}


@nb.njit(cache=True)
def _eval_many(sigp, sc, ts):
    out = np.empty(ts.size)
    for i in range(ts.size):
        out[i] = sig_eval(sigp, sc, ts[i], -1)
    return out


def steps_values(dem: Mapping, seed: int, t: np.ndarray) -> np.ndarray:
    """The staircase of a ``steps`` demand at the times ``t`` (from 0), without its offset."""
    rng = np.random.default_rng([int(seed), 7004])
    a, vmax = float(dem["amplitude"]), float(dem["v_max"])
    out = np.zeros(t.size)
    t_now, level = 0.0, 0.0
    end = float(t[-1]) if t.size else 0.0
    while t_now <= end:
        new = float(rng.uniform(-a, a))
        rise = max(float(dem["rise_s"]), math.pi * abs(new - level) / (2.0 * vmax))
        dwell = float(rng.uniform(dem["dwell_lo"], dem["dwell_hi"]))
        m = (t >= t_now) & (t < t_now + rise)
        out[m] = level + (new - level) * 0.5 * (1.0 - np.cos(math.pi * (t[m] - t_now) / rise))
        m = t >= t_now + rise
        out[m] = new
        t_now += rise + dwell
        level = new
    return out


def demand_values(dem: Mapping, seed: int, duration: float,
                  part_table: Callable[[dict, int, float], tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """``(times, values)`` of a ``steps`` or ``sequence`` demand on its grid over ``[0, duration]`` (with the
    offset). ``part_table(part, seed, seconds)``: the simulator's table of an analytic demand part."""
    grid = float(dem.get("grid_hz", SEQUENCE_DEFAULT["grid_hz"]))
    t = np.arange(int(math.ceil(duration * grid)) + 2) / grid
    if dem["kind"] == "steps":
        return t, steps_values(dem, seed, t) + float(dem["offset"])
    v = np.zeros(t.size)
    t_part = float(dem["onset_s"])
    fade = float(dem["fade_s"])
    for i, part in enumerate(dem["parts"]):
        seconds = float(part["seconds"])
        pseed = int(seed) * 64 + i + 1
        local = t - t_part
        m = (local >= 0.0) & (local < seconds)
        if m.any():
            if part["kind"] == "steps":
                vals = steps_values({**STEPS_DEFAULT, **part}, pseed, local[m])
            else:
                sigp, sc = part_table(dict(part), pseed, seconds)
                vals = _eval_many(sigp, sc, np.ascontiguousarray(local[m])) - float(sigp[5])
            tail = seconds - local[m]
            w = np.where(tail < fade, 0.5 * (1.0 - np.cos(math.pi * np.clip(tail / fade, 0.0, 1.0))), 1.0)
            v[m] += vals * w
        t_part += seconds
    return t, v + float(dem["offset"])


def variation_at(var, default: float, t: np.ndarray) -> np.ndarray:
    """A sensor drift's value at ``t``: a number, or a step, ramp or exponential from ``default``."""
    t = np.asarray(t, float)
    if var is None:
        return np.full(t.shape, float(default))
    if isinstance(var, (int, float)):
        return np.full(t.shape, float(var))
    kind = var.get("kind")
    v0 = float(var.get("start", var.get("before", default)))
    t0 = float(var["t0"])
    if kind == "step":
        return np.where(t < t0, v0, float(var["after"]))
    if kind == "ramp":
        t1 = float(var["t1"])
        return v0 + (float(var["end"]) - v0) * np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    if kind == "exp":
        v1 = float(var["end"])
        return np.where(t <= t0, v0, v1 + (v0 - v1) * np.exp(-np.maximum(t - t0, 0.0) / float(var["tau"])))
    raise ValueError(f"sensor drift: variation kind must be step, ramp or exp, got {kind!r}")


def drift_spec(drift: Mapping | None) -> dict:
    """A complete ``sensor_drift`` (checked, every sensor's three terms filled in)."""
    out: dict = {}
    for name, terms in (drift or {}).items():
        if name not in SENSORS:
            raise ValueError(f"sensor_drift: unknown sensor {name!r}; known: {', '.join(SENSORS)}")
        unknown = set(terms) - set(DRIFT_DEFAULT)
        if unknown:
            raise ValueError(f"sensor_drift.{name}: unknown term(s) {sorted(unknown)}; known: {list(DRIFT_DEFAULT)}")
        full = {**DRIFT_DEFAULT, **dict(terms)}
        for k, v in full.items():
            if isinstance(v, Mapping):
                if v.get("kind") not in ("step", "ramp", "exp"):
                    raise ValueError(f"sensor_drift.{name}.{k}: kind must be step, ramp or exp")
                full[k] = dict(v)
            else:
                full[k] = float(v)
        out[name] = full
    return out


def drifted(terms: Mapping, t: np.ndarray, value: np.ndarray, w: np.ndarray) -> np.ndarray:
    """A sensor's reading of ``value`` (noise included) at ``t`` under its drift ``terms``; ``w``: standard normal."""
    return (variation_at(terms["gain"], 1.0, t) * value + variation_at(terms["offset"], 0.0, t)
            + variation_at(terms["noise"], 0.0, t) * w)
