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
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numba as nb
import numpy as np

from fpdd.errors import DataError
from twin.models.base import DEFAULT_TIMING, FilterMap, FilterSpec, Model, SimResult, check_drive, start_of
from twin.models.intersample import input_at, slope_at
from twin.params import Effect, ParamSpec, Tracking
from twin.models import intersample as _intersample_src
from twin.models import base as _base_src
from twin.models.jitcache import keep_fresh

# the machine code cached for this module inlines these modules' compiled code and constants
keep_fresh(__file__, _intersample_src.__file__, _base_src.__file__)

TWO_PI = 2.0 * math.pi

# --- parameters --------------------------------------------------------------------
G, PH, PN, EX = "geometric", "physical", "phenomenological", "extension"

BASE = (
    ParamSpec("KP", "V/m", 0.0, 1e5, PH, "PID proportional gain"),
    ParamSpec("KI", "V/(m s)", 0.0, 1e7, PH, "PID integral gain"),
    ParamSpec("KD", "V s/m", 0.0, 1e3, PH, "PID derivative gain"),
    ParamSpec("rho", "kg/m^3", 700.0, 1100.0, PH, "oil density"),
    ParamSpec("V0", "m^3", 1e-6, 1e-1, G, "chamber A volume at mid stroke (both chambers unless V0B is given)",
              "cm^3", 1e6),
    ParamSpec("A", "m^2", 1e-6, 1e-1, G, "piston area AA of chamber A (both sides unless AB is given)", "mm^2",
              1e6),
    ParamSpec("m", "kg", 0.1, 1e5, PH, "moving mass"),
    ParamSpec("Bulk", "Pa", 1e7, 1e11, PH, "oil bulk modulus", "MPa", 1e-6),
    ParamSpec("vref", "m/s", 1e-7, 1.0, PH, "friction smoothing velocity", "mm/s", 1e3),
    ParamSpec("Ke", "A/V", 1e-6, 1e3, PH, "current amplifier gain"),
    ParamSpec("Ksp", "m/A", 1e-7, 1.0, PH, "current-to-spool gain"),
    ParamSpec("b", "m", 1e-5, 1.0, G, "valve port width", "mm", 1e3),
    ParamSpec("pP", "Pa", 1e5, 1e8, PH, "supply pressure", "MPa", 1e-6),
    ParamSpec("pT", "Pa", 0.0, 1e7, PH, "tank pressure", "MPa", 1e-6),
    ParamSpec("dp_lam", "Pa", 1.0, 1e6, PH, "laminar band of the valve ports' square roots", "kPa", 1e-3),
    ParamSpec("dp_lam_leak", "Pa", 1.0, 1e6, PH, "laminar band of the cross-piston leak's square root", "kPa",
              1e-3),
    ParamSpec("Fext", "N", -1e6, 1e6, PH, "constant external force on the rod"),
    ParamSpec("stroke", "m", 1e-3, 10.0, G, "full stroke (+/- half about mid stroke)", "mm", 1e3),
    # the phenomenological parameters drift as the rig wears; their Tracking says how the online twin follows
    # them: healthy band (relative), expected drift (log units per sqrt(s)), physical range (factors of the
    # rig's value) and the signal that makes each observable
    ParamSpec("Ffric", "N", 0.0, 1e5, PN, "maximal dry friction force", typical=50.0,
              tracking=Tracking(band=0.5, drift_rate=0.3, bounds=(1 / 20, 40.0), excited_by="rod_motion")),
    ParamSpec("CdAleak", "m^2", 1e-14, 1e-5, PN, "discharge coefficient times bypass area", "mm^2", 1e6,
              typical=3.2863e-9,
              tracking=Tracking(band=2.0, drift_rate=0.15, bounds=(1 / 100, 1000.0), excited_by="pressure_difference")),
    ParamSpec("Cd", "1", 1e-3, 1.0, PN, "valve discharge coefficient", typical=0.2191,
              tracking=Tracking(band=0.15, drift_rate=0.01, bounds=(1 / 4, 4.0), excited_by="valve_command")),
    ParamSpec("zeta", "1", 1e-3, 10.0, PN, "valve damping ratio", typical=0.3701,
              tracking=Tracking(band=0.3, drift_rate=0.01, bounds=(1 / 5, 5.0), excited_by="valve_command")),
    ParamSpec("wn", "rad/s", TWO_PI * 1.0, TWO_PI * 1000.0, PN, "valve natural frequency", "Hz",
              1.0 / TWO_PI, typical=TWO_PI * 43.0,
              tracking=Tracking(band=0.15, drift_rate=0.01, bounds=(1 / 3, 3.0), excited_by="valve_command")),
    # a single-rod cylinder: chamber B's annulus area and volume (0: the same as chamber A's, symmetric)
    ParamSpec("AB", "m^2", 0.0, 1e-1, G, "piston area AB of chamber B (0: equal to A, a symmetric cylinder)",
              "mm^2", 1e6),
    ParamSpec("V0B", "m^3", 0.0, 1e-1, G, "chamber B volume at mid stroke (0: equal to V0)", "cm^3", 1e6),
    # the controller as an industrial rig runs it (defaults: the paper's PID, no filter, limit at +-10 V)
    ParamSpec("Tf", "s", 0.0, 1.0, PH, "PID derivative filter time constant (0: unfiltered)", "ms", 1e3),
    ParamSpec("D_meas", "1", 0.0, 1.0, PH, "PID derivative on the measurement (1) or on the error (0)"),
    ParamSpec("Kff", "V s/m", 0.0, 1e4, PH, "velocity feed-forward gain on the demand's rate"),
    ParamSpec("u_max", "V", 1e-3, 1e3, PH, "controller output limit (+/-)"),
    ParamSpec("Kdp", "V/Pa", 0.0, 1e-3, PH, "pressure (delta-P) feedback gain on pA - pB AB/A", "V/MPa", 1e6),
    # the oil's temperature: an input (a record's logged T_oil) that scales the bulk modulus and the leakage
    ParamSpec("T_oil", "K", 233.15, 423.15, PH, "oil temperature (a record's logged T_oil; default T_ref)"),
    ParamSpec("T_ref", "K", 233.15, 423.15, PH, "oil temperature at which Bulk, CdAleak and K_lam hold"),
    ParamSpec("kB_T", "1/K", 0.0, 0.05, PH, "bulk modulus fall per kelvin above T_ref (fraction of Bulk)"),
    ParamSpec("b_visc", "1/K", 0.0, 0.2, PH, "leakage rise exp(b_visc (T_oil - T_ref)) (oil viscosity falling)"),
)

