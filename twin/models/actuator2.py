"""A hydraulic actuator whose servo-valve is a static gain: the smallest rig model the whole product runs.

States (SI): ``pA``, ``pB`` chamber pressures [Pa], ``x`` rod position [m], ``v`` rod velocity [m/s].  The valve
has no dynamics of its own: its flows follow the command ``u`` [V] at once, linearised about mid pressure
``pm = pP / 2`` (flow gain ``Kq``, flow-pressure coefficient ``Kc``)::

    qA =  Kq u - Kc (pA - pm)          qB = -Kq u - Kc (pB - pm)          qL = Cl (pA - pB)
    pA' = Bulk / (V0 + A x) (qA - qL - A v)
    pB' = Bulk / (V0 - A x) (qB + qL + A v)
    m v' = A (pA - pB) - Ffric tanh(v / vref) - c_visc v - Fext

Driven open loop by the logged command ``u`` or closed loop by the demand ``x_ref`` through a digital P
controller ``u = KP (x_ref - x)`` held between its ticks.  It declares everything the product asks of a model
(parameters with their tracking, effects, a filter interface), so fit, diagnosis and the online twin run it with
no change elsewhere; it is also this module's own filter interface (``advance``, ``lanes``; no side-by-side lanes).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numba as nb
import numpy as np

from fpdd.errors import DataError
from twin.models import base as _base_src
from twin.models import intersample as _intersample_src
from twin.models import hydraulic_signals
from twin.models.base import (DEFAULT_TIMING, FilterMap, FilterSpec, Model, SimResult, check_drive,
                              start_of)
from twin.models.intersample import input_at
from twin.models.jitcache import keep_fresh
from twin.params import Effect, ParamSpec, Tracking

keep_fresh(__file__, _intersample_src.__file__, _base_src.__file__)

PH, PN, G, EX = "physical", "phenomenological", "geometric", "extension"
BASE = (
    ParamSpec("KP", "V/m", 0.0, 1e5, PH, "proportional gain of the position controller"),
    ParamSpec("A", "m^2", 1e-6, 1e-1, G, "piston area", "mm^2", 1e6),
    ParamSpec("V0", "m^3", 1e-7, 1e-1, G, "chamber volume at mid stroke", "cm^3", 1e6),
    ParamSpec("m", "kg", 0.1, 1e5, PH, "moving mass"),
    ParamSpec("Bulk", "Pa", 1e7, 1e11, PH, "oil bulk modulus", "MPa", 1e-6),
    ParamSpec("pP", "Pa", 1e5, 1e8, PH, "supply pressure", "MPa", 1e-6),
    ParamSpec("Kc", "m^3/(s Pa)", 0.0, 1e-8, PH, "valve flow-pressure coefficient"),
    ParamSpec("vref", "m/s", 1e-7, 1.0, PH, "friction smoothing velocity", "mm/s", 1e3),
    ParamSpec("Fext", "N", -1e6, 1e6, PH, "constant external force on the rod"),
    ParamSpec("stroke", "m", 1e-3, 10.0, G, "half stroke about mid position", "mm", 1e3),
    ParamSpec("Ffric", "N", 0.0, 1e5, PN, "dry friction force", typical=40.0,
              tracking=Tracking(band=0.5, drift_rate=0.3, bounds=(1 / 20, 40.0), excited_by="rod_motion")),
    ParamSpec("Cl", "m^3/(s Pa)", 1e-16, 1e-8, PN, "cross-piston leakage conductance", typical=2e-12,
              tracking=Tracking(band=2.0, drift_rate=0.15, bounds=(1 / 100, 1000.0),
                                excited_by="pressure_difference")),
    ParamSpec("Kq", "m^3/(s V)", 1e-8, 1e-2, PN, "valve flow gain", typical=5e-5,
              tracking=Tracking(band=0.15, drift_rate=0.01, bounds=(1 / 4, 4.0), excited_by="valve_command")),
)
NOMINAL = {"KP": 400.0, "A": 1e-3, "V0": 3e-4, "m": 20.0, "Bulk": 1.5e9, "pP": 21e6, "Kc": 1e-12, "vref": 1e-3,
           "Fext": 0.0, "stroke": 0.1, "Ffric": 40.0, "Cl": 2e-12, "Kq": 5e-5}
PHENOMENOLOGICAL = ("Ffric", "Cl", "Kq")
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("viscous_friction", "friction force proportional to rod velocity",
           (ParamSpec("c_visc", "N s/m", 0.0, 1e6, EX, "viscous friction coefficient"),), (0.0,),
           "residual force linear in velocity", (2000.0,)),
)}
KERNEL_NAMES = tuple(s.name for s in BASE) + tuple(p.name for e in EFFECTS.values() for p in e.params)
NP = len(KERNEL_NAMES)
(I_KP, I_A, I_V0, I_M, I_BULK, I_PP, I_KC, I_VREF, I_FEXT, I_STROKE, I_FFRIC, I_CL, I_KQ, I_CVISC) = range(NP)
STATES = ("pA", "pB", "x", "v")
NS = 4
#: the filter interface: controller memory entries (a P controller keeps none), no side-by-side lanes
N_CTRL = 1
LANES = 0
LANE_WORK = 0


@nb.njit(cache=True)
def deriv(pA, pB, x, v, u, p):
    """Right-hand side of one state (the one definition of this model's physics)."""
    pm = 0.5 * p[I_PP]
    A = p[I_A]
    V0 = p[I_V0]
    qA = p[I_KQ] * u - p[I_KC] * (pA - pm)
    qB = -p[I_KQ] * u - p[I_KC] * (pB - pm)
    qL = p[I_CL] * (pA - pB)
    VA = max(V0 + A * x, 1e-3 * V0)
    VB = max(V0 - A * x, 1e-3 * V0)
    dpA = p[I_BULK] * (qA - qL - A * v) / VA
    dpB = p[I_BULK] * (qB + qL + A * v) / VB
    dv = (A * (pA - pB) - p[I_FFRIC] * math.tanh(v / p[I_VREF]) - p[I_CVISC] * v - p[I_FEXT]) / p[I_M]
    return dpA, dpB, v, dv


@nb.njit(cache=True)
def _rk4(s, k, drive, held, u, mode, p, dt, nsub, out):
    """``nsub`` RK4 substeps over ``dt`` from ``s``: the input ``u`` held, or ``drive`` interpolated by ``mode``."""
    h = dt / nsub
    a0, a1, a2, a3 = s[0], s[1], s[2], s[3]
    for j in range(nsub):
        f0 = j / nsub
        u1 = u if held else input_at(drive, k, f0, mode)
        u2 = u if held else input_at(drive, k, f0 + 0.5 / nsub, mode)
        u4 = u if held else input_at(drive, k, f0 + 1.0 / nsub, mode)
        k1 = deriv(a0, a1, a2, a3, u1, p)
        k2 = deriv(a0 + 0.5 * h * k1[0], a1 + 0.5 * h * k1[1], a2 + 0.5 * h * k1[2], a3 + 0.5 * h * k1[3], u2, p)
        k3 = deriv(a0 + 0.5 * h * k2[0], a1 + 0.5 * h * k2[1], a2 + 0.5 * h * k2[2], a3 + 0.5 * h * k2[3], u2, p)
        k4 = deriv(a0 + h * k3[0], a1 + h * k3[1], a2 + h * k3[2], a3 + h * k3[3], u4, p)
        c = h / 6.0
        a0 += c * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0])
        a1 += c * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1])
        a2 += c * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2])
        a3 += c * (k1[3] + 2.0 * k2[3] + 2.0 * k3[3] + k4[3])
    out[0] = a0
    out[1] = a1
    out[2] = a2
    out[3] = a3


