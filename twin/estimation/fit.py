"""Batch grey-box fitting: output-error (simulation-error) least squares, done properly.

* Free and fixed parameters by name; bounds from the parameter metadata.
* Coordinates: a free parameter with a wide positive range (``hi/lo > 100``)
  moves as ``log(theta)``, the others as ``theta / scale``; every coordinate is
  of order one and finite-difference steps are explicit (never proportional to
  a coordinate that may sit at zero).
* The Jacobian is a batch: all finite-difference columns (and all multi-start
  candidates) are simulated in one parallel call of the compiled model.
* Multi-start: a seeded Latin hypercube of physically sensible starts around
  the configured values, as many drawn log-uniformly over the free
  parameters' whole physical ranges (where a range spans decades), and the
  starts the model reads off the data (a second-order plant's own response,
  ``Model.starts_from_data``) are screened by cost in one batch; the best few are
  refined with trust-region least squares and the best result is kept.  A start
  far from the nominal values (a circuit in volts modelled as a mass of 5e-6)
  is so found without the user's help.
* Several records share the parameters; optional initial-state estimation adds
  per-record initial quantities (rod position, pressure difference).
* Residuals of each output are weighted by its noise level, so x [m] and
  pressures [Pa] can be fitted together.  A signal logged at its own, slower
  rate and held onto the grid counts only at its fresh samples
  (:func:`twin.record.fresh_mask`): a held value is not a measurement.
* The loop's timing (:class:`~twin.models.base.Timing`: controller rate,
  intersample behaviour of the logged inputs) is a property of the rig that
  every simulation of the fit honours.
* The initial state comes from the data: each record starts where its first
  samples say (rod position and speed, both chamber pressures, the spool where
  the first command holds it); ``estimate_init`` refines quantities on top.
* The loop noise: a closed loop's controller reads the noisy sensor, and the
  noise it feeds back shakes the rig; at velocity reversals that dithers the
  dry friction, an effect of second order in the noise that a simulation of
  the loop without noise cannot show (it pulls the friction estimate about
  0.1 % low, a sixth of its standard error, with a 2 um sensor).  After the
  best start has converged, the fit refines once more with the simulated
  controller reading the simulated displacement plus and minus a white noise
  at the level of the noise the controller read (:meth:`_Problem.loop_noise`),
  the outputs being the mean of the two loops: the even-order effect stays,
  the first-order one (a coloured disturbance the covariance accounts for)
  cancels (``loop_noise=False`` skips it).
* Standard errors are heteroskedasticity- and autocorrelation-consistent (a
  Newey-West sandwich with Bartlett weights and Andrews' AR(1) bandwidth, at
  least ``sqrt(n)`` lags, per output and record): output-error residuals of a closed loop fed by a noisy
  sensor are coloured, and the textbook ``s^2 (J'J)^-1`` then understates the
  uncertainty many times over.  ``std_white`` keeps the textbook figure.

:func:`fit` returns a :class:`FitResult` and never raises on non-convergence;
it raises :class:`~fpdd.errors.DataError` / :class:`~fpdd.errors.ParameterError`
only for malformed input.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from scipy import optimize

from fpdd.errors import DataError, ParameterError
from twin.models import Model, get_model
from twin.models.base import DEFAULT_TIMING, Timing
from twin.params import ParameterSet, ParamSpec, check_names
from twin.record import Record
from twin.units import check_lengths
from fpdd.units import NOMINAL_NOISE
from twin.estimation.fit_result import FitResult
from twin.estimation.fit_stats import hac_covariance, likelihood_ratio
from twin.estimation.threads import one_blas_thread

__all__ = ["FitResult", "fit", "hac_covariance", "likelihood_ratio", "make_problem", "noise_levels",
           "initial_from_data", "resolve_outputs"]

FD_STEP = 1e-6  # finite-difference step in the order-one fit coordinates
#: a refinement stops when the Gauss-Newton step left is under this fraction of a standard error in every
#: direction (its Mahalanobis length in the white-noise covariance, which the HAC one only widens): the digits it
#: would still add are far inside the estimate's own uncertainty
STEP_SE = 0.01
LOOP_NOISE_BAND = 0.4  # the loop noise's level is read off the residual above this fraction of Nyquist
INIT_SCALE = {"x0": 1e-3, "dp0": 1e5, "v0": 1e-3}
#: the weighting unit of an output whose units follow the record, as a fraction of its rms variation (a weight
#: only: the estimates do not depend on it, and the diagnosis's statistics are whitened)
RELATIVE_NOISE = 1e-3
#: a fit whose Fit % of an output is at or below this explains almost nothing of it: converged or not, the
#: result carries a warning (Fit % = 100 (1 - |e| / |y - mean y|): 10 % leaves 81 % of the variance)
FIT_WARN_PCT = 10.0


@dataclasses.dataclass
class _Problem:
    model: Model
    base: ParameterSet
    free: tuple[str, ...]
    specs: tuple[ParamSpec, ...]
    records: list[Record]
    drives: list[tuple[str, np.ndarray]]
    outputs: tuple[str, ...]
    sigma: dict[str, float]
    init_names: tuple[str, ...]
    init_fixed: list[dict[str, float]]
    substeps: int | None
    timing: Timing
    kidx: np.ndarray  # kernel index of each free parameter
    scale: np.ndarray  # linear scale per free coordinate (0 for log coordinates)
    base_vec: np.ndarray
    #: per record: the loop noise the simulated controller reads, in antithetic pairs (None: a noise-free loop)
    dither: list[np.ndarray | None] = dataclasses.field(default_factory=list)
    #: per record and output: 1 at fresh samples, 0 at held ones (None: every sample is a measurement)
    weights: list[dict[str, np.ndarray]] = dataclasses.field(default_factory=list)
    #: per record: its logged signals that set a parameter sample by sample (the oil temperature ``T_oil``)
    exo: list[dict[str, np.ndarray]] = dataclasses.field(default_factory=list)

    def weight(self, r: int, o: str) -> np.ndarray | None:
        return self.weights[r].get(o) if self.weights else None

    def fresh(self, r: int, o: str) -> np.ndarray:
        """Which samples of output ``o`` of record ``r`` are measurements."""
        w = self.weight(r, o)
        return np.ones(len(self.records[r]), bool) if w is None else w > 0

    def n_measured(self) -> int:
        """The number of residuals that are measurements (held samples weigh nothing)."""
        return sum(int(np.count_nonzero(self.fresh(r, o))) for r in range(len(self.records)) for o in self.outputs)

    @property
    def n_theta(self) -> int:
        return len(self.free)

    @property
    def n_z(self) -> int:
        return self.n_theta + len(self.init_names) * len(self.records)

    # --- coordinates ---------------------------------------------------------------
    def to_z(self, theta: np.ndarray, init: np.ndarray) -> np.ndarray:
        z = np.where(self.scale == 0, np.log(np.maximum(theta, 1e-300)), theta / np.where(self.scale == 0, 1, self.scale))
        zi = init.ravel() / np.array([INIT_SCALE[n] for n in self.init_names] * len(self.records)) if init.size else np.zeros(0)
        return np.concatenate([z, zi])

    def from_z(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        zt = z[..., : self.n_theta]
        log = self.scale == 0
        theta = np.where(log, np.exp(np.where(log, zt, 0.0)), zt * self.scale)  # exp of log coordinates only
        zi = z[..., self.n_theta:]
        if self.init_names:
            s = np.array([INIT_SCALE[n] for n in self.init_names] * len(self.records))
            init = (zi * s).reshape(z.shape[:-1] + (len(self.records), len(self.init_names)))
        else:
            init = np.zeros(z.shape[:-1] + (len(self.records), 0))
        return theta, init

    def dtheta_dz(self, theta: np.ndarray) -> np.ndarray:
        return np.where(self.scale == 0, theta, self.scale)

    def bounds_z(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.array([math.log(s.lo) if sc == 0 else s.lo / sc for s, sc in zip(self.specs, self.scale)])
        hi = np.array([math.log(s.hi) if sc == 0 else s.hi / sc for s, sc in zip(self.specs, self.scale)])
        ni = self.n_z - self.n_theta
        return np.concatenate([lo, np.full(ni, -np.inf)]), np.concatenate([hi, np.full(ni, np.inf)])

    # --- residuals of a batch of coordinate vectors ------------------------------------
    def residuals(self, Z: np.ndarray) -> np.ndarray:
        """Weighted residuals ``[K, N]`` of ``K`` coordinate vectors (one batched simulation per record)."""
        Z = np.atleast_2d(Z)
        theta, init = self.from_z(Z)
        P = np.repeat(self.base_vec[None, :], Z.shape[0], axis=0)
        P[:, self.kidx] = theta
        parts = []
        for r, rec in enumerate(self.records):
            S0 = np.concatenate([self.model.initial_state(P[k:k + 1], self._init_of(init[k, r], r))
                                 for k in range(Z.shape[0])]) if (self.init_names or self.init_fixed[r]) else None
            sim = self._simulate(r, P, S0)
            for o in self.outputs:
                e = (sim.outputs[o] - rec[o][None, :]) / self.sigma[o]
                w = self.weight(r, o)
                parts.append(e if w is None else e * w)
        return np.concatenate(parts, axis=1)

    def _simulate(self, r: int, P: np.ndarray, S0: np.ndarray | None):
        """Simulate record ``r`` for the parameter vectors ``P``; with a dither, the mean of the two loops whose
        controller reads the simulated displacement plus and minus the loop noise (the mean keeps the noise's
        even-order effect on the rig, the dithered friction, and cancels its first-order one)."""
        name, drive = self.drives[r]
        dt = self.records[r].dt
        d = self.dither[r] if self.dither else None
        exo = self.exo[r] if self.exo else None
        if d is None:
            return self.model.simulate_batch(P, name, drive, dt, S0, self.substeps, self.timing, exo)
        # the controller's error is demand - (x + n): the noise enters as a demand shifted by -n
        lo = self.model.simulate_batch(P, name, drive - d, dt, S0, self.substeps, self.timing, exo)
        hi = self.model.simulate_batch(P, name, drive + d, dt, S0, self.substeps, self.timing, exo)
        for o in lo.outputs:
            lo.outputs[o] = 0.5 * (lo.outputs[o] + hi.outputs[o])
        lo.states[...] = 0.5 * (lo.states + hi.states)
        if "u" in lo.inputs and name != "u":
            lo.inputs["u"] = 0.5 * (lo.inputs["u"] + hi.inputs["u"])
        lo.inputs[name] = drive
        return lo

    def loop_noise(self, z: np.ndarray, seed: int = 0) -> list[np.ndarray | None]:
        """Per record: a white noise at the level of the displacement noise the controller read, drawn from
        ``seed`` (``None`` for a record whose controller is not simulated, reads the sensor more often than the
        log samples it, or whose displacement is not fitted).

        The level comes from the high band of the residuals at ``z`` (above :data:`LOOP_NOISE_BAND` of the
        Nyquist frequency, where the loop and the model's error leave the sensor noise alone): of the logged
        controller output, through the digital PID's gain, when the record has it (noise added to the log
        after the controller, which never shook the rig, then counts for nothing), else of the displacement.
        Not the residual itself: below that band it is the noise through the loop's sensitivity plus the
        model's error, and that error, correlated with the noise, exaggerates the dither several times over
        (measured on the reference simulator)."""
        if "x" not in self.outputs:
            return [None] * len(self.records)
        rng = np.random.default_rng(seed)
        out: list[np.ndarray | None] = []
        preds = None  # simulated only when a record needs them (an analog controller's never does)
        for r, rec in enumerate(self.records):
            if self.drives[r][0] != "x_ref" or self.timing.ticks(rec.dt) != 1:
                out.append(None)  # no simulated controller, or one reading the sensor between logged samples
                continue
            if preds is None:
                preds = self.predict(z)
            pr = preds[r]
            n = len(rec)
            w = np.pi * np.arange(n // 2 + 1) / (n // 2)  # rfft frequencies, rad per sample
            band = w >= LOOP_NOISE_BAND * np.pi
            q = 1.0 - np.exp(-1j * w[band])
            ctrl = self.model.controller_response(self.base, q, rec.dt)  # None: the model has no digital controller
            if "u" in rec and "u" in pr and ctrl is not None:
                e = np.asarray(rec["u"] - pr["u"], dtype=np.float64)
                gain = np.abs(ctrl)
            else:
                e = np.asarray(rec["x"] - pr["x"], dtype=np.float64)
                gain = np.ones(int(band.sum()))
            f = np.fft.rfft(e - e.mean())[band] / np.maximum(gain, 1e-300)
            level = math.sqrt(2.0 * float(np.sum(np.abs(f) ** 2)) / (n * n * band.mean()))
            out.append(rng.normal(0.0, level, n))
        return out

    def block_sizes(self) -> list[tuple[int, int]]:
        """``(n_outputs, n_samples)`` per record, in the order :meth:`residuals` concatenates them."""
        return [(len(self.outputs), len(rec)) for rec in self.records]

    def _init_of(self, vals: np.ndarray, r: int) -> dict[str, float]:
        d = dict(self.init_fixed[r])
        d.update({n: float(v) for n, v in zip(self.init_names, vals)})
        return d

    def predict(self, z: np.ndarray) -> list[dict[str, np.ndarray]]:
        theta, init = self.from_z(z[None, :])
        P = self.base_vec[None, :].copy()
        P[:, self.kidx] = theta
        out = []
        for r in range(len(self.records)):
            S0 = self.model.initial_state(P, self._init_of(init[0, r], r))
            sim = self._simulate(r, P, S0)
            out.append({o: sim.outputs[o][0] for o in self.model.OUTPUTS} | {k: np.asarray(v)[0] if np.ndim(v) == 2 else v
                                                                             for k, v in sim.inputs.items()})
        return out


def _linear_scale(model: Model, spec: ParamSpec, value: float) -> float:
    """Order of magnitude of a linearly scaled coordinate: typical size, start value, or range."""
    typical = spec.typical
    effect = model.effect_of(spec.name)
    if typical is None and effect is not None:
        e = model.EFFECTS[effect]
        typical = e.typical[e.names.index(spec.name)]
    for c in (typical, value, spec.hi - spec.lo):
        if c is not None and c != 0 and math.isfinite(c):
            return abs(c)
    return 1.0


def resolve_outputs(model: Model, records: Sequence[Record], outputs: Sequence[str] | None) -> tuple[str, ...]:
    """The outputs to fit: those asked for (checked), or every model output all records have."""
    if outputs is None:
        outputs = tuple(o for o in model.OUTPUTS if all(o in r for r in records))
        if not outputs:
            raise DataError(f"no record has any of the outputs {', '.join(model.OUTPUTS)} of {model.name}")
    outputs = tuple(outputs)
    check_names(model.OUTPUTS, outputs, f"output of {model.name}")
    return outputs


def make_problem(model: Model | str, records: Sequence[Record], free: Sequence[str],
                 base: ParameterSet | None = None, outputs: Sequence[str] | None = None,
                 noise: Mapping[str, float] | None = None, drive: str = "auto",
                 estimate_init: Sequence[str] = (), init: Sequence[Mapping[str, float]] | None = None,
                 substeps: int | None = None, timing: Timing | None = None,
                 scales: Mapping[str, float] | None = None) -> _Problem:
    model = get_model(model) if isinstance(model, str) else model
    base = base or model.params()
    if not records:
        raise DataError("fit needs at least one record")
    free = tuple(dict.fromkeys(free))
    if not free:
        raise ParameterError("fit needs at least one free parameter")
    check_names(base.names, free, f"free parameter of {model.name} (with effects {list(base.effects)})")
    outputs = resolve_outputs(model, records, outputs)
    drives = []
    for r in records:
        r.require(outputs, f"fitting outputs {', '.join(outputs)}")
        model.check_record(base, r.signals, r.name)
        check_lengths(model, base, r.signals, r.name)  # a column in mm read as metres
        drives.append(model.drive_signal(r.signals, drive))
    check_names(model.INIT, estimate_init, f"initial-state quantity of {model.name}")
    if init is None:
        init = [initial_from_data(model, r, base) for r in records]
        moving = [q for q in model.INIT_IF_MOVING if any(q in i for i in init)]
        estimate_init = tuple(dict.fromkeys((*estimate_init, *moving)))
    sigma = noise_levels(model, records, outputs, noise)
    for o, s in sigma.items():
        if not s > 0:
            raise DataError(f"noise level of output {o!r} must be > 0 to weight residuals, got {s}")
    specs = tuple(base.spec(n) for n in free)
    kidx = np.array([model.kernel_index(n) for n in free])
    scales = {n: abs(float(v)) for n, v in (scales or {}).items() if v and math.isfinite(v)}
    scale = np.array([0.0 if s.log_scaled else scales.get(s.name) or _linear_scale(model, s, base[s.name])
                      for s in specs])
    init_fixed = [dict(i) for i in init]
    weights = []
    for r in records:
        w = {o: r.fresh_of(o) for o in outputs}
        weights.append({o: m.astype(np.float64) for o, m in w.items() if m is not None})
    exo = [model.exogenous_of(r.signals) for r in records]
    for r, e in zip(records, exo):
        for k, v in e.items():
            model.exogenous_table({k: v}, len(r))  # a value outside its parameter's range: refused here
        for k in e:
            par = model.FILTER.exogenous[k] if model.FILTER is not None else k
            if par in free:
                raise ParameterError(f"{par} is set sample by sample from {r.name}'s logged {k}: it cannot be free")
    return _Problem(model, base, free, specs, list(records), drives, outputs, sigma, tuple(estimate_init),
                    init_fixed, substeps, timing or DEFAULT_TIMING, kidx, scale, model.vector(base),
                    weights=weights, exo=exo)


def noise_levels(model: Model, records: Sequence[Record], outputs: Sequence[str],
                 noise: Mapping[str, float] | None = None) -> dict[str, float]:
    """The noise level that weights each output's residuals: as given, else the sensor's default for a
    model whose outputs are physical quantities of known sensors, else (``Model.NOISE_FROM_DATA``: the
    units follow the record, volts as well as metres) a fixed fraction, ``RELATIVE_NOISE``, of the output's
    rms variation on the records, so that the same record in other units or rescaled is weighed alike."""
    out = {}
    for o in outputs:
        if noise and o in noise:
            out[o] = float(noise[o])
        elif model.NOISE_FROM_DATA:
            y = np.concatenate([np.asarray(r[o], dtype=np.float64) for r in records if o in r])
            rms = float(np.std(y)) if y.size else 0.0
            out[o] = RELATIVE_NOISE * rms if rms > 0 and math.isfinite(rms) else NOMINAL_NOISE.get(o, 1.0)
        else:
            out[o] = float(NOMINAL_NOISE.get(o, 1.0))
    return out


def initial_from_data(model: Model, rec: Record, base: ParameterSet) -> dict[str, float]:
    """Where the record starts: its measured state, and for a loaded rig without logged pressures the
    pressure difference that carries the load (a fit may refine it with ``estimate_init``)."""
    init = model.initial_from_data(rec.signals, rec.dt)
    if "pA0" in model.INIT and "pA0" not in init and "pB0" not in init and base["Fext"] != 0:
        init["dp0"] = base["Fext"] / base["A"]
    return init


def _starts(prob: _Problem, start: Mapping[str, float], n: int, seed: int, spread: float) -> np.ndarray:
    """Start vectors in fit coordinates: the given start, a Latin hypercube of ``n - 1`` around it, then
    (``n > 1``) the starts the model reads off the data and ``n`` drawn log-uniformly over the whole bounds
    of the log-scaled free parameters (the others at the start)."""
    Z = _local_starts(prob, start, n, seed, spread)
    if n <= 1:
        return Z
    extra = []
    for rec in prob.records[:1]:
        for d in prob.model.starts_from_data(rec.signals, rec.dt):
            if any(f in d for f in prob.free):
                # the model's own response read off the data, its extensions switched off (at neutral)
                d = {**{n: v for e in prob.base.effects for n, v in
                        zip(prob.model.EFFECTS[e].names, prob.model.EFFECTS[e].neutral)}, **d}
                z = Z[0].copy()
                for j, f in enumerate(prob.free):
                    if f in d:
                        z[j] = (math.log(max(d[f], prob.specs[j].lo)) if prob.scale[j] == 0
                                else d[f] / prob.scale[j])
                extra.append(z)
    lo, hi = prob.bounds_z()
    logs = [j for j in range(prob.n_theta) if prob.scale[j] == 0 and np.isfinite(lo[j]) and np.isfinite(hi[j])]
    if logs:
        rng = np.random.default_rng(seed + 1)
        u = (rng.permuted(np.tile(np.arange(n), (len(logs), 1)), axis=1).T + rng.uniform(size=(n, len(logs)))) / n
        G = np.repeat(Z[:1], n, axis=0)
        for c, j in enumerate(logs):
            G[:, j] = lo[j] + (hi[j] - lo[j]) * u[:, c]
        extra.extend(G)
    if not extra:
        return Z
    fin_lo, fin_hi = np.isfinite(lo), np.isfinite(hi)
    E = np.clip(np.array(extra), np.where(fin_lo, lo + 1e-9 * (np.abs(np.where(fin_lo, lo, 0.0)) + 1), -np.inf),
                np.where(fin_hi, hi - 1e-9 * (np.abs(np.where(fin_hi, hi, 0.0)) + 1), np.inf))
    return np.vstack([Z, E])


def _local_starts(prob: _Problem, start: Mapping[str, float], n: int, seed: int, spread: float) -> np.ndarray:
    """``n`` start vectors in fit coordinates: the given start, then a Latin hypercube around it."""
    theta0 = np.array([start[f] for f in prob.free])
    init0 = np.array([[prob.init_fixed[r].get(q, 0.0) for q in prob.init_names] for r in range(len(prob.records))])
    z0 = prob.to_z(theta0, init0)
    if n <= 1:
        return z0[None, :]
    rng = np.random.default_rng(seed)
    d = prob.n_theta
    u = (rng.permuted(np.tile(np.arange(n - 1), (d, 1)), axis=1).T + rng.uniform(size=(n - 1, d))) / (n - 1)
    f = np.exp(np.log(spread) * (2 * u - 1))  # multiplicative factors in [1/spread, spread]
    lo, hi = prob.bounds_z()
    Z = np.repeat(z0[None, :], n, axis=0)
    for j in range(d):
        if prob.scale[j] == 0:
            Z[1:, j] = z0[j] + np.log(f[:, j])
        else:
            Z[1:, j] = z0[j] * f[:, j] if z0[j] != 0 else (2 * u[:, j] - 1) * spread
    fin = np.isfinite(lo)  # initial-state coordinates are unbounded
    lo_in = np.where(fin, lo + 1e-9 * (np.abs(np.where(fin, lo, 0.0)) + 1), -np.inf)
    fin = np.isfinite(hi)
    hi_in = np.where(fin, hi - 1e-9 * (np.abs(np.where(fin, hi, 0.0)) + 1), np.inf)
    return np.clip(Z, lo_in, hi_in)


class _Converged(Exception):
    """Raised from the Jacobian's callback: the refinement has converged at ``z`` by :data:`STEP_SE`."""

    def __init__(self, z: np.ndarray) -> None:
        super().__init__("converged")
        self.z = np.array(z, dtype=float)


