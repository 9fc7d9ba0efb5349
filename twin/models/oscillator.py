"""The paper's basic demonstration: a damped oscillator ``m x'' + d x' + k x = u``, ``y = x``.

States ``x`` [m], ``v`` [m/s]; input force ``u`` [N], smooth between samples
(a C1 cubic: no controller holds it) or, by the rig's
:class:`~twin.models.base.Timing`, held (zoh) or linear between them; output ``y = x`` [m].  Effects of the catalogue:
``coulomb_friction`` (tanh-smoothed dry friction), ``cubic_stiffness``
(hardening spring ``k3 x^3``), ``input_delay`` (the force acts late),
``input_offset`` (the logged input reads ``u0`` more than the force that acts)
and ``output_offset`` (the output reads ``y0`` more than the displacement).

The units are the record's: a circuit that obeys the same equation (the
Silverbox, volts in and out) is this model with ``u`` and ``y`` in volts.  So
the catalogue's typical sizes are not constants but follow the record and the
fitted nominal model (:meth:`Oscillator.effect_typicals`), and a fit starts
from the data's own second-order response (:meth:`Oscillator.starts_from_data`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numba as nb
import numpy as np

from fpdd.errors import DataError, ParameterError
from fpdd.units import text_to_si
from twin.models.base import (DEFAULT_TIMING, INTERSAMPLE_CODE, Experiment, FilterMap, FilterSpec, Model, Signal,
                              SimResult, check_drive, start_of)
from twin.models.intersample import input_at, input_between
from twin.params import Effect, ParamSpec, Tracking
from twin.models import intersample as _intersample_src
from twin.models import base as _base_src
from twin.models.jitcache import keep_fresh

# the machine code cached for this module inlines these modules' compiled code and constants
keep_fresh(__file__, _intersample_src.__file__, _base_src.__file__)

@dataclasses.dataclass(frozen=True)
class SpringSpec(ParamSpec):
    """The spring's spec: a fit moves k in log coordinates over [lo, hi] (scale-free: a circuit's k in volts is
    far from 3947.8 N/m), and k may also be held at exactly 0, a free mass with damping (a positioning axis:
    ``--set k=0``)."""

    def check(self, value: float | str) -> float:
        try:
            return super().check(value)
        except ParameterError:
            try:
                v = text_to_si(self.name, value, self.unit) if isinstance(value, str) else float(value)
            except (ParameterError, TypeError, ValueError):
                v = float("nan")
            if v == 0.0:
                return 0.0
            raise


BASE = (
    ParamSpec("m", "kg", 1e-9, 1e6, "physical", "mass", typical=1.0),
    ParamSpec("d", "N s/m", 0.0, 1e6, "phenomenological", "viscous damping", typical=0.1,
              tracking=Tracking(band=0.5, drift_rate=0.01, bounds=(1 / 20, 20.0), excited_by="rod_motion")),
    SpringSpec("k", "N/m", 1e-9, 1e9, "phenomenological", "stiffness (or exactly 0: a free mass)", typical=3947.8,
              tracking=Tracking(band=0.3, drift_rate=0.002, bounds=(1 / 4, 4.0), excited_by="rod_motion")),
)
NOMINAL = {"m": 1.0, "d": 0.1, "k": 3947.8}
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("coulomb_friction", "dry friction opposing the velocity",
           (ParamSpec("Fc", "N", 0.0, 1e6, "extension", "Coulomb friction force",
                      tracking=Tracking(band=1.0, drift_rate=0.05, bounds=(1 / 50, 50.0), excited_by="rod_motion")),
            ParamSpec("vc", "m/s", 1e-7, 10.0, "extension", "friction smoothing velocity", "mm/s", 1e3)),
           (0.0, 1e-3), "residual force of constant size, sign of velocity; amplitude-dependent damping",
           (0.5, 1e-3)),
    Effect("cubic_stiffness", "hardening spring k3 x^3",
           (ParamSpec("k3", "N/m^3", -1e12, 1e12, "extension", "cubic stiffness"),), (0.0,),
           "resonance shifts with amplitude; residual odd in displacement", (2e5,)),
    Effect("input_delay", "the force acts late",
           (ParamSpec("tau_u", "s", 0.0, 0.1, "extension", "input delay", "ms", 1e3),), (0.0,),
           "phase error growing with frequency; input cross-correlation peak at a lag", (2e-3,)),
    Effect("input_offset", "the logged input reads more than the force that acts (a measurement offset)",
           (ParamSpec("u0", "N", -1e9, 1e9, "extension", "input offset"),), (0.0,),
           "constant output error u0/k; shifts the operating point of a nonlinear spring", (1.0,)),
    Effect("output_offset", "the output reads more than the displacement (a sensor offset)",
           (ParamSpec("y0", "m", -1e3, 1e3, "extension", "output offset"),), (0.0,),
           "constant output error, independent of the motion", (1e-4,)),
)}
#: how a logged force behaves between samples when the timing does not say (no controller holds it)
DEFAULT_INTERSAMPLE = "cubic"
#: an effect's typical size as a fraction of the size the record sets (:meth:`Oscillator.effect_typicals`)
TYPICAL_FRACTION = 0.3
KERNEL_NAMES = tuple(s.name for s in BASE) + tuple(p.name for e in EFFECTS.values() for p in e.params)
NP = len(KERNEL_NAMES)
I_M, I_D, I_K, I_FC, I_VC, I_K3, I_TAU, I_U0, I_Y0 = range(NP)
STATES = ("x", "v")
#: the filter interface (twin.models.base.FilterSpec.functions): no controller memory; the sigma points integrated
#: side by side (:func:`lanes`): all of a filter tracking every trackable parameter, in whole vectors of 8
N_CTRL = 1
N_TRACKABLE = sum(1 for s in BASE + tuple(q for e in EFFECTS.values() for q in e.params) if s.tracking is not None)
LANES = 8 * ((2 * (len(STATES) + N_TRACKABLE) + 1 + 7) // 8)
#: a lane's entries of the work vector: the states x, v and the parameters m, d, k, k3, u0, Fc, vc
N_W = 9
LANE_WORK = N_W * LANES


@nb.njit(cache=True, inline="always")
def _force(x, v, u, d, k, k3, u0):
    """The force on the mass without its dry friction."""
    return u - u0 - d * v - k * x - k3 * x * x * x


@nb.njit(cache=True, inline="always")
def _acc(x, v, u, m, d, k, k3, u0, fc, vc, friction):
    """The acceleration; ``friction`` False leaves the dry friction out (a literal: no branch is left in a loop the
    compiler vectorises)."""
    f = _force(x, v, u, d, k, k3, u0)
    if friction and fc > 0.0:
        f -= fc * math.tanh(v / vc)
    return f / m


@nb.njit(cache=True)
def _accel(x, v, u, m, d, k, k3, u0, fc, vc):
    """The acceleration from the parameters as numbers (the filter's step reads them once per interval)."""
    return _acc(x, v, u, m, d, k, k3, u0, fc, vc, True)


@nb.njit(cache=True)
def deriv(x, v, u, p):
    return v, _accel(x, v, u, p[I_M], p[I_D], p[I_K], p[I_K3], p[I_U0], p[I_FC], p[I_VC])


@nb.njit(cache=True)
def _simulate_one(s0, p, u, mode, dt, nsub, S):
    T = u.shape[0]
    x = s0[0]
    v = s0[1]
    h = dt / nsub
    fh = 1.0 / nsub
    for k in range(T):
        S[k, 0] = x
        S[k, 1] = v
        if k + 1 == T:
            break
        for j in range(nsub):
            u0 = input_at(u, k, j * fh, mode)
            um = input_at(u, k, (j + 0.5) * fh, mode)
            u1 = input_at(u, k, (j + 1.0) * fh, mode)
            a = deriv(x, v, u0, p)
            b = deriv(x + 0.5 * h * a[0], v + 0.5 * h * a[1], um, p)
            c = deriv(x + 0.5 * h * b[0], v + 0.5 * h * b[1], um, p)
            d = deriv(x + h * c[0], v + h * c[1], u1, p)
            x += h / 6.0 * (a[0] + 2.0 * b[0] + 2.0 * c[0] + d[0])
            v += h / 6.0 * (a[1] + 2.0 * b[1] + 2.0 * c[1] + d[1])


@nb.njit(cache=True, parallel=True)
def simulate_kernel(S0, P, U, mode, dt, nsub):
    """``K`` parameter vectors, each with its own (delayed) input ``U [K, T]``, intersample ``mode``."""
    K = P.shape[0]
    T = U.shape[1]
    S = np.empty((K, T, 2))
    for k in nb.prange(K):
        _simulate_one(S0[k], P[k], U[k], mode, dt, nsub, S[k])
    return S


@nb.njit(cache=True)
def advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm_k, ctrl, out):
    """One log interval of the filter from sample ``k`` to ``k+1``: the logged force interpolated by ``mode``
    (no controller: ``closed``, ``ticks``, ``xm_k`` and ``ctrl`` are not read); returns the force at ``t_k``.

    Online the sample after the interval is not known yet (the filter's window repeats the last one), so a cubic
    becomes the linear interpolation: a cubic's end slope from a repeated sample lags the force, and a lag of a
    few microseconds reads as damping on a lightly damped oscillator (the reference record of seed 1001: d 11 %
    high with the lagging cubic, 0.4 % low with the linear one)."""
    if mode == 2:
        mode = 1
    n = drive.shape[0]
    x, v = _interval(s[0], s[1], p[I_M], p[I_D], p[I_K], p[I_K3], p[I_U0], p[I_FC], p[I_VC],
                     drive[k - 1 if k > 0 else 0], drive[k], drive[k + 1 if k + 1 < n else n - 1],
                     drive[k + 2 if k + 2 < n else n - 1], mode, dt, nsub)
    out[0] = x
    out[1] = v
    return drive[k]


