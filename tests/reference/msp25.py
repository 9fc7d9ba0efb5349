"""MSP25 records: a spec (plain dict, SI) and the simulation of one record from it.

Controllers (``controller``):

* ``analog``: u(t) = PID of r(t) - xm(t) inside the ODE; xm is the sensor's output
  (gain, Pade-delayed when ``sensor_delay`` is on) plus a continuous noise signal (a
  cubic spline through a seeded sequence at ``noise.oversample`` times the log rate;
  its knots at the log instants are the logged noise).
* ``digital``: at every tick of ``rate_hz`` the controller reads
  xm = quantise(gain x(t - delay) + noise), computes u and holds it to the next tick;
  the ODE is integrated tick by tick (a delayed x is taken from the integrator's output
  at the delayed instants).
* ``open_loop``: u given at the log instants (``drive``), with an intersample behaviour.

The digital controller is an industrial PID (``pid``): its derivative, of the error or of
minus the measurement, is the difference quotient low-passed at ``Tf`` (a first-order
filter discretised backward, ``D = a D_prev + (1 - a) ds / T``, ``a = Tf / (Tf + T)``), a
velocity feed-forward ``Kff`` times the demand's rate (its analytic rate, taken as a
symmetric difference of the demand at +-1 us), and the output clipped at ``u_max``.

The cylinder may have two areas (``known`` ``AB``: the rod side's annulus; ``V0B``: that
chamber's volume at mid stroke; both default to the piston side's ``A``, ``V0``).
``time_jitter_s``: the logged time stamps are late by a uniform draw in [0, jitter]
(CAN arbitration), the values are still those at the nominal instants.

The demand r(t) (``demand["kind"]``) is a multisine, a ``chirp`` (linear frequency rise) or ``sweep``
(logarithmic), both at the rig's speed limit ``v_max`` once the frequency is high enough, ``blocks``
(block loading: sines of drawn frequencies and amplitudes, block by block) or ``road`` (a road-load
profile, band-limited random), all drawn from the seed (see :mod:`.signals`), or given samples;
evaluated analytically (``intersample: analytic``) or its log samples held (``zoh``), linearly
interpolated (``foh``) or splined (``cubic``).

Signals at their own rates (``signal_rates``, Hz, e.g. ``{"pA": 500, "pB": 500}`` as the DBC logs
the pressures): a slower signal is sampled at every ``log_rate / rate``-th log instant and held onto
the log grid in between, as the product's CAN reader delivers it (the latest frame held, nothing
interpolated); ``hidden["fresh_<name>"]`` marks its fresh samples (1) and held ones (0).

Oil temperature (``temperature``): ``{"T": K or a time variation (step, ramp, exp, table),
"T0": 313.15, "a_bulk": 0.006, "b_visc": 0.03, "quant": 0.1}``; the bulk modulus and the leakage
follow it (laws in :mod:`.msp25_rhs`), ``Table 8``'s ``B`` and the truth's ``CdAleak`` hold at
``T0``; ``T_oil`` is logged (K, quantised at ``quant``; at its own rate when in ``signal_rates``).
A pre-roll of ``preroll`` seconds on the demand's first value, started from a solved
equilibrium, precedes the record; logging starts at t = 0.
"""

from __future__ import annotations

import copy
import hashlib
import math
import time
from typing import Any
from collections.abc import Mapping

import numpy as np
from scipy.optimize import root

from . import msp25_rhs as R
from .integrate import DRIVERS, METHODS, piece
from .record import Record
from .sequences import SEQUENCE_DEFAULT, STEPS_DEFAULT, demand_values, drift_spec, drifted
from .signals import (blocks_table, chirp_table, multisine_table, noise_sequence, pade_delay, poly_table, quantise,
                      road_table, sig_eval, tv_breaks, tv_eval, tv_row, tv_tables)
from .tables import MSP25_FREE, MSP25_KNOWN, draw_effects, draw_truth

CONTROLLERS = ("analog", "digital", "open_loop")
DEFAULT_NOISE = {"x": 2e-6, "pA": 2e4, "pB": 2e4, "tau": 0.0, "oversample": 1,
                 "quant": {"x": 0.0, "pA": 0.0, "pB": 0.0}}
DEFAULT_DEMAND = {"kind": "multisine", "amplitude": 5e-3, "f_lo": 0.2, "f_hi": 15.0, "n_lines": 16,
                  "ramp_s": 0.5, "offset": 0.0, "intersample": "analytic"}
#: the test engineer's demands (``sweep_s``, ``None``: the record's duration; ``v_max``: the rig's speed limit, m/s)
DEMAND_KINDS = {
    "multisine": DEFAULT_DEMAND,
    "chirp": {"kind": "chirp", "amplitude": 5e-3, "f_lo": 0.1, "f_hi": 8.0, "v_max": 0.25, "sweep_s": None,
              "ramp_s": 0.5, "offset": 0.0, "intersample": "analytic"},
    "sweep": {"kind": "sweep", "amplitude": 5e-3, "f_lo": 0.2, "f_hi": 15.0, "v_max": 0.25, "sweep_s": None,
              "ramp_s": 0.5, "offset": 0.0, "intersample": "analytic"},
    "blocks": {"kind": "blocks", "amplitude": 5e-3, "f_lo": 0.5, "f_hi": 10.0, "v_max": 0.25, "block_s": 2.0,
               "fade_s": 0.2, "min_fraction": 0.2, "offset": 0.0, "intersample": "analytic"},
    "road": {"kind": "road", "amplitude": 5e-3, "f_lo": 0.2, "f_hi": 20.0, "n_lines": 200, "v_max": 0.25,
             "ramp_s": 0.5, "offset": 0.0, "intersample": "analytic"},
    "steps": STEPS_DEFAULT,        # a staircase (:mod:`.sequences`)
    "sequence": SEQUENCE_DEFAULT,  # parts of these kinds one after the other (:mod:`.sequences`)
}
TEMPERATURE_DEFAULT = {"T": 313.15, "T0": 313.15, "a_bulk": 0.006, "b_visc": 0.03, "quant": 0.1}
# absolute tolerances per state (SI): xs vs pA pB x v x2 v2 zi zd z0..z3 pAm pBm
ATOL = np.array([1e-12, 1e-9, 1.0, 1.0, 1e-11, 1e-9, 1e-11, 1e-9, 1e-12, 1e-11, 1e-11, 1e-11, 1e-11, 1e-11,
                 1.0, 1.0, 1.0, 1e-10, 1.0])

