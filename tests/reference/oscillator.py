"""Oscillator records (model-spec section 1): m x'' + d x' + k x = u - Fc s(v), y = x + noise.

The force u is a multisine evaluated analytically, or its log samples held (``zoh``),
linearly interpolated (``foh``) or splined (``cubic``); or given samples.  The
optional ``coulomb_friction`` uses the smooth sign s(v) = v / sqrt(v^2 + v_eps^2).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping

import numba as nb
import numpy as np

from .integrate import DRIVERS, METHODS, piece
from .record import Record
from .signals import multisine_table, noise_sequence, poly_table, quantise, sig_eval, tv_eval, tv_row, tv_tables
from .tables import OSC_FREE, OSC_KNOWN, draw_effects, draw_truth

DEFAULT_FORCE = {"kind": "multisine", "amplitude": 10.0, "f_lo": 0.5, "f_hi": 25.0, "n_lines": 16,
                 "ramp_s": 0.5, "offset": 0.0}
V_EPS = 1e-4  # m/s, smoothing velocity of the Coulomb friction's sign
FREE_ORDER = ("d", "k")


@nb.njit(cache=True)
def rhs(t, y, p, tv, tab, sigp, sc, seg):
    """p = [m, Fc, v_eps]; d and k from the time-variation table."""
    u = sig_eval(sigp, sc, t, seg[0])
    d = tv_eval(tv, tab, 0, t)
    k = tv_eval(tv, tab, 1, t)
    f = u - d * y[1] - k * y[0]
    if p[1] > 0.0:
        f -= p[1] * y[1] / math.sqrt(y[1] * y[1] + p[2] * p[2])
    out = np.empty(2)
    out[0] = y[1]
    out[1] = f / p[0]
    return out


def oscillator_spec(seed: int = 0, *, duration: float = 20.0, log_rate_hz: float = 1000.0,
                    force: Mapping | None = None, intersample: str = "analytic", truth: Mapping | str | None = None,
                    spread: float = 0.2, time_varying: Mapping | None = None, known: Mapping | None = None,
                    effects=(), noise: Mapping | str | None = "default", init=None, rtol: float = 1e-8,
                    atol_scale: float = 1.0, max_step: float = 1e-3, method: str = "LSODA",
                    driver: str = "odeint") -> dict:
    """A complete oscillator spec.  ``force``: overrides :data:`DEFAULT_FORCE` or
    ``{"kind": "samples", "values": array}``; ``noise``: ``"default"`` (y: 1 um white), None, or
    ``{"y": sigma, "tau": s, "quant": lsb}``; ``truth``: None, ``"draw"`` or a dict of d, k."""
    n_log = int(round(duration * log_rate_hz))
    if truth is None:
        tr = dict(OSC_FREE)
    elif truth == "draw":
        tr = draw_truth(seed, spread, "oscillator")
    else:
        unknown = set(truth) - set(OSC_FREE)
        if unknown:
            raise ValueError(f"unknown free parameter(s) {sorted(unknown)}; known: {list(OSC_FREE)}")
        tr = {**OSC_FREE, **{k: float(v) for k, v in truth.items()}}
    frc = {**DEFAULT_FORCE, **dict(force or {})}
    if frc["kind"] == "samples":
        frc["values"] = np.asarray(frc["values"], float)
        if frc["values"].shape != (n_log,):
            raise ValueError(f"force samples must number {n_log}, got {frc['values'].shape}")
        if intersample == "analytic":
            raise ValueError("sampled force: intersample zoh, foh or cubic")
    if intersample not in ("analytic", "zoh", "foh", "cubic"):
        raise ValueError(f"intersample must be analytic, zoh, foh or cubic, got {intersample!r}")
    if method not in METHODS or driver not in DRIVERS or (driver == "odeint" and method != "LSODA"):
        raise ValueError(f"solver: driver in {DRIVERS}, method in {METHODS} (odeint: LSODA only)")
    nz = {"y": 1e-6, "tau": 0.0, "quant": 0.0}
    if noise is None:
        nz["y"] = 0.0
    elif noise != "default":
        nz.update(noise)
    tvs = dict(time_varying or {})
    for k, v in tvs.items():
        if k not in OSC_FREE:
            raise ValueError(f"time_varying names unknown free parameter {k!r}")
        if callable(v):
            tt = np.linspace(0.0, duration, int(round(duration * 1000)) + 1)
            tvs[k] = {"kind": "table", "t": tt.tolist(), "value": [float(v(t)) for t in tt]}
    return {
        "model": "oscillator", "seed": int(seed), "duration": float(duration), "log_rate_hz": float(log_rate_hz),
        "controller": "open_loop", "force": frc, "intersample": intersample, "truth": tr, "time_varying": tvs,
        "known": {**OSC_KNOWN, **{k: float(v) for k, v in (known or {}).items()}},
        "effects": draw_effects(seed, effects, "oscillator"), "noise": nz,
        "init": None if init is None else [float(v) for v in init],
        "solver": {"driver": driver, "method": method, "rtol": float(rtol), "atol_scale": float(atol_scale),
                   "max_step": float(max_step)},
    }


def simulate_oscillator(spec: dict) -> Record:
    """Simulate one complete oscillator spec into a :class:`Record` (signals ``u``, ``y``)."""
    t_start = time.perf_counter()
    n = int(round(spec["duration"] * spec["log_rate_hz"]))
    dt = 1.0 / spec["log_rate_hz"]
    tk = np.arange(n) * dt
    frc = spec["force"]
    if frc["kind"] == "multisine":
        msp, msc = multisine_table(frc["amplitude"], frc["f_lo"], frc["f_hi"], frc["n_lines"], spec["seed"],
                                   frc["ramp_s"], frc["offset"])
        u = np.array([sig_eval(msp, msc, t, -1) for t in tk])
    else:
        u = frc["values"]
    if spec["intersample"] == "analytic":
        sigp, sc = msp, msc
    else:
        sigp, sc = poly_table(u, dt, spec["intersample"])
    rows, tabs, truth = [], [], {}
    for name in FREE_ORDER:
        row, desc = tv_row(spec["time_varying"].get(name), spec["truth"][name], tabs, 0.0, spec["duration"])
        rows.append(row)
        truth[name] = desc if name in spec["time_varying"] else spec["truth"][name]
    tv, tab = tv_tables(rows, tabs)
    fc = spec["effects"].get("coulomb_friction", {}).get("Fc", 0.0)
    p = np.array([spec["known"]["m"], fc, V_EPS])
    seg = np.array([-1], dtype=np.int64)
    fun = lambda t, y: rhs(t, y, p, tv, tab, sigp, sc, seg)  # noqa: E731
    sv = spec["solver"]
    opts = {"driver": sv["driver"], "method": sv["method"], "rtol": sv["rtol"],
            "atol": np.array([1e-12, 1e-10]) * sv["atol_scale"], "max_step": min(sv["max_step"], dt)}
    y = np.zeros(2) if spec["init"] is None else np.array(spec["init"], float)
    states = np.empty((n, 2))
    states[0] = y
    if spec["intersample"] in ("zoh", "foh"):  # restart at every sample
        for k in range(n - 1):
            seg[0] = k
            y = piece(fun, tk[k], tk[k + 1], y, tk[k + 1: k + 2], **opts)[-1]
            states[k + 1] = y
    else:
        states[1:] = piece(fun, 0.0, tk[-1], y, tk[1:], **opts)
    rng = np.random.default_rng([spec["seed"], 4321])
    nz = spec["noise"]
    yl = quantise(states[:, 0] + noise_sequence(rng, n, nz["y"], dt, nz["tau"]), nz["quant"])
    truth.update({f"{e}.{k}": v for e, vals in spec["effects"].items() for k, v in vals.items()})
    hidden = {"x": states[:, 0].copy(), "v": states[:, 1].copy()}
    for i, name in enumerate(FREE_ORDER):
        if name in spec["time_varying"]:
            hidden[name] = np.array([tv_eval(tv, tab, i, t) for t in tk])
    from .msp25 import _describe

    meta = {k: _describe(v) for k, v in spec.items() if k != "truth"}
    meta.update({"state0": states[0].tolist(), "elapsed_s": time.perf_counter() - t_start})
    return Record(tk, {"u": np.array(u, float), "y": yl}, truth, meta, hidden)