@nb.njit(cache=True, inline="always")
def _substep_inputs(a0, a1, a2, a3, j, fh, mode):
    """The drive at substep ``j``'s start, middle and end (``fh``: a substep as a fraction of the interval)."""
    return (input_between(a0, a1, a2, a3, j * fh, mode), input_between(a0, a1, a2, a3, (j + 0.5) * fh, mode),
            input_between(a0, a1, a2, a3, (j + 1.0) * fh, mode))


@nb.njit(cache=True, inline="always")
def _substep(x, v, ua, um, ub, h, m, dm, km, k3, u0, fc, vc, friction):
    """One RK4 substep of length ``h`` with the drive ``ua, um, ub`` at its start, middle and end."""
    a_v = _acc(x, v, ua, m, dm, km, k3, u0, fc, vc, friction)
    b_x = v + 0.5 * h * a_v
    b_v = _acc(x + 0.5 * h * v, b_x, um, m, dm, km, k3, u0, fc, vc, friction)
    c_x = v + 0.5 * h * b_v
    c_v = _acc(x + 0.5 * h * b_x, c_x, um, m, dm, km, k3, u0, fc, vc, friction)
    d_x = v + h * c_v
    d_v = _acc(x + h * c_x, d_x, ub, m, dm, km, k3, u0, fc, vc, friction)
    return x + h / 6.0 * (v + 2.0 * b_x + 2.0 * c_x + d_x), v + h / 6.0 * (a_v + 2.0 * b_v + 2.0 * c_v + d_v)


