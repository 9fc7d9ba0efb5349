"""The online tracker: the compiled UKF (:mod:`twin.online.ukf`) behind a block-by-block interface.

``OnlineTracker.process(samples)`` filters a block of :class:`replay.base.Samples`
(any length, from one sample to a whole record) in one compiled call and
returns a :class:`TrackBlock`: per sample the tracked parameters in SI with
their standard deviations, NIS, log-likelihood, the filter's status, the
consistency guard's verdict (``hold``: the drift test must not count this
sample as evidence, ``guard``: why), each sensor's status, and which
parameters were frozen for lack of excitation.  The filter state carries over
from block to block, so the live service and the offline replay run the same
code.

Time is read from the timestamps: the filter predicts across the real time
between samples (dropped rows, lost frames), and re-initialises the model
states from the measurement after a gap longer than ``gap_max`` seconds.

The tracked parameters move between physical bounds with a random walk whose
intensity is the expected drift rate of each parameter; both are declared
beside the parameter's spec in the model (:class:`twin.params.Tracking`; physical caps such as a
stall force in the model's :meth:`~twin.models.base.Model.tracking_bounds`).  Everything else the filter needs
of the rig comes from the model too (:attr:`~twin.models.base.Model.FILTER`, :meth:`~twin.models.base.Model.
filter_map`): state scales, measurement map, process and prior noise, excitation thresholds, physical ranges.

A logged exogenous signal the model declares (``FILTER.exogenous``, e.g. an oil temperature ``T_oil``) sets
its parameter sample by sample where it is fresh and physical; the last fresh value holds between a slow
signal's samples and into the next block.

Sensor noise is a property of the rig: ``noise=`` (standard deviations, SI),
else the commissioning fit's residual RMS, else the model's nominal (``FILTER.noise``); the
filter learns it online (and its colour) from the innovations unless
``adapt_noise=False``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
import types

import numpy as np

from replay.base import Samples
from twin.online import chi2, sigma, split, ukf
from fpdd.errors import DataError, FilterError, ParameterError
from twin.models import DEFAULT_MODEL, get_model, trackable_models
from twin.models.base import Timing
from twin.params import EXCITATION

#: prior standard deviation of the parameters (log units): +-50 % starting errors are inside 1 sigma
DEFAULT_PRIOR_STD = 0.7
#: guard, noise-learning and sensor-fault settings (see twin.online.ukf); override with ``guard={...}``
DEFAULT_GUARD = {
    "nis_clip": 10.0,       # a sample's NIS per measurement counts at most this much in the guard's average
    "nis_hi": 2.0,          # average NIS per measurement above which the filter is inconsistent
    "rho_hi": 0.4,          # |lag-one autocorrelation| of normalised innovations above which it is inconsistent
    "tau_guard": 2.0,       # s, the guard's averaging time
    "div_nis": 200.0,       # fast-average NIS per measurement that means divergence
    "tau_div": 0.2,         # s
    "settle_s": 2.0,        # s the drift test holds after a re-initialisation or a recovery
    "checkpoint_s": 1.0,    # s of uninterrupted consistency before a checkpoint is taken
    "inflate": 4.0,         # parameter covariance factor after a re-initialisation or recovery
    "gap_max": 0.05,        # s: a longer gap re-initialises the model states from the measurement
    "tau_noise": 2.0,       # s, noise learning time constant
    "adapt": 1.0,           # learn the noise online (0: keep it)
    "noisy_factor": 5.0,    # learnt noise beyond this factor of the nominal: the sensor is 'noisy'
    "outlier_nu": 8.0,      # one output this many sigma off while another agrees: that output is suspect
    "offset_n": 20,         # suspect samples in a row: 'offset'
    "stuck_n": 20,          # the same value this many times while the model moves: 'stuck'
    "clear_n": 200,         # consistent samples in a row that clear a sensor fault
    "z_pin": 9.0,           # |logit| beyond which a parameter is pinned at a bound (divergence)
    "sig_lo": 0.2, "sig_hi": 50.0,  # learnt noise stays within these factors of the nominal
    "a_max": 0.99,          # largest AR(1) coefficient of the noise
    "warm_s": 1.0,          # s at the start during which the guard's averages fill
    # the predicted mean: the central sigma point's prediction (1; filterpy's x_mean_fn returning sigmas[0]) or
    # the points' weighted mean (0), and each innovation's weight in the noise learning by the sensor noise's
    # share of its variance (1) or in full (0); docs/explanation/tracking-and-alarms.md, "The central mean": with a parameter not yet
    # pinned by the data the weighted mean (centre weight -10.1) biases the stiff pressures by tens of kPa, and a
    # wide prior makes the plain learning halve the sensors' noise at a start
    "central_mean": 1.0,
    "noise_share": 1.0,
}
_GUARD_ORDER = ukf.CFG_NAMES
assert set(_GUARD_ORDER) == set(DEFAULT_GUARD)


_STATUS_NAMES = np.array(ukf.STATUS)
_GUARD_NAMES = np.array(ukf.GUARD)
_SENSOR_NAMES = np.array(ukf.SENSOR)


@dataclasses.dataclass
class TrackBlock:
    t_ns: np.ndarray            # [T]
    estimates: np.ndarray       # [T, p] SI
    stds: np.ndarray            # [T, p] SI (delta method on the logit coordinates)
    log_std: np.ndarray         # [T, p] relative standard deviation
    nis: np.ndarray             # [T]
    loglik: np.ndarray          # [T]
    status: np.ndarray          # [T] status names (twin.online.ukf.STATUS)
    frozen: np.ndarray          # [T, p] bool: no excitation, or zeta/wn not told apart (twin.online.split)
    innovation: np.ndarray      # [T, m] SI
    states: np.ndarray          # [T, ns] SI (the model's states)
    guard: np.ndarray | None = None    # [T] guard names (twin.online.ukf.GUARD); 'consistent' when the evidence counts
    sensors: np.ndarray | None = None  # [T, m] sensor status names (twin.online.ukf.SENSOR)
    noise: np.ndarray | None = None    # [T, m] learnt noise standard deviation (SI)
    outputs: tuple = ()
    used: np.ndarray | None = None     # [T, m] bool: the output entered the update (finite, no sensor fault, not suspect)
    held_stds: np.ndarray | None = None     # [T, p] SI: std of the estimate's error if the parameter has held still
    held_log_std: np.ndarray | None = None  # [T, p] the same, relative (see twin.online.ukf.held_variance)
    kernel_frozen: np.ndarray | None = None  # [T, p] bool: the filter's own freeze (no excitation: no gain); `frozen`
    #                                         adds what the drift test holds besides (zeta/wn not told apart)

    @property
    def interval_stds(self) -> np.ndarray:
        """[T, p] SI: the std behind the published 95 % intervals (:attr:`held_stds`; :attr:`stds` before it existed)."""
        return self.stds if self.held_stds is None else self.held_stds

    @property
    def hold(self) -> np.ndarray:
        """[T] bool: the drift test holds its evidence on these samples (the filter is not consistent)."""
        if self.guard is None:
            return np.zeros(len(self.t_ns), bool)
        return self.guard != "consistent"

    def __repr__(self) -> str:
        T, p = self.estimates.shape if self.estimates.ndim == 2 else (len(self.t_ns), 0)
        span = (int(self.t_ns[-1]) - int(self.t_ns[0])) * 1e-9 if T else 0.0
        last = str(self.status[-1]) if T else "-"
        return (f"TrackBlock({T} samples over {span:.3g} s, {p} parameters, outputs {', '.join(self.outputs) or '-'}; "
                f"last status {last})")

    def sensor_status(self, i: int = -1) -> dict[str, str]:
        """Each output's sensor status at sample ``i`` (default the last)."""
        if self.sensors is None or not len(self.t_ns):
            return {}
        return {o: str(self.sensors[i, j]) for j, o in enumerate(self.outputs)}


