"""A position-controlled electromechanical axis: a motor's force through a screw on a load, dry and viscous
friction, a constant force offset, and the digital cascaded position-velocity loop that drives it.

States (SI): ``x`` the load position [m], ``v`` its velocity [m/s].  The controller's output ``u`` [V] becomes
the force on the load side through the drive's gain ``gtau`` [N/V] (current amplifier, motor constant and screw
together)::

    M v' = gtau u - Fv v - Fc tanh(v / vc) - offset

(the published inverse-dynamics model ``M q'' + Fv q' + Fc sign(q') + offset = tau`` with the sign smoothed
over ``vc``).  The loop is the rig's own digital law at the log's rate, its output held between ticks::

    u_k = kv (kp (x_ref_k - xm_k) - (xm_k - xm_{k-2}) / (2 dt))

a proportional position loop (``kp`` [1/s]) around a velocity loop (``kv`` [V s/m]) whose velocity is the
backward difference of the mean of the last two measured positions (``qf_k = (xm_k + xm_{k-1}) / 2``,
``dqf_k = (qf_k - qf_{k-1}) / dt``).  Driven closed loop by the demand ``x_ref`` or open loop by the logged
controller output ``u``.  The EMPS benchmark axis (a DC motor on a ball screw, dSPACE at 1 kHz) is this model:
``gtau`` = 35.15 N/V, ``kp`` = 160.18 1/s, ``kv`` = 243.45 V s/m.

The friction's smoothing velocity ``vc`` is a known parameter scaled to the record: about a hundredth of its rms
velocity (the nominal 1 mm/s is that for the EMPS record, 88 mm/s rms; set it for another axis).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numba as nb
import numpy as np

from fpdd.errors import DataError
from twin.models import base as _base_src
from twin.models import intersample as _intersample_src
from twin.models.base import (DEFAULT_TIMING, Experiment, FilterMap, FilterSpec, Model, Signal, SimResult,
                              check_drive, start_of)
from twin.models.intersample import input_at
from twin.models.jitcache import keep_fresh
from twin.params import Effect, ParamSpec, Tracking

keep_fresh(__file__, _intersample_src.__file__, _base_src.__file__)

PH, PN, EX = "physical", "phenomenological", "extension"
BASE = (
    ParamSpec("gtau", "N/V", 1e-6, 1e6, PH, "drive gain: force on the load per volt of controller output"),
    ParamSpec("kp", "1/s", 0.0, 1e5, PH, "position loop gain"),
    ParamSpec("kv", "V s/m", 0.0, 1e6, PH, "velocity loop gain"),
    ParamSpec("vc", "m/s", 1e-7, 1.0, PH, "dry friction's smoothing velocity", "mm/s", 1e3),
    ParamSpec("M", "kg", 1e-3, 1e5, PH, "moving mass (load side, motor inertia included)", typical=80.0,
              tracking=Tracking(band=0.3, drift_rate=0.002, bounds=(1 / 4, 4.0), excited_by="valve_command")),
    ParamSpec("offset", "N", -1e5, 1e5, PN, "constant force offset (gravity, cable, amplifier offset)"),
    ParamSpec("Fv", "N s/m", 0.0, 1e6, PN, "viscous friction coefficient", typical=150.0,
              tracking=Tracking(band=0.5, drift_rate=0.01, bounds=(1 / 20, 20.0), excited_by="rod_motion")),
    ParamSpec("Fc", "N", 0.0, 1e5, PN, "dry (Coulomb) friction force", typical=15.0,
              tracking=Tracking(band=1.0, drift_rate=0.05, bounds=(1 / 50, 50.0), excited_by="rod_motion")),
)
#: round catalogue values of a small ball-screw axis (a record's own are fitted: these are starts, not truths)
NOMINAL = {"gtau": 35.15, "kp": 160.18, "kv": 243.45, "vc": 1e-3, "M": 80.0, "offset": 0.0, "Fv": 150.0,
           "Fc": 15.0}
PHENOMENOLOGICAL = ("Fv", "Fc")
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("asymmetric_friction", "friction larger in one direction than in the other",
           (ParamSpec("dFv", "N s/m", -1e6, 1e6, EX, "viscous friction asymmetry (half of Fv+ - Fv-)"),
            ParamSpec("dFc", "N", -1e5, 1e5, EX, "dry friction asymmetry (half of Fc+ - Fc-)")),
           (0.0, 0.0), "residual force even in velocity: one direction lags", (30.0, 3.0)),
)}
KERNEL_NAMES = tuple(s.name for s in BASE) + tuple(p.name for e in EFFECTS.values() for p in e.params)
NP = len(KERNEL_NAMES)
I_GTAU, I_KP, I_KV, I_VC, I_M, I_OFF, I_FV, I_FC, I_DFV, I_DFC = range(NP)
STATES = ("x", "v")
NS = 2
#: the filter interface: controller memory (the last two measured positions, started), no side-by-side lanes
N_CTRL = 3
LANES = 0
LANE_WORK = 0


@nb.njit(cache=True)
def deriv(x, v, u, p):
    """Right-hand side (the one definition of this model's physics)."""
    s = math.tanh(v / p[I_VC])
    f = p[I_GTAU] * u - (p[I_FV] + p[I_DFV] * s) * v - (p[I_FC] + p[I_DFC] * s) * s - p[I_OFF]
    return v, f / p[I_M]


@nb.njit(cache=True)
def _rk4(x, v, k, drive, held, u, mode, p, dt, nsub, out):
    h = dt / nsub
    for j in range(nsub):
        f0 = j / nsub
        u1 = u if held else input_at(drive, k, f0, mode)
        u2 = u if held else input_at(drive, k, f0 + 0.5 / nsub, mode)
        u4 = u if held else input_at(drive, k, f0 + 1.0 / nsub, mode)
        a = deriv(x, v, u1, p)
        b = deriv(x + 0.5 * h * a[0], v + 0.5 * h * a[1], u2, p)
        c = deriv(x + 0.5 * h * b[0], v + 0.5 * h * b[1], u2, p)
        d = deriv(x + h * c[0], v + h * c[1], u4, p)
        x += h / 6.0 * (a[0] + 2.0 * b[0] + 2.0 * c[0] + d[0])
        v += h / 6.0 * (a[1] + 2.0 * b[1] + 2.0 * c[1] + d[1])
    out[0] = x
    out[1] = v


@nb.njit(cache=True)
def control(r, xm, p, dt, ctrl):
    """The loop's output at a tick from the demand ``r`` and the measured position ``xm``; ``ctrl``: the last two
    measured positions and whether they are set (the first tick takes the axis as at rest)."""
    if ctrl[2] <= 0.0:
        ctrl[0] = xm
        ctrl[1] = xm
        ctrl[2] = 1.0
    dqf = (xm - ctrl[1]) / (2.0 * dt)
    ctrl[1] = ctrl[0]
    ctrl[0] = xm
    return p[I_KV] * (p[I_KP] * (r - xm) - dqf)


@nb.njit(cache=True)
def advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm_k, ctrl, out):
    """One log interval from sample ``k`` to ``k+1``; returns the command at ``t_k``.  Closed loop: the rig's law
    on the measured position ``xm_k`` at the log's rate, held; open loop: the logged command, held (``mode`` 0)
    or interpolated (the window of the online filter repeats its last sample, so a cubic is taken linear)."""
    if not closed:
        m = 1 if mode == 2 else mode
        _rk4(s[0], s[1], k, drive, m == 0, drive[k], m, p, dt, nsub, out)
        return drive[k]
    u = control(drive[k], xm_k, p, dt, ctrl)
    _rk4(s[0], s[1], k, drive, True, u, mode, p, dt, nsub, out)
    return u


