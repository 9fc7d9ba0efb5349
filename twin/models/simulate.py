"""Simulated measurements: drive a model, add sensor noise and quantisation, get a :class:`Record`.

The default experiment and the default sensor noise are the model's own (:attr:`Model.EXPERIMENT`, the
``noise`` of its measured outputs in :attr:`Model.SIGNALS`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from twin.models import excitation
from fpdd.errors import DataError
from twin.models import Model, get_model
from twin.models.base import Timing
from twin.params import ParameterSet
from twin.record import Record


def default_experiment(model: Model) -> dict[str, Any]:
    """``model``'s default identification experiment (:attr:`Model.EXPERIMENT`) as keywords."""
    import dataclasses

    if model.EXPERIMENT is None:
        raise DataError(f"the {model.name} model declares no default experiment")
    return dataclasses.asdict(model.EXPERIMENT)


def excite(model: Model | str, duration_s: float = 10.0, dt: float = 1e-3, kind: str | None = None,
           amplitude: float | None = None, seed: int | None = 0, f_lo: float | None = None,
           f_hi: float | None = None) -> tuple[str, np.ndarray]:
    """The default identification input of ``model``: (driving signal name, values)."""
    model = get_model(model) if isinstance(model, str) else model
    e = default_experiment(model)
    kind = kind or e["kind"]
    amp = e["amplitude"] if amplitude is None else amplitude
    lo = e["f_lo"] if f_lo is None else f_lo
    hi = e["f_hi"] if f_hi is None else f_hi
    if kind == "multisine":
        sig = excitation.multisine(duration_s, dt, lo, hi, amp, seed=seed)
    elif kind == "chirp":
        sig = excitation.chirp(duration_s, dt, lo, hi, amp)
    elif kind == "steps":
        sig = excitation.random_steps(duration_s, dt, amp, bandwidth_hz=hi, seed=seed or 0)
    else:
        raise DataError(f"unknown excitation {kind!r}; known: {', '.join(excitation.KINDS)}")
    return e["drive"], sig


def measure(model: Model, ps: ParameterSet, drive_name: str, drive: np.ndarray, dt: float,
            noise: Mapping[str, float] | None = None, quantisation: Mapping[str, float] | None = None,
            seed: int = 0, init: Mapping[str, float] | None = None, name: str = "simulated",
            timing: Timing | None = None, exogenous: Mapping[str, np.ndarray] | None = None,
            exogenous_every: int = 1) -> Record:
    """Simulate ``ps`` and return what the sensors would log (inputs exact, outputs noisy).

    ``noise`` maps signal names to standard deviations (SI); ``quantisation`` maps
    signal names to their least significant bit (SI); both applied to the logged
    signals with ``np.random.default_rng(seed)``.  ``exogenous``: signals that set a
    parameter sample by sample (the oil temperature ``T_oil [T]``, K): the rig runs on
    them and they are logged, refreshed every ``exogenous_every`` samples and held
    between (a 10 Hz HPU status on a 1 kHz log: 100), as a CAN log holds them.
    """
    res = model.simulate(ps, drive_name, drive, dt, init=init, timing=timing, exogenous=exogenous)
    sig: dict[str, np.ndarray] = {}
    for k, v in res.inputs.items():
        sig[k] = np.array(v, dtype=np.float64)
    every = max(1, int(exogenous_every))
    for k, v in (exogenous or {}).items():
        v = np.asarray(v, dtype=np.float64)
        sig[k] = v[(np.arange(v.size) // every) * every]
    for k, v in res.outputs.items():
        sig[k] = np.array(v, dtype=np.float64)
    rng = np.random.default_rng(seed)
    for k, sd in (noise or {}).items():
        if k not in sig:
            raise DataError(f"noise given for {k!r}, which the model does not log ({', '.join(sig)})")
        if sd > 0:
            sig[k] = sig[k] + rng.normal(0.0, sd, sig[k].shape)
    for k, lsb in (quantisation or {}).items():
        if k not in sig:
            raise DataError(f"quantisation given for {k!r}, which the model does not log ({', '.join(sig)})")
        if lsb > 0:
            sig[k] = np.round(sig[k] / lsb) * lsb
    order = [s.name for s in model.SIGNALS]  # the model's own order: demand, drive, outputs, exogenous
    sig = {k: sig[k] for k in sorted(sig, key=lambda n: order.index(n) if n in order else len(order))}
    return Record(dt, sig, name)


def ramp(start: float, end: float, n: int) -> np.ndarray:
    """``n`` samples rising linearly from ``start`` to ``end`` (a trajectory over a record, e.g. a warming oil)."""
    if n < 1:
        raise DataError(f"a trajectory needs at least one sample, got {n}")
    return np.linspace(float(start), float(end), int(n))


def default_noise(model: Model) -> dict[str, float]:
    """The nominal sensor noise of ``model``'s measured outputs (SI standard deviations)."""
    return model.nominal_noise()