NOMINAL = {
    "KP": 400.0, "KI": 0.0, "KD": 0.0, "rho": 960.0, "V0": 480e-6, "A": 1920e-6, "m": 45.0,
    "Bulk": 1.5e9, "vref": 1e-3, "Ke": 1.0, "Ksp": 0.0024, "b": 5e-3, "pP": 28e6, "pT": 0.0,
    "dp_lam": 1e3, "dp_lam_leak": 1e3, "Fext": 0.0, "stroke": 0.25,
    # paper Table 9 (the reference set)
    "Ffric": 50.0, "CdAleak": 3.2863e-9, "Cd": 0.2191, "zeta": 0.3701, "wn": TWO_PI * 43.0,
    "AB": 0.0, "V0B": 0.0, "Tf": 0.0, "D_meas": 0.0, "Kff": 0.0, "u_max": 10.0, "Kdp": 0.0,
    # mineral oil (ISO VG 46) about 40 degC: bulk modulus -0.6 %/K, viscosity exp(-0.03 (T - T_ref))
    "T_oil": 313.15, "T_ref": 313.15, "kB_T": 0.006, "b_visc": 0.03,
}
PHENOMENOLOGICAL = ("Ffric", "CdAleak", "Cd", "zeta", "wn")


def _fx(name, unit, lo, hi, meaning, display_unit=None, scale=1.0):
    return ParamSpec(name, unit, lo, hi, EX, meaning, display_unit, scale)


EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect("viscous_friction", "friction force proportional to rod velocity",
           (_fx("c_visc", "N s/m", 0.0, 1e6, "viscous friction coefficient"),), (0.0,),
           "residual force linear in velocity; phase lead at high speed", (2000.0,)),
    Effect("stribeck_friction", "friction falling from a breakaway level with speed, "
           "F_brk exp(-(|v| / v_str)^delta_str)",
           (_fx("F_brk", "N", 0.0, 1e5, "breakaway force above the dry (Coulomb) level"),
            _fx("v_str", "m/s", 1e-5, 1.0, "Stribeck velocity", "mm/s", 1e3),
            _fx("delta_str", "1", 0.25, 4.0, "Stribeck shape exponent (1: exponential, 2: Gaussian decay)")),
           (0.0, 0.01, 2.0),
           "residual force peaked at low speed after each reversal", (150.0, 0.01, 2.0)),
    Effect("laminar_leakage", "cross-piston flow proportional to the pressure difference",
           (_fx("K_lam", "m^3/(s Pa)", 0.0, 1e-9, "laminar leakage conductance"),), (0.0,),
           "pressure difference decays under load; velocity error grows with pA-pB", (2e-11,)),
    Effect("spool_deadband", "spool overlap: no flow for small openings",
           (_fx("xs_db", "m", 0.0, 1e-3, "spool overlap (dead band half width)", "um", 1e6),), (0.0,),
           "flat spots and lag at small errors and direction reversals", (2e-5,)),
    Effect("valve_null_bias", "spool offset at zero command",
           (_fx("xs_bias", "m", -1e-3, 1e-3, "spool null offset", "um", 1e6),), (0.0,),
           "constant position error / drift; asymmetric pressures at rest", (1e-5,)),
    Effect("supply_pressure_droop", "supply pressure falling with the flow drawn",
           (_fx("R_sup", "Pa s/m^3", 0.0, 1e13, "supply line resistance (pressure drop per flow)"),), (0.0,),
           "velocity saturates at high flow; pressures sag at high speed", (1.5e10,)),
    Effect("specimen_stiffness", "an external spring load on the rod",
           (_fx("k_spec", "N/m", 0.0, 1e9, "specimen stiffness", "kN/mm", 1e-6),), (0.0,),
           "pressure difference proportional to position", (2e6,)),
    Effect("sensor_delay", "displacement measured late",
           (_fx("tau_x", "s", 0.0, 0.05, "displacement sensor delay", "ms", 1e3),), (0.0,),
           "residual proportional to velocity; cross-correlation peak at a positive lag", (1.5e-3,)),
    Effect("entrained_air", "effective bulk modulus falling at low pressure",
           (_fx("eps_air", "1", 0.0, 0.2, "free air volume fraction at atmospheric pressure"),), (0.0,),
           "softer oil column when a chamber pressure is low", (0.08,)),
    Effect("spool_saturation", "spool stroke limit",
           (_fx("xs_max", "m", 1e-5, 1.0, "spool stroke limit", "mm", 1e3),), (1.0,),
           "velocity clipped at large errors", (0.5e-3,)),
    Effect("position_sensor_gain", "displacement transducer gain error (the controller reads it too)",
           (_fx("k_xm", "1", 0.5, 2.0, "measured / true displacement"),), (1.0,),
           "the rod follows x_ref / gain; flow and pressures scale against the measured displacement",
           (1.02,), mimicked_by=("Cd",),
           mimicry="written in the measured displacement, a gain g is the nominal rig with Cd x g, the bulk "
                   "modulus / g and the moving mass / g: the hydraulic resonance (bulk modulus / mass) is "
                   "unchanged, so only g - 1 of the inertial pressure difference tells it from a Cd change; "
                   "hold Cd at a value commissioned on the rig (--set Cd=... --free without Cd) to test it"),
    Effect("pressure_sensor_offset", "chamber pressure transducers read off by a constant",
           (_fx("pA_off", "Pa", -5e6, 5e6, "offset of the pA transducer", "MPa", 1e-6),
            _fx("pB_off", "Pa", -5e6, 5e6, "offset of the pB transducer", "MPa", 1e-6)), (0.0, 0.0),
           "constant pressure residual; force balance pA - pB against friction is off at rest", (3e5, 0.0)),
    Effect("supply_line_loss", "turbulent loss in the supply line: pressure drop with the square of the flow",
           (_fx("K_sup2", "Pa s^2/m^6", 0.0, 1e17, "supply line turbulent loss coefficient (drop per flow^2)"),),
           (0.0,), "supply pressure sags with the square of the flow: little at low speed, a hard limit on "
           "the speed at high flow", (8e13,)),
    Effect("pressure_sensor_lag", "chamber pressure transducers respond with a first-order lag",
           (_fx("tau_p", "s", 0.0, 0.1, "pressure transducer time constant", "ms", 1e3),), (0.0,),
           "pressure residual proportional to the pressure's rate of change; displacement unaffected",
           (1e-2,)),
)}

KERNEL_NAMES = tuple(s.name for s in BASE) + tuple(p.name for e in EFFECTS.values() for p in e.params)
NP = len(KERNEL_NAMES)
(I_KP, I_KI, I_KD, I_RHO, I_V0, I_A, I_M, I_BULK, I_VREF, I_KE, I_KSP, I_B, I_PP, I_PT, I_DPL, I_DPLL,
 I_FEXT, I_STROKE, I_FFRIC, I_CDALEAK, I_CD, I_ZETA, I_WN, I_AB, I_V0B, I_TF, I_DMEAS, I_KFF, I_UMAX, I_KDP,
 I_TOIL, I_TREF, I_KBT, I_BVISC,
 I_CVISC, I_FBRK, I_VSTR, I_DSTR, I_KLAM, I_XSDB, I_XSBIAS,
 I_RSUP, I_KSPEC, I_TAUX, I_EPS, I_XSMAX, I_KXM, I_PAOFF, I_PBOFF, I_KSUP2, I_TAUP) = range(NP)
assert NP == 51 and KERNEL_NAMES[I_PBOFF] == "pB_off" and KERNEL_NAMES[I_DPLL] == "dp_lam_leak"
assert KERNEL_NAMES[I_TOIL] == "T_oil" and KERNEL_NAMES[I_BVISC] == "b_visc"
assert KERNEL_NAMES[I_KSUP2] == "K_sup2" and KERNEL_NAMES[I_TAUP] == "tau_p" and KERNEL_NAMES[I_KDP] == "Kdp"

