"""Records for the diagnosis tests: catalogue effects switched on by name, and effects outside it.

Noise as a rig logs it (x: 2 um, pressures: 20 kPa; the oscillator's displacement 1 um), seeded.
"""

from __future__ import annotations

import numpy as np

from twin.models import get_model
from twin.record import Record
from twin.models.simulate import default_noise, excite, measure

RIG = get_model("msp25")
OSC = get_model("oscillator")


def record(model, effects=(), seed: int = 0, duration_s: float = 8.0, kind: str = "multisine",
           values: dict | None = None, **excitation) -> Record:
    """A noisy record of ``model`` with ``effects`` switched on (at their typical magnitudes unless
    ``values`` overrides) under the excitation ``kind``."""
    name, drive = excite(model, duration_s, 1e-3, kind=kind, seed=seed, **excitation)
    ps = model.params(effects=effects, **(values or {}))
    return measure(model, ps, name, drive, 1e-3, noise=default_noise(model), seed=seed,
                   name=f"{model.name}+{'+'.join(effects) or 'healthy'}")


def rig_with_pressure_sensor_drift(drift_pa: float = 2e5, seed: int = 3, duration_s: float = 8.0) -> Record:
    """A healthy rig whose chamber-A pressure sensor drifts linearly by ``drift_pa`` over the record
    (outside the catalogue: no physical effect raises pA alone while pB stays)."""
    rec = record(RIG, (), seed, duration_s)
    sig = dict(rec.signals)
    sig["pA"] = sig["pA"] + drift_pa * rec.t_s / rec.t_s[-1]
    return Record(rec.dt, sig, "msp25+pA-sensor-drift")


def oscillator_with_force_ripple(amplitude_n: float = 2.0, wavelength_m: float = 5e-3, seed: int = 5,
                                 duration_s: float = 8.0) -> Record:
    """The nominal oscillator plus a position-dependent force ripple ``a sin(2 pi x / lambda)``
    (a cogging-like effect outside the catalogue), simulated by its own RK4 (2 substeps, as the model)."""
    name, u = excite(OSC, duration_s, 1e-3, seed=seed)
    m, d, k = (OSC.NOMINAL[n] for n in ("m", "d", "k"))
    w = 2.0 * np.pi / wavelength_m

    def f(x, v, uk):
        return v, (uk - d * v - k * x - amplitude_n * np.sin(w * x)) / m

    h = 1e-3 / 2
    x = v = 0.0
    y = np.empty(u.size)
    for i in range(u.size):
        y[i] = x
        for _ in range(2):
            a = f(x, v, u[i])
            b = f(x + 0.5 * h * a[0], v + 0.5 * h * a[1], u[i])
            c = f(x + 0.5 * h * b[0], v + 0.5 * h * b[1], u[i])
            e = f(x + h * c[0], v + h * c[1], u[i])
            x += h / 6.0 * (a[0] + 2 * b[0] + 2 * c[0] + e[0])
            v += h / 6.0 * (a[1] + 2 * b[1] + 2 * c[1] + e[1])
    y = y + np.random.default_rng(seed).normal(0.0, default_noise(OSC)["y"], y.size)
    return Record(1e-3, {"u": u, "y": y}, "oscillator+force-ripple")