#: the supply's fixed parts (effect ``supply_dynamics``; the hose and the accumulator's size are drawn): the
#: accumulator's pre-charge as a fraction of the supply pressure (absolute), its gas's polytropic exponent, the
#: oil's dynamic viscosity [Pa s], the pump's outlet volume [m^3], its full flow [m^3/s] and its compensator's band
#: [Pa]
SUPPLY_FIXED = {"precharge": 0.65, "n": 1.4, "mu": 0.04, "pump_v": 1e-3, "pump_q": 1.5e-3, "band": 1e6}


def msp25_spec(seed: int = 0, *, duration: float = 20.0, log_rate_hz: float = 1000.0,
               controller: str = "digital", rate_hz: float | None = None,
               demand: Mapping | None = None, intersample: str | None = None,
               truth: Mapping | str | None = None, spread: float = 0.2,
               time_varying: Mapping | None = None, known: Mapping | None = None, Fext: float = 0.0,
               effects=(), noise: Mapping | str | None = "default", preroll: float = 0.5,
               drive: Mapping | None = None, init=None, rtol: float = 1e-8, atol_scale: float = 1.0,
               max_step: float = 1e-3, method: str = "LSODA", driver: str = "odeint", pade_order: int = 3,
               derivative_filter_s: float = 1e-3, pid: Mapping | None = None,
               time_jitter_s: float = 0.0, signal_rates: Mapping[str, float] | None = None,
               temperature: Mapping | None = None, specimen: Mapping | None = None,
               sensor_drift: Mapping | None = None) -> dict:
    """A complete MSP25 spec (plain dict): every default filled in, truth and effect sizes drawn.

    ``truth``: None (Table 9), ``"draw"`` (:func:`draw_truth` with ``spread``) or a dict of free
    parameters overriding Table 9.  ``time_varying``: free parameter -> variation (see
    :func:`signals.tv_row`).  ``effects``: names (sizes drawn from ``seed``) or a mapping
    name -> dict of explicit sizes.  ``noise``: ``"default"`` (x 2 um, pA/pB 20 kPa, white), None
    (none) or a dict overriding :data:`DEFAULT_NOISE` (``tau`` > 0: AR(1) of that correlation
    time; ``quant``: LSB per signal).  ``demand``: overrides :data:`DEFAULT_DEMAND`, or
    ``{"kind": "samples", "values": array}``; ``intersample`` sets the demand's (or the open-loop
    drive's) intersample behaviour.  ``specimen``: ``{"k": N/m or a time variation}`` (a specimen that
    stiffens or cracks; not with the ``specimen_stiffness`` effect).  ``sensor_drift``: sensor -> drifting
    offset, gain, noise (:mod:`.sequences`; ``x`` with a digital controller only).  ``drive`` (open loop): ``{"u": array}`` at the log instants
    (optionally ``"x_ref"``).  ``init``: a full initial state (14 values) instead of the equilibrium.
    Solver: ``driver`` ``odeint`` (LSODA, default) or ``solve_ivp`` with ``method`` LSODA, Radau or BDF;
    ``rtol``, per-state absolute tolerances :data:`ATOL` times ``atol_scale``, ``max_step`` [s].
    """
    if controller not in CONTROLLERS:
        raise ValueError(f"controller must be one of {CONTROLLERS}, got {controller!r}")
    if method not in METHODS or driver not in DRIVERS or (driver == "odeint" and method != "LSODA"):
        raise ValueError(f"solver: driver in {DRIVERS}, method in {METHODS} (odeint: LSODA only), "
                         f"got {driver!r}, {method!r}")
    n_log = int(round(duration * log_rate_hz))
    if truth is None:
        tr = dict(MSP25_FREE)
    elif truth == "draw":
        tr = draw_truth(seed, spread, "msp25")
    else:
        unknown = set(truth) - set(MSP25_FREE)
        if unknown:
            raise ValueError(f"unknown free parameter(s) {sorted(unknown)}; known: {list(MSP25_FREE)}")
        tr = {**MSP25_FREE, **{k: float(v) for k, v in truth.items()}}
    kn = dict(MSP25_KNOWN)
    kn["AB"] = float((known or {}).get("AB", (known or {}).get("A", kn["A"])))
    kn["V0B"] = float((known or {}).get("V0B", (known or {}).get("V0", kn["V0"])))
    for k, v in (known or {}).items():
        if k not in kn:
            raise ValueError(f"unknown known parameter {k!r}; known: {list(kn)}")
        kn[k] = float(v)
    eff = draw_effects(seed, effects, "msp25")
    tvspec = dict(time_varying or {})
    unknown = set(tvspec) - set(MSP25_FREE)
    if unknown:
        raise ValueError(f"time_varying names unknown free parameter(s) {sorted(unknown)}")
    if "parameter_drift" in eff:
        d = eff["parameter_drift"]
        if d["param"] in tvspec:
            raise ValueError(f"parameter_drift and time_varying both set {d['param']!r}")
        v0 = tr[d["param"]]
        tvspec[d["param"]] = {"kind": "ramp", "t0": 0.0, "t1": float(duration), "start": v0,
                              "end": v0 * d["factor"]}
    for k, v in tvspec.items():
        if callable(v):  # tabulate now so that the spec is data
            t_lo = -float(preroll)
            tt = np.linspace(t_lo, duration, int(round((duration - t_lo) * 1000)) + 1)
            tvspec[k] = {"kind": "table", "t": tt.tolist(), "value": [float(v(t)) for t in tt]}
    if noise == "default":
        nz = copy.deepcopy(DEFAULT_NOISE)
    elif noise is None:
        nz = copy.deepcopy(DEFAULT_NOISE)
        nz.update({"x": 0.0, "pA": 0.0, "pB": 0.0})
    else:
        nz = copy.deepcopy(DEFAULT_NOISE)
        quant = {**nz["quant"], **dict(noise.get("quant", {}))}
        nz.update({k: v for k, v in noise.items() if k != "quant"})
        nz["quant"] = quant
    if controller == "open_loop":
        if drive is None or "u" not in drive:
            raise ValueError("an open-loop spec needs drive={'u': samples at the log instants}")
        drv = {k: np.asarray(v, float) for k, v in drive.items()}
        if drv["u"].shape != (n_log,):
            raise ValueError(f"drive u must have {n_log} samples (duration * log rate), got {drv['u'].shape}")
        dem = None
        isamp = intersample or "zoh"
        if isamp == "analytic":
            raise ValueError("an open-loop drive is sampled: intersample zoh, foh or cubic")
    else:
        drv = None
        kind = (demand or {}).get("kind", "multisine")
        dem = {**DEMAND_KINDS.get(kind, DEFAULT_DEMAND), **dict(demand or {})}
        if kind in ("chirp", "sweep") and dem["sweep_s"] is None:
            dem["sweep_s"] = float(duration)
        if kind == "sequence":
            dem["parts"] = [_part_spec(p) for p in dem["parts"]]
        if dem["kind"] == "samples":
            dem["values"] = np.asarray(dem["values"], float)
            dem.setdefault("intersample", "zoh")
            if dem["values"].shape != (n_log,):
                raise ValueError(f"demand samples must number {n_log}, got {dem['values'].shape}")
        elif dem["kind"] not in DEMAND_KINDS:
            raise ValueError(f"demand kind must be one of {', '.join(DEMAND_KINDS)} or samples, got {dem['kind']!r}")
        if intersample:
            dem["intersample"] = intersample
        isamp = dem["intersample"]
        if dem["kind"] == "samples" and isamp == "analytic":
            raise ValueError("sampled demand: intersample zoh, foh or cubic")
    if isamp not in ("analytic", "zoh", "foh", "cubic"):
        raise ValueError(f"intersample must be analytic, zoh, foh or cubic, got {isamp!r}")
    drift = drift_spec(sensor_drift)
    if "x" in drift and controller != "digital":
        raise ValueError("sensor_drift on x needs a digital controller (the analog one reads x inside the ODE)")
    spm = None
    if specimen is not None:
        if "specimen_stiffness" in eff:
            raise ValueError("specimen and the specimen_stiffness effect both set the specimen")
        spm = {"k": dict(specimen["k"]) if isinstance(specimen["k"], Mapping) else float(specimen["k"])}
    rate = float(rate_hz or log_rate_hz) if controller == "digital" else None
    if rate is not None:
        hi, lo = max(rate, log_rate_hz), min(rate, log_rate_hz)
        if abs(hi / lo - round(hi / lo)) > 1e-9:
            raise ValueError(f"controller rate {rate} Hz and log rate {log_rate_hz} Hz must be integer multiples")
    return {
        "model": "msp25", "seed": int(seed), "duration": float(duration), "log_rate_hz": float(log_rate_hz),
        "controller": controller, "rate_hz": rate, "demand": dem, "intersample": isamp, "drive": drv,
        "truth": tr, "time_varying": tvspec, "known": kn, "Fext": float(Fext), "effects": eff, "noise": nz,
        "preroll": float(preroll), "init": None if init is None else [float(v) for v in init],
        "solver": {"driver": driver, "method": method, "rtol": float(rtol), "atol_scale": float(atol_scale),
                   "max_step": float(max_step)},
        "pade_order": int(pade_order), "derivative_filter_s": float(derivative_filter_s),
        "pid": _pid_spec(pid), "time_jitter_s": float(time_jitter_s),
        "signal_rates": _rates_spec(signal_rates, log_rate_hz), "temperature": _temperature_spec(temperature),
        "specimen": spm, "sensor_drift": drift,
    }