#: the largest mean friction a working actuator shows, as a fraction of its stall force pP A (a physical bound:
#: servo-actuator seals are a percent or two of it); a record's mean pressure force beyond it is a wrong geometry
PLAUSIBLE_FRICTION = 0.1

STATES = ("xs", "vs", "pA", "pB", "x", "v")
NS = 6
P_ATM = 1.0e5
KAPPA_AIR = 1.4


# --- the compiled core ----------------------------------------------------------------
@nb.njit(cache=True, inline="always")
def _sqrt_reg(dp, dpl):
    """sgn(dp) sqrt(|dp|) regularised in a laminar band dpl."""
    return dp / math.sqrt(math.sqrt(dp * dp + dpl * dpl))


@nb.njit(cache=True, inline="always")
def _bulk(p, B, eps):
    if eps <= 0.0:
        return B
    pe = max(p, P_ATM)
    air = eps * (P_ATM / pe) ** (1.0 / KAPPA_AIR)
    return 1.0 / (1.0 / B + air / (KAPPA_AIR * pe))


@nb.njit(cache=True, inline="always")
def fast_tanh(x):
    """tanh through one exp (libm's tanh costs about 100 ns between 1 and 19); equal to 1e-15."""
    a = abs(x)
    if a > 19.1:
        return math.copysign(1.0, x)
    if a < 0.02:  # series: 1 - 2/(e^2a + 1) loses digits near zero
        a2 = a * a
        return x * (1.0 - a2 * (1.0 / 3.0 - a2 * (2.0 / 15.0 - a2 * (17.0 / 315.0))))
    t = 1.0 - 2.0 / (math.exp(2.0 * a) + 1.0)
    return math.copysign(t, x)


@nb.njit(cache=True)
def deriv(xs, vs, pA, pB, x, v, u, p):
    """Right-hand side of one state (scalars in, tuple of six derivatives out).

    The one definition of the rig's physics: the filter's side-by-side form (:mod:`twin.models.msp25_lanes`)
    computes, with every effect neutral, the same operations in the same order (``tests/test_models.py`` checks
    it bit for bit), so the reciprocals ``1 / vref`` and ``1 / m`` are multiplied, not divided by."""
    rho = p[I_RHO]
    A = p[I_A]
    V0 = p[I_V0]
    dpl = p[I_DPL]
    pT = p[I_PT]
    wn = p[I_WN]
    # servo-valve, second order (eq. 4)
    dxs = vs
    dvs = wn * wn * (p[I_KE] * p[I_KSP] * u - xs) - 2.0 * p[I_ZETA] * wn * vs
    # spool opening: null bias, stroke limit, overlap
    o = xs + p[I_XSBIAS]
    xm = p[I_XSMAX]
    if o > xm:
        o = xm
    elif o < -xm:
        o = -xm
    db = p[I_XSDB]
    if db > 0.0:
        if o > db:
            o = o - db
        elif o < -db:
            o = o + db
        else:
            o = 0.0
    g = p[I_CD] * p[I_B] * math.sqrt(2.0 / rho)
    pP = p[I_PP]
    qPA = 0.0
    qBT = 0.0
    qAT = 0.0
    qPB = 0.0
    if o >= 0.0:
        qPA = g * o * _sqrt_reg(pP - pA, dpl)
        qBT = g * o * _sqrt_reg(pB - pT, dpl)
    else:
        qAT = -g * o * _sqrt_reg(pA - pT, dpl)
        qPB = -g * o * _sqrt_reg(pP - pB, dpl)
    R = p[I_RSUP]
    K2 = p[I_KSUP2]
    if R > 0.0 or K2 > 0.0:  # supply droop (R q) and turbulent line loss (K2 q^2): one fixed-point pass
        qs = qPA + qPB
        if qs > 0.0:
            pPe = max(pP - R * qs - K2 * qs * qs, pT)
            if o >= 0.0:
                qPA = g * o * _sqrt_reg(pPe - pA, dpl)
            else:
                qPB = -g * o * _sqrt_reg(pPe - pB, dpl)
    dpAB = pA - pB
    # the oil's temperature: bulk modulus and leakage at T_oil (factors exactly 1 at T_ref)
    dT = p[I_TOIL] - p[I_TREF]
    lf = math.exp(p[I_BVISC] * dT) if dT != 0.0 else 1.0
    qAB = p[I_CDALEAK] * lf * math.sqrt(2.0 / rho) * _sqrt_reg(dpAB, p[I_DPLL]) + p[I_KLAM] * lf * dpAB
    qA = qPA - qAT - qAB
    qB = qPB - qBT + qAB
    AB = p[I_AB] if p[I_AB] > 0.0 else A
    V0B = p[I_V0B] if p[I_V0B] > 0.0 else V0
    VA = max(V0 + A * x, 1e-3 * V0)
    VB = max(V0B - AB * x, 1e-3 * V0B)
    eps = p[I_EPS]
    Bt = p[I_BULK] * (1.0 - p[I_KBT] * dT)
    dpA = _bulk(pA, Bt, eps) * (qA - A * v) / VA
    dpB = _bulk(pB, Bt, eps) * (qB + AB * v) / VB
    # rod (eq. 11-12) with the friction extensions
    ff = p[I_FFRIC]
    fb = p[I_FBRK]
    if fb > 0.0:  # Stribeck: exp(-(|v| / v_str)^delta), Gaussian (delta 2) by default
        r = abs(v) / p[I_VSTR]
        dl = p[I_DSTR]
        ff = ff + fb * math.exp(-(r * r if dl == 2.0 else r ** dl))
    Ffr = ff * fast_tanh(v * (1.0 / p[I_VREF])) + p[I_CVISC] * v
    # pA A - pB AB, written so that a symmetric cylinder (AB = A) gives the same numbers as (pA - pB) A
    dv = (dpAB * A - pB * (AB - A) - Ffr - p[I_FEXT] - p[I_KSPEC] * x) * (1.0 / p[I_M])
    return dxs, dvs, dpA, dpB, v, dv


