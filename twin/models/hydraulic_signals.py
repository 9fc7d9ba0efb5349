"""The signals of a servo-hydraulic test rig's records (the MSP25 and the smaller hydraulic actuator models):
roles, SI units, physical ranges and nominal sensor noise (an LVDT of 2 um, pressure transducers of 20 kPa)."""

from __future__ import annotations

from twin.models.base import Experiment, Signal

SIGNALS: tuple[Signal, ...] = (
    Signal("x_ref", "demand", "m", -0.5, 0.5, "demanded rod displacement", noise=0.0),
    Signal("u", "drive", "V", -15.0, 15.0, "controller output (servo-valve voltage)", noise=0.0),
    Signal("x", "output", "m", -0.5, 0.5, "measured rod displacement (LVDT)", noise=2e-6),
    Signal("pA", "output", "Pa", -1.0e6, 60.0e6, "pressure in chamber A", noise=2e4),
    Signal("pB", "output", "Pa", -1.0e6, 60.0e6, "pressure in chamber B", noise=2e4),
    Signal("T_oil", "exogenous", "K", 233.15, 423.15, "oil temperature"),
    Signal("F", "logged", "N", -1.0e6, 1.0e6, "rod force (load cell)"),
    Signal("pP", "logged", "Pa", -1.0e6, 60.0e6, "supply pressure"),
)
#: the default identification experiment: a multisine demand of 10 mm, 0.2-12 Hz
EXPERIMENT = Experiment("multisine", "x_ref", 0.01, 0.2, 12.0)