def _part_spec(part: Mapping) -> dict:
    """A sequence's part with its kind's defaults filled in (a chirp or sweep over the part)."""
    kind = part.get("kind")
    if kind not in DEMAND_KINDS or kind == "sequence" or "seconds" not in part:
        raise ValueError(f"a sequence's part needs a kind (not sequence) and its seconds, got {dict(part)}")
    out = {**DEMAND_KINDS[kind], **dict(part)}
    out["seconds"] = float(out["seconds"])
    if kind in ("chirp", "sweep") and out["sweep_s"] is None:
        out["sweep_s"] = out["seconds"]
    return out


def _rates_spec(rates: Mapping[str, float] | None, log_rate_hz: float) -> dict:
    out = {}
    for k, v in (rates or {}).items():
        if k not in ("x", "pA", "pB", "u", "x_ref", "T_oil"):
            raise ValueError(f"signal_rates: unknown signal {k!r}")
        ratio = log_rate_hz / float(v)
        if not (v > 0 and ratio >= 1 and abs(ratio - round(ratio)) < 1e-9):
            raise ValueError(f"signal_rates: {k} at {v} Hz must divide the log rate {log_rate_hz} Hz")
        out[k] = float(v)
    return out


def _temperature_spec(temp: Mapping | None) -> dict | None:
    if temp is None:
        return None
    unknown = set(temp) - set(TEMPERATURE_DEFAULT)
    if unknown:
        raise ValueError(f"temperature: unknown setting(s) {sorted(unknown)}; known: {list(TEMPERATURE_DEFAULT)}")
    out = {**TEMPERATURE_DEFAULT, **dict(temp)}
    for k in ("T0", "a_bulk", "b_visc", "quant"):
        out[k] = float(out[k])
    if not isinstance(out["T"], Mapping):
        out["T"] = float(out["T"])
    return out


PID_DEFAULT = {"Tf": 0.0, "d_on": "error", "Kff": 0.0, "u_max": None}