@nb.njit(cache=True, inline="always")
def rk4_combine(a0, a1, a2, a3, a4, a5, k1, k2, k3, k4, h):
    """The RK4 update of the six states from the four stage derivatives (the one copy every RK4 step of the
    rig uses: :func:`step`, :func:`step_varying`, the filter's lean step)."""
    c = h / 6.0
    return (a0 + c * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0]),
            a1 + c * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1]),
            a2 + c * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2]),
            a3 + c * (k1[3] + 2.0 * k2[3] + 2.0 * k3[3] + k4[3]),
            a4 + c * (k1[4] + 2.0 * k2[4] + 2.0 * k3[4] + k4[4]),
            a5 + c * (k1[5] + 2.0 * k2[5] + 2.0 * k3[5] + k4[5]))


@nb.njit(cache=True, inline="always")
def store6(out, a0, a1, a2, a3, a4, a5):
    out[0] = a0
    out[1] = a1
    out[2] = a2
    out[3] = a3
    out[4] = a4
    out[5] = a5


@nb.njit(cache=True)
def step(s, u, p, dt, nsub, out):
    """Advance state ``s[6]`` by ``dt`` with ``nsub`` RK4 substeps, input ``u`` held; write ``out``."""
    h = dt / nsub
    a0, a1, a2, a3, a4, a5 = s[0], s[1], s[2], s[3], s[4], s[5]
    for _ in range(nsub):
        k1 = deriv(a0, a1, a2, a3, a4, a5, u, p)
        k2 = deriv(a0 + 0.5 * h * k1[0], a1 + 0.5 * h * k1[1], a2 + 0.5 * h * k1[2],
                   a3 + 0.5 * h * k1[3], a4 + 0.5 * h * k1[4], a5 + 0.5 * h * k1[5], u, p)
        k3 = deriv(a0 + 0.5 * h * k2[0], a1 + 0.5 * h * k2[1], a2 + 0.5 * h * k2[2],
                   a3 + 0.5 * h * k2[3], a4 + 0.5 * h * k2[4], a5 + 0.5 * h * k2[5], u, p)
        k4 = deriv(a0 + h * k3[0], a1 + h * k3[1], a2 + h * k3[2],
                   a3 + h * k3[3], a4 + h * k3[4], a5 + h * k3[5], u, p)
        a0, a1, a2, a3, a4, a5 = rk4_combine(a0, a1, a2, a3, a4, a5, k1, k2, k3, k4, h)
    store6(out, a0, a1, a2, a3, a4, a5)


@nb.njit(cache=True)
def rhs_batch(S, U, P):
    """Derivatives of a batch: ``S [K, 6]``, ``U [K]``, ``P [K, NP]`` -> ``[K, 6]``."""
    K = S.shape[0]
    out = np.empty((K, NS))
    for k in range(K):
        d = deriv(S[k, 0], S[k, 1], S[k, 2], S[k, 3], S[k, 4], S[k, 5], U[k], P[k])
        for j in range(NS):
            out[k, j] = d[j]
    return out


@nb.njit(cache=True)
def step_batch(S, U, P, dt, nsub):
    """One sample step of a batch: ``S [K, 6]``, ``U [K]``, ``P [K, NP]`` -> ``[K, 6]``."""
    K = S.shape[0]
    out = np.empty((K, NS))
    for k in range(K):
        step(S[k], U[k], P[k], dt, nsub, out[k])
    return out


