"""The scenarios of :mod:`benchmarks.campaign`: each a pure function of its seed (and the draw's length).

A scenario is plain data (JSON): the rig (geometry, size), its controller, the excitation, the sensor noise,
how the twin starts, the truth, and what happens to the rig (nothing, a wear, a drifting sensor, a specimen
that stiffens or cracks). :func:`reference_spec` turns it into a spec of the independent reference simulator
(``tests/reference``), :func:`commissioning_spec` into the healthy record of the same rig that a commissioned
start is fitted on, :func:`product_params` into what the rig's configuration tells the twin.

The distribution (every draw from ``numpy.random.default_rng([seed, 9034])``):

* kind: healthy 45 %, wear 30 %, sensor drift 15 %, specimen 10 %;
* rig: a symmetric cylinder (60 %) or a single rod (annulus 0.5-0.8 of the piston area, its chamber
  0.6-1.0 of the matching volume), piston area, volumes and moving mass scaled together by 0.9-1.25
  (Table 8 at 1);
* controller: P (40 %), PI (30 %), PID with a derivative filter of 0.5-2 ms (30 %); KP 250-400 V/m (a single
  rod, or with a derivative: 200-300 and 250-350), KI 200-2000 V/(m s), KD 0.1-0.6 V s/m; digital (70 %:
  at 1 kHz 50 %, 2 kHz 30 %, 5 kHz 20 %) or analog (30 %);
* excitation: one to three parts of chirp, multisine, steps, sweep, blocks, road load in a drawn order
  (repeats allowed), sharing the record by a Dirichlet draw (each at least 15 %); amplitude 1-8 mm
  (multisine 1-5 mm), speed limit 0.08-0.3 m/s; the first part starts 0-1 s into the record, ramped in over
  0.05-0.5 s;
* noise: 0.5-2.5 times (x 2 um, pA and pB 20 kPa), white (60 %) or AR(1) of 2-20 ms (40 %);
* start: cold at Table 9 with the default bands (55 %; truth 3-10 % off Table 9, inside the bands), or
  from a commissioning fit on a healthy 30-s multisine record of the same rig (45 %; truth 3-20 % off);
* wear: Ffric (up), CdAleak (up), Cd (down), zeta (up or down), wn (down), each 20 %; step, ramp or
  exponential (accelerating); onset 20-45 % into the record, over 20-35 % of it and done by 80 % (a step:
  at the onset); its
  end ``v0 (edge / v0)^g`` with the band's edge around the truth and ``g`` 1.3-2.5 (70 %: it leaves the
  band) or 0.3-0.7 (30 %: it stays inside);
* sensor drift: x (digital controllers only), pA or pB; an offset (x 20-200 um, pressures 0.1-0.6 MPa), a
  gain (1.01-1.04 on x, 0.92-0.98 or 1.02-1.08 on pressures) or extra white noise (2-5 times the sensor's
  noise); a step or a ramp, timed as a wear;
* specimen: a spring of 1-4 kN/mm on the rod from the start, that stiffens (x1.2-1.6) or cracks
  (x0.5-0.85), as a ramp or (a crack, 40 %) a step, timed as a wear.
"""

from __future__ import annotations

import math
import os
import sys
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
_TESTS = os.path.join(os.path.dirname(HERE), "tests")

#: named draw sets: disjoint seed ranges
SETS = {"calibration": (0, 1000), "verification": (1000, 1_000_000)}
KINDS = ("healthy", "wear", "sensor", "specimen")
KIND_WEIGHTS = (0.45, 0.30, 0.15, 0.10)
EXCITATIONS = ("chirp", "multisine", "steps", "sweep", "blocks", "road")
WEAR_PARAMS = ("Ffric", "CdAleak", "Cd", "zeta", "wn")
#: the default healthy bands' relative half-widths (the reference's copy: hi = v (1 + r), lo = v / (1 + r))
BAND = {"Ffric": 0.5, "CdAleak": 2.0, "Cd": 0.15, "zeta": 0.3, "wn": 0.15}
#: where each wear heads ("either": drawn)
WEAR_EDGE = {"Ffric": "hi", "CdAleak": "hi", "Cd": "lo", "zeta": "either", "wn": "lo"}
#: the reference simulator's default sensor noise (SI)
NOISE = {"x": 2e-6, "pA": 2e4, "pB": 2e4}
COMMISSION_S = 30.0