def _pid_spec(pid: Mapping | None) -> dict:
    out = dict(PID_DEFAULT)
    for k, v in (pid or {}).items():
        if k not in out:
            raise ValueError(f"unknown pid setting {k!r}; known: {list(out)}")
        out[k] = v
    if out["d_on"] not in ("error", "measurement"):
        raise ValueError(f"pid d_on must be error or measurement, got {out['d_on']!r}")
    out["Tf"], out["Kff"] = float(out["Tf"]), float(out["Kff"])
    out["u_max"] = None if out["u_max"] is None else float(out["u_max"])
    return out


def _demand_table(dem: dict, seed: int, duration: float) -> tuple[np.ndarray, np.ndarray]:
    """The analytic demand of a spec: its signal table (see :mod:`.signals`), drawn from ``seed``."""
    kind = dem["kind"]
    if kind in ("steps", "sequence"):
        tt, vv = demand_values(dem, seed, duration, _demand_table)
        return poly_table(vv, float(tt[1] - tt[0]), "cubic")
    if kind == "multisine":
        return multisine_table(dem["amplitude"], dem["f_lo"], dem["f_hi"], dem["n_lines"], seed, dem["ramp_s"],
                               dem["offset"])
    if kind in ("chirp", "sweep"):
        return chirp_table(dem["amplitude"], dem["f_lo"], dem["f_hi"], dem["sweep_s"], dem["v_max"],
                           kind == "sweep", dem["ramp_s"], dem["offset"])
    if kind == "road":
        return road_table(dem["amplitude"], dem["f_lo"], dem["f_hi"], dem["n_lines"], seed, dem["v_max"], duration,
                          dem["ramp_s"], dem["offset"])
    rng = np.random.default_rng([int(seed), 7002])
    n = int(math.ceil(duration / dem["block_s"])) + 1
    f = np.exp(rng.uniform(math.log(dem["f_lo"]), math.log(dem["f_hi"]), n))
    a = dem["amplitude"] * rng.uniform(dem["min_fraction"], 1.0, n)
    a = np.minimum(a, dem["v_max"] / (2 * math.pi * f))
    return blocks_table(a, f, dem["block_s"], dem["fade_s"], dem["offset"])


# --- set-up -----------------------------------------------------------------------------------
def _param_vector(spec: dict) -> np.ndarray:
    kn = spec["known"]
    eff = spec["effects"]
    P = np.zeros(R.NP)
    P[R.RHO], P[R.V0], P[R.AREA], P[R.MASS], P[R.BULK] = kn["rho"], kn["V0"], kn["A"], kn["m"], kn["B"]
    P[R.AREA_B], P[R.V0_B] = kn["AB"], kn["V0B"]
    P[R.VREF], P[R.KE], P[R.KSP], P[R.PORT], P[R.PP], P[R.PT] = (kn["vref"], kn["Ke"], kn["Ksp"], kn["b"],
                                                                 kn["pP"], kn["pT"])
    P[R.FEXT] = spec["Fext"]
    P[R.KP], P[R.KI], P[R.KD], P[R.TD] = kn["KP"], kn["KI"], kn["KD"], spec["derivative_filter_s"]
    P[R.GAIN] = 1.0
    P[R.DPREG] = 1.0
    P[R.PATM] = 1.0e5
    P[R.SEG] = -1.0
    if "viscous_friction" in eff:
        P[R.CVISC] = eff["viscous_friction"]["c"]
    if "stribeck_friction" in eff:
        P[R.FSTR] = eff["stribeck_friction"]["Fs"]
        P[R.VSTR] = eff["stribeck_friction"]["vs"]
    if "laminar_leakage" in eff:
        P[R.GLAM] = eff["laminar_leakage"]["G"]
    if "spool_deadband" in eff:
        P[R.OVERLAP] = eff["spool_deadband"]["overlap"]
    if "valve_null_bias" in eff:
        P[R.BIAS] = eff["valve_null_bias"]["offset"] * eff["valve_null_bias"]["sign"]
    if "supply_pressure_droop" in eff:
        P[R.RSUP] = eff["supply_pressure_droop"]["R"]
    if "supply_line_loss" in eff:
        P[R.KTURB] = eff["supply_line_loss"]["K"]
    if "pressure_sensor_lag" in eff:
        P[R.TAUP] = eff["pressure_sensor_lag"]["tau"]
    if "supply_dynamics" in eff:
        e = eff["supply_dynamics"]
        f = SUPPLY_FIXED
        P[R.SUP_ON] = 1.0
        P[R.HOSE_L], P[R.HOSE_D], P[R.ACC_V] = e["hose_l"], e["hose_d"], e["acc_v"]
        P[R.ACC_P] = f["precharge"] * (kn["pP"] + P[R.PATM])
        P[R.ACC_N], P[R.MU] = f["n"], f["mu"]
        P[R.PUMP_V], P[R.PUMP_Q], P[R.PUMP_BAND] = f["pump_v"], f["pump_q"], f["band"]
    if "specimen_stiffness" in eff:
        P[R.KSPEC] = eff["specimen_stiffness"]["k"]
    if "entrained_air" in eff:
        P[R.AIR] = eff["entrained_air"]["air_fraction"]
    if "spool_saturation" in eff:
        P[R.XSMAX] = eff["spool_saturation"]["xs_max"]
    if "position_sensor_gain" in eff:
        P[R.GAIN] = eff["position_sensor_gain"]["gain"]
    if "mechanical_resonance" in eff:
        e = eff["mechanical_resonance"]
        w2 = 2.0 * math.pi * e["f"]
        P[R.M2] = e["m2"]
        P[R.K2] = e["m2"] * w2 * w2
        P[R.C2] = 2.0 * e["zeta2"] * e["m2"] * w2
    if "sensor_delay" in eff and spec["controller"] == "analog":
        n = spec["pade_order"]
        if not 1 <= n <= 4:
            raise ValueError("pade_order must be 1..4")
        A, _, C, D = pade_delay(1.0, n)
        P[R.PADE_N] = n
        P[R.PA0:R.PA0 + n] = -A[-1, :]
        P[R.PC0:R.PC0 + n] = C
        P[R.PD] = D
        P[R.PTAU] = eff["sensor_delay"]["delay"]
    return P