@nb.njit(cache=True)
def lanes_applicable(p):
    """No side-by-side lanes: the filter integrates one sigma point at a time."""
    return False


@nb.njit(cache=True)
def lanes(S, TH, m, p, idx, wnd, mode, dt, nsub, W):
    """No side-by-side lanes (never called: :func:`lanes_applicable` is false)."""
    return None


@nb.njit(cache=True, parallel=True)
def simulate_kernel(S0, P, drive, closed, mode, dt, nsub):
    K = P.shape[0]
    T = drive.shape[0]
    S = np.empty((K, T, NS))
    U = np.empty((K, T))
    for r in nb.prange(K):
        s = S0[r].copy()
        ctrl = np.zeros(N_CTRL)
        for k in range(T):
            S[r, k, 0] = s[0]
            S[r, k, 1] = s[1]
            if k + 1 < T:
                U[r, k] = advance(s, k, drive, closed, 1, mode, P[r], dt, nsub, s[0], ctrl, s)
            else:
                U[r, k] = control(drive[k], s[0], P[r], dt, ctrl) if closed else drive[k]
    return S, U


class Axis(Model):
    """The electromechanical axis; see the module docstring."""

    name = "axis"
    STATES = STATES
    INPUTS = ("x_ref", "u")
    OUTPUTS = ("x",)
    BASE = BASE
    NOMINAL = NOMINAL
    EFFECTS = EFFECTS
    PHENOMENOLOGICAL = PHENOMENOLOGICAL
    CLOSED_LOOP = True
    TRACKABLE = True
    substeps = 2
    INIT = ("x0", "v0")
    SIGNALS = (
        Signal("x_ref", "demand", "m", -5.0, 5.0, "demanded load position", noise=0.0),
        Signal("u", "drive", "V", -100.0, 100.0, "controller output (force command)", noise=0.0),
        Signal("x", "output", "m", -5.0, 5.0, "measured load position (encoder)", noise=2e-7),
    )
    EXPERIMENT = Experiment("multisine", "x_ref", 0.02, 0.1, 5.0)
    #: the online filter: states in mm and cm/s; process noise set on the EMPS estimation record (DATA_EMPS,
    #: tracked open loop from its controller output): (1e-10, 1e-6) left the innovations coloured (AR(1) 0.99,
    #: consistent 15 % of the time), (1e-8, 1e-3) is consistent 96 % of the time with white innovations;
    #: the encoder's noise (a 50 nm count) learnt at 0.12 um
    FILTER = FilterSpec(
        functions="twin.models.axis",
        state_scale=(1e-3, 1e-2),
        measures={"x": 0},
        q_state=(1e-8, 1e-3),
        prior_state=(1.0, 10.0),
        noise={"x": 2e-7},
        excite=(1e-3, 1e-2, 1e-6),
        feedback="x",
    )

    def controller_response(self, ps, q, dt):
        """The loop's response from the position error to the command: ``kv kp`` (its velocity loop acts on the
        measured position alone, not on the error)."""
        return np.full(np.shape(q), ps["kv"] * ps["kp"], dtype=complex)

    def fast_controller(self, ps) -> bool:
        """The model runs the rig's law exactly (at the log's rate)."""
        return True

    def filter_map(self, ps) -> FilterMap:
        exc = np.zeros((3, NS))
        exc[0, 1] = 1.0
        exc[2, 0] = 1.0
        return FilterMap(rest=np.zeros(NS), input_state=-1, input_gain=0.0, demand_gain=ps["kv"] * ps["kp"],
                         ranges={"x": (-5.0, 5.0)}, centres={"x": 0.0}, excitation=exc)

    def initial_state(self, P: np.ndarray, init: Mapping[str, float] | None = None) -> np.ndarray:
        P = np.atleast_2d(P)
        init = dict(init or {})
        x0 = float(init.pop("x0", 0.0))
        v0 = float(init.pop("v0", 0.0))
        if init:
            raise DataError(f"unknown initial-state quantities {sorted(init)}; known: x0 [m], v0 [m/s]")
        S0 = np.zeros((P.shape[0], NS))
        S0[:, 0] = x0
        S0[:, 1] = v0
        return S0

    def initial_from_data(self, signals, dt):
        return {"x0": start_of(signals["x"], dt)[0]} if "x" in signals else {}

    def drive_signal(self, signals, drive="auto"):
        if drive == "auto":
            drive = "x_ref" if "x_ref" in signals else "u"
        if drive not in ("x_ref", "u") or drive not in signals:
            raise DataError(f"the axis is driven by the demand 'x_ref' or the controller output 'u'; the record "
                            f"has {', '.join(signals)}")
        return drive, np.asarray(signals[drive], dtype=np.float64)

    def simulate_batch(self, P, drive_name, drive, dt, x0=None, substeps=None, timing=None,
                       exogenous=None) -> SimResult:
        self.exogenous_table(exogenous, np.shape(drive)[0])  # reads none: refuses any
        P = np.ascontiguousarray(np.atleast_2d(P), dtype=np.float64)
        if P.shape[1] != NP:
            raise DataError(f"axis kernel vectors have {NP} entries, got {P.shape[1]}")
        drive = check_drive(drive_name, drive, dt)
        timing = timing or DEFAULT_TIMING
        if timing.ticks(dt) != 1:
            raise DataError(f"the axis's controller runs at the log's rate; timing {timing.label} is not modelled")
        S0 = self.initial_state(P) if x0 is None else np.ascontiguousarray(np.atleast_2d(x0), dtype=np.float64)
        closed = drive_name == "x_ref"
        S, U = simulate_kernel(S0, P, drive, closed, timing.intersample_code(dt), float(dt),
                               int(substeps or self.substeps))
        t = np.arange(drive.shape[0]) * dt
        inputs = {"u": U, drive_name: drive} if closed else {"u": drive}
        return SimResult(t, {"x": S[:, :, 0]}, S, inputs)


MODEL = Axis()
