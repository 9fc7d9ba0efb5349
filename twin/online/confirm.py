"""Alarms confirmed by the data: a batch re-fit of the recent window decides every warning and alarm.

The tracker's filter is the fast, continuous estimate; its drift test (:class:`twin.online.drift.DriftMonitor`,
a CUSUM on the filter's estimates) is only the *trigger*.  A warning or an alarm on a parameter is raised when
the product's own output-error fit (:func:`twin.estimation.fit.fit`, the fit of ``twin fit``, with its
heteroskedasticity- and autocorrelation-consistent standard errors and the adequacy test of the fitted model,
:func:`twin.estimation.diagnose.check.judge`) of the last :data:`WINDOW_S` seconds of samples says so:

* the window's fit must be adequate (the adequacy test of ``twin fit`` at its level): a window the model does
  not represent (an un-modelled load, a chirp beyond what the model reaches) tests nothing: every parameter is
  ``not_testable`` and the status says "the model does not represent the rig now";
* the parameter's window standard error (relative) must be at most :data:`RESOLVE` times the half-width of its
  healthy band in log units (the drift test's own ``resolve``): a window that does not inform a parameter gives
  ``not_testable``, never an alarm (a window beyond the band on the side of a standing confirmation is not gated
  so: it can only replicate, and its likelihood ratio says whether it informs the parameter);
* the fitted value must lie outside the healthy band **and** differ from the commissioning baseline by the
  two-sample test ``z = log(theta_w / theta_0) / sqrt(s_w^2 + s_0^2)`` at the two-sided level :data:`ALPHA`
  (``s_w``: the window's relative standard error, ``s_0``: the commissioning fit's, 0 for a configured value),
  both by the Wald ``s_w`` and by the window's likelihood ratio (the window fitted again with the parameter held
  at its baseline; :meth:`ConfirmedDrift._likelihood_ratio`), the same in every parametrisation.

A confirmed parameter is **replicated** by a later disjoint window that puts it beyond the band on the same side
at the one-sided level :data:`REPLICATE_ALPHA` by its likelihood ratio too (the first confirmation holds the
level ALPHA; the replication rules out one window's systematic error).

A window's verdict counts as a confirmation when the filter's estimate at the window's end lies beyond the band
on the same side too (the filter is the trigger, the window its check; holds of the filter's drift test do not
matter here): two estimators of different kinds, each wrong at times (the filter diverging under a fast chirp,
a short window's fit biased by what the model lacks under one demand), must agree.  Two confirmations on one
side (the first at ALPHA, the next ones replications), on disjoint windows with none between them finding the
parameter inside its band (:data:`WARN_CONFIRMATIONS`), raise a **warning**; three (:data:`ALARM_CONFIRMATIONS`,
or two while the filter's drift test is at alarm) the **alarm**.  A raised parameter returns only on a window that puts it inside its band
at the same level: the band's edge it crossed rejected, ``log(theta_w / edge) / sqrt(s_w^2 + s_0^2)`` beyond the
critical value on the band's side (:func:`back_inside`).  A window whose point estimate merely falls inside
changes nothing then: while a wear goes on just past the edge, half the windows' estimates fall inside by chance,
and each had returned the alarm (an all-clear while the rig kept wearing; on a leakage drifting exponentially
past its band the alarm was raised three times and returned twice within 60 s).  A window that cannot test it changes nothing: the
parameter is ``not_testable`` now, its level and count stay.

The window is fitted twice, from the filter's current estimate and from the baseline (a wear in progress moves
the filter ahead of the baseline; a diverged filter is far from both), and the lower cost is kept.  The fit
frees the catalogue's pressure-transducer offsets too (``pA_off``, ``pB_off``): an offset drifting on a
transducer is fitted as what it is, and a significant one (Wald and likelihood ratio against 0 Pa) beyond :data:`OFFSET_TOLERANCE_PA` in two windows
(no window between them finding it within) becomes a *sensor* event on the offset (``pA_off``), never a
parameter's alarm; it returns when two windows in a row find it within.  While a transducer's offset is confirmed or suspected (one window), the parameters are
``not_testable``: the filter, whose estimate each confirmation needs, reads that transducer as it is.

When the fits run: a **triggered** fit when the filter's drift test leaves ``ok`` on a parameter (and again
every window while it stays there unconfirmed), and a **scheduled** fit every :data:`PERIOD_S` seconds whatever
the filter says: a drift the filter froze or followed slowly is found at most one period plus one window after
it left its band, and no parameter goes untested for longer (:attr:`ConfirmedDrift.tested`: the record time of
each parameter's last test).  The fits run in the caller's thread once per block at most, amortised over the
samples between them (``python -m benchmarks.tracker`` measures the cost per sample).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Mapping, Sequence
from statistics import NormalDist

import numpy as np

from twin.online.baseline import Baseline
from twin.online.drift import DriftMonitor
from twin.online.events import ALARM_LEVELS, AlarmEvent

#: seconds of samples each re-fit reads: short against a wear (a wn decay of 30 % over 20 s moves 6 % in it),
#: long against the slowest loop dynamics (a 0.2 Hz multisine line has most of a period in it)
WINDOW_S = 4.0
#: seconds between scheduled re-fits
PERIOD_S = 20.0
FITS_KEPT = 200
"""Window fits kept for inspection (``ConfirmedDrift.fits``, the last ones): a service runs for months."""
#: two-sided level of each parameter's two-sample test (z = 3.29)
ALPHA = 1e-3
#: a window standard error (relative) above this share of the band's log half-width: ``not_testable``
RESOLVE = 0.5
#: the pressure transducers' offsets the window fit frees beside the rig's parameters (the catalogue's effect)
SENSOR_EFFECT = "pressure_sensor_offset"
SENSOR_PARAMS = {"pA_off": "pA", "pB_off": "pB"}
#: an offset smaller than this is within a transducer's calibration (0.5 % of a 25 MPa span, a common
#: tolerance class of industrial pressure transducers): no sensor event below it
OFFSET_TOLERANCE_PA = 0.125e6
#: windows confirming a parameter on one side, with no window between them finding it inside, that raise a
#: warning and an alarm (each confirmation at the level ALPHA; a systematic error of one window, a fit that
#: landed on the wrong side of a ridge on a chirp, is not repeated by the next)
WARN_CONFIRMATIONS = 2
ALARM_CONFIRMATIONS = 3
#: a parameter whose window estimate shares more than this correlation with a transducer offset's is not told
#: apart from the sensor by the window (R^2 0.81: most of its uncertainty is the offset's): not testable
SENSOR_CORR = 0.9
#: seconds of samples between two decisions: a longer block is written to the twin in pieces this long, so a
#: re-fit falls due at most this late whatever the reader's chunk
STEP_S = 0.5
#: the shortest span (s) of residual autocorrelation a window's standard errors count: a closed loop's
#: output-error residuals are its sensor noise through the loop, correlated over the loop's slowest closed-loop
#: time constant (a PI or PID loop's integral action: a tenth to a quarter of a second on these rigs), longer than
#: the ``sqrt(n)`` lags of the fit's automatic choice on a 4-s window (64 ms at 1 kHz), which left a healthy
#: window's leakage 11 times its truth at z 4.4 (reference simulator, a PID loop); at 0.25 s, z 2.7
HAC_LAG_S = 0.25
#: seconds at a window's start whose residuals the fit and its adequacy test do not count: the window's simulated
#: loop starts from a state read off noisy samples (velocity, pressures, spool, a controller's integral), and the
#: error of that start decays over the loop's first tenths of a second.  On the product's own exact record of a
#: friction step (a P loop, white noise outside the loop), the displacement residual at the truth was 9-24 times
#: the noise over the first 0.1 s and white from 0.3 s on; counted, it pulled the fit along the leakage-valve
#: ridge (leakage to zero, zeta and wn 1.1-1.5 times their truth) and failed the adequacy test there
BURN_S = 0.5
#: one-sided level of a replication: a window that confirms a parameter confirmed once already, on the same side
#: beyond its band (z 1.64).  The first confirmation holds the level ALPHA against the noise; a replication rules
#: out that one window's systematic error, and at ALPHA itself it asked a leakage wear to show the evidence of
#: the first window twice over: on a PI loop under road and block demands, a 7x leakage whose windows gave ratio
#: z 4.9 then 2.5 was never raised
REPLICATE_ALPHA = 0.05
#: the fit's budget per start (function evaluations of the trust-region refinement)
MAX_NFEV = 25


@dataclasses.dataclass(frozen=True)
class Verdict:
    """What one window says of one parameter: ``state`` ``inside``, ``high``, ``low`` or ``not_testable``."""

    name: str
    state: str
    value: float = math.nan
    rel_std: float = math.nan
    z: float = math.nan
    why: str = ""


def critical_z(alpha: float = ALPHA) -> float:
    """The two-sided standard normal quantile of ``alpha``."""
    return NormalDist().inv_cdf(1.0 - 0.5 * alpha)


def log_z(value: float, ref: float, rel_std: float, base_rel_std: float = 0.0) -> float:
    """``log(value / ref) / sqrt(s_w^2 + s_0^2)``: a window's value against a reference (the baseline, a band's
    edge) in units of the two relative standard errors (``s_0`` NaN counts as 0; both 0: an infinite z)."""
    s0 = base_rel_std if math.isfinite(base_rel_std) else 0.0
    sd = math.sqrt(rel_std * rel_std + s0 * s0)
    d = math.log(value / ref)
    return d / sd if sd > 0 else math.copysign(math.inf, d)


def decide(name: str, value: float, rel_std: float, base: Baseline, adequate: bool, base_rel_std: float = 0.0,
           alpha: float = ALPHA, resolve: float = RESOLVE) -> Verdict:
    """The window's verdict on one parameter (module docstring): ``not_testable`` when the window's fit is not
    adequate or its standard error is too wide for the band; ``high``/``low`` when the value lies outside the band
    and the two-sample test rejects the baseline at ``alpha``; else ``inside``."""
    if not adequate:
        return Verdict(name, "not_testable", value, rel_std, why="the model does not represent the rig now")
    half = 0.5 * math.log(base.hi / base.lo)
    if not (value > 0 and math.isfinite(value) and math.isfinite(rel_std) and rel_std >= 0):
        return Verdict(name, "not_testable", value, rel_std, why="the window's fit gives it no standard error")
    if rel_std > resolve * half:
        return Verdict(name, "not_testable", value, rel_std,
                       why=f"the window informs it to +-{100 * rel_std:.0f} % only (at most "
                           f"{100 * resolve * half:.0f} % tests its band)")
    z = log_z(value, base.value, rel_std, base_rel_std)
    zc = critical_z(alpha)
    if value > base.hi and z > zc:
        return Verdict(name, "high", value, rel_std, z)
    if value < base.lo and z < -zc:
        return Verdict(name, "low", value, rel_std, z)
    if not base.lo <= value <= base.hi:  # beyond the band, but the baseline is not rejected: no evidence either way
        return Verdict(name, "unresolved", value, rel_std, z,
                       why=f"outside its band but not away from the baseline at the level {alpha:g} (z {z:+.1f})")
    return Verdict(name, "inside", value, rel_std, z)


def back_inside(value: float, rel_std: float, base: Baseline, side: str, base_rel_std: float = 0.0,
                alpha: float = ALPHA) -> tuple[bool, float]:
    """Does a window put a parameter raised on ``side`` (``high``/``low``) back inside its band at the level
    ``alpha``?  ``(verdict, z)`` with ``z = log(value / edge) / sqrt(s_w^2 + s_0^2)`` against the band's edge on
    that side: back when ``z`` lies beyond the two-sided critical value towards the band's inside."""
    if not (value > 0 and math.isfinite(value) and math.isfinite(rel_std) and rel_std >= 0):
        return False, math.nan
    edge = base.hi if side == "high" else base.lo
    z = log_z(value, edge, rel_std, base_rel_std)
    zc = critical_z(alpha)
    return (z < -zc if side == "high" else z > zc), z