class _Setup:
    """Everything the right-hand side needs, built from a complete spec."""

    def __init__(self, spec: dict):
        self.spec = spec
        self.n_log = int(round(spec["duration"] * spec["log_rate_hz"]))
        self.dt_log = 1.0 / spec["log_rate_hz"]
        self.P = _param_vector(spec)
        rows, tabs, self.truth_desc = [], [], {}
        t_lo = -spec["preroll"]
        for name in R.FREE_ORDER:
            row, desc = tv_row(spec["time_varying"].get(name), spec["truth"][name], tabs, t_lo, spec["duration"])
            rows.append(row)
            self.truth_desc[name] = desc if name in spec["time_varying"] else spec["truth"][name]
        temp = spec.get("temperature")
        if temp is not None:
            row, _ = tv_row(temp["T"], temp["T0"], tabs, t_lo, spec["duration"])
            self.P[R.TEMP_ON], self.P[R.TREF] = 1.0, temp["T0"]
            self.P[R.ABULK], self.P[R.BVISC] = temp["a_bulk"], temp["b_visc"]
            rows.append(row)
        else:
            rows.append([0.0, 0.0, 0.0, 0.0, 0.0])
        k_var = (spec.get("specimen") or {}).get("k")
        row, desc = tv_row(k_var, float(self.P[R.KSPEC]), tabs, t_lo, spec["duration"])
        rows.append(row)
        if k_var is not None:
            self.truth_desc["k_spec"] = desc
        self.tv, self.tab = tv_tables(rows, tabs)
        ctrl = spec["controller"]
        rng = np.random.default_rng([spec["seed"], 1234])
        nz = spec["noise"]
        # input table: the demand (closed loop) or the drive (open loop)
        if ctrl == "open_loop":
            self.sigp, self.sc = poly_table(spec["drive"]["u"], self.dt_log, spec["intersample"])
            self.P[R.MODE] = R.M_SIGNAL
        else:
            dem = spec["demand"]
            if dem["kind"] != "samples":
                self.msp, self.msc = _demand_table(dem, spec["seed"], spec["duration"])
                tk = np.arange(self.n_log) * self.dt_log
                self.x_ref = np.array([sig_eval(self.msp, self.msc, t, -1) for t in tk])
            else:
                self.x_ref = np.asarray(dem["values"], float)
            if spec["intersample"] == "analytic":
                self.sigp, self.sc = self.msp, self.msc
            else:
                self.sigp, self.sc = poly_table(self.x_ref, self.dt_log, spec["intersample"])
            self.P[R.MODE] = R.M_ANALOG if ctrl == "analog" else R.M_HELD
        # measurement noise on x: the sequence the controller sees, at the base (digital) or noise grid
        if ctrl == "digital":
            self.base_rate = max(spec["rate_hz"], spec["log_rate_hz"])
            self.L = int(round(self.base_rate / spec["log_rate_hz"]))
            self.C = int(round(self.base_rate / spec["rate_hz"]))
            n_base = (self.n_log - 1) * self.L + 1
            self.xnoise = noise_sequence(rng, n_base, nz["x"], 1.0 / self.base_rate, nz["tau"])
            self.xdrift_w = (np.random.default_rng([spec["seed"], 5152]).standard_normal(n_base)
                             if "x" in (spec.get("sensor_drift") or {}) else None)
        else:
            self.base_rate = spec["log_rate_hz"]
            self.L = self.C = 1
            # analog: a continuous noise signal (spline through a sequence at oversample x the log
            # rate); open loop: the noise is only logged
            self.noise_os = int(nz["oversample"]) if ctrl == "analog" else 1
            n_nz = (self.n_log - 1) * self.noise_os + 1
            self.xnoise = noise_sequence(rng, n_nz, nz["x"], self.dt_log / self.noise_os, nz["tau"])
        if ctrl == "analog" and nz["x"] > 0.0:
            self.nzp, self.nzc = poly_table(self.xnoise, self.dt_log / self.noise_os, "cubic")
            self.P[R.NOISE_ON] = 1.0
        else:
            self.nzp, self.nzc = np.array([0.0, 0.0, 1.0, 1.0, 0.0, 0.0]), np.zeros((1, 4))
        self.pnoise = {k: noise_sequence(rng, self.n_log, nz[k], self.dt_log, nz["tau"]) for k in ("pA", "pB")}
        sv = spec["solver"]
        self.atol = ATOL * sv["atol_scale"]
        self.opts = {"driver": sv["driver"], "method": sv["method"], "rtol": sv["rtol"], "atol": self.atol}
        self.max_step = sv["max_step"]
        self.delay = spec["effects"].get("sensor_delay", {}).get("delay", 0.0)
        # the adaptive solver sees the RHS through this closure (P is updated in place between pieces)
        P, tv, tab, sigp, sc, nzp, nzc = self.P, self.tv, self.tab, self.sigp, self.sc, self.nzp, self.nzc
        act = list(range(6))
        if P[R.M2] > 0.0:
            act += [R.S_X2, R.S_V2]
        if ctrl == "analog" and P[R.KI] != 0.0:
            act.append(R.S_ZI)
        if ctrl == "analog" and P[R.KD] != 0.0:
            act.append(R.S_ZD)
        act += [R.S_Z0 + i for i in range(int(P[R.PADE_N]))]
        if P[R.TAUP] > 0.0:
            act += [R.S_PAM, R.S_PBM]
        if P[R.SUP_ON] > 0.0:
            act += [R.S_PV, R.S_QH, R.S_PU]
        self.active = idx = np.array(act, dtype=np.int64)
        self.opts["atol"] = self.atol[idx]
        self.fun = lambda t, y: R.rhs_sub(t, y, idx, P, tv, tab, sigp, sc, nzp, nzc)

    def piece(self, ta: float, tb: float, y: np.ndarray, t_eval: np.ndarray, opts: dict) -> np.ndarray:
        """Full states at ``t_eval`` from full state ``y`` at ``ta`` (integrating the active ones)."""
        yr = piece(self.fun, ta, tb, y[self.active], t_eval, **opts)
        out = np.zeros((t_eval.size, R.NS))
        out[:, self.active] = yr
        return out

    def u_now(self, t: float, y: np.ndarray) -> float:
        return float(R.control(t, y, self.P, self.sigp, self.sc, self.nzp, self.nzc))


