"""The Hydropuls MSP25 servo-hydraulic test rig (paper section 2, ``shared/model-spec.md``).

States (SI): ``xs`` spool position [m], ``vs`` spool velocity [m/s], ``pA``, ``pB``
chamber pressures [Pa], ``x`` rod position [m], ``v`` rod velocity [m/s].

Two ways to drive it:

* closed loop from the demanded displacement ``x_ref`` (the paper's setup): the
  IST8000 is a digital controller, so the PID runs at the sample instants on the
  measured displacement and its output ``u`` is held between samples (zero-order
  hold, as a DAC does).  The logged ``u`` of a closed-loop simulation therefore
  reproduces the same trajectory when fed back open loop.
* open loop from the logged controller output ``u`` [V] (what a filter uses).

The controller is an industrial PID: derivative on the error or on the
measurement (``D_meas``), through a first-order filter ``Tf``, velocity
feed-forward ``Kff`` of the demand's rate, pressure feedback ``Kdp`` on the
load pressure, output limit ``u_max`` (:func:`pid_tick`); the defaults are
the paper's loop.  The cylinder has the piston side's area ``A`` and the rod
side's ``AB`` (``0``: the same, symmetric), with chamber volumes ``V0`` and
``V0B`` at mid stroke; a record whose pressures the stated geometry cannot
hold is refused (:meth:`MSP25.check_record`).

Orifice square roots follow the paper's turbulent law wherever the rig operates:
``sqrt(|dp|) sgn(dp)`` is replaced by ``dp / (dp^2 + dp_lam^2)^(1/4)`` only so that
the slope stays finite at zero drop.  The band is 1 kPa by default, separately
for the valve ports (``dp_lam``) and the cross-piston leak (``dp_lam_leak``):
the leak of an unloaded rig works at drops below about 0.1 MPa, where a 1 bar
band would turn the turbulent leak into a mostly laminar one and bias
``CdAleak`` by about +54 %.  Truly laminar flow is the effect
``laminar_leakage``.

The loop's timing is a property of the rig (:class:`twin.models.base.Timing`):
a digital controller at the log's rate (default; output held between
samples), a digital controller ``N`` times faster than the log (``N`` ticks per
sample, each reading the measured displacement), or a continuous (analog) one;
logged inputs between samples are held (``zoh``), linear (``foh``) or a C1
piecewise cubic (``cubic``).

The catalogue of effects (switched on by name, neutral when off) is compiled
into the one right-hand side; see :data:`EFFECTS`.

The model in four modules, one concept each: the parameters and the catalogue of effects
(:mod:`twin.models.msp25_params`), the right-hand side (:mod:`twin.models.msp25_rhs`), the controller, loop timing
and simulation (:mod:`twin.models.msp25_loop`), and here the model object the fit, the diagnosis and the
filter use; their names are importable from here too (``from twin.models import msp25 as M; M.deriv, M.I_WN``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from fpdd.errors import DataError
from twin.models import msp25_loop, msp25_params, msp25_rhs
from twin.models import hydraulic_signals
from twin.models.base import (DEFAULT_TIMING, FilterMap, FilterSpec, Model, SimResult, check_drive,
                              start_of)
from twin.models.effect_scale import msp25_typicals
from twin.models.msp25_loop import (
    N_CTRL, N_LINE, advance, pid_tick, sensor_lag, simulate_kernel, step_varying,
)
from twin.models.msp25_params import (
    BASE, EFFECTS, I_A, I_AB, I_B, I_BULK, I_BVISC, I_CD, I_CDALEAK, I_CVISC, I_DMEAS, I_DPL, I_DPLL, I_DSTR, I_EPS,
    I_FBRK, I_FEXT, I_FFRIC, I_KBT, I_KD, I_KDP, I_KE, I_KFF, I_KI, I_KLAM, I_KP, I_KSP, I_KSPEC, I_KSUP2, I_KXM,
    I_CSUP, I_LSUP, I_RHOSE,
    I_M, I_PAOFF, I_PBOFF, I_PP, I_PT, I_RHO, I_RSUP, I_STROKE, I_TAUP, I_TAUX, I_TF, I_TOIL, I_TREF, I_UMAX, I_V0,
    I_V0B, I_VREF, I_VSTR, I_WN, I_XSBIAS, I_XSDB, I_XSMAX, I_ZETA, KAPPA_AIR, KERNEL_NAMES, NOMINAL, NP, NS,
    PHENOMENOLOGICAL, PLAUSIBLE_FRICTION, P_ATM, STATES, TWO_PI,
)
from twin.models.msp25_rhs import (
    deriv, deriv_line, fast_tanh, line_advance, rhs_batch, rk4_combine, step, step_batch, step_line, store6,
)

#: the source files of the compiled code (a module inlining it keeps its numba cache in step with all of them)
SOURCES = (msp25_params.__file__, msp25_rhs.__file__, msp25_loop.__file__)


# --- the model object ---------------------------------------------------------------------
class MSP25(Model):
    """The MSP25 rig; see the module docstring."""

    name = "msp25"
    STATES = STATES
    INPUTS = ("x_ref", "u")
    OUTPUTS = ("x", "pA", "pB")
    BASE = BASE
    NOMINAL = NOMINAL
    EFFECTS = EFFECTS
    PHENOMENOLOGICAL = PHENOMENOLOGICAL
    CLOSED_LOOP = True
    TRACKABLE = True
    SIGNALS = hydraulic_signals.SIGNALS
    EXPERIMENT = hydraulic_signals.EXPERIMENT
    substeps = 3
    #: the online filter: spool in mm and 0.1 m/s, pressures in MPa, rod in mm and 0.1 m/s; x, pA, pB measured
    FILTER = FilterSpec(
        functions="twin.models.msp25_lanes",
        state_scale=(1e-3, 0.1, 1e6, 1e6, 1e-3, 0.1),
        measures={"x": 4, "pA": 2, "pB": 3},
        q_state=(1e-10, 1e-10, 3e-7, 3e-7, 1e-10, 1e-7),
        prior_state=(0.01, 0.01, 0.1, 0.1, 0.01, 0.01),
        noise={"x": 2e-6, "pA": 2e4, "pB": 2e4},
        excite=(2e-3, 0.5, 2e4),  # rod speed [m/s], command rate [V/s], piston pressure difference [Pa]
        feedback="x",
        exogenous={"T_oil": "T_oil"},
        second_order=(1, "zeta", "wn"),  # the spool: its speed vs, its damping ratio and natural frequency
    )
    #: initial-state quantities: rod position and velocity, pressure difference or each chamber, spool
    INIT = ("x0", "dp0", "v0", "pA0", "pB0", "u0")
    #: the ones a fit may estimate per record
    INIT_FREE = ("x0", "dp0", "v0")

    def filter_map(self, ps) -> FilterMap:
        """Re-initialised at mid pressure with the spool where the drive holds it; the stroke and the supply
        bound the readings; rod motion and the piston's pressure difference excite the parameters."""
        pmid = 0.5 * (ps["pP"] + ps["pT"])
        rest = np.zeros(NS)
        rest[2] = rest[3] = pmid
        exc = np.zeros((3, NS))
        exc[0, 5] = 1.0             # rod_motion: |v|
        exc[2, 2], exc[2, 3] = 1.0, -1.0  # pressure_difference: |pA - pB|
        return FilterMap(rest=rest, input_state=0, input_gain=ps["Ke"] * ps["Ksp"], demand_gain=ps["KP"],
                         ranges={"x": (-ps["stroke"], ps["stroke"]), "pA": (ps["pT"] - 2e6, ps["pP"] + 5e6),
                                 "pB": (ps["pT"] - 2e6, ps["pP"] + 5e6)},
                         centres={"x": 0.0, "pA": pmid, "pB": pmid}, excitation=exc)

    def fast_controller(self, ps) -> bool:
        """The paper's P controller (no integral, no derivative) is the law the model runs between the log's
        samples."""
        return ps["KI"] == 0 and ps["KD"] == 0

    def controller_response(self, ps, q, dt):
        """The digital PID's response ``KP + KI dt / q + KD q / dt``."""
        return ps["KP"] + ps["KI"] * dt / q + ps["KD"] * q / dt

    def effect_typicals(self, ps, signals, predicted, dt):
        """Each effect's typical size from the record and the fitted rig (:mod:`twin.models.effect_scale`)."""
        return msp25_typicals(EFFECTS, NOMINAL, ps, signals, predicted, dt)

    def tracking_bounds(self, ps, name: str) -> tuple[float, float]:
        """The tracking range, and physics: friction cannot exceed the actuator's stall force pP A."""
        lo, hi = super().tracking_bounds(ps, name)
        if name == "Ffric":
            hi = min(hi, ps["pP"] * ps["A"])
        return lo, hi

    def untracked(self, ps):
        """The supply line's dynamics are states outside the filter's (its memory carries the controller's only)."""
        if "C_sup" in ps and ps["C_sup"] > 0.0:
            return ("the online filter does not carry the supply line's states (effect supply_dynamics, C_sup > 0); "
                    "track the rig with its static equivalent, supply_pressure_droop with R_sup = R_hose")
        return None

    def check_record(self, ps, signals, name="record"):
        """The force the record's chamber pressures put on the rod must be one the rig can hold.

        Over a record the rod's momentum comes back to about where it started, so the time average of the
        pressure force ``pA AA - pB AB`` minus the stated external force (and spring) is the average friction,
        which a working actuator keeps far below its stall force ``pP AA``.  An average beyond
        :data:`PLAUSIBLE_FRICTION` of it means the stated geometry is not the rig's: a single-rod cylinder
        fitted as a symmetric one (its rest pressures sit in the inverse area ratio), or an unstated load.
        """
        if "pA" not in signals or "pB" not in signals:
            return
        pa_s = np.asarray(signals["pA"], dtype=np.float64)
        pb_s = np.asarray(signals["pB"], dtype=np.float64)
        ok = np.isfinite(pa_s) & np.isfinite(pb_s)
        if ok.sum() < 2:
            return
        given = ps.as_dict()
        pa = float(np.mean(pa_s[ok])) - given.get("pA_off", 0.0)
        pb = float(np.mean(pb_s[ok])) - given.get("pB_off", 0.0)
        A = ps["A"]
        AB = ps["AB"] if ps["AB"] > 0.0 else A
        load = ps["Fext"]
        if "k_spec" in ps and "x" in signals:
            x = np.asarray(signals["x"], dtype=np.float64)
            load += ps["k_spec"] * float(np.mean(x[np.isfinite(x)])) if np.isfinite(x).any() else 0.0
        F = pa * A - pb * AB - load
        stall = ps["pP"] * max(A, AB)
        if abs(F) <= PLAUSIBLE_FRICTION * stall:
            return
        ratio = (pa * A - load) / (pb * A) if pb > 0.0 else float("nan")
        raise DataError(
            f"{name}: mean pressures pA {pa * 1e-6:.2f} MPa, pB {pb * 1e-6:.2f} MPa are impossible for the stated "
            f"cylinder (A {A * 1e6:.0f} mm^2, AB {AB * 1e6:.0f} mm^2, Fext {ps['Fext']:.0f} N): they leave "
            f"{F * 1e-3:.1f} kN on the rod, {100 * abs(F) / stall:.0f} % of the stall force (friction holds at most "
            f"{100 * PLAUSIBLE_FRICTION:.0f} %); a single-rod cylinder with AB/A = {ratio:.2f} or an external "
            f"force of {F:.0f} N would balance them (--set AB=... V0B=... or --set Fext=...)")

    def initial_state(self, P: np.ndarray, init: Mapping[str, float] | None = None) -> np.ndarray:
        """Rod at ``x0`` moving at ``v0``, chambers at ``pA0``/``pB0``, spool where the command ``u0`` holds it.

        ``x0``, ``pA0`` and ``pB0`` are measured values: a row of ``P`` with a position sensor gain or pressure
        sensor offsets starts at the true state they imply (measured / gain, measured - offset).

        With neither ``pA0`` nor ``pB0`` the chambers sit about the mid pressure
        ``(pP+pT)/2`` with the difference ``dp0``; given pressures are shifted by
        ``dp0`` split evenly (so ``dp0`` stays a correction a fit can estimate).
        """
        P = np.atleast_2d(P)
        init = dict(init or {})
        x0 = float(init.pop("x0", 0.0))
        dp0 = float(init.pop("dp0", 0.0))
        v0 = float(init.pop("v0", 0.0))
        u0 = float(init.pop("u0", 0.0))
        pA0 = init.pop("pA0", None)
        pB0 = init.pop("pB0", None)
        if init:
            raise DataError(f"unknown initial-state quantities {sorted(init)}; known: x0 [m], dp0 [Pa], v0 [m/s], "
                            "pA0 [Pa], pB0 [Pa], u0 [V]")
        S0 = np.zeros((P.shape[0], NS))
        pm = 0.5 * (P[:, I_PP] + P[:, I_PT])
        S0[:, 0] = P[:, I_KE] * P[:, I_KSP] * u0
        # measured starts are read through the transducers' own errors (an offset, a gain) where P has them
        # two areas: at rest the valve's null shares pP + pT between the chambers and the areas share the load
        two = (P[:, I_AB] > 0.0) & (P[:, I_AB] != P[:, I_A])
        AB = np.where(P[:, I_AB] > 0.0, P[:, I_AB], P[:, I_A])
        pAe = np.where(two, (P[:, I_FEXT] + 2.0 * pm * AB) / (P[:, I_A] + AB), pm)
        pBe = np.where(two, 2.0 * pm - pAe, pm)
        S0[:, 2] = (pAe if pA0 is None else float(pA0) - P[:, I_PAOFF]) + 0.5 * dp0
        S0[:, 3] = (pBe if pB0 is None else float(pB0) - P[:, I_PBOFF]) - 0.5 * dp0
        S0[:, 4] = x0 / P[:, I_KXM]
        S0[:, 5] = v0
        return S0

    def initial_from_data(self, signals: Mapping[str, np.ndarray], dt: float) -> dict[str, float]:
        """The measured state at the first sample: rod position and both chamber pressures.

        Each is read through a cubic over the first 20 ms (noise averages out).
        Rod speed and spool are left at rest: the position loop forgets them
        within a few tens of milliseconds, while a wrong pressure (a loaded rig
        started at equal pressures) bends every parameter of a fit.
        """
        out: dict[str, float] = {}
        for name, key in (("x", "x0"), ("pA", "pA0"), ("pB", "pB0")):
            if name in signals:
                out[key] = start_of(signals[name], dt)[0]
        return out

    def drive_signal(self, signals, drive="auto"):
        if drive == "auto":
            drive = "x_ref" if "x_ref" in signals else "u"
        if drive not in ("x_ref", "u"):
            raise DataError(f"msp25 is driven by 'x_ref' (closed loop) or 'u' (open loop), not {drive!r}")
        if drive not in signals:
            raise DataError(f"msp25 driven by {drive!r} but the record has only {', '.join(signals)}")
        return drive, np.asarray(signals[drive], dtype=np.float64)

    def simulate_batch(self, P, drive_name, drive, dt, x0=None, substeps=None, timing=None,
                       exogenous=None) -> SimResult:
        P = np.ascontiguousarray(np.atleast_2d(P), dtype=np.float64)
        if P.shape[1] != NP:
            raise DataError(f"msp25 kernel vectors have {NP} entries, got {P.shape[1]}")
        drive = check_drive(drive_name, drive, dt)
        exo_idx, EXO = self.exogenous_table(exogenous, drive.shape[0])
        timing = timing or DEFAULT_TIMING
        S0 = self.initial_state(P) if x0 is None else np.ascontiguousarray(np.atleast_2d(x0), dtype=np.float64)
        closed = drive_name == "x_ref"
        S, U, XM = simulate_kernel(S0, P, drive, closed, timing.ticks(dt), timing.intersample_code(dt), float(dt),
                                   int(substeps or self.substeps), exo_idx, EXO)
        t = np.arange(drive.shape[0]) * dt
        pA, pB = S[:, :, 2], S[:, :, 3]
        if np.any(P[:, I_TAUP] > 0.0):  # the transducers' first-order lag, on what they measure
            pA, pB = sensor_lag(pA, P[:, I_TAUP], dt), sensor_lag(pB, P[:, I_TAUP], dt)
        outputs = {"x": XM, "pA": pA + P[:, I_PAOFF, None], "pB": pB + P[:, I_PBOFF, None]}
        inputs = {"u": U, drive_name: drive} if closed else {"u": drive}
        return SimResult(t, outputs, S, inputs)