@nb.njit(cache=True, inline="always")
def _delayed(hist, k, tau, dt):
    """Linear interpolation of the sampled history ``hist[:k+1]`` at ``t_k - tau``."""
    if tau <= 0.0:
        return hist[k]
    d = tau / dt
    j = int(d)
    f = d - j
    i0 = k - j
    if i0 <= 0:
        return hist[0]
    return (1.0 - f) * hist[i0] + f * hist[i0 - 1]


#: controller memory entries: integral of the error, previous error, started flag, derivative filter state (the
#: filtered derivative of a digital controller, the filtered signal of a continuous one), previous measurement
N_CTRL = 5


@nb.njit(cache=True, inline="always")
def _shape_output(u, rdot, pa, pb, p):
    """The PID output ``u`` with velocity feed-forward of the demand's rate ``rdot``, pressure feedback of the
    measured ``pa``, ``pb`` (the load pressure pA - pB AB/A) and the output limit."""
    if p[I_KFF] != 0.0:
        u = u + p[I_KFF] * rdot
    if p[I_KDP] != 0.0:
        ratio = p[I_AB] / p[I_A] if p[I_AB] > 0.0 else 1.0
        u = u - p[I_KDP] * (pa - pb * ratio)
    um = p[I_UMAX]
    if u > um:
        u = um
    elif u < -um:
        u = -um
    return u


@nb.njit(cache=True, inline="always")
def pid_tick(r, rdot, xm, pa, pb, h, p, ctrl):
    """One tick of the digital controller (period ``h``): output ``u`` [V] from the demand ``r``, its rate
    ``rdot``, the measured displacement ``xm`` and chamber pressures ``pa``, ``pb``; ``ctrl`` (:data:`N_CTRL`)
    updated.  The derivative (of the error, or of minus the measurement) is a backward difference through the
    first-order filter ``Tf``: ``D_k = (Tf D_{k-1} + s_k - s_{k-1}) / (Tf + h)`` (``Tf = 0``: the raw difference)."""
    e = r - xm
    ctrl[0] += e * h
    if p[I_DMEAS] > 0.0:
        ds = ctrl[4] - xm
    else:
        ds = e - ctrl[1]
    if ctrl[2] > 0.0:
        tf = p[I_TF]
        de = (tf * ctrl[3] + ds) / (tf + h)
    else:
        de = 0.0
    ctrl[1] = e
    ctrl[2] = 1.0
    ctrl[3] = de
    ctrl[4] = xm
    u = p[I_KP] * e + p[I_KI] * ctrl[0] + p[I_KD] * de
    return _shape_output(u, rdot, pa, pb, p)


@nb.njit(cache=True, inline="always")
def _d_signal(a4, a5, k, f, drive, mode, p, dt):
    """A continuous controller's measured displacement, error, demand rate, the signal its derivative acts on
    and that signal's rate."""
    g = p[I_KXM]
    xm = g * (a4 - p[I_TAUX] * a5)  # x(t - tau) to first order
    e = input_at(drive, k, f, mode) - xm
    rdot = slope_at(drive, k, f, mode, dt)
    if p[I_DMEAS] > 0.0:
        return xm, e, rdot, -xm, -g * a5
    return xm, e, rdot, e, rdot - g * a5


@nb.njit(cache=True, inline="always")
def _u_stage(a2, a3, a4, a5, k, f, drive, closed, mode, p, integ, dflt, dt):
    """Controller output at a stage of a continuous loop (closed) or an interpolated logged input (open).
    ``dflt``: the derivative filter's state (the filtered signal) when ``Tf > 0``."""
    if not closed:
        return input_at(drive, k, f, mode)
    xm, e, rdot, sig, dsig = _d_signal(a4, a5, k, f, drive, mode, p, dt)
    tf = p[I_TF]
    d = dsig if tf <= 0.0 else (sig - dflt) / tf
    u = p[I_KP] * e + p[I_KI] * integ + p[I_KD] * d
    return _shape_output(u, rdot, a2 + p[I_PAOFF], a3 + p[I_PBOFF], p)