# --- initial state ----------------------------------------------------------------------------------
def _equilibrium(s: _Setup, t: float) -> tuple[np.ndarray, str]:
    """A state at rest on the demand's value at ``t`` (static equilibrium of the closed loop)."""
    P = s.P
    spec = s.spec
    y = np.zeros(R.NS)
    y[R.S_PV] = y[R.S_PU] = P[R.PP]  # the supply at rest (unused without it)
    pm = 0.5 * (P[R.PP] + P[R.PT])
    if P[R.AREA_B] != P[R.AREA]:  # two areas: the valve's null shares pP, the areas share the load
        pA_eq = (spec["Fext"] + P[R.PP] * P[R.AREA_B]) / (P[R.AREA] + P[R.AREA_B])
        pm, dp_half = 0.5 * P[R.PP], pA_eq - 0.5 * P[R.PP]
    else:
        dp_half = 0.5 * spec["Fext"] / P[R.AREA]
    if spec["controller"] == "open_loop":
        y[R.S_PA] = pm + dp_half
        y[R.S_PB] = pm - dp_half
        return y, "rest"
    r0 = float(sig_eval(s.sigp, s.sc, t, -1))
    x0 = r0 / P[R.GAIN]
    dpF = (spec["Fext"] + tv_eval(s.tv, s.tab, R.TV_KSPEC, t) * x0) / P[R.AREA]
    y[R.S_X] = x0
    y[R.S_X2] = x0
    y[R.S_PA] = pm + (0.5 * dpF if P[R.AREA_B] == P[R.AREA] else dp_half)
    y[R.S_PB] = pm - (0.5 * dpF if P[R.AREA_B] == P[R.AREA] else dp_half)
    n = int(P[R.PADE_N])
    has_i = P[R.KI] != 0.0
    mode_save = P[R.MODE], P[R.UHELD], P[R.NOISE_ON]
    P[R.MODE] = R.M_ANALOG  # static loop: u = KP e (+ KI zi)
    P[R.NOISE_ON] = 0.0
    scale = np.array([1e-4, 1e6, 1e6, 1e-3, 1e-3] + ([1e-3] if has_i else []))

    def full(z):
        yy = y.copy()
        yy[R.S_XS], yy[R.S_PA], yy[R.S_PB], yy[R.S_X], yy[R.S_X2] = z[:5] * scale[:5]
        if has_i:
            yy[R.S_ZI] = z[5] * scale[5]
        if n > 0:
            yy[R.S_Z0] = P[R.GAIN] * yy[R.S_X] / P[R.PA0]
        yy[R.S_ZD] = r0 - P[R.GAIN] * yy[R.S_X]
        return yy

    def resid(z):
        yy = full(z)
        d = R.rhs(t, yy, P, s.tv, s.tab, s.sigp, s.sc, s.nzp, s.nzc)
        wn = tv_eval(s.tv, s.tab, R.TV_WN, t)
        res = [d[R.S_VS] / (wn * wn * 1e-4), d[R.S_PA] * P[R.V0] / P[R.BULK] / 1e-7,
               d[R.S_PB] * P[R.V0] / P[R.BULK] / 1e-7, d[R.S_V] * P[R.MASS], z[4] - z[3]]
        if P[R.M2] > 0.0:
            res[4] = d[R.S_V2] * P[R.M2]
        if has_i:
            res.append((r0 - P[R.GAIN] * yy[R.S_X]) / 1e-6)
        return np.array(res)

    z0 = np.array([0.0, y[R.S_PA], y[R.S_PB], x0, x0] + ([0.0] if has_i else [])) / scale
    try:
        r0res = np.max(np.abs(resid(z0)))
        how = "rest"
        best = z0
        if r0res > 1e-9:
            sol = root(resid, z0, method="hybr", options={"xtol": 1e-13})
            ys = full(sol.x)
            inside = all(P[R.PT] < ys[i] < P[R.PP] for i in (R.S_PA, R.S_PB))  # not the empty chambers' root
            if np.max(np.abs(resid(sol.x))) < min(r0res, 1e-6) and inside:
                best, how = sol.x, "solved"
            else:
                how = "guess"
        return full(best), how
    finally:
        P[R.MODE], P[R.UHELD], P[R.NOISE_ON] = mode_save


# --- the runs ---------------------------------------------------------------------------------------
def simulate_msp25(spec: dict) -> Record:
    """Simulate one complete MSP25 spec (from :func:`msp25_spec`) into a :class:`Record`."""
    t_start = time.perf_counter()
    s = _Setup(spec)
    hb = 1.0 / s.base_rate
    j_pre = s.C * int(round(spec["preroll"] / (s.C * hb)))
    t_first = -j_pre * hb
    if spec["init"] is not None:
        y0 = np.zeros(R.NS)
        y0[R.S_PV] = y0[R.S_PU] = s.P[R.PP]
        y0[: len(spec["init"])] = spec["init"]
        how = "given"
    else:
        y0, how = _equilibrium(s, t_first)
    y0[R.S_PAM], y0[R.S_PBM] = y0[R.S_PA], y0[R.S_PB]  # the transducers settled on the start
    ctrl = spec["controller"]
    held = spec["intersample"] in ("zoh", "foh")
    if ctrl == "digital" or held:
        states, u_log, xm_log, xclean = _run_ticks(s, y0, j_pre)
    else:
        states, u_log, xm_log, xclean = _run_smooth(s, y0, t_first)
    return _record(s, states, u_log, xm_log, xclean, how, time.perf_counter() - t_start)