@nb.njit(cache=True, inline="always")
def _interval(x, v, m, dm, km, k3, u0, fc, vc, a0, a1, a2, a3, mode, dt, nsub):
    """RK4 over one log interval from the state ``x, v`` with the parameters and the drive around the interval as
    numbers (an array handed to a compiled function is reference-counted at each call: 28 atomic operations a sigma
    point); the one definition :func:`advance` and :func:`lanes` share."""
    h = dt / nsub
    fh = 1.0 / nsub
    for j in range(nsub):
        ua, um, ub = _substep_inputs(a0, a1, a2, a3, j, fh, mode)
        x, v = _substep(x, v, ua, um, ub, h, m, dm, km, k3, u0, fc, vc, True)
    return x, v


@nb.njit(cache=True)
def lanes_applicable(p):
    """The lanes are exact for every kernel vector (they run :func:`advance`'s own interval)."""
    return True


@nb.njit(cache=True)
def lanes(S, TH, m, p, idx, wnd, mode, dt, nsub, W):
    """One log interval of the states ``S[ln]`` (SI) with the parameters ``idx`` at ``TH[ln]``, ``ln < m <=
    LANES``, in place: :func:`advance` for each, in one call (the filter's prediction then makes one compiled call
    a sample instead of one per sigma point).  ``wnd``: the logged force at samples k-1, k (index 1: this sample),
    k+1, k+2; ``p`` is overwritten at ``idx``; ``W``: work (:data:`LANE_WORK` entries), row ``r`` (one quantity:
    x, v, m, d, k, k3, u0, Fc, vc) of lane ``ln`` at ``r * LANES + ln``; unused lanes repeat lane 0.

    Without dry friction in any lane the lanes run side by side, one RK4 stage over all of them in a loop the
    compiler vectorises (:func:`_lanes_rk4`, the same operations as :func:`advance` in the same order: each lane's
    numbers are its point's, bit for bit); with it, one lane after the other (``tanh`` is not vectorised)."""
    if mode == 2:
        mode = 1
    p_count = idx.shape[0]
    friction = False
    for ln in range(LANES):  # each lane's parameters read before W is written (W might be p for all the compiler knows)
        r = ln if ln < m else 0
        for j in range(p_count):
            p[idx[j]] = TH[r, j]
        x0, v0, mm, dm, km, k3, u0, fc, vc = S[r, 0], S[r, 1], p[I_M], p[I_D], p[I_K], p[I_K3], p[I_U0], p[I_FC], \
            p[I_VC]
        friction = friction or fc > 0.0
        W[ln] = x0
        W[LANES + ln] = v0
        W[2 * LANES + ln] = mm
        W[3 * LANES + ln] = dm
        W[4 * LANES + ln] = km
        W[5 * LANES + ln] = k3
        W[6 * LANES + ln] = u0
        W[7 * LANES + ln] = fc
        W[8 * LANES + ln] = vc
    a0, a1, a2, a3 = wnd[0], wnd[1], wnd[2], wnd[3]
    if friction:
        for ln in range(m):
            x, v = _interval(W[ln], W[LANES + ln], W[2 * LANES + ln], W[3 * LANES + ln], W[4 * LANES + ln],
                             W[5 * LANES + ln], W[6 * LANES + ln], W[7 * LANES + ln], W[8 * LANES + ln], a0, a1, a2,
                             a3, mode, dt, nsub)
            S[ln, 0] = x
            S[ln, 1] = v
        return
    _lanes_rk4(W, a0, a1, a2, a3, mode, dt, nsub)
    for ln in range(m):
        S[ln, 0] = W[ln]
        S[ln, 1] = W[LANES + ln]