class OnlineTracker:
    """Augmented-state UKF of one rig; see the module docstring.

    ``model``: the rig model's name (default :data:`twin.models.DEFAULT_MODEL`);
    ``params``: known parameter overrides (the rig configuration); ``tracked``: the parameters to track
    (default: the model's phenomenological ones); ``start``:
    starting values of the tracked parameters (default: the configuration's);
    ``outputs``: which of the model's measured outputs to use when present (default: all); ``noise``: sensor noise
    standard deviations (SI) per output; ``timing``: the loop's
    :class:`~twin.models.base.Timing` (or its spelling ``"continuous"``,
    ``"digital:5000"``); ``guard``: overrides of :data:`DEFAULT_GUARD`; ``effects``: effects of the model's
    catalogue switched on (an extended model, e.g. a commissioning fit's ``specimen_stiffness``), their
    parameters in ``params``.
    ``points``: a sigma-point object (:class:`~twin.online.sigma.SigmaPoints`: Merwe's scaled points
    from ``alpha, beta, kappa`` by default; filterpy's ``MerweScaledSigmaPoints`` or
    ``JulierSigmaPoints`` are taken as they are).
    """

    def __init__(self, model: str = DEFAULT_MODEL, params: Mapping[str, float] | None = None,
                 tracked: Sequence[str] | None = None, dt: float | None = None,
                 start: Mapping[str, float] | None = None, outputs: Sequence[str] | None = None,
                 q_rate: Mapping[str, float] | None = None, q_state: np.ndarray | None = None,
                 prior_std: float = DEFAULT_PRIOR_STD, alpha: float = 0.3, beta: float = 2.0,
                 kappa: float = 0.0, points=None, substeps: int = 2, excite: Sequence[float] | None = None,
                 tau_excite: float = 0.5, gate_p: float = 1e-9, max_gated: int = 5,
                 noise: Mapping[str, float] | None = None, timing=None, adapt_noise: bool = True,
                 guard: Mapping[str, float] | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
                 noise_colour: Mapping[str, float] | None = None, effects: Sequence[str] = ()):
        self.model = get_model(model)
        if not self.model.TRACKABLE or self.model.FILTER is None:
            raise ParameterError(f"the online twin does not run the {model} model; it runs: "
                                 f"{', '.join(trackable_models())}")
        spec = self.model.FILTER
        self.ps = self.model.params(tuple(effects), **dict(params or {}))  # an extended model: effects switched on
        why = self.model.untracked(self.ps)
        if why:
            raise ParameterError(why)
        self.tracked = tuple(self.model.PHENOMENOLOGICAL if tracked is None else tracked)
        bad = [t for t in self.tracked if t not in self.model.trackable]
        if bad or not self.tracked:
            raise ParameterError(f"cannot track {bad or 'nothing'}; trackable: {', '.join(self.model.trackable)}")
        self.outputs = tuple(spec.measures if outputs is None else outputs)
        self.meas_index = dict(spec.measures)  # the model's measurement map: output -> state
        for o in self.outputs:
            if o not in self.meas_index:
                raise ParameterError(f"unknown measurement {o!r}; known: {', '.join(self.meas_index)}")
        self.units = tuple(self.ps.spec(t).unit for t in self.tracked)
        self.displays = tuple((self.ps.spec(t).display_unit or self.ps.spec(t).unit, float(self.ps.spec(t).display_scale))
                              for t in self.tracked)  # (display unit, scale) of each: value shown = SI x scale
        if isinstance(timing, str):
            timing = Timing.parse(timing)
        self.timing = timing or Timing()
        start = {**{t: self.ps[t] for t in self.tracked}, **dict(start or {})}
        self.ref = np.array([self.ps[t] for t in self.tracked])
        bnd = {t: self.model.tracking_bounds(self.ps, t) for t in self.tracked}
        for t, (lo, hi) in dict(bounds or {}).items():
            if t not in bnd:
                raise ParameterError(f"bounds for {t!r}, which is not tracked ({', '.join(self.tracked)})")
            if not (0 < lo < hi and math.isfinite(hi)):
                raise ParameterError(f"bounds of {t}: need 0 < lo < hi, got ({lo}, {hi})")
            bnd[t] = (float(lo), float(hi))
        self.bounds = bnd
        for t in self.tracked:
            self.ps.spec(t).check(start[t])
            lo, hi = bnd[t]
            if not lo < start[t] < hi:
                raise ParameterError(f"start value of {t} ({start[t]:g}) is outside its physical bounds "
                                     f"{lo:g} .. {hi:g}")
        self.lo_log = np.array([math.log(bnd[t][0]) for t in self.tracked])
        self.width = np.array([math.log(bnd[t][1] / bnd[t][0]) for t in self.tracked])
        self.idx = np.array([self.model.kernel_index(t) for t in self.tracked], dtype=np.int64)
        self.pvec = self.model.vector(self.ps)
        self.scale = np.array(spec.state_scale, dtype=float)
        self.ns = ns = self.scale.size
        self.dt = dt
        self.substeps = int(substeps)
        p, q = len(self.tracked), len(self.outputs)
        self.nmod = ns + p
        self.n = n = ns + p + q
        self.alpha, self.beta, self.kappa = alpha, beta, kappa
        self.points = points if points is not None else sigma.MerweWeights(n, alpha=alpha, beta=beta, kappa=kappa)
        try:
            spread = sigma.spread(self.points)
        except (AttributeError, IndexError, TypeError, ValueError) as e:
            raise ParameterError(f"sigma points {type(self.points).__name__}: the compiled filter needs an object "
                                 f"with n, Wm and Wc, as filterpy's MerweScaledSigmaPoints ({e})") from None
        if self.points.n != n:
            raise ParameterError(f"sigma points for n={self.points.n}, the filter has n={n} states "
                                 f"({ns} model states, {p} parameters, {q} sensor-noise states)")
        self.lam = spread - n
        self.Wm = np.ascontiguousarray(self.points.Wm, dtype=float)
        self.Wc = np.ascontiguousarray(self.points.Wc, dtype=float)
        rates = {**{t: self.model.tracking(t).drift_rate for t in self.tracked}, **dict(q_rate or {})}
        self.q_rate = np.array([rates[t] for t in self.tracked], dtype=float)
        self.q_state = np.array(spec.q_state if q_state is None else q_state, dtype=float)
        self.meas_idx = np.array([self.meas_index[o] for o in self.outputs], dtype=np.int64)
        fb = spec.feedback
        self.fb_col = self.outputs.index(fb) if fb in self.outputs else -1
        noise = {**spec.noise, **dict(noise or {})}
        for o in self.outputs:
            v = noise[o]
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ParameterError(f"noise level of {o} must be a positive number (SI), got {v!r}")
        self.noise_nominal = {o: float(noise[o]) for o in self.outputs}
        self.chan = np.array([EXCITATION.index(self.model.tracking(t).excited_by) for t in self.tracked],
                             dtype=np.int64)
        self.excite_thresh = np.array(spec.excite if excite is None else excite, dtype=float)
        self.tau_excite = tau_excite
        lag = spec.second_order  # a lag whose two parameters the drift test holds while not told apart
        self.lag = (lag[0], self.tracked.index(lag[1]), self.tracked.index(lag[2])) if (
            lag is not None and lag[1] in self.tracked and lag[2] in self.tracked) else None
        self.split_ratio = split.SPLIT_RATIO
        self.gate = chi2.isf(gate_p, len(self.outputs))
        self.max_gated = int(max_gated)
        g = {**DEFAULT_GUARD, **{"adapt": 1.0 if adapt_noise else 0.0}, **dict(guard or {})}
        unknown = set(g) - set(_GUARD_ORDER)
        if unknown:
            raise ParameterError(f"unknown guard setting(s) {sorted(unknown)}; known: {', '.join(DEFAULT_GUARD)}")
        self.guard_settings = g
        self.cfg = np.array([float(g[k]) for k in _GUARD_ORDER])
        fmap = self.model.filter_map(self.ps)
        self.ranges = {o: fmap.ranges[o] for o in self.outputs}
        self.prior_model = np.array(spec.prior_state, dtype=float)
        fns = ukf.functions_of(self.model)
        ukf.kernel_for(self.model)  # generated (and loaded from numba's cache) here, not on the first block
        # state
        s0 = self.model.initial_state(self.pvec[None])[0] / self.scale
        z0 = np.array([self._z_of(j, start[t]) for j, t in enumerate(self.tracked)])
        self.x = np.concatenate([s0, z0, np.zeros(q)])
        zstd = np.array([prior_std / ukf.dlog_dz(z0[j], self.width[j]) for j in range(p)])
        sig = np.array([self.noise_nominal[o] / self.scale[self.meas_index[o]] for o in self.outputs])
        self.P = np.diag(np.concatenate([self.prior_model, zstd, sig]) ** 2)
        self.floor = np.concatenate([np.full(ns, 1e-12), np.full(p, 1e-10), (1e-3 * sig) ** 2])
        self.fs = np.zeros(ukf.n_fs(self.model))
        self.fs[ukf.F_NIS_EMA] = 1.0
        self.fs[ukf.F_NIS_FAST] = 1.0
        self.fs[ukf.F_U1] = np.nan
        self.fs[ukf.F_U2] = np.nan
        self.ch = np.zeros((q, ukf.N_CH))
        self.ch[:, ukf.H_SIG] = sig
        self.ch[:, ukf.H_SIG_NOM] = sig
        self.ch[:, ukf.H_R_FLOOR] = (0.05 * sig) ** 2
        self.ch[:, ukf.H_C] = 1.0
        self.ch[:, ukf.H_LAST_RAW] = np.nan
        for o, a in dict(noise_colour or {}).items():
            if o in self.outputs:
                self.ch[self.outputs.index(o), ukf.H_A] = float(a)
        self.x_ck = self.x.copy()  # the first checkpoint: the prior (a divergence before any consistent
        self.P_ck = self.P.copy()  # stretch goes back to it)
        self.fs[ukf.F_CK_OK] = 1.0
        self.samples = 0
        self.counters = {s: 0 for s in ukf.STATUS}
        self._held = np.full((2, p), np.nan)  # (E, V) of the last sample for ukf.held_variance
        self._split = np.full(5, np.nan)  # the lag's averages and its rate filter (twin.online.split)
        self._last_t_ns: int | None = None
        self._pending: Samples | None = None
        self._started = False
        # the loop-scale watch while the scale is open: the blocks gathered, the samples at the last check
        self._scale_watch: types.SimpleNamespace | None = None
        self.closed_fast = True
        self._setup_args = types.SimpleNamespace(  # constant: what the kernel's Setup takes of the configuration
            mia=self.meas_idx, idx=self.idx, lo_log=self.lo_log, width=self.width, scale=self.scale,
            prior_mod=self.prior_model, Wm=self.Wm, Wc=self.Wc, lam=float(self.lam), floor=self.floor,
            gate=float(self.gate), max_gated=self.max_gated, chan=self.chan, tau_excite=float(self.tau_excite),
            rest=np.asarray(fmap.rest, dtype=float), input_state=int(fmap.input_state),
            input_gain=float(fmap.input_gain), demand_gain=float(fmap.demand_gain),
            fb_state=int(spec.measures[fb]) if fb is not None else -1, fb_col=self.fb_col,
            out_lo=np.array([self.ranges[o][0] for o in self.outputs], dtype=float),
            out_hi=np.array([self.ranges[o][1] for o in self.outputs], dtype=float),
            out_centre=np.array([fmap.centres[o] / self.scale[self.meas_index[o]] for o in self.outputs]),
            excitation=np.ascontiguousarray(fmap.excitation, dtype=float), lanes=int(fns.LANES),
            lane_work=int(fns.LANE_WORK),
            exo_idx=np.array([self.model.kernel_index(p) for p in spec.exogenous.values()], dtype=np.int64))
        self.exogenous = dict(spec.exogenous)  # logged signal -> parameter it sets sample by sample (T_oil)
        self.exo_idx: np.ndarray = self._setup_args.exo_idx
        self.exo_last = np.full(self.exo_idx.size, np.nan)  # the last fresh value of each exogenous signal

    def _setup(self) -> tuple:
        """The kernel's :data:`twin.online.ukf.Setup` record for the current settings."""
        assert self.dt is not None
        pvec = self.pvec
        if np.isfinite(self.exo_last).any():  # the rig's vector at the last fresh exogenous values (T_oil)
            pvec = pvec.copy()
            ok = np.isfinite(self.exo_last)
            pvec[self.exo_idx[ok]] = self.exo_last[ok]
        return ukf.Setup(dt0=float(self.dt), nsub=self.substeps, q_state=self.q_state, q_param=self.q_rate ** 2,
                         thresh=self.excite_thresh, cfg=self.cfg, pvec=pvec, **vars(self._setup_args))

    # --- coordinates ---------------------------------------------------------------------
    def _z_of(self, j: int, value: float) -> float:
        s = (math.log(value) - self.lo_log[j]) / self.width[j]
        return math.log(s / (1.0 - s))

    def values_of(self, z: np.ndarray) -> np.ndarray:
        """SI values of logit coordinates ``z [..., p]``."""
        s = 1.0 / (1.0 + np.exp(-np.asarray(z)))
        return np.exp(self.lo_log + self.width * s)

    def dlog_dz(self, z: np.ndarray) -> np.ndarray:
        s = 1.0 / (1.0 + np.exp(-np.asarray(z)))
        return self.width * s * (1.0 - s)

    def process_noise(self, dt: float, x: np.ndarray | None = None, P: np.ndarray | None = None) -> np.ndarray:
        """The ``Q`` the kernel adds over ``dt`` seconds at state ``x`` (for filterpy mirrors)."""
        x = self.x if x is None else x
        P = self.P if P is None else P
        assert self.dt is not None, "the sample time is not known yet"
        n, nm = self.n, self.nmod
        ns = self.ns
        Q = np.zeros((n, n))
        Q[np.arange(ns), np.arange(ns)] = self.q_state * dt / self.dt
        for j in range(len(self.tracked)):
            g = 1.0 / max(float(ukf.dlog_dz(x[ns + j], self.width[j])), 1e-12)
            add = self.q_rate[j] ** 2 * dt * g * g
            cap = ukf.PARAM_STD_CAP ** 2 * g * g
            if P[ns + j, ns + j] + add > cap:
                add = max(0.0, cap - P[ns + j, ns + j])
            Q[ns + j, ns + j] = add
        for j in range(len(self.outputs)):
            a = self.ch[j, ukf.H_A]
            Q[nm + j, nm + j] = self.ch[j, ukf.H_SIG] ** 2 * (1 - a * a)
        return Q

    @property
    def R_floor(self) -> np.ndarray:
        return self.ch[:, ukf.H_R_FLOOR].copy()

    #: how long the tracker keeps re-checking the loop's scale (x against x_ref) while it is not settled, s
    SCALE_WATCH_S = 60.0

    def _check_scale_on(self, samples: Samples) -> None:
        """The loop's scale (a position in mm read as metres, :func:`twin.units.check_loop_scale`) checked again on
        the blocks gathered so far each time they have doubled, until it is settled
        (:func:`twin.units.loop_scale_settled`) or :data:`SCALE_WATCH_S` have passed: a record that starts at rest
        cannot tell it on its first block.  Doubling keeps the whole watch linear in the samples it reads."""
        from twin.units import check_loop_scale, loop_scale_settled

        w = self._scale_watch
        assert w is not None
        names = [k for k in ("x", "x_ref", "u") if k in samples.signals]
        w.blocks.append({k: np.asarray(samples.signals[k], dtype=float) for k in names})
        n = sum(len(next(iter(b.values()))) for b in w.blocks if b)
        if len(w.blocks) > 1 and n < 2 * w.checked_at:
            return
        seen = {k: np.concatenate([b[k] for b in w.blocks if k in b]) for k in names}
        if len(w.blocks) > 1:  # the first block was checked with the record's ranges
            check_loop_scale(self.ps, seen, "the tracked signals")
        w.checked_at = max(n, 100)
        if loop_scale_settled(seen) or n * (self.dt or 0.0) >= self.SCALE_WATCH_S:
            self._scale_watch = None

    def _start_from_data(self, samples: Samples) -> None:
        """The measured state at the first sample (the model's measured outputs) instead of rest."""
        sig = samples.signals
        assert self.dt is not None  # process() learns it first
        self.model.check_record(self.ps, sig, "the tracked signals")
        from twin.units import check_lengths

        check_lengths(self.model, self.ps, sig, "the tracked signals")  # a column in mm read as metres
        if len(samples) >= 8:
            init = self.model.initial_from_data({k: v for k, v in sig.items() if k in self.outputs
                                                 and np.all(np.isfinite(v[:8]))}, self.dt)
        else:
            init = {f"{k}0": float(sig[k][0]) for k in self.outputs if k in sig and np.isfinite(sig[k][0])}
        for o, i in self.meas_index.items():
            key = f"{o}0"
            if key in init and np.isfinite(init[key]):
                v = init[key]
                lo, hi = self.model.filter_map(self.ps).ranges[o]
                if not lo <= v <= hi:
                    continue
                self.x[i] = v / self.scale[i]
        self.x_ck = self.x.copy()

    def process(self, samples) -> TrackBlock:
        """Filter a block of samples (signals in SI; the model's drive and demand, its measured outputs); numpy's
        BLAS on one thread meanwhile (:func:`twin.estimation.threads.numpy_one_thread`)."""
        from twin.estimation.threads import numpy_one_thread

        with numpy_one_thread():
            return self._process(samples)

    def _process(self, samples) -> TrackBlock:
        T = len(samples)
        sig = samples.signals
        drive, demand = self.model.drive_name, self.model.demand_name
        if drive not in sig and demand not in sig:
            needs = f"the {'controller output' if self.model.CLOSED_LOOP else 'drive'} {drive!r}" + (
                f" or the demand {demand!r}" if demand is not None else "")
            raise DataError(f"the {self.model.name} tracker needs {needs}; "
                            f"the block has {', '.join(sig) or 'no signals'}")
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
            steps = np.diff(t_ns)
            steps = steps[steps > 0]
            self.dt = float(np.median(steps)) * 1e-9 if steps.size else math.nan
            if not self.dt > 0:
                raise DataError(f"sample times do not increase (median step {self.dt} s)")
        ticks = self.timing.ticks(self.dt)
        mode = self.model.intersample_code(self.timing, self.dt)  # the model says how its drive moves between samples
        if not self._started:
            self._start_from_data(samples)
            self._started = True
            self._scale_watch = types.SimpleNamespace(blocks=[], checked_at=0)
        if self._scale_watch is not None:
            self._check_scale_on(samples)
        # seconds since the previous sample (NaN before the first one ever)
        DT = np.empty(T)
        if T:
            prev = self._last_t_ns
            DT[0] = (t_ns[0] - prev) * 1e-9 if prev is not None else np.nan
            DT[1:] = np.diff(t_ns) * 1e-9
            self._last_t_ns = int(t_ns[-1])
        nan = np.full(T, np.nan)
        # a digital controller faster than the log: its output between samples is a staircase the logged drive
        # cannot show, so the controller itself drives the model from the demand (when the model runs its law)
        closed = drive not in sig or (ticks > 1 and demand in sig and self.model.fast_controller(self.ps)
                                      and self.closed_fast)
        U = np.ascontiguousarray(sig.get(drive, nan), dtype=float)
        XREF = np.ascontiguousarray(sig.get(demand, nan) if demand is not None else nan, dtype=float)
        Z = np.empty((T, len(self.outputs)))
        for a, o in enumerate(self.outputs):
            Z[:, a] = np.asarray(sig[o], dtype=float) / self.scale[self.meas_index[o]] if o in sig else np.nan
        Z[~np.isfinite(Z)] = np.nan
        U = np.where(np.isfinite(U), U, np.nan)
        XREF = np.where(np.isfinite(XREF), XREF, np.nan)
        EXO = np.full((T, len(self.exogenous)), np.nan)
        for j, (name, par) in enumerate(self.exogenous.items()):
            if name in sig:  # the logged value where it is fresh and physical (a slow signal's NaNs: held)
                spec = self.ps.spec(par)
                v = np.asarray(sig[name], dtype=float)
                EXO[:, j] = np.where(np.isfinite(v) & (v >= spec.lo) & (v <= spec.hi), v, np.nan)
        n, p, m = self.n, len(self.tracked), len(self.outputs)
        X = np.empty((T, n))
        Pd = np.empty((T, n))
        nis = np.empty(T)
        ll = np.empty(T)
        st = np.empty(T, dtype=np.int64)
        innov = np.empty((T, m))
        Sd = np.empty((T, m))
        frozen = np.empty((T, p), dtype=np.bool_)
        guard = np.empty(T, dtype=np.int64)
        sens = np.empty((T, m), dtype=np.int64)
        noise = np.empty((T, m))
        used = np.empty((T, m), dtype=np.bool_)
        q_param = self.q_rate ** 2
        bad = self._run_kernel(ukf.Block(U, XREF, Z, DT, EXO), closed, ticks, mode,
                               ukf.Out(X, Pd, nis, ll, st, innov, Sd, frozen, guard, sens, noise, used))
        if bad >= 0:
            raise FilterError(f"the filter diverged at sample {self.samples + bad} (t_ns={int(t_ns[bad])}) and "
                              "has no checkpoint to go back to: state or covariance not finite")
        for j in range(self.exo_idx.size):  # the next block starts from the last fresh value
            fresh = np.flatnonzero(np.isfinite(EXO[:, j]))
            if fresh.size:
                self.exo_last[j] = EXO[fresh[-1], j]
        self.samples += T
        counts = np.bincount(st, minlength=len(ukf.STATUS))
        for c in np.flatnonzero(counts):
            self.counters[ukf.STATUS[c]] += int(counts[c])
        ns = self.ns
        z = X[:, ns:ns + p]
        dz = np.sqrt(np.maximum(Pd[:, ns:ns + p], 0.0))
        est = self.values_of(z)
        log_std = dz * self.dlog_dz(z)
        held = np.empty_like(log_std)
        if getattr(self, "_held", None) is None:  # trackers pickled before the held-still variance existed
            self._held = np.full((2, p), np.nan)
        ukf.held_variance(np.ascontiguousarray(log_std * log_std), DT, q_param, ukf.PARAM_STD_CAP ** 2, self._held,
                          held)
        held_log_std = np.sqrt(held)
        states = X[:, :ns] * self.scale
        kernel_frozen = frozen.copy()
        if self.lag is not None:  # zeta and wn not told apart by the recent motion: the drift test holds them
            iv, jz, jw = self.lag
            zw = float(self.ps[self.tracked[jz]]), float(self.ps[self.tracked[jw]])  # the rig's, not the wander's
            rate = split.lag_rate(U, DT, *zw, self._split[3:]) if np.isfinite(U).any() else states[:, iv]
            un = split.unsplit(rate, DT, *zw, min(1.0, self.dt / self.tau_excite),
                               self._split[:3], self.split_ratio)
            frozen[:, jz] |= un
            frozen[:, jw] |= un
        msc = np.array([self.scale[self.meas_index[o]] for o in self.outputs])
        return TrackBlock(t_ns=t_ns, estimates=est, stds=est * log_std, log_std=log_std, nis=nis, loglik=ll,
                          status=_STATUS_NAMES[st], frozen=frozen, innovation=innov * msc, states=states,
                          guard=_GUARD_NAMES[guard], sensors=_SENSOR_NAMES[sens],
                          noise=noise * msc, outputs=self.outputs, used=used, held_stds=est * held_log_std,
                          held_log_std=held_log_std, kernel_frozen=kernel_frozen)

    def _run_kernel(self, block, closed: bool, ticks: int, mode: int, out) -> int:
        """The model's compiled kernel over one block (:func:`twin.online.ukf.kernel_for`)."""
        kernel = ukf.kernel_for(self.model)
        return kernel(self._setup(), ukf.Carry(self.x, self.P, self.fs, self.ch, self.x_ck, self.P_ck), block, closed,
                      ticks, mode, out)

    def _empty(self) -> TrackBlock:
        p, m = len(self.tracked), len(self.outputs)
        z = np.zeros((0, p))
        return TrackBlock(np.zeros(0, np.int64), z, z, z, np.zeros(0), np.zeros(0), np.zeros(0, dtype="<U19"),
                          np.zeros((0, p), bool), np.zeros((0, m)), np.zeros((0, self.ns)),
                          np.zeros(0, dtype="<U19"), np.zeros((0, m), dtype="<U10"), np.zeros((0, m)), self.outputs,
                          np.zeros((0, m), bool), z, z, np.zeros((0, p), bool))

    def estimate(self) -> dict[str, tuple[float, float]]:
        """Current (value, std) of every tracked parameter (SI); the std of the published intervals (the error's
        if the parameter has held still, :func:`twin.online.ukf.held_variance`), the filter's before any sample."""
        p = len(self.tracked)
        z = self.x[self.ns:self.ns + p]
        s = np.sqrt(np.maximum(np.diag(self.P)[self.ns:self.ns + p], 0.0)) * self.dlog_dz(z)
        held = getattr(self, "_held", None)
        if held is not None:
            s = np.where(np.isfinite(held[0]), np.sqrt(np.maximum(held[0], 0.0)), s)
        v = self.values_of(z)
        return {t: (float(v[j]), float(v[j] * s[j])) for j, t in enumerate(self.tracked)}

    def noise_levels(self) -> dict[str, dict[str, float]]:
        """Learnt sensor noise per output: standard deviation (SI), AR(1) coefficient, nominal."""
        out = {}
        for j, o in enumerate(self.outputs):
            sc = self.scale[self.meas_index[o]]
            out[o] = {"std": float(self.ch[j, ukf.H_SIG] * sc), "ar1": float(self.ch[j, ukf.H_A]),
                      "nominal": float(self.ch[j, ukf.H_SIG_NOM] * sc)}
        return out

    def sensor_status(self) -> dict[str, str]:
        return {o: ukf.SENSOR[int(self.ch[j, ukf.H_STATUS])] for j, o in enumerate(self.outputs)}

    # --- checkpoints ---------------------------------------------------------------------
    STATE_VERSION = 1
    _STATE_ARRAYS = ("x", "P", "fs", "ch", "x_ck", "P_ck", "_held", "exo_last", "_split")

    def state(self) -> dict:
        """What the filter's future output depends on beyond its construction, as plain data (numbers,
        strings, lists, numpy arrays): restore it into a tracker built the same way (:meth:`restore`)."""
        pending = self._pending
        return {"version": self.STATE_VERSION, "tracked": list(self.tracked), "outputs": list(self.outputs),
                "dt": self.dt, "samples": int(self.samples), "counters": {k: int(v) for k, v in self.counters.items()},
                "last_t_ns": self._last_t_ns, "started": bool(self._started), "closed_fast": bool(self.closed_fast),
                # the loop-scale watch still open (its blocks are not kept: restored, it starts again from there)
                "scale_watch": self._scale_watch is not None,
                "pending": None if pending is None else {"t_ns": np.asarray(pending.t_ns, dtype=np.int64),
                                                         "signals": {k: np.asarray(v, dtype=float)
                                                                     for k, v in pending.signals.items()}},
                **{k.lstrip("_"): np.array(getattr(self, k), dtype=float) for k in self._STATE_ARRAYS}}

    def restore(self, state: Mapping) -> None:
        """Continue from :meth:`state` of a tracker of the same configuration.

        :raises DataError: a state of another version, other tracked parameters or outputs, or arrays of
            other shapes (nothing is changed then).
        """
        def fail(what: str) -> DataError:
            return DataError(f"tracker state: {what}")

        if state.get("version") != self.STATE_VERSION:
            raise fail(f"version {state.get('version')!r}, this program reads {self.STATE_VERSION}")
        if list(state.get("tracked", ())) != list(self.tracked) or list(state.get("outputs", ())) != list(self.outputs):
            raise fail(f"tracks {state.get('tracked')} from {state.get('outputs')}, this rig "
                       f"{list(self.tracked)} from {list(self.outputs)}")
        arrays = {}
        for k in self._STATE_ARRAYS:
            a = state.get(k.lstrip("_"))
            ref = getattr(self, k)
            if k in ("exo_last", "_split") and a is None:  # a state written before these: none seen yet
                a = np.full(ref.shape, np.nan)
            if not isinstance(a, np.ndarray) or a.shape != ref.shape:
                raise fail(f"{k.lstrip('_')} is not an array of shape {ref.shape}")
            arrays[k] = np.array(a, dtype=float)
        counters = state.get("counters")
        if not isinstance(counters, Mapping) or set(counters) - set(self.counters):
            raise fail("counters unknown to this program")
        dt = state.get("dt")
        if dt is not None and not (isinstance(dt, float) and dt > 0):
            raise fail(f"sample time {dt!r}")
        last = state.get("last_t_ns")
        if last is not None and not isinstance(last, int):
            raise fail(f"last_t_ns {last!r}")
        pend = state.get("pending")
        pending = None
        if pend is not None:
            try:
                pending = Samples(np.asarray(pend["t_ns"], dtype=np.int64),
                                  {str(k): np.asarray(v, dtype=float) for k, v in pend["signals"].items()})
            except (KeyError, TypeError, ValueError, AttributeError) as exc:
                raise fail(f"pending samples ({exc})") from None
        try:
            samples, started, closed_fast = int(state["samples"]), bool(state["started"]), bool(state["closed_fast"])
        except (KeyError, TypeError, ValueError) as exc:
            raise fail(f"samples, started or closed_fast ({exc})") from None
        for k, a in arrays.items():
            setattr(self, k, np.ascontiguousarray(a))
        self.counters.update({k: int(v) for k, v in counters.items()})
        self.dt = dt
        self.samples = samples
        self._last_t_ns = last
        self._started = started
        # a checkpoint written before the watch existed: the rig was accepted then
        self._scale_watch = types.SimpleNamespace(blocks=[], checked_at=0) if state.get("scale_watch") else None
        self.closed_fast = closed_fast
        self._pending = pending

    def break_covariance(self) -> None:
        """Make the covariance indefinite (what round-off does to long runs); for tests and drills."""
        w, V = np.linalg.eigh(self.P)
        w[0] = -abs(w[-1])
        self.P[:, :] = (V * w) @ V.T

    def __repr__(self) -> str:
        return (f"OnlineTracker(tracked={self.tracked}, outputs={self.outputs}, dt={self.dt}, "
                f"timing={self.timing.label}, samples={self.samples})")


def fmt_estimate(name: str, value: float, std: float, model: str = DEFAULT_MODEL) -> str:
    spec = get_model(model).params().spec(name)
    return f"{name} = {spec.show(value)} +- {spec.show(std)}" if math.isfinite(std) else f"{name} = {spec.show(value)}"


def consistency_note(tracker: OnlineTracker, drift=None, sensors: Mapping[str, str] | None = None) -> str:
    """One line for the rig's status message: faulty sensors (``sensors``, default the filter's own verdicts) and
    why the drift test holds ("" when all is well)."""
    sensors = tracker.sensor_status() if sensors is None else sensors
    parts = [f"sensor {o}: {s}" for o, s in sensors.items() if s not in ("ok", "missing")]
    guard = getattr(drift, "guard", "consistent")
    if guard and guard != "consistent":
        parts.append(f"drift test holds: {guard.replace('_', ' ')}")
    return "; ".join(parts)