def _run_ticks(s: _Setup, y: np.ndarray, j_pre: int):
    """Piecewise integration between base-grid instants, restarting at each (held inputs, ticks)."""
    spec = s.spec
    P = s.P
    hb = 1.0 / s.base_rate
    L, C = s.L, s.C
    j_end = (s.n_log - 1) * L
    states = np.empty((s.n_log, R.NS))
    u_log = np.empty(s.n_log)
    xm_log = np.empty(s.n_log)
    xclean = np.empty(s.n_log)
    digital = spec["controller"] == "digital"
    open_loop = spec["controller"] == "open_loop"
    kn = spec["known"]
    qx = spec["noise"]["quant"]["x"]
    delay = s.delay if digital else 0.0
    x_first = y[R.S_X]
    integ = float(y[R.S_ZI])
    e_prev = None
    xm_prev = 0.0
    dfilt = 0.0
    pid = spec["pid"]
    a_f = pid["Tf"] / (pid["Tf"] + C * hb)
    Tc = C * hb
    if open_loop and spec["intersample"] == "zoh":
        P[R.MODE] = R.M_HELD
    u_drive = spec["drive"]["u"] if open_loop else None
    # delayed reads: instant j reads x at t_j - delay, taken from the integrator on the way
    if delay > 0.0:
        jr = np.array([j for j in range(-j_pre, j_end + 1) if j % C == 0 or (j >= 0 and j % L == 0)])
        t_read = jr * hb - delay
        on_grid = np.round(t_read / hb)
        snap = np.abs(t_read / hb - on_grid) < 1e-9  # a read on a piece boundary comes from its end state
        t_read[snap] = on_grid[snap] * hb
        x_read = np.full(jr.size, x_first)
        read_of = {int(j): i for i, j in enumerate(jr)}

    def measure(j: int, t: float, y_now: np.ndarray) -> tuple[float, float]:
        """(reading, noise-free sensor output) at base instant j."""
        xt = x_read[read_of[j]] if delay > 0.0 else y_now[R.S_X]
        clean = P[R.GAIN] * xt
        xm = clean + (s.xnoise[j] if j >= 0 else 0.0)
        if xdrift is not None and j >= 0:
            xm = float(drifted(xdrift, np.array([t]), np.array([xm]), np.array([s.xdrift_w[j]]))[0])
        return float(quantise(np.array(xm), qx)), clean

    xdrift = spec.get("sensor_drift", {}).get("x")
    held_demand = spec["intersample"] in ("zoh", "foh")
    opts = dict(s.opts, max_step=min(s.max_step, hb))
    for j in range(-j_pre, j_end + 1):
        t = j * hb
        k, on_log = divmod(j, L) if j >= 0 else (-1, 1)
        xm = None
        if digital and j % C == 0:
            xm, clean = measure(j, t, y)
            r = sig_eval(s.sigp, s.sc, t, j // L if (j >= 0 and held_demand) else -1)
            e = r - xm
            integ += e * Tc
            if e_prev is None:
                dfilt = 0.0
            else:
                ds = (xm_prev - xm) if pid["d_on"] == "measurement" else (e - e_prev)
                dfilt = a_f * dfilt + (1.0 - a_f) * ds / Tc
            e_prev = e
            xm_prev = xm
            u_c = kn["KP"] * e + kn["KI"] * integ + kn["KD"] * dfilt
            if pid["Kff"] != 0.0:
                seg = j // L if (j >= 0 and held_demand) else -1
                rate = (sig_eval(s.sigp, s.sc, t + 1e-6, seg) - sig_eval(s.sigp, s.sc, t - 1e-6, seg)) / 2e-6
                u_c += pid["Kff"] * rate
            if pid["u_max"] is not None:
                u_c = min(max(u_c, -pid["u_max"]), pid["u_max"])
            P[R.UHELD] = u_c
        elif not digital:
            P[R.SEG] = float(j) if j >= 0 else -1.0
            if open_loop and spec["intersample"] == "zoh":
                P[R.UHELD] = u_drive[max(j, 0)]
        if j >= 0 and on_log == 0:
            states[k] = y
            u_log[k] = P[R.UHELD] if (digital or P[R.MODE] == R.M_HELD) else s.u_now(t, y)
            if digital:
                xm_log[k], xclean[k] = (xm, clean) if xm is not None else measure(j, t, y)
            else:
                xm_log[k] = xclean[k] = R.measured_nonoise(y, P)  # noise added in _record
        if j == j_end:
            break
        tb = (j + 1) * hb
        if delay > 0.0:
            lo = np.searchsorted(t_read, t, side="right")
            hi = np.searchsorted(t_read, tb, side="left")
            ys = s.piece(t, tb, y, np.append(t_read[lo:hi], tb), opts)
            x_read[lo:hi] = ys[:-1, R.S_X]
            x_read[hi:np.searchsorted(t_read, tb, side="right")] = ys[-1, R.S_X]
        else:
            ys = s.piece(t, tb, y, np.array([tb]), opts)
        y = ys[-1].copy()
    return states, u_log, xm_log, xclean


def _run_smooth(s: _Setup, y: np.ndarray, t_first: float):
    """One adaptive integration across the record (smooth inputs), split only at parameter steps."""
    tk = np.arange(s.n_log) * s.dt_log
    t_end = tk[-1]
    cuts = [t_first, 0.0] + [b for b in tv_breaks(s.tv) if 0.0 < b < t_end] + [t_end]
    cuts = sorted(set(c for c in cuts if t_first <= c <= t_end))
    states = np.empty((s.n_log, R.NS))
    filled = 0
    if cuts[0] == 0.0:  # no pre-roll: the first sample is the initial state
        states[0] = y
        filled = 1
    for ta, tb in zip(cuts[:-1], cuts[1:]):
        te = tk[(tk > ta) & (tk <= tb)]
        n_te = te.size
        if not n_te or te[-1] != tb:
            te = np.append(te, tb)
        ys = s.piece(ta, tb, y, te, dict(s.opts, max_step=s.max_step))
        if ta == 0.0 and filled == 0:
            raise RuntimeError("internal: sample at t=0 missing")
        states[filled: filled + n_te] = ys[:n_te]
        filled += n_te
        y = ys[-1].copy()
        if tb == 0.0:
            states[0] = y
            filled = 1
    if filled != s.n_log:
        raise RuntimeError(f"smooth run logged {filled} of {s.n_log} samples")
    u_log = np.array([s.u_now(t, states[i]) for i, t in enumerate(tk)])
    xm_log = np.array([R.measured_nonoise(states[i], s.P) for i in range(s.n_log)])
    return states, u_log, xm_log, xm_log.copy()


def _record(s: _Setup, states, u_log, xm_log, xclean, how: str, elapsed: float) -> Record:
    spec = s.spec
    nz = spec["noise"]
    tk = np.arange(s.n_log) * s.dt_log
    if spec["controller"] == "digital":
        x = xm_log
    else:
        x = quantise(xm_log + s.xnoise[:: s.noise_os], nz["quant"]["x"])
    lag = s.P[R.TAUP] > 0.0  # what lagging transducers read
    pA = states[:, R.S_PAM if lag else R.S_PA] + s.pnoise["pA"]
    pB = states[:, R.S_PBM if lag else R.S_PB] + s.pnoise["pB"]
    off = spec["effects"].get("pressure_sensor_offset")
    if off:
        if off["channel"] == "pA":
            pA = pA + off["sign"] * off["offset"]
        else:
            pB = pB + off["sign"] * off["offset"]
    drift = spec.get("sensor_drift") or {}
    wd = np.random.default_rng([spec["seed"], 5151]).standard_normal((2, tk.size))
    if "pA" in drift:
        pA = drifted(drift["pA"], tk, pA, wd[0])
    if "pB" in drift:
        pB = drifted(drift["pB"], tk, pB, wd[1])
    pA = quantise(pA, nz["quant"]["pA"])
    pB = quantise(pB, nz["quant"]["pB"])
    if spec["controller"] == "open_loop":
        signals = {}
        if "x_ref" in spec["drive"]:
            signals["x_ref"] = spec["drive"]["x_ref"]
        signals["u"] = spec["drive"]["u"].copy()
    else:
        signals = {"x_ref": s.x_ref.copy(), "u": u_log}
    signals.update({"x": x, "pA": pA, "pB": pB})
    temp = spec.get("temperature")
    T = None
    if temp is not None:
        T = np.array([tv_eval(s.tv, s.tab, R.TV_TEMP, t) for t in tk])
        signals["T_oil"] = quantise(T, temp["quant"])
    fresh = {}
    for name, rate in spec.get("signal_rates", {}).items():  # sampled at its own rate, held onto the log grid
        if name not in signals:
            continue
        every = int(round(spec["log_rate_hz"] / rate))
        k = np.arange(tk.size)
        signals[name] = signals[name][k - k % every].copy()
        fresh[f"fresh_{name}"] = (k % every == 0).astype(float)
    hidden = {"x": states[:, R.S_X].copy(), "v": states[:, R.S_V].copy(), "pA": states[:, R.S_PA].copy(),
              "pB": states[:, R.S_PB].copy(), "xs": states[:, R.S_XS].copy(), "x_sensor": xclean}
    for i, name in enumerate(R.FREE_ORDER):
        if name in spec["time_varying"]:
            hidden[name] = np.array([tv_eval(s.tv, s.tab, i, t) for t in tk])
    hidden.update(fresh)
    if s.P[R.SUP_ON] > 0.0:
        hidden["p_supply"] = states[:, R.S_PV].copy()
    if (spec.get("specimen") or {}).get("k") is not None:
        hidden["k_spec"] = np.array([tv_eval(s.tv, s.tab, R.TV_KSPEC, t) for t in tk])
    if T is not None:
        dT = T - temp["T0"]
        hidden.update({"T_oil": T, "B": s.P[R.BULK] * (1.0 - temp["a_bulk"] * dT),
                       "leak_factor": np.exp(temp["b_visc"] * dT)})
    truth = dict(s.truth_desc)
    truth["Fext"] = spec["Fext"]
    for ename, vals in spec["effects"].items():
        for p, v in vals.items():
            truth[f"{ename}.{p}"] = v
    if spec["time_jitter_s"] > 0.0:  # stamped late by the bus, values from the nominal instants
        jit = np.random.default_rng([spec["seed"], 4242]).uniform(0.0, spec["time_jitter_s"], tk.size)
        tk = tk + jit
    meta = {k: v for k, v in spec.items() if k not in ("drive", "demand", "truth")}
    meta["demand"] = _describe(spec["demand"])
    meta["drive"] = _describe(spec["drive"])
    meta["state0"] = states[0].tolist()
    meta["equilibrium"] = how
    meta["elapsed_s"] = elapsed
    meta["time_varying"] = {k: _describe(v) for k, v in spec["time_varying"].items()}
    return Record(tk, signals, truth, meta, hidden)


def _describe(d: Any) -> Any:
    """A JSON-able summary (arrays as their length and digest)."""
    if isinstance(d, np.ndarray):
        return f"array[{d.size}] sha1:{hashlib.sha1(np.ascontiguousarray(d).tobytes()).hexdigest()[:12]}"
    if isinstance(d, Mapping):
        return {k: _describe(v) for k, v in d.items()}
    if isinstance(d, list) and len(d) > 16:
        return f"list[{len(d)}]"
    return d


def replay_spec(spec: dict, record: Record, intersample: str = "zoh", noise=None) -> dict:
    """An open-loop spec driving the rig of ``spec`` by ``record``'s logged u (with ``intersample``),
    from the record's initial state, without pre-roll."""
    return msp25_spec(spec["seed"], duration=spec["duration"], log_rate_hz=spec["log_rate_hz"],
                      controller="open_loop", intersample=intersample,
                      drive={"u": record.signals["u"], "x_ref": record.signals["x_ref"]},
                      truth=spec["truth"], time_varying=spec["time_varying"], known=spec["known"],
                      Fext=spec["Fext"], effects=spec["effects"], noise=noise, preroll=0.0,
                      init=record.meta["state0"], rtol=spec["solver"]["rtol"],
                      atol_scale=spec["solver"]["atol_scale"], max_step=spec["solver"]["max_step"],
                      method=spec["solver"]["method"], driver=spec["solver"]["driver"])
