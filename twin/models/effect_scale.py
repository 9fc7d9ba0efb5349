"""Each MSP25 effect's typical size from the record and the fitted nominal rig (:func:`msp25_typicals`).

The catalogue states an effect's typical size for the paper's Table 9 rig logged at 1 kHz (the sizes the
reference's calibration records, seeds 0-2, were diagnosed with).  On another rig, or another log, the same
effect is as large when it changes the same physical balance by the same fraction, so each size follows the
scale of the quantity it acts on, by dimensional analysis:

* **force** ``F0 = (pP - pT) A``: the rig's force range (stall force) - a friction, a breakaway;
* **pressure** ``P0 = pP - pT``: the pressure range - a transducer offset;
* **speed** ``V0``: the rms rod speed the record exercises (from the fitted model's predicted displacement,
  the measured one is noisy);
* **flow** ``Q0 = A V0``: the flow the record draws - a leak is ``Q0 / P0`` of conductance, a supply
  resistance ``P0 / Q0``, a turbulent supply loss ``P0 / Q0^2``;
* **spool opening** ``XS0 = Q0 / (Cd b sqrt(P0 / rho))``: the valve opening that passes that flow (the fitted
  discharge coefficient) - an overlap, a null bias, a stroke limit;
* **stroke** ``X0``: the rms rod displacement the record exercises - a specimen stiffness is ``F0 / X0``;
* **time** the record's sample period ``dt`` - a displacement sensor's delay, a pressure transducer's lag.

An effect's typical size is its catalogue size times the ratio of its scale on this record to the same scale
on the catalogue's rig (:data:`CATALOGUE_RIG`: Table 9, 1 ms, and the rms rod speed and displacement of the
calibration records).  Dimensionless effects (entrained air, a position sensor's gain, the Stribeck shape) and
the Stribeck velocity (a secondary parameter probed at multiples of its own size) keep the catalogue's.  The
screen probes 0.3, 1 and 3 times these sizes, a fit starts from them, and a named effect lies within 10 times
them (twin/estimation/diagnose/constants.py).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

#: the rig and record the catalogue's sizes are stated for: Table 9 (``twin.models.msp25.NOMINAL``), logged at
#: 1 kHz, and the rms rod speed [m/s] and displacement [m] of the healthy calibration records (reference seeds
#: 0-2, 6 s: 0.0174-0.0191 m/s and 1.64-1.92 mm; README "Tuned constants")
CATALOGUE_RIG = {"dt": 1e-3, "v_rms": 0.018, "x_rms": 1.8e-3}

#: effect -> per parameter, the scale its size follows (None: the catalogue's size)
SCALES: dict[str, tuple[str | None, ...]] = {
    "viscous_friction": ("F/V",),
    "stribeck_friction": ("F", None, None),
    "laminar_leakage": ("Q/P",),
    "spool_deadband": ("XS",),
    "valve_null_bias": ("XS",),
    "supply_pressure_droop": ("P/Q",),
    "specimen_stiffness": ("F/X",),
    "sensor_delay": ("T",),
    "entrained_air": (None,),
    "spool_saturation": ("XS",),
    "position_sensor_gain": (None,),
    "pressure_sensor_offset": ("P", "P"),
    "supply_line_loss": ("P/Q2",),
    "pressure_sensor_lag": ("T",),
    "supply_dynamics": (None, None, "P/Q"),
}


def _rms(a: np.ndarray) -> float:
    a = np.asarray(a, dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean((a - a.mean()) ** 2))) if a.size else 0.0


def rig_scales(ps: Mapping[str, float], x: np.ndarray, x_predicted: np.ndarray, dt: float,
               v_rms: float | None = None, x_rms: float | None = None) -> dict[str, float]:
    """The scales of the module docstring for the rig ``ps`` on a record with displacement ``x`` (measured)
    and ``x_predicted`` (the fitted model's) at sample period ``dt``; ``v_rms``/``x_rms`` override the
    record's (the catalogue's rig)."""
    P0 = max(float(ps["pP"]) - float(ps["pT"]), 1.0)
    A = float(ps["A"])
    if v_rms is None:
        v_rms = _rms(np.gradient(np.asarray(x_predicted, dtype=np.float64), dt)) if len(x_predicted) > 2 else 0.0
    if x_rms is None:
        x_rms = _rms(x)
    V0 = v_rms if v_rms > 0 and math.isfinite(v_rms) else CATALOGUE_RIG["v_rms"]
    X0 = x_rms if x_rms > 0 and math.isfinite(x_rms) else CATALOGUE_RIG["x_rms"]
    F0 = P0 * A
    Q0 = A * V0
    XS0 = Q0 / (float(ps["Cd"]) * float(ps["b"]) * math.sqrt(P0 / float(ps["rho"])))
    return {"F": F0, "P": P0, "V": V0, "Q": Q0, "XS": XS0, "X": X0, "T": float(dt),
            "F/V": F0 / V0, "Q/P": Q0 / P0, "P/Q": P0 / Q0, "P/Q2": P0 / Q0 ** 2, "F/X": F0 / X0}


def msp25_typicals(effects: Mapping, nominal: Mapping[str, float], ps: Mapping[str, float],
                   signals: Mapping[str, np.ndarray], predicted: Mapping[str, np.ndarray],
                   dt: float) -> dict[str, tuple[float, ...]]:
    """Each effect's typical size on this record (module docstring): ``effects`` the catalogue
    (name -> :class:`~twin.params.Effect`), ``nominal`` the catalogue's rig (Table 9), ``ps`` the fitted
    nominal rig, ``signals`` the record, ``predicted`` the fitted model's prediction of it."""
    x = np.asarray(signals["x"], dtype=np.float64)
    here = rig_scales(ps, x, np.asarray(predicted.get("x", x), dtype=np.float64), dt)
    ref = rig_scales(nominal, x, x, CATALOGUE_RIG["dt"], CATALOGUE_RIG["v_rms"], CATALOGUE_RIG["x_rms"])
    out: dict[str, tuple[float, ...]] = {}
    for name, E in effects.items():
        scales = SCALES.get(name, (None,) * len(E.typical))
        out[name] = tuple(float(t) if s is None else float(t) * here[s] / ref[s]
                          for t, s in zip(E.typical, scales))
    return out