def _step_within_noise(J: np.ndarray, r: np.ndarray, n: int, lo: np.ndarray, hi: np.ndarray,
                       z: np.ndarray) -> bool:
    """Whether the Gauss-Newton step from ``z`` (Jacobian ``J`` [N, p], residuals ``r``) is shorter than
    :data:`STEP_SE` standard errors in every direction, ``||J step||^2 / s^2 < STEP_SE^2`` with ``s^2`` the
    residuals' variance, and stays inside the bounds (a step a bound blocks is left to the trust region)."""
    p = J.shape[1]
    s2 = float(r @ r) / max(n - p, 1)
    if not (s2 > 0.0 and np.all(np.isfinite(J))):
        return False
    step, *_ = np.linalg.lstsq(J, -r, rcond=None)
    if not np.all(np.isfinite(step)) or np.any(z + step <= lo) or np.any(z + step >= hi):
        return False
    Js = J @ step
    return float(Js @ Js) / s2 < STEP_SE * STEP_SE


@one_blas_thread
def fit(model: Model | str, records: Sequence[Record] | Record, free: Sequence[str],
        base: ParameterSet | None = None, start: Mapping[str, float] | None = None,
        outputs: Sequence[str] | None = None, noise: Mapping[str, float] | None = None,
        drive: str = "auto", estimate_init: Sequence[str] = (),
        init: Sequence[Mapping[str, float]] | None = None, n_starts: int = 8, n_refine: int = 2,
        spread: float = 2.0, seed: int = 0, max_nfev: int = 60, tol: float = 1e-12,
        substeps: int | None = None, progress: Callable[[str], None] | None = None,
        timing: Timing | None = None, loop_noise: bool = True,
        scales: Mapping[str, float] | None = None, hac_lag_s: float = 0.0) -> FitResult:
    """Fit ``free`` parameters of ``model`` to ``records`` by output-error least squares.

    The fit alone: ``twin.fit`` (:func:`twin.estimation.fit_checked.fit`, what ``twin fit`` and a commissioning
    run) adds the adequacy test of the fitted model.

    ``base`` holds the known parameters (and switched-on effects); ``start`` the
    starting values of the free ones (default: ``base``'s values).  ``n_starts``
    candidates are screened in one batch and the best ``n_refine`` refined.
    ``init``: initial-state quantities per record (default: read off the data);
    ``timing``: the loop's timing (default: a digital controller at the log's
    rate, inputs held between samples).  ``loop_noise``: a closed loop's
    controller reads the noisy sensor, which dithers the rig (above all its
    friction at reversals) in a way a noise-free simulated loop cannot show; the
    fit then refines once more with the noise read off the displacement
    residual fed to the simulated controller, averaged over the two signs
    (module docstring).  ``scales``: the order of magnitude of linearly
    scaled free parameters (default: their typical sizes in the catalogue).
    ``hac_lag_s``: the shortest span (s) of residual autocorrelation the
    standard errors count (default: the automatic lag alone).
    """
    t_start = time.perf_counter()
    if isinstance(records, Record):
        records = [records]
    prob = make_problem(model, records, free, base, outputs, noise, drive, estimate_init, init, substeps, timing,
                        scales)
    start = {**prob.base.as_dict(), **(start or {})}
    for n in prob.free:
        prob.base.spec(n).check(start[n])
    lo, hi = prob.bounds_z()
    Z0 = _starts(prob, start, max(1, n_starts), seed, spread)
    # screen all candidates in one batched simulation
    with np.errstate(over="ignore", invalid="ignore"):  # a start far off may diverge: its cost is infinite
        R0 = prob.residuals(Z0)
        costs0 = 0.5 * np.sum(R0 * R0, axis=1)
    costs0 = np.where(np.isfinite(costs0), costs0, np.inf)
    # the best n_refine of the starts around the given values are refined, and the best of the starts over the
    # whole ranges and from the data when it screens lower than all of those (a far start's screened cost says
    # less than a near one's: it is refined in addition, never instead)
    n_local = min(max(1, n_starts), Z0.shape[0])
    order = list(np.argsort(costs0[:n_local])[: max(1, n_refine)])
    if Z0.shape[0] > n_local:
        far = n_local + int(np.argmin(costs0[n_local:]))
        if costs0[far] < costs0[order[0]]:
            order.insert(0, far)
    starts_info = [{"theta": dict(zip(prob.free, prob.from_z(Z0[i])[0].tolist())), "cost": float(costs0[i]),
                    "refined": bool(i in order)} for i in range(Z0.shape[0])]
    if progress:
        progress(f"screened {Z0.shape[0]} starts in one batch; refining the best {len(order)}")

    history: list[dict] = []
    nfev_total = 0
    #: residuals (and their finite-difference neighbours) of the last points evaluated under the current problem:
    #: the result's Jacobian at the solution is one of them, not simulated again
    evaluated: dict[bytes, np.ndarray] = {}

    def refine(z_start: np.ndarray, rank: int):
        cache: dict = {}  # the residuals at the last point, and its finite-difference neighbours once asked for
        calls = [0]

        def fun(z):
            key = z.tobytes()
            if key not in cache:
                cache.clear()
                cache[key] = prob.residuals(z[None, :])  # a step tried: its residuals alone (a rejected one
                calls[0] += 1                              # never needs the Jacobian)
            return cache[key][0]

        def jac(z):
            fun(z)
            key = z.tobytes()
            R = cache[key]
            if R.shape[0] == 1:  # the step was taken: its Jacobian by finite differences, in one batch
                R = cache[key] = np.vstack([R, prob.residuals(z + FD_STEP * np.eye(prob.n_z))])
            evaluated[key] = R
            while len(evaluated) > 4:
                evaluated.pop(next(iter(evaluated)))
            J = ((R[1:] - R[0]) / FD_STEP).T
            th = prob.from_z(z)[0]
            history.append({"start": rank, "iteration": len([h for h in history if h["start"] == rank]),
                            "cost": float(0.5 * R[0] @ R[0]), "theta": dict(zip(prob.free, th.tolist()))})
            if progress:  # a person reads it: each value in its display unit (``wn=43.0051 Hz``)
                progress(f"start {rank}: iteration {history[-1]['iteration']:3d} cost {history[-1]['cost']:.6g} "
                         + ", ".join(f"{s.name}={s.show(v)}" for s, v in zip(prob.specs, th.tolist())))
            if _step_within_noise(J, R[0], prob.n_measured(), lo, hi, z):
                raise _Converged(z)
            return J

        try:
            res = optimize.least_squares(fun, z_start, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                                         ftol=tol, xtol=tol, gtol=tol, max_nfev=max_nfev)
        except _Converged as done:
            r = cache[done.z.tobytes()][0]
            res = optimize.OptimizeResult(
                x=done.z, cost=0.5 * float(r @ r), fun=r, status=2, success=True,
                message=f"converged: the remaining Gauss-Newton step is under {STEP_SE:g} of a standard error")
        last = cache.get(np.asarray(res.x).tobytes())
        if last is not None:  # the residuals at the solution (its neighbours too when asked for): not simulated again
            evaluated[np.asarray(res.x).tobytes()] = last
        res.nfev = calls[0]
        return res

    best = None
    for rank, i in enumerate(order):
        try:
            res = refine(Z0[i], rank)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
            starts_info[i]["error"] = str(exc)
            continue
        nfev_total += int(res.nfev)
        starts_info[i]["final_cost"] = float(res.cost)
        if best is None or res.cost < best.cost:
            best = res
        if best.cost <= 0.75 * prob.n_measured():  # residuals at the noise floor: other starts cannot do better
            break
    if best is None:  # every refinement failed numerically: report the best screened start
        z = Z0[order[0]]
        r = prob.residuals(z[None, :])[0]
        best = optimize.OptimizeResult(x=z, cost=0.5 * float(r @ r), fun=r, status=-1, success=False,
                                       message="every refinement failed numerically", nfev=0)
    elif loop_noise:
        dither = prob.loop_noise(best.x, seed)
        if any(d is not None for d in dither):
            # the controller read the noisy sensor: refine again with that noise in the simulated loop
            prob.dither = dither
            evaluated.clear()  # another problem: those residuals were without the loop noise
            if progress:
                progress("refining with the loop noise read off the displacement residual")
            try:
                res = refine(best.x, len(order))
                nfev_total += int(res.nfev)
                best = res
            except (ValueError, np.linalg.LinAlgError, FloatingPointError):
                prob.dither = []
                evaluated.clear()
    min_lag = int(math.ceil(hac_lag_s / min(rec.dt for rec in prob.records))) if hac_lag_s > 0 else 0
    return _result(prob, best, history, starts_info, nfev_total, time.perf_counter() - t_start,
                   evaluated.get(np.asarray(best.x).tobytes()), min_lag)