@nb.njit(cache=True)
def advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm_k, ctrl, out):
    """One log interval from sample ``k`` to ``k+1``; returns the command at ``t_k``.  Closed loop: the P
    controller ticks ``max(ticks, 1)`` times per sample on the measured position (``xm_k``, then the model's),
    its output held; open loop: the logged command, interpolated by ``mode``."""
    if not closed:
        _rk4(s, k, drive, mode == 0, drive[k], mode, p, dt, nsub, out)
        return drive[k]
    n = max(ticks, 1)
    h = dt / n
    u0 = 0.0
    for i in range(n):
        xm = xm_k if i == 0 else out[2]
        u = p[I_KP] * (input_at(drive, k, i / n, mode) - xm)
        if i == 0:
            u0 = u
            _rk4(s, k, drive, True, u, mode, p, h, max(1, nsub // n), out)
        else:
            _rk4(out, k, drive, True, u, mode, p, h, max(1, nsub // n), out)
    return u0


@nb.njit(cache=True)
def lanes_applicable(p):
    """No side-by-side lanes: the filter integrates one sigma point at a time."""
    return False


@nb.njit(cache=True)
def lanes(S, TH, m, p, idx, wnd, mode, dt, nsub, W):
    """No side-by-side lanes (never called: :func:`lanes_applicable` is false)."""
    return None


@nb.njit(cache=True, parallel=True)
def simulate_kernel(S0, P, drive, closed, ticks, mode, dt, nsub):
    K = P.shape[0]
    T = drive.shape[0]
    S = np.empty((K, T, NS))
    U = np.empty((K, T))
    for r in nb.prange(K):
        s = S0[r].copy()
        ctrl = np.zeros(N_CTRL)
        for k in range(T):
            for j in range(NS):
                S[r, k, j] = s[j]
            if k + 1 < T:
                U[r, k] = advance(s, k, drive, closed, ticks, mode, P[r], dt, nsub, s[2], ctrl, s)
            else:
                U[r, k] = P[r, I_KP] * (drive[k] - s[2]) if closed else drive[k]
    return S, U


class Actuator2(Model):
    """The actuator with a static-gain valve; see the module docstring."""

    name = "actuator2"
    STATES = STATES
    INPUTS = ("x_ref", "u")
    OUTPUTS = ("x", "pA", "pB")
    BASE = BASE
    NOMINAL = NOMINAL
    EFFECTS = EFFECTS
    PHENOMENOLOGICAL = PHENOMENOLOGICAL
    CLOSED_LOOP = True
    TRACKABLE = True
    SIGNALS = tuple(s for s in hydraulic_signals.SIGNALS if s.name in ("x_ref", "u", "x", "pA", "pB"))
    EXPERIMENT = hydraulic_signals.EXPERIMENT
    substeps = 3
    INIT = ("x0", "dp0", "v0", "pA0", "pB0")
    INIT_FREE = ("x0", "dp0", "v0")
    FILTER = FilterSpec(
        functions="twin.models.actuator2",
        state_scale=(1e6, 1e6, 1e-3, 0.1),
        measures={"x": 2, "pA": 0, "pB": 1},
        q_state=(1e-6, 1e-6, 1e-10, 1e-7),
        prior_state=(0.1, 0.1, 0.01, 0.01),
        noise={"x": 2e-6, "pA": 2e4, "pB": 2e4},
        excite=(2e-3, 0.5, 2e4),
        feedback="x",
    )

    def fast_controller(self, ps) -> bool:
        """A P controller: the law the model runs between the log's samples."""
        return True

    def controller_response(self, ps, q, dt):
        """The P controller's response: its gain at every frequency."""
        return np.full(np.shape(q), ps["KP"], dtype=complex)

    def filter_map(self, ps) -> FilterMap:
        pm = 0.5 * ps["pP"]
        exc = np.zeros((3, NS))
        exc[0, 3] = 1.0
        exc[2, 0], exc[2, 1] = 1.0, -1.0
        return FilterMap(rest=np.array([pm, pm, 0.0, 0.0]), input_state=-1, input_gain=0.0, demand_gain=ps["KP"],
                         ranges={"x": (-ps["stroke"], ps["stroke"]), "pA": (-2e6, ps["pP"] + 5e6),
                                 "pB": (-2e6, ps["pP"] + 5e6)},
                         centres={"x": 0.0, "pA": pm, "pB": pm}, excitation=exc)

    def initial_state(self, P: np.ndarray, init: Mapping[str, float] | None = None) -> np.ndarray:
        P = np.atleast_2d(P)
        init = dict(init or {})
        vals = {k: float(init.pop(k, 0.0)) for k in ("x0", "dp0", "v0")}
        pA0, pB0 = init.pop("pA0", None), init.pop("pB0", None)
        if init:
            raise DataError(f"unknown initial-state quantities {sorted(init)}; known: {', '.join(self.INIT)}")
        pm = 0.5 * P[:, I_PP]
        S0 = np.zeros((P.shape[0], NS))
        S0[:, 0] = (pm if pA0 is None else float(pA0)) + 0.5 * vals["dp0"]
        S0[:, 1] = (pm if pB0 is None else float(pB0)) - 0.5 * vals["dp0"]
        S0[:, 2] = vals["x0"]
        S0[:, 3] = vals["v0"]
        return S0

    def initial_from_data(self, signals, dt):
        return {f"{n}0": start_of(signals[n], dt)[0] for n in ("x", "pA", "pB") if n in signals}

    def drive_signal(self, signals, drive="auto"):
        if drive == "auto":
            drive = "x_ref" if "x_ref" in signals else "u"
        if drive not in ("x_ref", "u") or drive not in signals:
            raise DataError(f"actuator2 is driven by 'x_ref' or 'u'; the record has {', '.join(signals)}")
        return drive, np.asarray(signals[drive], dtype=np.float64)

    def simulate_batch(self, P, drive_name, drive, dt, x0=None, substeps=None, timing=None,
                       exogenous=None) -> SimResult:
        self.exogenous_table(exogenous, np.shape(drive)[0])  # reads none: refuses any
        P = np.ascontiguousarray(np.atleast_2d(P), dtype=np.float64)
        if P.shape[1] != NP:
            raise DataError(f"actuator2 kernel vectors have {NP} entries, got {P.shape[1]}")
        drive = check_drive(drive_name, drive, dt)
        timing = timing or DEFAULT_TIMING
        S0 = self.initial_state(P) if x0 is None else np.ascontiguousarray(np.atleast_2d(x0), dtype=np.float64)
        closed = drive_name == "x_ref"
        S, U = simulate_kernel(S0, P, drive, closed, timing.ticks(dt), timing.intersample_code(dt), float(dt),
                               int(substeps or self.substeps))
        t = np.arange(drive.shape[0]) * dt
        outputs = {"x": S[:, :, 2], "pA": S[:, :, 0], "pB": S[:, :, 1]}
        inputs = {"u": U, drive_name: drive} if closed else {"u": drive}
        return SimResult(t, outputs, S, inputs)


MODEL = Actuator2()