def reference():
    """The independent reference simulator (``tests/reference``, imported as the package ``reference``)."""
    if _TESTS not in sys.path:
        sys.path.insert(0, _TESTS)
    import reference as ref

    return ref


def set_of(seed: int) -> str:
    for name, (lo, hi) in SETS.items():
        if lo <= seed < hi:
            return name
    raise ValueError(f"seed {seed} is in no draw set ({SETS})")


def _pick(rng: np.random.Generator, items, weights=None):
    return items[int(rng.choice(len(items), p=None if weights is None else np.asarray(weights) / sum(weights)))]


def draw(seed: int, minutes: float = 2.0) -> dict[str, Any]:
    """The scenario of draw ``seed`` (a pure function of ``seed`` and ``minutes``, the record's length)."""
    rng = np.random.default_rng([int(seed), 9034])
    T = float(minutes) * 60.0
    kind = _pick(rng, KINDS, KIND_WEIGHTS)
    # rig
    single = rng.random() < 0.4
    size = float(rng.uniform(0.9, 1.25))
    ref = reference()
    kn = ref.MSP25_KNOWN
    A, V0, m = kn["A"] * size, kn["V0"] * size, kn["m"] * size
    known: dict[str, float] = {"A": A, "V0": V0, "m": m}
    if single:
        ab = float(rng.uniform(0.5, 0.8))
        known.update(AB=A * ab, V0B=V0 * ab * float(rng.uniform(0.6, 1.0)))
    # controller
    ctype = _pick(rng, ("P", "PI", "PID"), (0.4, 0.3, 0.3))
    if ctype == "PID":
        kp_lo, kp_hi = (200.0, 300.0) if single else (250.0, 350.0)
    else:
        kp_lo, kp_hi = (200.0, 300.0) if single else (250.0, 400.0)
    known["KP"] = float(rng.uniform(kp_lo, kp_hi))
    known["KI"] = float(rng.uniform(200.0, 2000.0)) if ctype in ("PI", "PID") else 0.0
    known["KD"] = float(rng.uniform(0.1, 0.6)) if ctype == "PID" else 0.0
    tf = float(rng.uniform(0.5e-3, 2e-3)) if ctype == "PID" else 0.0
    digital = rng.random() < 0.7
    rate = float(_pick(rng, (1000.0, 2000.0, 5000.0), (0.5, 0.3, 0.2))) if digital else None
    # excitation
    n_parts = int(rng.integers(1, 4))
    order = [str(_pick(rng, EXCITATIONS)) for _ in range(n_parts)]
    onset = float(rng.uniform(0.0, 1.0))
    share = 0.15 + (1.0 - 0.15 * n_parts) * rng.dirichlet(np.ones(n_parts))
    parts = []
    for i, (k, sh) in enumerate(zip(order, share)):
        amp = float(rng.uniform(1e-3, 5e-3 if k == "multisine" else 8e-3))
        vmax = float(rng.uniform(0.08, 0.3))
        part: dict[str, Any] = {"kind": k, "seconds": round(float(sh) * (T - onset), 3), "amplitude": amp}
        if k != "multisine":
            part["v_max"] = vmax
        if k in ("chirp", "sweep", "multisine", "road"):
            part["ramp_s"] = float(rng.uniform(0.05, 0.5)) if i == 0 else 0.5
        parts.append(part)
    # noise
    lvl = float(rng.uniform(0.5, 2.5))
    tau = float(rng.uniform(2e-3, 20e-3)) if rng.random() < 0.4 else 0.0
    noise = {"x": NOISE["x"] * lvl, "pA": NOISE["pA"] * lvl, "pB": NOISE["pB"] * lvl, "tau": tau}
    # start and truth
    start = "commissioned" if rng.random() < 0.45 else "cold"
    truth = ref.draw_truth(int(seed), 0.2 if start == "commissioned" else 0.1, "msp25")
    scn: dict[str, Any] = {
        "seed": int(seed), "set": set_of(int(seed)), "kind": kind, "duration_s": T,
        "rig": {"geometry": "single_rod" if single else "symmetric", "size": size, "known": known},
        "controller": {"type": ctype, "timing": "digital" if digital else "analog", "rate_hz": rate, "Tf": tf},
        "excitation": {"order": order, "onset_s": onset, "parts": parts},
        "noise": noise, "start": start, "truth": truth, "wear": None, "sensor": None, "specimen": None,
    }
    t0 = float(rng.uniform(0.2, 0.45)) * T
    t1 = min(t0 + float(rng.uniform(0.2, 0.35)) * T, 0.8 * T)
    if kind == "wear":
        p = str(_pick(rng, WEAR_PARAMS))
        edge = WEAR_EDGE[p] if WEAR_EDGE[p] != "either" else ("hi" if rng.random() < 0.5 else "lo")
        shape = str(_pick(rng, ("step", "ramp", "exp")))
        leaves = bool(rng.random() < 0.7)
        g = float(rng.uniform(1.3, 2.5)) if leaves else float(rng.uniform(0.3, 0.7))
        v0 = truth[p]
        e = v0 * (1 + BAND[p]) if edge == "hi" else v0 / (1 + BAND[p])
        scn["wear"] = {"parameter": p, "shape": shape, "edge": edge, "t0": t0, "t1": t0 if shape == "step" else t1,
                       "start": v0, "end": float(v0 * (e / v0) ** g), "leaves_band": leaves}
    elif kind == "sensor":
        sensors = ("x", "pA", "pB") if digital else ("pA", "pB")
        s = str(_pick(rng, sensors))
        term = str(_pick(rng, ("offset", "gain", "noise")))
        if term == "offset":
            size_v = float(rng.uniform(20e-6, 200e-6)) if s == "x" else float(rng.uniform(0.1e6, 0.6e6))
            size_v *= 1.0 if rng.random() < 0.5 else -1.0
        elif term == "gain":
            size_v = (float(rng.uniform(1.01, 1.04)) if s == "x" else
                      float(rng.uniform(1.02, 1.08)) if rng.random() < 0.5 else float(rng.uniform(0.92, 0.98)))
        else:
            size_v = float(rng.uniform(2.0, 5.0)) * noise[s]
        shape = str(_pick(rng, ("step", "ramp")))
        scn["sensor"] = {"sensor": s, "term": term, "shape": shape, "t0": t0, "t1": t0 if shape == "step" else t1,
                         "size": size_v}
    elif kind == "specimen":
        k0 = float(rng.uniform(1e6, 4e6))
        change = "crack" if rng.random() < 0.5 else "stiffen"
        factor = float(rng.uniform(0.5, 0.85)) if change == "crack" else float(rng.uniform(1.2, 1.6))
        shape = "step" if change == "crack" and rng.random() < 0.4 else "ramp"
        scn["specimen"] = {"k0": k0, "change": change, "factor": factor, "shape": shape, "t0": t0,
                           "t1": t0 if shape == "step" else t1}
    return scn