def decide_offset(name: str, value: float, std: float, adequate: bool, alpha: float = ALPHA,
                  tolerance: float = OFFSET_TOLERANCE_PA) -> Verdict:
    """A transducer offset (Pa) against zero: ``high``/``low`` when beyond ``tolerance`` and significant at
    ``alpha``; ``not_testable`` when the window is not adequate or gives no standard error; else ``inside``."""
    if not adequate:
        return Verdict(name, "not_testable", value, why="the model does not represent the rig now")
    if not (math.isfinite(value) and math.isfinite(std) and std > 0):
        return Verdict(name, "not_testable", value, why="the window's fit gives it no standard error")
    z = value / std
    if abs(value) > tolerance and abs(z) > critical_z(alpha):
        return Verdict(name, "high" if value > 0 else "low", value, std, z)
    if abs(value) > tolerance:  # beyond the tolerance, not significant: no evidence either way
        return Verdict(name, "unresolved", value, std, z,
                       why=f"beyond the tolerance but not significant at the level {alpha:g} (z {z:+.1f})")
    return Verdict(name, "inside", value, std, z)


@dataclasses.dataclass
class WindowFit:
    """One window's re-fit: the verdicts, the fit's time and cost, the adequacy's reasons."""

    t_s: float
    t_ns: int
    verdicts: dict[str, Verdict]
    sensors: dict[str, Verdict]
    adequate: bool
    reasons: list[str]
    estimate: dict[str, float]
    std: dict[str, float]
    corr: np.ndarray
    start: str
    seconds: float