def _result(prob: _Problem, res, history, starts_info, nfev, elapsed, R: np.ndarray | None = None,
            min_lag: int = 0) -> FitResult:
    """The fit's result at ``res.x``; ``R``: the residuals there and at its finite-difference neighbours when the
    refinement evaluated them already."""
    z = res.x
    theta, init = prob.from_z(z)
    if R is None:
        R = prob.residuals(np.vstack([z, z + FD_STEP * np.eye(prob.n_z)]))
    elif R.shape[0] == 1:
        R = np.vstack([R, prob.residuals(z + FD_STEP * np.eye(prob.n_z))])
    r = R[0]
    J = ((R[1:] - r) / FD_STEP).T
    N = prob.n_measured()
    p = prob.n_z
    s2 = float(r @ r) / max(N - p, 1)
    g = np.concatenate([prob.dtheta_dz(theta), np.ones(p - prob.n_theta)])
    try:
        H_inv = np.linalg.pinv(J.T @ J)
        cov_white = s2 * H_inv * np.outer(g, g)
        cov = hac_covariance(J, r, prob.block_sizes(), H_inv, N, min_lag) * np.outer(g, g)
    except np.linalg.LinAlgError:
        cov_white = cov = np.full((p, p), np.nan)
    ct = cov[: prob.n_theta, : prob.n_theta]
    std = np.sqrt(np.clip(np.diag(ct), 0, None))
    std_white = np.sqrt(np.clip(np.diag(cov_white)[: prob.n_theta], 0, None))
    # a parameter held at a bound has no meaningful standard error: say so
    lo, hi = prob.bounds_z()
    zt = z[: prob.n_theta]
    at_bound = [n for n, zi, a, b in zip(prob.free, zt, lo, hi) if min(zi - a, b - zi) < 1e-6]  # z is order one
    std = np.where([n in at_bound for n in prob.free], np.nan, std)
    std_white = np.where([n in at_bound for n in prob.free], np.nan, std_white)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = ct / np.outer(std, std)
    ps = prob.base.update(dict(zip(prob.free, theta.tolist())))
    pred = prob.predict(z)
    fit_pct, mse, nrmse = {}, {}, {}
    loglik = 0.0
    for o in prob.outputs:
        keep = [prob.fresh(i, o) for i in range(len(prob.records))]
        y = np.concatenate([rec[o][k] for rec, k in zip(prob.records, keep)])
        yh = np.concatenate([pr[o][k] for pr, k in zip(pred, keep)])
        e = y - yh
        m = float(np.mean(e * e))
        den = float(np.linalg.norm(y - y.mean()))
        fit_pct[o] = 100.0 * (1.0 - float(np.linalg.norm(e)) / den) if den > 0 else float("nan")
        nrmse[o] = float(np.sqrt(m)) / float(np.std(y)) if np.std(y) > 0 else float("nan")
        mse[o] = m
        loglik += -0.5 * y.size * (math.log(2 * math.pi * max(m, 1e-300)) + 1.0)
    n_out = len(prob.outputs)
    n_obs = N
    aic = -2 * loglik + 2 * p
    aicc = aic + 2 * p * (p + 1) / max(n_obs - p - 1, 1)
    bic = -2 * loglik + p * math.log(n_obs)
    v = float(np.prod([mse[o] for o in prob.outputs])) ** (1.0 / n_out)
    fpe = v * (1 + p / n_obs) / (1 - p / n_obs) if n_obs > p else float("inf")
    init_list = [prob._init_of(init[r], r) for r in range(len(prob.records))]
    warnings = [f"Fit({o}) = {fit_pct[o]:.1f} %: the model explains almost none of this output (at most "
                f"{FIT_WARN_PCT:g} %); the estimates are not to be trusted: check the rig's geometry, controller "
                "and loop timing" for o in prob.outputs if not fit_pct[o] > FIT_WARN_PCT]
    message = str(res.message) + (f"; at a bound (no standard error): {', '.join(at_bound)}" if at_bound else "")
    message += "".join(f"; WARNING {w}" for w in warnings)
    return FitResult(
        model=prob.model.name, params=ps, free=prob.free, estimate=dict(zip(prob.free, theta.tolist())),
        std=dict(zip(prob.free, std.tolist())), corr=corr, outputs=prob.outputs, fit_pct=fit_pct, mse=mse,
        nrmse=nrmse, loglik=loglik, aic=aic, aicc=aicc, bic=bic, fpe=fpe, n_obs=n_obs, n_par=p,
        cost=float(res.cost), success=bool(res.status > 0), status=int(res.status),
        message=message, nfev=nfev, history=history, starts=starts_info, init=init_list, time_s=elapsed,
        predicted=pred, std_white=dict(zip(prob.free, std_white.tolist())), timing=prob.timing.to_dict(),
        warnings=warnings, noise=dict(prob.sigma))