@nb.njit(cache=True)
def step_varying(s, k, drive, closed, mode, p, dt, nsub, ctrl, out):
    """Advance ``s`` from sample ``k`` to ``k+1`` with the input varying inside the interval.

    ``closed``: a continuous controller reads the state at every stage (its memory ``ctrl``, integral and
    derivative filter, updated per substep); else the logged input ``drive`` is interpolated by ``mode``.
    """
    h = dt / nsub
    fh = 1.0 / nsub
    a0, a1, a2, a3, a4, a5 = s[0], s[1], s[2], s[3], s[4], s[5]
    integ = ctrl[0]
    dflt = ctrl[3]
    tf = p[I_TF]
    for j in range(nsub):
        f0 = j * fh
        u1 = _u_stage(a2, a3, a4, a5, k, f0, drive, closed, mode, p, integ, dflt, dt)
        k1 = deriv(a0, a1, a2, a3, a4, a5, u1, p)
        b2 = a2 + 0.5 * h * k1[2]
        b3 = a3 + 0.5 * h * k1[3]
        b4 = a4 + 0.5 * h * k1[4]
        b5 = a5 + 0.5 * h * k1[5]
        u2 = _u_stage(b2, b3, b4, b5, k, f0 + 0.5 * fh, drive, closed, mode, p, integ, dflt, dt)
        k2 = deriv(a0 + 0.5 * h * k1[0], a1 + 0.5 * h * k1[1], b2, b3, b4, b5, u2, p)
        c2 = a2 + 0.5 * h * k2[2]
        c3 = a3 + 0.5 * h * k2[3]
        c4 = a4 + 0.5 * h * k2[4]
        c5 = a5 + 0.5 * h * k2[5]
        u3 = _u_stage(c2, c3, c4, c5, k, f0 + 0.5 * fh, drive, closed, mode, p, integ, dflt, dt)
        k3 = deriv(a0 + 0.5 * h * k2[0], a1 + 0.5 * h * k2[1], c2, c3, c4, c5, u3, p)
        d2 = a2 + h * k3[2]
        d3 = a3 + h * k3[3]
        d4 = a4 + h * k3[4]
        d5 = a5 + h * k3[5]
        u4 = _u_stage(d2, d3, d4, d5, k, f0 + fh, drive, closed, mode, p, integ, dflt, dt)
        k4 = deriv(a0 + h * k3[0], a1 + h * k3[1], d2, d3, d4, d5, u4, p)
        if closed:
            _, e0, _, s0, _ = _d_signal(a4, a5, k, f0, drive, mode, p, dt)
            _, e1, _, s1, _ = _d_signal(d4, d5, k, f0 + fh, drive, mode, p, dt)
            integ += 0.5 * h * (e0 + e1)
            if tf > 0.0:  # the filter over the substep, its input linear between the ends
                dflt += (1.0 - math.exp(-h / tf)) * (0.5 * (s0 + s1) - dflt)
        a0, a1, a2, a3, a4, a5 = rk4_combine(a0, a1, a2, a3, a4, a5, k1, k2, k3, k4, h)
    store6(out, a0, a1, a2, a3, a4, a5)
    ctrl[0] = integ
    ctrl[3] = dflt


@nb.njit(cache=True)
def advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm_k, ctrl, out):
    """One log interval from sample ``k`` to ``k+1`` under any loop timing; returns ``u`` at ``t_k``.

    ``ticks``: controller ticks per sample (1: digital at the log's rate, N: a
    digital controller N times faster, 0: continuous).  ``mode``: intersample of
    ``drive`` (0 zoh, 1 foh, 2 cubic).  ``xm_k``: the measured displacement at
    ``t_k``.  ``ctrl``: controller memory (:data:`N_CTRL` entries: integral,
    previous error, started, derivative filter, previous measurement), updated in
    place.  ``out`` may be ``s``.  A digital controller's feed-forward reads the
    demand's rate as the cubic's slope (at a sample: the central difference).
    """
    if not closed:
        u = drive[k]
        if mode == 0:
            step(s, u, p, dt, nsub, out)
        else:
            step_varying(s, k, drive, False, mode, p, dt, nsub, ctrl, out)
        return u
    if ticks == 0:
        if ctrl[2] <= 0.0:  # the derivative filter starts at its input
            ctrl[3] = _d_signal(s[4], s[5], k, 0.0, drive, mode, p, dt)[3]
            ctrl[2] = 1.0
        e = drive[k] - xm_k
        rdot = slope_at(drive, k, 0.0, mode, dt)
        tf = p[I_TF]
        sig = -xm_k if p[I_DMEAS] > 0.0 else e
        d = (-p[I_KXM] * s[5] if p[I_DMEAS] > 0.0 else rdot - p[I_KXM] * s[5]) if tf <= 0.0 else \
            (sig - ctrl[3]) / tf
        u = p[I_KP] * e + p[I_KI] * ctrl[0] + p[I_KD] * d
        u = _shape_output(u, rdot, s[2] + p[I_PAOFF], s[3] + p[I_PBOFF], p)
        step_varying(s, k, drive, True, mode, p, dt, nsub, ctrl, out)
        return u
    h = dt / ticks
    nsub_t = max(1, (nsub + ticks - 1) // ticks)
    u0 = 0.0
    for i in range(ticks):
        if i == 0:
            xm = xm_k
            pa = s[2] + p[I_PAOFF]
            pb = s[3] + p[I_PBOFF]
        else:
            xm = p[I_KXM] * (out[4] - p[I_TAUX] * out[5])
            pa = out[2] + p[I_PAOFF]
            pb = out[3] + p[I_PBOFF]
        rdot = slope_at(drive, k, i / ticks, 2, dt) if p[I_KFF] != 0.0 else 0.0
        u = pid_tick(input_at(drive, k, i / ticks, mode), rdot, xm, pa, pb, h, p, ctrl)
        if i == 0:
            u0 = u
            step(s, u, p, h, nsub_t, out)
        else:
            step(out, u, p, h, nsub_t, out)
    return u0


@nb.njit(cache=True)
def _simulate_one(s0, p, drive, closed, ticks, mode, dt, nsub, S, U, XM, exo_idx, EXO):
    T = drive.shape[0]
    s = s0.copy()
    if exo_idx.shape[0] > 0:  # logged signals set parameters sample by sample: this record's own vector
        p = p.copy()
    xhist = np.empty(T)
    ctrl = np.zeros(N_CTRL)
    tau = p[I_TAUX]
    g = p[I_KXM]
    for k in range(T):
        for j in range(NS):
            S[k, j] = s[j]
        xhist[k] = s[4]
        xm = g * _delayed(xhist, k, tau, dt)
        XM[k] = xm
        for j in range(exo_idx.shape[0]):  # held over the interval from sample k (NaN: the last value holds)
            if math.isfinite(EXO[k, j]):
                p[exo_idx[j]] = EXO[k, j]
        if k + 1 < T:
            U[k] = advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm, ctrl, s)
        elif closed:  # the last sample: the controller's output at t_k, no step
            c = ctrl.copy()
            if ticks != 1:
                c[2] = 0.0
            rdot = slope_at(drive, k, 0.0, 2, dt) if p[I_KFF] != 0.0 else 0.0
            U[k] = pid_tick(drive[k], rdot, xm, s[2] + p[I_PAOFF], s[3] + p[I_PBOFF], dt, p, c)
        else:
            U[k] = drive[k]