def _variation(shape: str, t0: float, t1: float, start: float, end: float, T: float) -> dict[str, Any]:
    """A time variation of the reference simulator: a step at ``t0``, a ramp over ``[t0, t1]`` or an accelerating
    exponential over it (tabulated every 0.1 s: ``start (end / start)^((e^(s/tau) - 1) / (e - 1))``, ``s`` the time
    since ``t0``, ``tau = t1 - t0``)."""
    if shape == "step":
        return {"kind": "step", "t0": t0, "before": start, "after": end}
    if shape == "ramp":
        return {"kind": "ramp", "t0": t0, "t1": t1, "start": start, "end": end}
    tt = np.arange(-1.0, T + 0.1, 0.1)
    frac = np.clip((np.exp(np.clip(tt - t0, 0.0, None) / (t1 - t0)) - 1.0) / (math.e - 1.0), 0.0, 1.0)
    vv = start * (end / start) ** frac
    return {"kind": "table", "t": [float(v) for v in tt], "value": [float(v) for v in vv]}


def _controller_kw(scn: dict[str, Any]) -> dict[str, Any]:
    c = scn["controller"]
    kw: dict[str, Any] = {"known": dict(scn["rig"]["known"])}
    if c["timing"] == "digital":
        kw.update(controller="digital", rate_hz=c["rate_hz"])
        if c["Tf"] > 0.0:
            kw["pid"] = {"Tf": c["Tf"]}
    else:
        kw["controller"] = "analog"
        if c["Tf"] > 0.0:
            kw["derivative_filter_s"] = c["Tf"]
    return kw


