"""Parameter values (SI) of the reference simulator, effect ranges, and the draws of truth and effect sizes.

Known MSP25 parameters: model-spec Table 8; free parameters: Table 9.  The
oscillator: model-spec section 1.  Nothing here is read from the product.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping

import numpy as np

#: MSP25 known parameters (Table 8), SI.  ``B`` is the oil bulk modulus.
MSP25_KNOWN: dict[str, float] = {
    "KP": 400.0, "KI": 0.0, "KD": 0.0, "rho": 960.0, "V0": 480e-6, "A": 1920e-6, "m": 45.0,
    "B": 1.5e9, "vref": 1e-3, "Ke": 1.0, "Ksp": 0.0024, "b": 5e-3, "pP": 28e6, "pT": 0.0,
    "stroke": 0.25,
}

#: MSP25 free parameters (Table 9), SI; ``wn`` in rad/s.
MSP25_FREE: dict[str, float] = {
    "Ffric": 50.0, "CdAleak": 3.2863e-9, "Cd": 0.2191, "zeta": 0.3701, "wn": 2.0 * math.pi * 43.0,
}

#: Oscillator parameters (model-spec section 1); ``d`` and ``k`` are free.
OSC_KNOWN: dict[str, float] = {"m": 1.0}
OSC_FREE: dict[str, float] = {"d": 0.1, "k": 3947.8}

#: Effects of the MSP25: parameter -> (low, high) of the per-seed draw (SI).
#: A parameter given as a 1-tuple is fixed; ``sign`` draws +1 or -1; ``channel`` draws pA or pB.
MSP25_EFFECTS: dict[str, dict[str, tuple]] = {
    "viscous_friction": {"c": (1000.0, 4000.0)},                      # N s/m
    "stribeck_friction": {"Fs": (80.0, 250.0), "vs": (3e-3, 20e-3)},  # N, m/s
    "laminar_leakage": {"G": (1e-11, 4e-11)},                         # m^3/(s Pa)
    "spool_deadband": {"overlap": (10e-6, 30e-6)},                    # m
    "valve_null_bias": {"offset": (5e-6, 20e-6), "sign": ()},         # m
    "supply_pressure_droop": {"R": (5e9, 2e10)},                      # Pa s/m^3
    "specimen_stiffness": {"k": (1e6, 4e6)},                          # N/m
    "sensor_delay": {"delay": (1e-3, 3e-3)},                          # s
    "entrained_air": {"air_fraction": (0.03, 0.12)},                  # 1, at atmospheric pressure
    "spool_saturation": {"xs_max": (0.3e-3, 0.7e-3)},                 # m
    "position_sensor_gain": {"gain": (1.01, 1.04)},                   # 1
    "pressure_sensor_offset": {"offset": (0.2e6, 1.0e6), "sign": (), "channel": ()},  # Pa
    "supply_line_loss": {"K": (4e13, 1.6e14)},                         # Pa s^2/m^6 (drop = K q^2)
    "pressure_sensor_lag": {"tau": (1.5e-3, 4e-3)},                   # s, both transducers
    # the supply line: hose length and bore [m], accumulator gas volume at pre-charge [m^3] (rings at 4-19 Hz)
    "supply_dynamics": {"hose_l": (4.0, 10.0), "hose_d": (5e-3, 8e-3), "acc_v": (0.05e-3, 0.2e-3)},
    "mechanical_resonance": {"f": (50.0, 90.0), "m2": (10.0, 30.0), "zeta2": (0.02, 0.05)},
    "parameter_drift": {"param": ("Ffric",), "factor": (1.5, 2.5)},
}

OSC_EFFECTS: dict[str, dict[str, tuple]] = {
    "coulomb_friction": {"Fc": (0.5, 3.0)},  # N
}


def _rng(seed: int, label: str) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(label.encode())])


def draw_truth(seed: int, spread: float = 0.2, model: str = "msp25", min_offset: float = 0.03) -> dict[str, float]:
    """Free parameters drawn uniformly within +-``spread`` of the defaults, at least ``min_offset`` away."""
    if not 0.0 <= min_offset < spread:
        raise ValueError(f"need 0 <= min_offset < spread, got {min_offset}, {spread}")
    base = MSP25_FREE if model == "msp25" else OSC_FREE
    rng = _rng(seed, f"truth/{model}")
    out = {}
    for name, v in base.items():
        mag = rng.uniform(min_offset, spread)
        sgn = 1.0 if rng.random() < 0.5 else -1.0
        out[name] = float(v * (1.0 + sgn * mag))
    return out


def draw_effects(seed: int, effects, model: str = "msp25") -> dict[str, dict]:
    """Effect sizes for ``effects`` (names, or a mapping name -> partial dict of explicit values).

    Values not given are drawn per seed from the plausible range of the catalogue.
    """
    table = MSP25_EFFECTS if model == "msp25" else OSC_EFFECTS
    given: Mapping[str, Mapping] = effects if isinstance(effects, Mapping) else {e: {} for e in effects}
    out: dict[str, dict] = {}
    for name, explicit in given.items():
        if name not in table:
            raise ValueError(f"unknown {model} effect {name!r}; known: {', '.join(table)}")
        explicit = dict(explicit or {})
        unknown = set(explicit) - set(table[name])
        if unknown:
            raise ValueError(f"effect {name!r} has no parameter(s) {sorted(unknown)}; known: {sorted(table[name])}")
        rng = _rng(seed, f"effect/{model}/{name}")
        vals: dict = {}
        for p, rngspec in table[name].items():
            if p == "sign":
                draw = 1.0 if rng.random() < 0.5 else -1.0
            elif p == "channel":
                draw = "pA" if rng.random() < 0.5 else "pB"
            elif len(rngspec) == 1:
                draw = rngspec[0]
            else:
                draw = float(rng.uniform(*rngspec))
            vals[p] = explicit.get(p, draw)
        out[name] = vals
    return out
