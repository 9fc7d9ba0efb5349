"""The online tracker: the compiled UKF (:mod:`twin.ukf`) behind a block-by-block interface.

``OnlineTracker.process(samples)`` filters a block of :class:`replay.base.Samples`
(any length, from one sample to a whole record) in one compiled call and
returns a :class:`TrackBlock`: per sample the tracked parameters in SI with
their standard deviations, NIS, log-likelihood, the filter's status and which
parameters were frozen for lack of excitation.  The filter state carries over
from block to block, so the live service and the offline replay run the same
code.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping, Sequence

import numpy as np
from filterpy.kalman import JulierSigmaPoints, MerweScaledSigmaPoints
from scipy import stats

from replay.base import Samples
from twin import ukf
from twin.errors import DataError, FilterError, ParameterError
from twin.models import get_model
from twin.models import msp25 as M

#: random-walk intensity of each parameter, in log units per sqrt(second)
DEFAULT_Q_RATE = {"Ffric": 0.3, "CdAleak": 0.15, "Cd": 0.02, "zeta": 0.02, "wn": 0.02}
#: per-step process noise of the scaled model states (filter units, variance per sample at 1 kHz)
DEFAULT_Q_STATE = np.array([1e-10, 1e-10, 1e-6, 1e-6, 1e-10, 1e-7])
#: prior standard deviation of the parameters (log units): +-50 % starting errors are inside 1 sigma
DEFAULT_PRIOR_STD = 0.7
#: excitation thresholds: rod speed [m/s], command rate [V/s], piston pressure difference [Pa]
DEFAULT_EXCITE = (2e-3, 0.5, 2e4)


@dataclasses.dataclass
class TrackBlock:
    t_ns: np.ndarray            # [T]
    estimates: np.ndarray       # [T, p] SI
    stds: np.ndarray            # [T, p] SI (delta method on the log coordinates)
    log_std: np.ndarray         # [T, p] relative standard deviation
    nis: np.ndarray             # [T]
    loglik: np.ndarray          # [T]
    status: np.ndarray          # [T] status names
    frozen: np.ndarray          # [T, p] bool
    innovation: np.ndarray      # [T, m] SI
    states: np.ndarray          # [T, 6] SI

    @property
    def param_status(self) -> np.ndarray:
        """Per sample and parameter: 'frozen' or 'ok'."""
        return np.where(self.frozen, "frozen", "ok")


class OnlineTracker:
    """Augmented-state UKF of one rig; see the module docstring.

    ``params``: known parameter overrides (the rig configuration); ``start``:
    starting values of the tracked parameters (default: the configuration's);
    ``outputs``: which of x, pA, pB to use when present.  ``points``: a filterpy
    sigma-point object (``MerweScaledSigmaPoints`` from ``alpha, beta, kappa`` by
    default, or ``JulierSigmaPoints``) whose weights and spread the filter uses.
    """

    def __init__(self, model: str = "msp25", params: Mapping[str, float] | None = None,
                 tracked: Sequence[str] = M.PHENOMENOLOGICAL, dt: float | None = None,
                 start: Mapping[str, float] | None = None, outputs: Sequence[str] = ("x", "pA", "pB"),
                 q_rate: Mapping[str, float] | None = None, q_state: np.ndarray | None = None,
                 prior_std: float = DEFAULT_PRIOR_STD, alpha: float = 0.3, beta: float = 2.0,
                 kappa: float = 0.0, points=None, substeps: int = 2, excite: Sequence[float] = DEFAULT_EXCITE,
                 tau_excite: float = 0.5, gate_p: float = 1e-9, max_gated: int = 5):
        if model != "msp25":
            raise ParameterError(f"the tracker follows the msp25 rig model, not {model!r}")
        self.model = get_model(model)
        self.ps = self.model.params(**dict(params or {}))
        self.tracked = tuple(tracked)
        bad = [t for t in self.tracked if t not in ukf.TRACKABLE]
        if bad or not self.tracked:
            raise ParameterError(f"cannot track {bad or 'nothing'}; trackable: {', '.join(ukf.TRACKABLE)}")
        self.outputs = tuple(o for o in outputs)
        for o in self.outputs:
            if o not in ukf.MEAS_INDEX:
                raise ParameterError(f"unknown measurement {o!r}; known: x, pA, pB")
        self.units = tuple(self.ps.spec(t).unit for t in self.tracked)
        start = {**{t: self.ps[t] for t in self.tracked}, **dict(start or {})}
        for t in self.tracked:
            self.ps.spec(t).check(start[t])
        self.ref = np.array([self.ps[t] for t in self.tracked])
        self.idx = np.array([self.model.kernel_index(t) for t in self.tracked], dtype=np.int64)
        self.pvec = self.model.vector(self.ps)
        self.scale = ukf.STATE_SCALE.copy()
        self.dt = dt
        self.substeps = int(substeps)
        p = len(self.tracked)
        self.n = n = 6 + p
        self.alpha, self.beta, self.kappa = alpha, beta, kappa
        # filterpy's sigma points: their weights, and their spread (sigmas = x +- rows of sqrt(c P))
        self.points = points if points is not None else MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
        if isinstance(self.points, MerweScaledSigmaPoints):
            spread = self.points.alpha**2 * (n + self.points.kappa)
        elif isinstance(self.points, JulierSigmaPoints):
            spread = n + self.points.kappa
        else:
            raise ParameterError(f"sigma points {type(self.points).__name__}: the compiled filter takes "
                                 "filterpy's MerweScaledSigmaPoints or JulierSigmaPoints")
        if self.points.n != n:
            raise ParameterError(f"sigma points for n={self.points.n}, the filter has n={n} states")
        self.lam = spread - n
        self.Wm = np.ascontiguousarray(self.points.Wm, dtype=float)
        self.Wc = np.ascontiguousarray(self.points.Wc, dtype=float)
        self.q_rate = np.array([{**DEFAULT_Q_RATE, **dict(q_rate or {})}[t] for t in self.tracked])
        self.q_state = np.array(DEFAULT_Q_STATE if q_state is None else q_state, dtype=float)
        self.meas_idx = np.array([ukf.MEAS_INDEX[o] for o in self.outputs], dtype=np.int64)
        noise = {"x": 2e-6, "pA": 2e4, "pB": 2e4}
        self.R = np.array([(noise[o] / self.scale[ukf.MEAS_INDEX[o]]) ** 2 for o in self.outputs])
        self.chan = np.array([ukf.EXCITE_CHANNEL[t] for t in self.tracked], dtype=np.int64)
        self.excite_thresh = np.array(excite, dtype=float)
        self.tau_excite = tau_excite
        self.gate = float(stats.chi2.isf(gate_p, len(self.outputs)))
        self.max_gated = int(max_gated)
        # state
        s0 = self.model.initial_state(self.pvec[None])[0] / self.scale
        self.x = np.concatenate([s0, np.log(np.array([start[t] for t in self.tracked]) / self.ref)])
        prior = np.concatenate([[0.01, 0.01, 0.1, 0.1, 0.01, 0.01], np.full(p, prior_std)])
        self.P = np.diag(prior**2)
        self.floor = np.concatenate([np.full(6, 1e-12), np.full(p, 1e-10)])
        self.exc = np.zeros(3)
        self.u_prev = np.nan
        self.gated_run = 0
        self.samples = 0
        self.counters = {s: 0 for s in ukf.STATUS}
        self._Q = None
        self._pending = None

    def _q(self, dt: float) -> np.ndarray:
        if self._Q is None or self._Q_dt != dt:
            scale_dt = dt / 1e-3
            self._Q = np.diag(np.concatenate([self.q_state * scale_dt, self.q_rate**2 * dt]))
            self._Q_dt = dt
        return self._Q

    def process(self, samples) -> TrackBlock:
        """Filter a block of samples (signals in SI; ``u`` or ``x_ref`` drive, x/pA/pB measure)."""
        T = len(samples)
        sig = samples.signals
        if "u" not in sig and "x_ref" not in sig:
            raise DataError("the tracker needs the controller output 'u' or the demand 'x_ref'; "
                            f"the block has {', '.join(sig) or 'no signals'}")
        if "u" not in sig and (self.ps["KI"] != 0 or self.ps["KD"] != 0):
            raise DataError("without a logged 'u' the tracker drives the rig from 'x_ref' through a P controller, "
                            f"but this rig has KI={self.ps['KI']:g}, KD={self.ps['KD']:g}; log the controller "
                            "output u")
        if not any(o in sig for o in self.outputs):
            raise DataError(f"the tracker needs at least one of {', '.join(self.outputs)}; "
                            f"the block has {', '.join(sig)}")
        if self.dt is None:  # the sample time is learnt from the first samples: wait for two
            if self._pending is not None:
                samples = Samples.concat([self._pending, samples])
                self._pending = None
                T, sig = len(samples), samples.signals
            if T < 2:
                self._pending = samples
                return self._empty()
        t_ns = np.asarray(samples.t_ns, dtype=np.int64)
        if self.dt is None:
            self.dt = float(np.median(np.diff(t_ns))) * 1e-9
            if not self.dt > 0:
                raise DataError(f"sample times do not increase (median step {self.dt} s)")
        nan = np.full(T, np.nan)
        U = np.ascontiguousarray(sig.get("u", nan), dtype=float)
        XREF = np.ascontiguousarray(sig.get("x_ref", nan), dtype=float)
        Z = np.empty((T, len(self.outputs)))
        for a, o in enumerate(self.outputs):
            Z[:, a] = np.asarray(sig[o], dtype=float) / self.scale[ukf.MEAS_INDEX[o]] if o in sig else np.nan
        n, p, m = self.n, len(self.tracked), len(self.outputs)
        X = np.empty((T, n))
        Pd = np.empty((T, n))
        nis = np.empty(T)
        ll = np.empty(T)
        st = np.empty(T, dtype=np.int64)
        innov = np.empty((T, m))
        Sd = np.empty((T, m))
        frozen = np.empty((T, p), dtype=np.bool_)
        alpha_exc = min(1.0, self.dt / self.tau_excite)
        self.u_prev, self.gated_run, bad = ukf.run_kernel(
            self.x, self.P, self.exc, U, XREF, Z, self.pvec, self.idx, self.ref, self.scale, self.dt,
            self.substeps, self._q(self.dt), self.R, self.meas_idx, self.Wm, self.Wc, self.lam, self.floor,
            self.gate, self.max_gated, self.chan, self.excite_thresh, alpha_exc, self.u_prev, self.gated_run,
            self.outputs.index("x") if "x" in self.outputs else -1,
            X, Pd, nis, ll, st, innov, Sd, frozen)
        if bad >= 0:
            raise FilterError(f"the filter diverged at sample {self.samples + bad} (t_ns={int(t_ns[bad])}): "
                              "state or covariance not finite and not repairable")
        self.samples += T
        codes, counts = np.unique(st, return_counts=True)
        for c, k in zip(codes, counts):
            self.counters[ukf.STATUS[c]] += int(k)
        z = X[:, 6:]
        zs = np.sqrt(np.maximum(Pd[:, 6:], 0.0))
        est = self.ref * np.exp(z)
        states = X[:, :6] * self.scale
        innov_si = innov * np.array([self.scale[ukf.MEAS_INDEX[o]] for o in self.outputs])
        return TrackBlock(t_ns=t_ns, estimates=est, stds=est * zs, log_std=zs, nis=nis, loglik=ll,
                          status=np.array(ukf.STATUS)[st], frozen=frozen, innovation=innov_si, states=states)

    def _empty(self) -> TrackBlock:
        p, m = len(self.tracked), len(self.outputs)
        z = np.zeros((0, p))
        return TrackBlock(np.zeros(0, np.int64), z, z, z, np.zeros(0), np.zeros(0), np.zeros(0, dtype="<U19"),
                          np.zeros((0, p), bool), np.zeros((0, m)), np.zeros((0, 6)))

    def estimate(self) -> dict[str, tuple[float, float]]:
        """Current (value, std) of every tracked parameter (SI)."""
        z = self.x[6:]
        s = np.sqrt(np.maximum(np.diag(self.P)[6:], 0.0))
        v = self.ref * np.exp(z)
        return {t: (float(v[j]), float(v[j] * s[j])) for j, t in enumerate(self.tracked)}

    def break_covariance(self) -> None:
        """Make the covariance indefinite (what round-off does to long runs); for tests and drills."""
        w, V = np.linalg.eigh(self.P)
        w[0] = -abs(w[-1])
        self.P[:, :] = (V * w) @ V.T

    @property
    def rel_std(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.P)[6:], 0.0))

    def __repr__(self) -> str:
        return (f"OnlineTracker(tracked={self.tracked}, outputs={self.outputs}, dt={self.dt}, "
                f"samples={self.samples})")


def fmt_estimate(name: str, value: float, std: float) -> str:
    spec = M.MODEL.params().spec(name)
    return f"{name} = {spec.show(value)} +- {spec.show(std)}" if math.isfinite(std) else f"{name} = {spec.show(value)}"
