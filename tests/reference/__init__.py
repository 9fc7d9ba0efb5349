"""Independent reference simulator of the MSP25 rig and the oscillator, for tests and benchmarks.

Shares no code with the product (``twin``, ``replay``): its own equations (exact
orifice square roots), scipy's adaptive integrator (LSODA by default), real analog
and digital controllers reading the noisy measured displacement, effects in their
own formulation with sizes drawn per seed, and a disk cache of records.
"""

from .msp25 import msp25_spec, simulate_msp25
from .record import Record
from .tables import MSP25_EFFECTS, MSP25_FREE, MSP25_KNOWN, OSC_EFFECTS, OSC_FREE, draw_effects, draw_truth

__all__ = ["Record", "msp25_spec", "simulate_msp25", "draw_truth", "draw_effects", "MSP25_KNOWN",
           "MSP25_FREE", "MSP25_EFFECTS", "OSC_FREE", "OSC_EFFECTS"]