@nb.njit(cache=True, error_model="numpy")
def _lanes_rk4(W, a0, a1, a2, a3, mode, dt, nsub):
    """:func:`_interval` without dry friction over the :data:`LANES` lanes of ``W`` at once, in place (numpy's
    error model: a division is the processor's, with no test for a zero divisor that would keep the loop scalar;
    a mass is never 0, its bound is 1e-9 kg)."""
    h = dt / nsub
    fh = 1.0 / nsub
    for j in range(nsub):
        ua, um, ub = _substep_inputs(a0, a1, a2, a3, j, fh, mode)
        for ln in range(LANES):
            W[ln], W[LANES + ln] = _substep(W[ln], W[LANES + ln], ua, um, ub, h, W[2 * LANES + ln],
                                            W[3 * LANES + ln], W[4 * LANES + ln], W[5 * LANES + ln],
                                            W[6 * LANES + ln], 0.0, 1.0, False)


def delay_signal(u: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """``u(t - tau)`` on the same grid by linear interpolation, holding the first value before t=0."""
    if tau <= 0.0:
        return u
    t = np.arange(u.shape[0]) * dt
    return np.interp(t - tau, t, u)


class Oscillator(Model):
    """The damped oscillator; see the module docstring."""

    name = "oscillator"
    STATES = STATES
    INPUTS = ("u",)
    OUTPUTS = ("y",)
    BASE = BASE
    NOMINAL = NOMINAL
    EFFECTS = EFFECTS
    PHENOMENOLOGICAL = ("d", "k")
    substeps = 2
    NOISE_FROM_DATA = True
    TRACKABLE = True
    SIGNALS = (
        Signal("u", "drive", "N", -1e7, 1e7, "input force (or any quantity: volts of a circuit)", noise=0.0,
               accepts=("*",)),
        Signal("y", "output", "m", -10.0, 10.0, "output displacement (or any quantity: volts of a circuit)",
               noise=1e-6, accepts=("*",)),
    )
    EXPERIMENT = Experiment("multisine", "u", 100.0, 1.0, 30.0)
    #: the online filter: states in mm and cm/s, the displacement measured (the output offset ``y0`` is not
    #: tracked); a velocity of 0.1 mm/s (rms over the excitation time) makes d, k and Fc observable
    FILTER = FilterSpec(
        functions="twin.models.oscillator",
        state_scale=(1e-3, 1e-2),
        measures={"y": 0},
        q_state=(1e-10, 1e-8),
        prior_state=(10.0, 10.0),
        noise={"y": 1e-6},
        excite=(1e-4, 1e-3, 1e-6),
    )

    def filter_map(self, ps) -> FilterMap:
        exc = np.zeros((3, 2))
        exc[0, 1] = 1.0  # the motion: the velocity
        exc[2, 0] = 1.0  # the load: the spring's displacement
        return FilterMap(rest=np.zeros(2), input_state=-1, input_gain=0.0, demand_gain=0.0,
                         ranges={"y": (-10.0, 10.0)}, centres={"y": 0.0}, excitation=exc)
    INIT = ("x0", "v0")
    #: a record that does not start at rest: these are estimated, from the values its first samples show
    INIT_IF_MOVING = ("x0", "v0")

    def initial_state(self, P: np.ndarray, init: Mapping[str, float] | None = None) -> np.ndarray:
        P = np.atleast_2d(P)
        init = dict(init or {})
        x0 = float(init.pop("x0", 0.0))
        v0 = float(init.pop("v0", 0.0))
        if init:
            raise DataError(f"unknown initial-state quantities {sorted(init)}; known: x0 [m], v0 [m/s]")
        S0 = np.zeros((P.shape[0], 2))
        # a measured start is read through the output offset (the first predicted sample is the measured one)
        S0[:, 0] = x0 - P[:, I_Y0] if x0 != 0.0 else 0.0
        S0[:, 1] = v0
        return S0

    def drive_signal(self, signals, drive="auto"):
        if drive not in ("auto", "u"):
            raise DataError(f"the oscillator is driven by the force 'u', not {drive!r}")
        if "u" not in signals:
            raise DataError(f"the oscillator needs the input force 'u'; the record has {', '.join(signals)}")
        return "u", np.asarray(signals["u"], dtype=np.float64)

    def initial_from_data(self, signals, dt):
        """Displacement and velocity at the first sample where the data show them (five standard errors);
        a lightly damped oscillator rings for a long time after a wrong start, so noise alone is not taken
        for one."""
        if "y" not in signals:
            return {}
        x0, v0, se_x, se_v = start_of(signals["y"], dt)
        scale = float(np.std(signals["y"]))  # below 1 % of the motion (per second for v0): at rest
        out = {}
        if abs(x0) > max(5.0 * se_x, 1e-2 * scale) or abs(v0) > max(5.0 * se_v, 1e-2 * scale):
            out["x0"] = x0
            out["v0"] = v0
        return out

    def intersample_code(self, timing, dt):
        """No controller holds the input: unless the timing says otherwise, a logged force is smooth between
        its samples (a signal generator's, a shaker's), the C1 cubic (:data:`DEFAULT_INTERSAMPLE`)."""
        t = timing or DEFAULT_TIMING
        return INTERSAMPLE_CODE[t.intersample or DEFAULT_INTERSAMPLE]

    def effect_typicals(self, ps, signals, predicted, dt):
        """Each effect's typical size from the record and the fitted nominal model ``ps`` (its prediction
        ``predicted``, a dict of whole-record signals): the size that changes the force balance by
        :data:`TYPICAL_FRACTION` of what the record exercises.  A cubic spring stiffens by that fraction at
        the measured rms displacement (``k3 = 0.3 k / x_rms^2``); a dry friction or an input offset is that
        fraction of the rms input force, its smoothing velocity a hundredth of the predicted rms velocity; an
        output offset that fraction of the rms displacement; a delay two sample periods.  The screen probes
        0.3, 1 and 3 times these sizes and a named effect lies within 10 times them.  The same record in other units, or
        rescaled, has effects of the same relative size (the diagnosis is unit-free)."""
        y = np.asarray(signals["y"], dtype=np.float64)  # the record's motion (the prediction may be far off)
        x_rms = float(np.std(y)) or 1.0
        v = np.gradient(np.asarray(predicted["y"], dtype=np.float64), dt)
        v_rms = float(np.sqrt(np.mean(v * v))) or 1.0
        u = np.asarray(signals["u"], dtype=np.float64)
        u_rms = float(np.sqrt(np.mean((u - u.mean()) ** 2))) or 1.0
        f = TYPICAL_FRACTION
        return {"coulomb_friction": (f * u_rms, 1e-2 * v_rms), "cubic_stiffness": (f * ps["k"] / x_rms ** 2,),
                "input_delay": (2.0 * dt,), "input_offset": (f * u_rms,), "output_offset": (f * x_rms,)}

    def starts_from_data(self, signals, dt):
        """Starts of m, d, k from the data's own second-order response: an ARX(2, 2) least-squares fit of
        ``y`` on ``u`` (means removed), its poles mapped to continuous time (``s = log(z) / dt``) and its
        static gain read as ``1 / k``: ``k = 1 / gain``, ``m = k / wn^2``, ``d = 2 zeta wn m``.  Empty when
        the data show no stable, lightly damped pair of poles with a positive gain (then the multi-start's
        log-uniform cover of the physical ranges is all there is)."""
        if "u" not in signals or "y" not in signals:
            return []
        u = np.asarray(signals["u"], dtype=np.float64)
        y = np.asarray(signals["y"], dtype=np.float64)
        if u.size < 20:
            return []
        u = u - u.mean()
        y = y - y.mean()
        X = np.stack([y[1:-1], y[:-2], u[1:-1], u[:-2]], axis=1)
        try:
            a1, a2, b1, b2 = np.linalg.lstsq(X, y[2:], rcond=None)[0]
        except np.linalg.LinAlgError:
            return []
        z = np.roots([1.0, -a1, -a2]).astype(complex)
        if not (np.all(np.abs(z) < 1.0) and np.all(np.abs(z) > 0.0)):
            return []
        s = np.log(z) / dt
        wn = float(np.sqrt(np.real(s[0] * s[1])))
        zeta = float(-np.real(s[0] + s[1]) / (2.0 * wn)) if wn > 0 else -1.0
        gain = float((b1 + b2) / (1.0 - a1 - a2))
        if not (np.isfinite(wn) and wn > 0 and zeta > 0 and gain > 0 and np.isfinite(gain)):
            return []
        k = 1.0 / gain
        m = k / wn ** 2
        out = {"m": m, "d": 2.0 * zeta * wn * m, "k": k}
        specs = {sp.name: sp for sp in self.BASE}
        if not all(specs[n].lo <= v <= specs[n].hi for n, v in out.items()):
            return []
        return [out]

    def simulate_batch(self, P, drive_name, drive, dt, x0=None, substeps=None, timing=None,
                       exogenous=None) -> SimResult:
        self.exogenous_table(exogenous, np.shape(drive)[0])  # reads none: refuses any
        P = np.ascontiguousarray(np.atleast_2d(P), dtype=np.float64)
        if P.shape[1] != NP:
            raise DataError(f"oscillator kernel vectors have {NP} entries, got {P.shape[1]}")
        drive = check_drive(drive_name, drive, dt)
        taus = P[:, I_TAU]
        if np.all(taus == taus[0]):
            U = np.broadcast_to(delay_signal(drive, taus[0], dt), (P.shape[0], drive.shape[0]))
            U = np.ascontiguousarray(U)
        else:
            U = np.stack([delay_signal(drive, t, dt) for t in taus])
        S0 = self.initial_state(P) if x0 is None else np.ascontiguousarray(np.atleast_2d(x0), dtype=np.float64)
        mode = self.intersample_code(timing, dt)
        S = simulate_kernel(S0, P, U, mode, float(dt), int(substeps or self.substeps))
        t = np.arange(drive.shape[0]) * dt
        return SimResult(t, {"y": S[:, :, 0] + P[:, I_Y0, None]}, S, {"u": drive})

    def state_space(self, ps) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C, D) of the linear nominal model (eq. 2-3 of the paper)."""
        m, d, k = ps["m"], ps["d"], ps["k"]
        return (np.array([[0.0, 1.0], [-k / m, -d / m]]), np.array([[0.0], [1.0 / m]]),
                np.array([[1.0, 0.0]]), np.array([[0.0]]))

    def transfer_function(self, ps) -> tuple[np.ndarray, np.ndarray]:
        """Numerator and denominator of Y(s)/U(s) = 1 / (m s^2 + d s + k)."""
        return np.array([1.0]), np.array([ps["m"], ps["d"], ps["k"]])


MODEL = Oscillator()