MODEL = MSP25()


__all__ = [
    "MODEL", "MSP25", "SOURCES", "N_CTRL", "N_LINE", "advance", "pid_tick", "sensor_lag", "simulate_kernel",
    "step_varying", "BASE", "EFFECTS", "I_A", "I_AB", "I_B", "I_BULK", "I_BVISC",
    "I_CD", "I_CDALEAK", "I_CSUP", "I_LSUP", "I_RHOSE", "I_CVISC", "I_DMEAS", "I_DPL", "I_DPLL", "I_DSTR", "I_EPS",
    "I_FBRK", "I_FEXT", "I_FFRIC", "I_KBT", "I_KD", "I_KDP", "I_KE", "I_KFF",
    "I_KI", "I_KLAM", "I_KP", "I_KSP", "I_KSPEC", "I_KSUP2", "I_KXM", "I_M",
    "I_PAOFF", "I_PBOFF", "I_PP", "I_PT", "I_RHO", "I_RSUP", "I_STROKE", "I_TAUP",
    "I_TAUX", "I_TF", "I_TOIL", "I_TREF", "I_UMAX", "I_V0", "I_V0B", "I_VREF",
    "I_VSTR", "I_WN", "I_XSBIAS", "I_XSDB", "I_XSMAX", "I_ZETA", "KAPPA_AIR", "KERNEL_NAMES",
    "NOMINAL", "NP", "NS", "PHENOMENOLOGICAL", "PLAUSIBLE_FRICTION", "P_ATM", "STATES", "TWO_PI",
    "deriv", "deriv_line", "fast_tanh", "line_advance", "step_line", "rhs_batch", "rk4_combine", "step", "step_batch", "store6",
]