def reference_spec(scn: dict[str, Any]) -> dict:
    """The reference simulator's spec of a scenario's record."""
    ref = reference()
    T = scn["duration_s"]
    kw = _controller_kw(scn)
    kw["demand"] = {"kind": "sequence", "onset_s": scn["excitation"]["onset_s"], "parts": scn["excitation"]["parts"]}
    kw["noise"] = dict(scn["noise"])
    kw["truth"] = dict(scn["truth"])
    w = scn.get("wear")
    if w:
        kw["time_varying"] = {w["parameter"]: _variation(w["shape"], w["t0"], w["t1"], w["start"], w["end"], T)}
    s = scn.get("sensor")
    if s:
        default = 1.0 if s["term"] == "gain" else 0.0
        kw["sensor_drift"] = {s["sensor"]: {s["term"]: _variation(s["shape"], s["t0"], s["t1"], default, s["size"], T)}}
    sp = scn.get("specimen")
    if sp:
        kw["specimen"] = {"k": _variation(sp["shape"], sp["t0"], sp["t1"], sp["k0"], sp["k0"] * sp["factor"], T)}
    return ref.msp25_spec(scn["seed"], duration=T, **kw)


def commissioning_spec(scn: dict[str, Any]) -> dict | None:
    """The healthy record of the same rig a commissioned start is fitted on (a 30-s multisine of 4 mm; the
    specimen at its first stiffness), or None for a cold start."""
    if scn["start"] != "commissioned":
        return None
    ref = reference()
    kw = _controller_kw(scn)
    kw["demand"] = {"kind": "multisine", "amplitude": 4e-3}
    kw["noise"] = dict(scn["noise"])
    kw["truth"] = dict(scn["truth"])
    if scn.get("specimen"):
        kw["specimen"] = {"k": scn["specimen"]["k0"]}
    return ref.msp25_spec(scn["seed"] + 500_000, duration=COMMISSION_S, **kw)


def product_params(scn: dict[str, Any]) -> dict[str, float]:
    """What the rig's configuration tells the twin (known values, SI): geometry and controller."""
    kn = scn["rig"]["known"]
    out = {k: float(kn[k]) for k in ("A", "V0", "m", "KP", "KI", "KD") if k in kn}
    if "AB" in kn:
        out.update(AB=float(kn["AB"]), V0B=float(kn["V0B"]))
    if scn["controller"]["Tf"] > 0.0:
        out["Tf"] = float(scn["controller"]["Tf"])
    return out


def timing_spelling(scn: dict[str, Any]) -> tuple[str, str | None]:
    """The twin's ``--controller`` and ``--intersample`` for the scenario's loop."""
    c = scn["controller"]
    if c["timing"] == "analog":
        return "continuous", "cubic"
    return f"digital:{c['rate_hz']:g}", None


def seeds(which: str, n: int, minutes: float = 2.0, kinds: tuple[str, ...] | None = None,
          first: int | None = None) -> list[int]:
    """The first ``n`` seeds of a set (from ``first``) whose scenario kind is one of ``kinds``."""
    lo, hi = SETS[which]
    out: list[int] = []
    s = lo if first is None else first
    while len(out) < n and s < hi:
        if kinds is None or draw(s, minutes)["kind"] in kinds:
            out.append(s)
        s += 1
    return out


def describe(scn: dict[str, Any]) -> str:
    """One line: the scenario's kind, rig, controller, excitation, noise, start and event."""
    c = scn["controller"]
    loop = "analog" if c["timing"] == "analog" else f"digital {c['rate_hz'] / 1e3:g} kHz"
    ctrl = f"{c['type']} {loop}"
    ex = "+".join(scn["excitation"]["order"])
    nz = f"noise x{scn['noise']['x'] / NOISE['x']:.1f}{' AR(1)' if scn['noise']['tau'] > 0 else ''}"
    what = scn["kind"]
    if scn["wear"]:
        w = scn["wear"]
        what = f"wear {w['parameter']} {w['shape']} x{w['end'] / w['start']:.2f}{'' if w['leaves_band'] else ' (inside)'}"
    elif scn["sensor"]:
        s = scn["sensor"]
        what = f"sensor {s['sensor']} {s['term']} {s['shape']}"
    elif scn["specimen"]:
        sp = scn["specimen"]
        what = f"specimen {sp['change']} {sp['shape']} x{sp['factor']:.2f}"
    return f"{what}; {scn['rig']['geometry']} x{scn['rig']['size']:.2f}, {ctrl}, {ex}, {nz}, {scn['start']}"
