"""The MSP25's parameters: the base set with units, bounds and tracking (:data:`BASE`), the paper's values
(:data:`NOMINAL`), the catalogue of effects switched on by name (:data:`EFFECTS`), and the layout of the kernel
vector the compiled code reads (:data:`KERNEL_NAMES`, the indices ``I_*``).

Plain data: :mod:`twin.models.msp25_rhs` (the right-hand side), :mod:`twin.models.msp25_loop` (controller, loop
timing, simulation) and the model object :mod:`twin.models.msp25` read it.
"""

from __future__ import annotations

import math

from twin.params import Effect, ParamSpec, Tracking


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
    Effect("supply_dynamics", "the supply line's own dynamics: the pump holds pP behind a hose (inertance, "
           "resistance) that fills an accumulator at the valve, from which the valve draws (supply pressure not logged)",
           (_fx("C_sup", "m^3/Pa", 0.0, 1e-9, "compliance at the valve's supply port (accumulator gas, hose oil)",
                "cm^3/MPa", 1e12),
            _fx("L_sup", "Pa s^2/m^3", 1e5, 1e12, "supply hose inertance (oil density x length / bore area)",
                "MPa s^2/L", 1e-9),
            _fx("R_hose", "Pa s/m^3", 0.0, 1e13, "supply hose resistance (pressure drop per flow)", "MPa s/L", 1e-9)),
           (0.0, 2.5e8, 0.0),
           "supply pressure sags with the flow drawn and rings at the line's frequency 1 / (2 pi sqrt(L_sup C_sup)): "
           "speed lost and a ringing in the pressures after each change of flow", (2e-12, 2.5e8, 4.5e9),
           generalises=(("supply_pressure_droop", (("R_sup", "R_hose"),)),)),
)}

KERNEL_NAMES = tuple(s.name for s in BASE) + tuple(p.name for e in EFFECTS.values() for p in e.params)
NP = len(KERNEL_NAMES)
(I_KP, I_KI, I_KD, I_RHO, I_V0, I_A, I_M, I_BULK, I_VREF, I_KE, I_KSP, I_B, I_PP, I_PT, I_DPL, I_DPLL,
 I_FEXT, I_STROKE, I_FFRIC, I_CDALEAK, I_CD, I_ZETA, I_WN, I_AB, I_V0B, I_TF, I_DMEAS, I_KFF, I_UMAX, I_KDP,
 I_TOIL, I_TREF, I_KBT, I_BVISC,
 I_CVISC, I_FBRK, I_VSTR, I_DSTR, I_KLAM, I_XSDB, I_XSBIAS,
 I_RSUP, I_KSPEC, I_TAUX, I_EPS, I_XSMAX, I_KXM, I_PAOFF, I_PBOFF, I_KSUP2, I_TAUP, I_CSUP, I_LSUP, I_RHOSE) = range(NP)
assert NP == 54 and KERNEL_NAMES[I_PBOFF] == "pB_off" and KERNEL_NAMES[I_DPLL] == "dp_lam_leak"
assert KERNEL_NAMES[I_TOIL] == "T_oil" and KERNEL_NAMES[I_BVISC] == "b_visc"
assert KERNEL_NAMES[I_CSUP] == "C_sup" and KERNEL_NAMES[I_RHOSE] == "R_hose"
assert KERNEL_NAMES[I_KSUP2] == "K_sup2" and KERNEL_NAMES[I_TAUP] == "tau_p" and KERNEL_NAMES[I_KDP] == "Kdp"

#: the largest mean friction a working actuator shows, as a fraction of its stall force pP A (a physical bound:
#: servo-actuator seals are a percent or two of it); a record's mean pressure force beyond it is a wrong geometry
PLAUSIBLE_FRICTION = 0.1

STATES = ("xs", "vs", "pA", "pB", "x", "v")
NS = 6
P_ATM = 1.0e5
KAPPA_AIR = 1.4