@nb.njit(cache=True, parallel=True)
def simulate_kernel(S0, P, drive, closed, ticks, mode, dt, nsub, exo_idx, EXO):
    """Simulate ``K`` parameter vectors in parallel.

    Returns states ``[K, T, 6]``, controller output ``[K, T]`` and measured
    displacement ``[K, T]`` (the rod position seen through the sensor).
    """
    K = P.shape[0]
    T = drive.shape[0]
    S = np.empty((K, T, NS))
    U = np.empty((K, T))
    XM = np.empty((K, T))
    for k in nb.prange(K):
        _simulate_one(S0[k], P[k], drive, closed, ticks, mode, dt, nsub, S[k], U[k], XM[k], exo_idx, EXO)
    return S, U, XM


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
    substeps = 3
    #: the online filter: spool in mm and 0.1 m/s, pressures in MPa, rod in mm and 0.1 m/s; x, pA, pB measured
    FILTER = FilterSpec(
        functions="twin.models.msp25_lanes",
        state_scale=(1e-3, 0.1, 1e6, 1e6, 1e-3, 0.1),
        measures={"x": 4, "pA": 2, "pB": 3},
        q_state=(1e-10, 1e-10, 1e-6, 1e-6, 1e-10, 1e-7),
        prior_state=(0.01, 0.01, 0.1, 0.1, 0.01, 0.01),
        noise={"x": 2e-6, "pA": 2e4, "pB": 2e4},
        excite=(2e-3, 0.5, 2e4),  # rod speed [m/s], command rate [V/s], piston pressure difference [Pa]
        feedback="x",
        exogenous={"T_oil": "T_oil"},
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

    def controller_response(self, ps, q, dt):
        """The digital PID's response ``KP + KI dt / q + KD q / dt``."""
        return ps["KP"] + ps["KI"] * dt / q + ps["KD"] * q / dt

    def tracking_bounds(self, ps, name: str) -> tuple[float, float]:
        """The tracking range, and physics: friction cannot exceed the actuator's stall force pP A."""
        lo, hi = super().tracking_bounds(ps, name)
        if name == "Ffric":
            hi = min(hi, ps["pP"] * ps["A"])
        return lo, hi

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


@nb.njit(cache=True)
def sensor_lag(p: np.ndarray, tau: np.ndarray, dt: float) -> np.ndarray:
    """A first-order transducer ``tau y' = p - y`` on each row of ``p [K, T]`` (its own ``tau[k]``),
    settled at the first sample; exact for ``p`` linear between samples:
    ``y[n+1] = a y[n] + p[n+1] - a p[n] - c (p[n+1] - p[n])``, ``a = exp(-dt / tau)``, ``c = tau (1 - a) / dt``."""
    K, T = p.shape
    out = np.empty((K, T))
    for k in range(K):
        t = tau[k]
        out[k, 0] = p[k, 0]
        if t <= 0.0:
            for n in range(1, T):
                out[k, n] = p[k, n]
            continue
        a = math.exp(-dt / t)
        c = t * (1.0 - a) / dt
        for n in range(T - 1):
            out[k, n + 1] = a * out[k, n] + p[k, n + 1] - a * p[k, n] - c * (p[k, n + 1] - p[k, n])
    return out


MODEL = MSP25()