class Window:
    """The last ``seconds`` of samples (blocks kept, trimmed by sample time)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = float(seconds)
        self._blocks: list = []

    def add(self, samples) -> None:
        if len(samples) == 0:
            return
        self._blocks.append(samples)
        end = int(samples.t_ns[-1])
        keep_ns = int(round(self.seconds * 1e9))
        while len(self._blocks) > 1 and int(self._blocks[1].t_ns[0]) <= end - keep_ns:
            self._blocks.pop(0)

    def span_s(self) -> float:
        if not self._blocks:
            return 0.0
        return (int(self._blocks[-1].t_ns[-1]) - int(self._blocks[0].t_ns[0])) * 1e-9

    def samples(self):
        """The last ``seconds`` of samples in one block."""
        from replay.base import Samples

        s = Samples.concat(self._blocks)
        k = int(np.searchsorted(s.t_ns, int(s.t_ns[-1]) - int(round(self.seconds * 1e9)), side="left"))
        return s.slice(k, len(s)) if k > 0 else s

    def clear(self) -> None:
        self._blocks = []


def window_record(samples, tracker, burn_s: float = BURN_S):
    """The window's samples as a :class:`twin.record.Record` of the signals the fit reads; its outputs' first
    ``burn_s`` seconds marked as no measurement (:data:`BURN_S`: the simulated loop's start is read off them, its
    residuals there are not counted)."""
    from twin.record import Record

    t_ns = np.asarray(samples.t_ns)
    dt = tracker.dt or float(np.median(np.diff(t_ns))) * 1e-9
    sig = {k: np.asarray(v, float) for k, v in samples.signals.items() if k in ("x_ref", "u", "x", "pA", "pB")}
    rec = Record(dt, sig, "window")
    rec.burn_start(burn_s, ("x", "pA", "pB"))
    return rec


def noise_ratios(res) -> dict[str, float]:
    """Each output's residual RMS in the window fit ``res`` (the burn-in not counted) over the nominal noise its
    residuals were weighted with; outputs without a nominal noise are left out."""
    out = {}
    for o in res.outputs:
        sd, m = float(res.noise.get(o, math.nan)), float(res.mse.get(o, math.nan))
        if sd > 0 and math.isfinite(m) and m >= 0:
            out[o] = math.sqrt(m) / sd
    return out


def quiet_sensors(ratios: Mapping[str, float], factor: float, adequate: bool) -> dict[str, bool]:
    """Per output, whether a window with these residual-to-noise ``ratios`` (:func:`noise_ratios`) leaves the
    filter's model-based verdict on it unconfirmed: within ``factor``, or several outputs beyond it at once (a
    common cause, the model: a load it lacks moves both pressures), or the window not ``adequate``.  One output
    beyond it while the others read the rig as the model does is that sensor."""
    beyond = [o for o, r in ratios.items() if not r <= factor]
    return {o: not adequate or r <= factor or len(beyond) > 1 for o, r in ratios.items()}


def fit_window(rec, tracker, names: Sequence[str], start: Mapping[str, float], sensors: bool = True,
               max_nfev: int = MAX_NFEV, held: Mapping[str, float] | None = None):
    """The window's output-error fit of ``names`` (and the transducer offsets when ``sensors``) from ``start``,
    with the rig's known values, noise and timing of ``tracker``; ``held``: parameters of ``names`` held at these
    values (the restricted fit of a likelihood-ratio test); ``None`` when the fit cannot run."""
    from twin.estimation.fit import fit

    model = tracker.model
    effects = (SENSOR_EFFECT,) if sensors and SENSOR_EFFECT in model.EFFECTS else ()
    held = dict(held or {})
    base = model.params(effects, **{**tracker.ps.as_dict(), **held})
    names = [n for n in names if n not in held]
    free = tuple(names) + (tuple(p for p in SENSOR_PARAMS if p not in held) if effects else ())
    noise = {o: v for o, v in tracker.noise_nominal.items() if o in rec}
    st = {}
    for n in free:
        v = float(start.get(n, math.nan))
        lo, hi = tracker.bounds.get(n, (-math.inf, math.inf))
        if math.isfinite(v) and lo < v < hi:
            st[n] = v
    try:
        return fit(model, [rec], free, base=base, start=st, noise=noise or None, timing=tracker.timing,
                   n_starts=1, n_refine=1, loop_noise=False, max_nfev=max_nfev, hac_lag_s=HAC_LAG_S)
    except (ValueError, ArithmeticError):  # a malformed window: no verdict from this start
        return None


class ConfirmedDrift:
    """The drift decision of one rig: the filter's drift test triggers, window re-fits decide (module docstring).

    Feed it each block with :meth:`update` (the samples, the tracker's :class:`~twin.online.tracker.TrackBlock`,
    the record times); it returns the confirmed events.  ``base_std``: each parameter's relative standard error
    at commissioning (0 for configured values).
    """

    def __init__(self, rig: str, baseline: Mapping[str, Baseline], model: str, window_s: float = WINDOW_S,
                 period_s: float = PERIOD_S, alpha: float = ALPHA, sensors: bool = True,
                 base_std: Mapping[str, float] | None = None, settle_s: float = 2.0) -> None:
        self.rig = rig
        self.baseline = dict(baseline)
        self.trigger = DriftMonitor(rig, baseline, model=model, settle_s=settle_s)
        self.window = Window(window_s)
        self.window_s, self.period_s, self.alpha = float(window_s), float(period_s), float(alpha)
        self.sensors = sensors
        self.base_std = {n: float((base_std or {}).get(n, 0.0)) for n in baseline}
        self.level = {n: "ok" for n in baseline}
        self.side = {n: "" for n in baseline}
        #: the side of the band a raised parameter left (its return is tested against that edge)
        self.raised_side = {n: "high" for n in baseline}
        self.count = {n: 0 for n in baseline}
        self.state = {n: "untested" for n in baseline}
        #: record time (s) of each parameter's last test that could test it (None: not yet)
        self.tested: dict[str, float | None] = {n: None for n in baseline}
        self.sensor_level = {o: "ok" for o in SENSOR_PARAMS.values()}
        self.sensor_count = {o: 0 for o in SENSOR_PARAMS.values()}
        self.adequate = True
        #: per output, whether the last window leaves the filter's model-based verdict on it unconfirmed
        #: (:func:`quiet_sensors`: its residuals within the filter's ``noisy_factor`` of its nominal noise, or
        #: several sensors beyond it at once, or the window not adequate)
        self.quiet: dict[str, bool] = {}
        #: per output, the last window's residual RMS over its nominal noise (after the burn-in)
        self.noise_ratio: dict[str, float] = {}
        self.reasons: list[str] = []
        self.fits: collections.deque[WindowFit] = collections.deque(maxlen=FITS_KEPT)
        self.n_fits = 0
        """Window fits run so far (``fits`` keeps the last :data:`FITS_KEPT`)."""
        #: the filter's drift test's own events (triggers, never published): what it would have raised alone
        #: (the last :data:`FITS_KEPT`)
        self.triggered: collections.deque[AlarmEvent] = collections.deque(maxlen=FITS_KEPT)
        self._t_first: float | None = None
        self._next_scheduled: float | None = None
        self._last_fit_t = -math.inf
        self.fit_seconds = 0.0

    # -- what the status says ------------------------------------------------------------------
    def statuses(self) -> dict[str, str]:
        """Per parameter: its confirmed level when not ok, else what the last window said (``ok``,
        ``not_testable``) or ``untested`` before the first window."""
        return {n: (self.level[n] if self.level[n] != "ok" else self.state[n]) for n in self.baseline}

    @property
    def guard(self) -> str:
        """The filter's consistency (the trigger's), or that the model does not represent the rig now."""
        if not self.adequate:
            return "model_does_not_represent_the_rig_now"
        return self.trigger.guard

    def sensor_status(self, filter_status: Mapping[str, str]) -> dict[str, str]:
        """The filter's sensor statuses as the window re-fits decide them: a transducer offset the last windows
        confirmed is ``offset``; a verdict of the filter that rests on its model (``offset``, ``noisy``) is
        shown only when the last window confirms it, as an alarm is confirmed: ``ok`` before the first window (a
        cold filter's first seconds read a load the model lacks, or its own unconverged parameters, as a faulty
        sensor), while the model does not represent the rig (the window's adequacy test failed: a load the model
        lacks is not three faulty sensors), and while the last window predicted that sensor to within the filter's
        ``noisy_factor`` of its nominal noise (:attr:`quiet`: the window's residual RMS on it, the burn-in not
        counted, says the sensor reads the rig as the model does, its noise included) or found several sensors
        beyond it at once (a common cause: the model); a signal's own faults
        (``stuck``, ``clipped``, ``missing``, ``wrong_unit``) stay.  A pressure transducer's offset is the
        windows' word alone (the fitted offsets)."""
        out = dict(filter_status)
        for o, s in filter_status.items():
            windows_say = s == "offset" and o in self.sensor_level  # a transducer's offset: the windows' word
            # confirmed by the last window, as an alarm is: a window that predicted this sensor to within its noise
            # says it is neither off nor noisy; before the first window the model the verdict rests on is untested
            unconfirmed = not self.fits or not self.adequate or self.quiet.get(o, False)
            if (s in ("offset", "noisy") and unconfirmed) or windows_say:
                out[o] = "ok"
        for o, lv in self.sensor_level.items():
            if lv != "ok" and o in out:
                out[o] = "offset"
        return out

    # -- the decision ------------------------------------------------------------------------------
    def update(self, samples, out, t_s: np.ndarray, tracker) -> list[AlarmEvent]:
        """One block: the trigger on the filter's estimates, then a window re-fit when one is due."""
        if len(out.t_ns) == 0:
            return []
        self.window.add(samples)
        triggers = self.trigger.update_block(tracker.tracked, out.t_ns, t_s, out.estimates, out.log_std,
                                             out.frozen, out.hold, out.guard)
        self.triggered += triggers
        now = float(t_s[-1])
        if self._t_first is None:
            self._t_first = float(t_s[0])
            self._next_scheduled = self._t_first + self.window_s
        assert self._next_scheduled is not None
        pending = {e.parameter for e in triggers if e.level != "ok"}
        pending |= {n for n, q in self.trigger.params.items() if q.level != "ok" and self.level[n] == "ok"}
        # a parameter confirmed once, or at a level, is re-tested on each next disjoint window
        pending |= {n for n in self.baseline if self.level[n] != "ok" or self.count[n] > 0}
        pending |= {o for o in self.sensor_level if self.sensor_level[o] != "ok" or self.sensor_count[o] > 0}
        full = self.window.span_s() >= self.window_s - 2 * (tracker.dt or 0.0)
        disjoint = now - self._last_fit_t >= self.window_s
        reason = ""
        if full and now >= self._next_scheduled:
            reason = "scheduled"
        elif full and pending and disjoint:
            reason = "triggered by " + ", ".join(sorted(pending))
        if not reason:
            return []
        return self._test(int(out.t_ns[-1]), now, tracker, reason)

    def _test(self, t_ns: int, now: float, tracker, reason: str) -> list[AlarmEvent]:
        import time

        t0 = time.perf_counter()
        from twin.estimation.diagnose.check import judge

        names = [n for n in tracker.tracked if n in self.baseline]
        rec = window_record(self.window.samples(), tracker)
        est = {n: v for n, (v, _) in tracker.estimate().items()}
        runs = []  # (label, fit, parameter verdicts, sensor verdicts)
        for label, start in (("filter", est), ("baseline", {n: self.baseline[n].value for n in names})):
            res = fit_window(rec, tracker, names, start, self.sensors)
            if res is None:
                continue
            judge(res, tracker.model, [rec], timing=tracker.timing)
            adequate = bool((res.adequacy or {}).get("adequate", True))
            if not adequate and self._adequate_at(res, {n: est[n] for n in names if n in est}, rec, tracker):
                adequate = True  # the model represents the window at the filter's estimate
                res.adequacy = {**res.adequacy, "adequate": True, "reasons": [], "adequate_at": "filter"}
            runs.append((label, res, *self._verdicts(res, names, tracker.bounds, adequate)))
            # a second start only where the first finds something to confirm: a verdict needs both to agree
            if not any(v.state in ("high", "low") for v in (*runs[-1][2].values(), *runs[-1][3].values())):
                break
        elapsed = time.perf_counter() - t0
        self.fit_seconds += elapsed
        self._last_fit_t = now
        if reason == "scheduled" or now >= (self._next_scheduled or now):
            self._next_scheduled = now + self.period_s
        if not runs:
            return []
        which, res, verdicts, sensors = min(runs, key=lambda r: r[1].cost)
        for other in runs:  # the starts disagree: the window's fit is not unique, it does not decide
            for mine, theirs in ((verdicts, other[2]), (sensors, other[3])):
                for n, v in list(mine.items()):
                    if v.state in ("high", "low") and theirs[n].state != v.state:
                        mine[n] = dataclasses.replace(v, state="not_testable",
                                                      why="fits of the window from the filter's estimate and "
                                                          "from the baseline disagree")
        for n, v in list(verdicts.items()):  # the window's evidence against the baseline: its likelihood ratio
            if v.state in ("high", "low") or self._may_replicate(n, v):
                verdicts[n] = self._likelihood_ratio(v, res, rec, tracker, names, est)
        for p, v in list(sensors.items()):  # ... and against a transducer read true
            if v.state in ("high", "low"):
                sensors[p] = self._likelihood_ratio(v, res, rec, tracker, names, est)
        adequacy = getattr(res, "adequacy", None) or {}
        adequate = bool(adequacy.get("adequate", True))
        self.reasons = list(adequacy.get("reasons", []))
        self.adequate = adequate
        factor = float(getattr(tracker, "guard_settings", {}).get("noisy_factor", math.inf))
        self.noise_ratio = noise_ratios(res)
        self.quiet = quiet_sensors(self.noise_ratio, factor, adequate)
        self.n_fits += 1
        self.fits.append(WindowFit(now, t_ns, verdicts, sensors, adequate, self.reasons, dict(res.estimate),
                                   dict(res.std), np.asarray(res.corr), which, elapsed))
        events = []
        for p, vd in sensors.items():
            events += self._apply_sensor(p, vd, t_ns, now)
        off = [o for o in self.sensor_level if self.sensor_level[o] != "ok" or self.sensor_count[o] > 0]
        for n, vd in verdicts.items():
            if off and vd.state != "not_testable":  # the filter, half of each confirmation, reads that sensor
                vd = dataclasses.replace(vd, state="not_testable",
                                         why=f"the {', '.join(off)} transducer reads off: the filter's estimates "
                                             "are not the rig's until it is fixed")
            events += self._apply(n, vd, t_ns, now, reason, est.get(n, math.nan))
        return events

    def _beyond_confirmed(self, n: str, value: float) -> bool:
        """Is ``value`` beyond ``n``'s band on the side of a standing confirmation (count above 0)?"""
        if self.count[n] <= 0 or not (value > 0 and math.isfinite(value)):
            return False
        base = self.baseline[n]
        return value > base.hi if self.side[n] == "high" else value < base.lo if self.side[n] == "low" else False

    def _may_replicate(self, n: str, vd: Verdict) -> bool:
        """Could the window's verdict ``vd`` on ``n`` replicate a confirmation (:meth:`_apply`)?  An ``unresolved``
        verdict beyond the band on the side ``n`` was confirmed on.  Its test is the likelihood ratio too, as the
        first confirmation's is: the Wald z only chose the windows worth the restricted fit."""
        if vd.state != "unresolved" or not math.isfinite(vd.z):
            return False
        return self.side[n] == ("high" if vd.z > 0 else "low") and self._beyond_confirmed(n, vd.value)

    def _likelihood_ratio(self, vd: Verdict, res, rec, tracker, names: Sequence[str],
                          filtered: Mapping[str, float] | None = None) -> Verdict:
        """The verdict ``vd`` (``high``/``low`` by the window's Wald test) tested again by the window's likelihood
        ratio: the window fitted once more with the parameter held at its baseline (the others and the offsets
        free, started from the window's estimate and from the filter's, the lower kept), and
        ``z^2 = 2 (cost_0 - cost) / s^2 x (s_white / s_HAC)^2``
        (the rise of the weighted squared residuals in units of their variance, widened as the HAC standard
        error widens the white one).  The Wald test's standard error is a curvature at the window's estimate:
        in the log of a parameter whose effect is linear (the leakage), it shrinks as the estimate grows, and a
        window that ran to five times the leakage was "4.3 standard errors" from a baseline that fitted it
        almost as well.  The ratio is the same in every parametrisation, and a restricted fit that ends lower
        than the window's own says the window's minimum was not the one (no evidence).  The two-sample test
        then reads the ratio's z as an effective standard error ``|log(theta_w / theta_0)| / z`` beside the
        baseline's own.  A transducer offset is tested the same way against 0 Pa: where the window's leakage ran to
        zero, an offset took its place (a leakage step read as a pB offset), and the restricted fit, free to move
        the leakage, fits the window as well with the transducer read true."""
        offset = vd.name in SENSOR_PARAMS  # a transducer's offset, tested against 0 Pa
        null = 0.0 if offset else self.baseline[vd.name].value
        sw, sh = float(res.std_white.get(vd.name, math.nan)), float(res.std.get(vd.name, math.nan))
        # from the window's estimate (a parameter it ran off its range from the rig's configured value) and from
        # the filter's: the lower of the two restricted fits
        starts = [{k: float(v) for k, v in res.estimate.items()}]
        if filtered:
            starts.append({**starts[0], **{k: float(v) for k, v in filtered.items()}})
        fits = [r for r in (fit_window(rec, tracker, names, st, self.sensors, held={vd.name: null})
                            for st in starts) if r is not None]
        r0 = min(fits, key=lambda r: r.cost) if fits else None
        n_obs, n_par = int(res.n_obs), int(res.n_par)
        s2 = 2.0 * float(res.cost) / max(n_obs - n_par, 1)
        if r0 is None or not (math.isfinite(sw) and math.isfinite(sh) and sh > 0 and s2 > 0):
            return dataclasses.replace(vd, state="not_testable", why="the window's likelihood ratio could not be "
                                                                   "computed (the restricted fit failed)")
        rise = 2.0 * (float(r0.cost) - float(res.cost))
        z_lr = math.sqrt(max(rise, 0.0) / s2) * (sw / sh)
        if offset:
            d = vd.value
            out = decide_offset(vd.name, vd.value, abs(d) / max(z_lr, 1e-12), True, self.alpha)
        else:
            base = self.baseline[vd.name]
            d = math.log(vd.value / base.value)
            out = decide(vd.name, vd.value, abs(d) / max(z_lr, 1e-12), base, True, self.base_std.get(vd.name, 0.0),
                         self.alpha, resolve=math.inf)
        why = (f"likelihood ratio against {'a true transducer' if offset else 'the baseline'}: z "
               f"{math.copysign(z_lr, d):+.1f} (Wald {vd.z:+.1f})")
        if out.state not in ("high", "low"):
            why += f"; {'0 Pa' if offset else 'the baseline'} fits the window nearly as well"
        return dataclasses.replace(out, rel_std=vd.rel_std, why=why)

    @staticmethod
    def _adequate_at(res, values: Mapping[str, float], rec, tracker) -> bool:
        """Does the adequacy test pass at the filter's estimate ``values`` (the window fit's sensor offsets
        kept)?  The test at the least-squares point can fail on a right model: a short window's output-error fit
        can land off the truth along a ridge it cannot pin down (the leakage against the valve's dynamics), and
        the drive then explains a share of the prediction errors.  A parameter point of the model that passes
        says the model represents the window; accepting on either point can only lower the rate of windows
        called "not represented", never raise a false inadequacy."""
        from twin.estimation.diagnose.check import fit_adequacy

        vals = {n: float(v) for n, v in values.items() if math.isfinite(v) and v > 0}
        if not vals:
            return False
        at = dataclasses.replace(res, params=res.params.update(vals))
        try:
            check = fit_adequacy(tracker.model, [rec], at, timing=tracker.timing)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            return False
        return bool(check.get("adequate", False))

    def _verdicts(self, res, names, bounds, adequate: bool) -> tuple[dict[str, Verdict], dict[str, Verdict]]:
        """Each parameter's and each transducer offset's verdict from the window fit ``res``; ``adequate``: the
        window's adequacy (at the fitted values or at the filter's estimate, :meth:`_adequate_at`)."""
        verdicts = {}
        for n in names:
            v = float(res.estimate[n])
            sd = float(res.std.get(n, math.nan))
            lo, hi = bounds[n]
            if adequate and not lo < v < hi:  # beyond what the filter may hold for this rig: the fit ran off
                verdicts[n] = Verdict(n, "not_testable", v, why="the window's fit left the parameter's physical "
                                                                f"range ({lo:.3g} .. {hi:.3g})")
                continue
            shared = [p for p in SENSOR_PARAMS if p in res.free and abs(float(
                res.corr[res.free.index(n), res.free.index(p)])) > SENSOR_CORR]
            if adequate and shared:
                verdicts[n] = Verdict(n, "not_testable", v, sd / v if v > 0 else math.nan,
                                      why=f"the window cannot tell it from the offset of {', '.join(shared)}")
                continue
            # a window beyond the band on the side of a standing confirmation is not gated by its width: its
            # test is the likelihood ratio (:meth:`_may_replicate`), which a window that does not inform the
            # parameter passes at the replication's level only
            verdicts[n] = decide(n, v, sd / v if v > 0 else math.nan, self.baseline[n], adequate,
                                 self.base_std.get(n, 0.0), self.alpha,
                                 resolve=math.inf if self._beyond_confirmed(n, v) else RESOLVE)
        sensors = {p: decide_offset(p, float(res.estimate[p]), float(res.std.get(p, math.nan)), adequate,
                                    self.alpha) for p in SENSOR_PARAMS if p in res.estimate}
        return verdicts, sensors

    def _event(self, name: str, level: str, kind: str, vd: Verdict, t_ns: int, now: float, base: Baseline,
               msg: str) -> AlarmEvent:
        v = vd.value if math.isfinite(vd.value) else base.value
        sd = abs(v) * vd.rel_std if math.isfinite(vd.rel_std) else 0.0
        return AlarmEvent(rig=self.rig, parameter=name, level=level, kind=kind, t_ns=t_ns, t_s=now, estimate=v,
                          std=sd, baseline=base.value, band_lo=base.lo, band_hi=base.hi,
                          statistic=vd.z if math.isfinite(vd.z) else 0.0, message=msg)

    def _apply(self, n: str, vd: Verdict, t_ns: int, now: float, reason: str,
               filtered: float = math.nan) -> list[AlarmEvent]:
        """One window's verdict on ``n``; ``filtered``: the filter's estimate at the window's end (NaN: not known,
        the window decides alone)."""
        base = self.baseline[n]
        if vd.state == "not_testable":
            self.state[n] = "not_testable"
            return []
        self.tested[n] = now
        self.state[n] = "ok"
        old = self.level[n]
        if vd.state == "unresolved":
            # a replication: a parameter confirmed once is confirmed again by a later window beyond its band on the
            # same side at the replication level (the first confirmation holds the level ALPHA)
            if not (self._may_replicate(n, vd) and abs(vd.z) >= critical_z(2 * REPLICATE_ALPHA)):
                return []  # tested, but the window neither confirms nor returns it: nothing changes
            vd = dataclasses.replace(vd, state=self.side[n])
        if vd.state in ("high", "low") and math.isfinite(filtered) and not (
                filtered > base.hi if vd.state == "high" else filtered < base.lo):
            return []  # the window alone says so, the filter does not: no decision (the count stays)
        if vd.state == "inside":
            self.count[n] = 0
            self.side[n] = ""
            if old == "ok":
                return []
            back, zb = back_inside(vd.value, vd.rel_std, base, self.raised_side[n], self.base_std.get(n, 0.0),
                                   self.alpha)
            if not back:  # inside by its point estimate, not by the test: the alarm stays
                return []
            self.level[n] = "ok"
            edge = "upper" if self.raised_side[n] == "high" else "lower"
            return [self._event(n, "ok", "returned", dataclasses.replace(vd, z=zb), t_ns, now, base,
                                f"{n} back inside its band (re-fit of the last {self.window_s:g} s; z {zb:+.1f} "
                                f"against its {edge} edge, level {self.alpha:g})")]
        side = "high" if vd.state == "high" else "low"
        self.count[n] = self.count[n] + 1 if self.side[n] == side else 1
        self.side[n] = side
        filt = self.trigger.params[n].level if n in self.trigger.params else "ok"
        c = self.count[n]
        new = ("alarm" if c >= ALARM_CONFIRMATIONS or (c >= WARN_CONFIRMATIONS and filt == "alarm") else
               "warning" if c >= WARN_CONFIRMATIONS else "ok")
        if ALARM_LEVELS.index(new) <= ALARM_LEVELS.index(old):
            return []
        self.level[n] = new
        self.raised_side[n] = side  # the side of the level it holds now
        kind = "escalated" if old == "warning" else "raised"
        where = "above" if side == "high" else "below"
        msg = (f"{n} {where} its healthy band, confirmed by {c} re-fits of {self.window_s:g} s windows "
               f"(last {reason}; two-sample z {vd.z:+.1f} against the baseline, level {self.alpha:g} each)")
        return [self._event(n, new, kind, vd, t_ns, now, base, msg)]

    def _apply_sensor(self, p: str, vd: Verdict, t_ns: int, now: float) -> list[AlarmEvent]:
        o = SENSOR_PARAMS[p]
        if vd.state in ("not_testable", "unresolved"):
            return []
        old = self.sensor_level[o]
        band = Baseline(0.0, -OFFSET_TOLERANCE_PA, OFFSET_TOLERANCE_PA)
        vd_abs = dataclasses.replace(vd, rel_std=vd.rel_std / abs(vd.value) if vd.value else math.nan)
        if vd.state == "inside":
            self.sensor_count[o] = min(self.sensor_count[o], 0) - 1  # windows in a row finding it within
            if old == "ok" or -self.sensor_count[o] < WARN_CONFIRMATIONS:
                return []
            self.sensor_count[o] = 0
            self.sensor_level[o] = "ok"
            return [self._event(p, "ok", "returned", vd_abs, t_ns, now, band,
                                f"sensor {o}: offset back within {OFFSET_TOLERANCE_PA * 1e-6:g} MPa")]
        self.sensor_count[o] = max(self.sensor_count[o], 0) + 1
        if old != "ok" or self.sensor_count[o] < WARN_CONFIRMATIONS:
            return []
        self.sensor_level[o] = "warning"
        return [self._event(p, "warning", "raised", vd_abs, t_ns, now, band,
                            f"sensor {o} reads {vd.value * 1e-6:+.3f} MPa off (a sensor event, not the rig: "
                            f"re-fit of the last {self.window_s:g} s, z {vd.z:+.1f})")]


def track_confirmed(samples, tracker, baseline: Mapping[str, Baseline], chunk: int = 1000,
                    **options) -> tuple[ConfirmedDrift, list[AlarmEvent]]:
    """A whole record through ``tracker`` and a :class:`ConfirmedDrift` (``options``) in blocks of ``chunk``
    samples, as the service runs a rig: the confirmation and its events."""
    cd = ConfirmedDrift("rig", baseline, tracker.model.name, **options)
    events: list[AlarmEvent] = []
    t0 = int(samples.t_ns[0])
    for i in range(0, len(samples), chunk):
        block = samples.slice(i, min(i + chunk, len(samples)))
        out = tracker.process(block)
        events += cd.update(block, out, (out.t_ns - t0) * 1e-9, tracker)
    return cd, events
