"""Independent reference simulator of the MSP25 rig and the oscillator, for tests and benchmarks.

Shares no code with the product (``twin``, ``replay``): its own equations (exact
orifice square roots), scipy's adaptive LSODA, real analog and digital controllers
reading the noisy measured displacement, effects in their own formulation with sizes
drawn per seed, and a disk cache of records.  Specs are plain dicts (SI)::

    spec = msp25_spec(seed, controller="digital", rate_hz=5000, effects=["sensor_delay"])
    rec, = batch([spec])          # cached in $FPDD_REFCACHE (default tests/.refcache/)
    rec.to_csv("rig.csv")         # t,x_ref,u,x,pA,pB
"""

from .cache import batch, cache_dir, get_record, simulate, spec_key
from .msp25 import msp25_spec, replay_spec, simulate_msp25
from .oscillator import oscillator_spec, simulate_oscillator
from .record import Record
from .tables import (MSP25_EFFECTS, MSP25_FREE, MSP25_KNOWN, OSC_EFFECTS, OSC_FREE, OSC_KNOWN, draw_effects,
                     draw_truth)

__all__ = ["Record", "msp25_spec", "oscillator_spec", "replay_spec", "simulate", "simulate_msp25",
           "simulate_oscillator", "batch", "get_record", "cache_dir", "spec_key", "draw_truth", "draw_effects",
           "MSP25_KNOWN", "MSP25_FREE", "MSP25_EFFECTS", "OSC_KNOWN", "OSC_FREE", "OSC_EFFECTS"]
