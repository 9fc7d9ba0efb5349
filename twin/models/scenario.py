"""Rigs that wear: simulations whose phenomenological parameters change over time.

A :class:`Drift` describes one parameter's trajectory (a step, a ramp, an
exponential decay); :func:`simulate_wear` runs the MSP25 closed loop from
``x_ref`` sample by sample with the parameter vector of each sample, in one
compiled loop, and returns what the sensors log.  The demo and the tracker's
fault tests are built on it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numba as nb
import numpy as np

from fpdd.errors import ParameterError
from twin.models import msp25 as M
from twin.params import ParameterSet
from twin.record import Record
from twin.models import intersample as _intersample_src
from twin.models import base as _base_src
from twin.models.jitcache import keep_fresh

# the machine code cached for this module inlines these modules' compiled code and constants
keep_fresh(__file__, M.__file__, *M.SOURCES, _intersample_src.__file__, _base_src.__file__)


@dataclasses.dataclass(frozen=True)
class Drift:
    """``parameter`` goes from its nominal value to ``factor`` times it.

    ``shape`` is ``step`` (at ``t_start``), ``ramp`` (linear from ``t_start`` to
    ``t_end``) or ``exp`` (log-linear, i.e. a geometric decay or growth).
    """

    parameter: str
    factor: float
    t_start: float
    t_end: float | None = None
    shape: str = "ramp"

    def trajectory(self, nominal: float, t: np.ndarray) -> np.ndarray:
        if self.shape == "step":
            return np.where(t >= self.t_start, nominal * self.factor, nominal)
        end = self.t_end if self.t_end is not None else self.t_start
        if end <= self.t_start:
            raise ParameterError(f"drift of {self.parameter}: t_end ({end}) must follow t_start ({self.t_start})")
        r = np.clip((t - self.t_start) / (end - self.t_start), 0.0, 1.0)
        if self.shape == "ramp":
            return nominal * (1.0 + (self.factor - 1.0) * r)
        if self.shape == "exp":
            return nominal * self.factor ** r
        raise ParameterError(f"drift of {self.parameter}: shape {self.shape!r} is not step, ramp or exp")

    def crossing(self, nominal: float, lo: float, hi: float, t: np.ndarray) -> float | None:
        """First time the true value leaves [lo, hi] (None if it never does)."""
        v = self.trajectory(nominal, t)
        out = np.flatnonzero((v < lo) | (v > hi))
        return float(t[out[0]]) if out.size else None


@nb.njit(cache=True)
def _run(P, xref, dt, nsub, s0):
    T = xref.shape[0]
    S = np.empty((T, M.NS))
    U = np.empty(T)
    s = s0.copy()
    nxt = np.empty(M.NS)
    for k in range(T):
        S[k] = s
        u = P[k, M.I_KP] * (xref[k] - s[4])
        U[k] = u
        if k + 1 < T:
            M.step(s, u, P[k], dt, nsub, nxt)
            s[:] = nxt
    return S, U


def parameter_matrix(ps: ParameterSet, drifts: Sequence[Drift], t: np.ndarray) -> np.ndarray:
    """Per-sample kernel vectors ``[T, NP]`` with the drifts applied."""
    P = np.repeat(M.MODEL.vector(ps)[None, :], t.size, axis=0)
    for d in drifts:
        spec = ps.spec(d.parameter)
        traj = d.trajectory(ps[d.parameter], t)
        for v in (traj.min(), traj.max()):
            spec.check(v)
        P[:, M.MODEL.kernel_index(d.parameter)] = traj
    return P


def simulate_wear(ps: ParameterSet, xref: np.ndarray, dt: float, drifts: Sequence[Drift] = (),
                  noise: Mapping[str, float] | None = None, seed: int = 0, name: str = "wear") -> tuple[Record, np.ndarray]:
    """Closed-loop MSP25 record with drifting parameters: (logged record, true kernel vectors [T, NP])."""
    if ps.model != "msp25":
        raise ParameterError(f"simulate_wear runs the msp25 model, got a {ps.model} parameter set")
    if ps["KI"] != 0 or ps["KD"] != 0:
        raise ParameterError("simulate_wear models the paper's P controller (KI = KD = 0)")
    xref = np.ascontiguousarray(xref, dtype=np.float64)
    t = np.arange(xref.size) * dt
    P = parameter_matrix(ps, drifts, t)
    S, U = _run(P, xref, float(dt), M.MODEL.substeps, M.MODEL.initial_state(P[:1])[0])
    rng = np.random.default_rng(seed)
    sig = {"x_ref": xref, "u": U, "x": S[:, 4].copy(), "pA": S[:, 2].copy(), "pB": S[:, 3].copy()}
    for k, sd in (noise or {}).items():
        if sd > 0:
            sig[k] = sig[k] + rng.normal(0.0, sd, xref.size)
    return Record(dt, sig, name), P
