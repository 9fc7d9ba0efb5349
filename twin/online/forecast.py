"""Early warning: when each tracked parameter will leave its healthy band, with a 90 % interval.

A degradation model per tracked parameter, fed by the tracker's estimates and
their standard deviations (as the drift test, :mod:`twin.online.drift`, is):

* **Decimation.** The estimates are averaged in the filter's log coordinates
  ``y = log(theta / baseline)`` over bins of ``step_s`` (1 s by default); a bin
  keeps the *mean* of the filter's log standard deviation, not the mean divided
  by the square root of its sample count, since the estimates inside a bin are
  one correlated stretch of the filter's memory, not independent samples.
  Samples the drift test would not count (frozen, held by the consistency guard,
  unresolved: standard deviation above ``resolve`` times the band's log
  half-width) are left out, and so are the first ``settle_s`` seconds after a
  start or a reset (the filter converging from its start is not wear).
* **Two trend models**, as the two degradation models of MATLAB's Predictive
  Maintenance Toolbox: *linear* in the parameter (``theta/baseline = a + b t``,
  linearDegradationModel) and *exponential* in the parameter (``y = a + b t``
  in the log coordinates, exponentialDegradationModel with no offset).  Each is
  a weighted linear regression (weights the inverse of each bin's variance in
  the model's own coordinates) with an unknown noise scale, updated in closed
  form as a conjugate normal-inverse-gamma model under the reference (Jeffreys)
  prior: the coefficients' posterior is a Student t with ``n_eff - 2`` degrees
  of freedom around the weighted least-squares line, its scale the residual
  variance.  The noise scale is learnt from the residuals, so a filter that
  under- or over-states its uncertainty does not make the forecast over- or
  under-confident.
* **Onset.** A wear may start after healthy running: a straight line through all the data then bends the evidence
  away (its residuals are one long excursion). Besides the trend over all the data, each model is fitted from
  :data:`HINGE_POINTS` candidate onsets (geometric from ``min_span_s`` to :data:`HINGE_REACH` of the data's span
  before now): flat before the onset, the trend after it (a hinge, one more parameter in the BIC), the hinges
  sharing half the prior. All candidates are averaged by weight; each one's exit counts within the reach of its own
  stretch (from its onset).
* **Correlation.** Bins are not independent either when the filter's memory, an
  estimation error that follows the excitation, or a model misfit (a curved
  wear on a straight line) outlasts a bin: the integrated autocorrelation time
  ``tau_int`` of the chosen model's standardised residuals (Geyer's initial
  positive sequence; for AR(1) errors it is the ``(1 + r)/(1 - r)`` the drift
  test weights its increments by) gives an effective sample size
  ``n_eff = n / tau_int``, and the likelihood is tempered by ``kappa = n_eff / n``: the coefficients' covariance grows by
  ``1 / kappa`` and the degrees of freedom shrink to ``n_eff - 2``.  The filter's own memory is its time constant
  ``V / q`` (posterior variance over the random walk's rate, log units): 4-7 s for the leakage, under a second
  for friction and the valve; Geyer's ``tau_int`` of the 1 s bins is about twice it (5-9 bins on the
  leakage, 1 on friction), as for an Ornstein-Uhlenbeck error, and covers the slower errors the
  excitation leaves too.  On a short stretch Geyer's estimate falls short (a minute of the leakage holds a few
  excursions of its wander, not enough to see their length), so ``tau_int`` is never taken below the filter's own
  memory: the bins of an estimate that forgets with ``V / q`` are AR(1) with ``r = exp(-step / (V / q))``, whose
  integrated time is ``(1 + r) / (1 - r)`` (the drift test's factor, :mod:`twin.online.drift`; ``V`` the mean of
  the bins' variances, ``q`` the parameter's ``drift_rate`` squared).
* **Evidence.** The two models are averaged by their BIC weights (their
  likelihoods compared in the same coordinates, the Jacobian of the change of
  variables included; both have two coefficients), and a forecast exists only
  when the better trend beats a flat line by ``evidence`` (default 10: "very
  strong" on Kass & Raftery's scale) in ``BIC`` computed with the tempered
  likelihood and ``n_eff`` - a flat, healthy parameter has none.
* **Forecast.** For each model the trend's level at ``tau`` seconds from now is
  Student-t distributed, so the probability that the parameter has left its band
  by ``now + tau`` is closed form, ``P(level(tau) >= hi) + P(level(tau) <= lo)``
  (the level is a straight line in the model's coordinates, so having crossed
  an edge before ``tau`` and being beyond it at ``tau`` are the same event); the
  model average of the two is the distribution of the exit time, its median
  and 5 % / 95 % quantiles are read off a grid of ``tau`` (no random draws: the
  same data give the same forecast, before and after a restart), the interval
  widened by one bin (``step_s``) on either side (the decimated time axis
  resolves no finer; near the exit, where the interval is a few seconds wide,
  the filter's own bias, which no trend can see, is of that order), and its value
  at the horizon is ``p_within_horizon``.  A quantile beyond the grid's end
  (``1000`` horizons) is ``None``: the trend may never get there.
* **Discrepancy.** A level error of the twin against the plant that moves slower than the regression can see is in
  the intercept, not in the residuals, so no trend sees it. Its standard deviation is a fraction ``discrepancy``
  (:data:`DISCREPANCY`) of the bins' own scatter about the trend (``sqrt(rss / (n - 2))`` in the filter's
  weights): the slow error is driven by the same sensor noise as the fast one (the joint filter's noise-driven
  parameter error), so a noisier rig's allowance grows with it. Its variance is added to that of the trend's level
  at every future time; near the exit it sets the interval's width.
* **Reach.** ``p_within_horizon`` counts only exits no further ahead than ``reach`` (:data:`REACH`, 2) times the
  span of the data the trend was fitted on: a trend is not extrapolated far beyond the stretch that supports it (a
  curve that flattens, such as a warming oil's leakage, looks straight over a short stretch; on the calibration
  record of a warming oil the unlimited probability reached 0.98 within an hour while the leakage levelled off at
  +30 %).  The exit-time quantiles are those of the trend carried on.
* **Early alarm.** Level ``early`` (:class:`twin.online.events.AlarmEvent`,
  kind ``raised``) when ``p_within_horizon >= p_early`` (0.9); it returns
  (level ``ok``, kind ``returned``) when the probability has stayed below
  ``p_clear`` (0.5), or no forecast has existed, for ``clear_s`` (60 s):
  hysteresis so a noisy trend does not flap.
* **Reset** (:meth:`ForecastMonitor.reset`): a re-commissioning or a recorded
  maintenance event (:mod:`twin.service.maintenance`) forgets a parameter's history (and returns its ``early``
  alarm); a maintenance is kept per parameter (:attr:`ForecastMonitor.maintained`, in the forecast messages) with
  the ``seq`` of the last one applied (:attr:`ForecastMonitor.maintenance_seq`, in the state: a restart applies
  each once).

Per sample the monitor only bins (vectorised over a block); the regression runs
once per completed bin and parameter on at most ``max_points`` bins (older bins
are merged pairwise beyond that: the span stays, the resolution of the old part
halves).  :meth:`ForecastMonitor.state` / :meth:`ForecastMonitor.restore` are
plain data (numbers and lists) for checkpoints.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numba as nb
import numpy as np

from twin.online.baseline import Baseline
from twin.online.drift import drift_rates, memory_factor
from twin.models import DEFAULT_MODEL
from twin.online.events import AlarmEvent
from twin.online.events.forecast import Forecast, describe, fmt_duration

#: Default forecast horizon [s] (``forecast_horizon_s`` per rig, ``twin track --forecast-horizon``).
DEFAULT_HORIZON_S = 3600.0
#: The exit-time grid: from 0 to this many horizons (beyond: "maybe never").
GRID_HORIZONS = 1000.0
#: Points of the exit-time grid (geometric from one bin): 1000 points put neighbours 1.5 % apart, a resolution
#: finer than any interval the forecast gives (160 points, 10 % apart, widened an interval 60 s ahead by up to 6 s).
GRID_POINTS = 1000
_QUANTILES = (0.05, 0.5, 0.95)
#: The twin's slow level error against the plant, per parameter, as a fraction of the bins' scatter about the trend
#: [1]: the tracker's estimate of a parameter differs from the plant's by an error that moves slowly (a model-form
#: bias, a weakly identified parameter's wander) and that no trend sees (it is in the intercept, not in the
#: residuals). Each is the RMS, over the independent reference simulator's calibration records where that parameter
#: wears (Cd and zeta, which none wears: all six calibration records), of the *excess* level error over the bins'
#: scatter: the 60-s means of (log estimate - log truth), after the first minute and up to the exit, vary by
#: ``sqrt(excess^2 + sigma^2 tau / 60)`` where ``sigma`` is the bins' scatter about the truth and ``tau`` their
#: integrated autocorrelation time (the part the regression already counts); ``excess / sigma`` per record, by
#: ``python -m benchmarks.forecast --set calib --json`` (each record's ``level_error``, the summary's
#: ``discrepancy_rule``): Ffric seed 14 (0.164), CdAleak seeds 11 and 13 (0.252, 0), wn seed 12 (0.105), Cd
#: (0.136, 0, 0.181, 0.272, 0.072, 0.182), zeta (0.129, 0, 0, 0, 0.069, 0). docs/explanation/constants.md.
DISCREPANCY = {"Ffric": 0.164, "CdAleak": 0.178, "Cd": 0.165, "zeta": 0.060, "wn": 0.105}
#: a parameter of another model (no calibration records): the largest of the table
DISCREPANCY_OTHER = max(DISCREPANCY.values())


#: Candidate onsets of a wear (the hinge of a trend that is flat before it), in seconds before now: geometric from
#: ``min_span_s`` to this fraction of the data's span, this many points (neighbours 6 % apart over 60-1000 s).
#: Chosen on a synthetic late-onset wear (``tests/test_forecast.py``, 10 healthy minutes, then a linear wear): the
#: last third's coverage 64 % with 12 points, 66 % with 24, 91 % with 48 (a coarse grid puts the onset off and
#: biases the slope). docs/explanation/constants.md.
HINGE_REACH = 0.9
HINGE_POINTS = 48
#: How far ahead ``p_within_horizon`` counts an exit, in spans of the data the trend was fitted on [1]. Tuned on the
#: calibration records (``python -m benchmarks.forecast --set calib``, seeds < 1000): every wear record's first
#: early alarm comes a quarter of its wear ahead from 1.1 on (the exponential leakage wear at doubled noise, seed 13:
#: 0.23 at 1, 0.25 at 1.1, 0.26 at 1.2, 0.50 at 2), and the healthy warming record (seed 21, the leakage rising 30 %
#: and levelling off) stays far from an early alarm up to 3 (its largest probability 0.01 at 2, 0.14 at 3, 0.31 at 4,
#: 0.75 at 6, an early alarm at 8): 2 leaves a factor of about two on either side. docs/explanation/constants.md.
REACH = 2.0


def discrepancy_of(names, given: float | Mapping[str, float] | None = None) -> dict[str, float]:
    """Each parameter's slow level error as a fraction of its bins' scatter: ``given`` (one number for all, or per
    name) over :data:`DISCREPANCY`, :data:`DISCREPANCY_OTHER` for a name in neither."""
    if given is not None and not isinstance(given, Mapping):
        return {n: float(given) for n in names}
    table = {**DISCREPANCY, **dict(given or {})}
    return {n: float(table.get(n, DISCREPANCY_OTHER)) for n in names}


@dataclasses.dataclass
class _Param:
    name: str
    base: Baseline
    pts: np.ndarray  # rows: t, y, log std, held; the history's whole length (the first ``n`` hold bins)
    n: int = 0
    acc: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0, 0.0])  # sum t, y, s, h; count
    since: float | None = None  # record time of the first usable sample after a start or reset
    level: str = "ok"
    clear_since: float | None = None
    last: Forecast | None = None


class ForecastMonitor:
    """Per-rig degradation forecasts; feed it the tracker's blocks with :meth:`update_block`.

    ``baseline``: each parameter's healthy value and band; ``horizon_s``: the horizon of ``p_within_horizon``;
    ``step_s``: the decimation (one bin, one regression point and one forecast per ``step_s`` of record);
    ``drift_rate``: each parameter's random-walk intensity in the tracker (log units per sqrt(s), default its spec's,
    as the drift test's), whose memory bounds the bins' correlation from below.
    See the module docstring for the other settings.
    """

    def __init__(self, rig: str, baseline: Mapping[str, Baseline], horizon_s: float = DEFAULT_HORIZON_S,
                 step_s: float = 1.0, p_early: float = 0.9, p_clear: float = 0.5, clear_s: float = 60.0,
                 settle_s: float = 30.0, min_span_s: float = 60.0, evidence: float = 10.0, resolve: float = 0.5,
                 max_points: int = 1800, reach: float = REACH,
                 discrepancy: float | Mapping[str, float] | None = None, model: str = DEFAULT_MODEL,
                 drift_rate: Mapping[str, float] | None = None):
        if not (horizon_s > 0 and math.isfinite(horizon_s)):
            raise ValueError(f"forecast horizon must be a positive number of seconds, got {horizon_s!r}")
        self.rig = rig
        self.model = model
        self.horizon_s = float(horizon_s)
        self.step_s = float(step_s)
        self.p_early, self.p_clear, self.clear_s = float(p_early), float(p_clear), float(clear_s)
        self.settle_s, self.min_span_s, self.evidence = float(settle_s), float(min_span_s), float(evidence)
        self.resolve = float(resolve)
        self.max_points = int(max_points)
        self.reach = float(reach)
        self.discrepancy = discrepancy_of(baseline, discrepancy)
        self.drift_rate = drift_rates(model, baseline, drift_rate)
        # each parameter's bins in an array of the history's full length from the start, written through once: the
        # history's memory is taken in the first second, not over its first 30 minutes
        self.params = {n: _Param(n, b, pts=np.full((self.max_points, 4), np.nan)) for n, b in baseline.items()}
        self._origin: float | None = None
        self._bin = -1  # index of the bin being filled
        self._bin_last: tuple[int, float] | None = None  # (t_ns, t_s) of the last sample of the bin being filled
        self._last_values: tuple[np.ndarray, np.ndarray, list[str]] | None = None  # for the alarms' estimate
        self.maintenance_seq = 0
        """``seq`` of the last recorded maintenance event applied (:mod:`twin.service.maintenance`)."""
        self.maintained: dict[str, dict[str, Any]] = {}
        """parameter -> its last maintenance: ``t`` (record s), ``seq``, ``note``, ``wall_ns``."""
        grid = np.concatenate([[0.0], np.geomspace(self.step_s, GRID_HORIZONS * self.horizon_s, GRID_POINTS)])
        self._grid = np.unique(np.append(grid, self.horizon_s))

    # -- data in ----------------------------------------------------------------------------------------------
    def update_block(self, names: Sequence[str], t_ns: np.ndarray, t_s: np.ndarray, est: np.ndarray,
                     log_std: np.ndarray, frozen: np.ndarray, hold: np.ndarray | None = None,
                     held_log_std: np.ndarray | None = None) -> tuple[list[AlarmEvent], list[Forecast]]:
        """Bin a block of the tracker's output; at every completed bin, a forecast per parameter that has one.

        ``log_std``: the filter's standard deviation of the log estimate (the regression's weights);
        ``held_log_std``: the estimate's error if the parameter held still
        (:attr:`twin.online.tracker.TrackBlock.held_log_std`, default ``log_std``), the uncertainty of the
        current level that the trend does not average away.

        Returns the ``early`` alarm events raised or returned and the forecasts made (in time order)."""
        T = len(t_s)
        if T == 0:
            return [], []
        cols = [(j, n) for j, n in enumerate(names) if n in self.params]
        if not cols:
            return [], []
        t_s = np.asarray(t_s, float)
        if self._origin is None:
            self._origin = float(t_s[0])
            self._bin = 0
        jj = [j for j, _ in cols]
        ps = [self.params[n] for _, n in cols]
        val = np.array([q.base.value for q in ps])
        half = 0.5 * np.log(np.array([q.base.hi / q.base.lo for q in ps]))
        E = np.asarray(est, float)[:, jj]
        S = np.asarray(log_std, float)[:, jj]
        ok = ~np.asarray(frozen, bool)[:, jj] & np.isfinite(S) & (S > 0) & (self.resolve * half >= S) & (E > 0)
        if hold is not None:
            ok &= ~np.asarray(hold, bool)[:, None]
        Y = np.log(np.where(ok, E, 1.0) / val)
        Sm = np.where(ok, S, 0.0)
        Hm = Sm if held_log_std is None else np.where(ok, np.asarray(held_log_std, float)[:, jj], 0.0)
        Y = np.where(ok, Y, 0.0)
        b = np.floor((t_s - self._origin) / self.step_s).astype(np.int64)
        b = np.maximum.accumulate(np.maximum(b, self._bin))  # a sample out of order (jitter) joins the open bin
        cuts = np.flatnonzero(np.diff(b)) + 1
        starts = np.concatenate([[0], cuts])
        okf = ok.astype(float)
        sums_t = np.add.reduceat(okf * t_s[:, None], starts, axis=0)
        sums_y = np.add.reduceat(Y, starts, axis=0)
        sums_s = np.add.reduceat(Sm, starts, axis=0)
        sums_h = np.add.reduceat(Hm, starts, axis=0)
        counts = np.add.reduceat(okf, starts, axis=0)
        ends = np.concatenate([cuts, [T]]) - 1
        events: list[AlarmEvent] = []
        forecasts: list[Forecast] = []
        for k, i0 in enumerate(starts):
            seg_bin = int(b[i0])
            if seg_bin != self._bin:  # the bin being filled is complete
                events_k, fc_k = self._close_bin(ps)
                events += events_k
                forecasts += fc_k
                self._bin = seg_bin
            for m, q in enumerate(ps):
                a = q.acc
                a[0] += float(sums_t[k, m])
                a[1] += float(sums_y[k, m])
                a[2] += float(sums_s[k, m])
                a[3] += float(sums_h[k, m])
                a[4] += float(counts[k, m])
            i1 = int(ends[k])
            self._bin_last = (int(t_ns[i1]), float(t_s[i1]))
            self._last_values = (E[i1].copy(), S[i1].copy(), [q.name for q in ps])
        return events, forecasts

    def _close_bin(self, ps: list[_Param]) -> tuple[list[AlarmEvent], list[Forecast]]:
        if self._bin_last is None:
            return [], []
        t_ns, now = self._bin_last
        events, out = [], []
        for q in ps:
            n_acc = q.acc[4]
            if n_acc > 0:
                tm = q.acc[0] / n_acc
                if q.since is None:
                    q.since = tm
                if tm - q.since >= self.settle_s:
                    if q.n == len(q.pts):  # the history is full (its array has its whole length from the start)
                        self._merge(q)
                    q.pts[q.n] = (tm, q.acc[1] / n_acc, q.acc[2] / n_acc, q.acc[3] / n_acc)
                    q.n += 1
            q.acc = [0.0, 0.0, 0.0, 0.0, 0.0]
            fc = self._forecast(q, now, t_ns)
            q.last = fc
            if fc is not None:
                out.append(fc)
            ev = self._level(q, fc, now, t_ns)
            if ev is not None:
                events.append(ev)
        return events, out

    @staticmethod
    def _merge(q: _Param) -> None:
        """Halve the resolution: consecutive pairs of bins averaged (time, level, log std)."""
        m = q.n // 2 * 2
        merged = 0.5 * (q.pts[:m:2] + q.pts[1:m:2])
        rest = q.pts[m:q.n].copy()
        q.pts[:len(merged)] = merged
        q.pts[len(merged):len(merged) + len(rest)] = rest
        q.n = len(merged) + len(rest)

    # -- the models ---------------------------------------------------------------------------------------------
    def _forecast(self, q: _Param, now: float, t_ns: int) -> Forecast | None:
        n = q.n
        if n < 10 or q.pts[n - 1, 0] - q.pts[0, 0] < self.min_span_s:
            return None
        t = q.pts[:n, 0] - now
        y = np.ascontiguousarray(q.pts[:n, 1])  # one layout for the compiled fits
        s = q.pts[:n, 2]
        u = np.exp(y)
        w_e = 1.0 / (s * s)  # log coordinates: exponential model
        w_l = 1.0 / (u * u * s * s)  # the parameter over its baseline: linear model (delta method)
        span = float(t[-1] - t[0])
        # candidate onsets of the wear (hinges, seconds before now): a trend that starts there and is flat before it,
        # each with at least ``min_span_s`` and 10 bins after it; the first is no hinge (the trend over all the data)
        onsets = np.concatenate([[span], _geometric(self.min_span_s, HINGE_REACH * span)
                                 if HINGE_REACH * span > self.min_span_s else []])
        # the bins are in time order: each hinge's count of bins after it, and where its flat part ends
        onsets = onsets[np.concatenate([[True], n - np.searchsorted(t, -onsets[1:], side="right") >= 10])]
        cuts = np.concatenate([[0], np.searchsorted(t, -onsets[1:], side="left")]).astype(np.intp)  # bins before
        k_par = np.where(np.arange(onsets.size) == 0, 2.0, 3.0)  # a hinge adds its onset
        n_hinge = onsets.size - 1
        # prior: half on the trend over all the data, half spread over the hinges (none: all on it)
        log_prior = np.where(np.arange(onsets.size) == 0, math.log(0.5 if n_hinge else 1.0),
                             math.log(0.5 / max(n_hinge, 1)))
        # the candidates, each shape over every onset (the exponential's first): shape, onset index, coefficients,
        # covariances, weighted rss
        fit_e, fit_l = (_wls_hinges(t, -onsets, cuts, obs, w) for obs, w in ((y, w_e), (u, w_l)))
        is_exp_all = np.repeat([True, False], onsets.size)
        j_on = np.tile(np.arange(onsets.size), 2)
        coef_all, cov_all, rss_all = (np.concatenate([a, b]) for a, b in zip(fit_e, fit_l))
        log_rss = np.log(np.maximum(rss_all, 1e-300))
        rss_flat = float(np.sum(w_e * (y - np.sum(w_e * y) / np.sum(w_e)) ** 2))
        # the correlation from the residuals of the best candidate (untempered BIC), never below the filter's memory
        ib = int(np.argmin(n * log_rss + k_par[j_on] * math.log(n)))
        obs_b, w_b = (y, w_e) if is_exp_all[ib] else (u, w_l)
        z_b = t if j_on[ib] == 0 else np.maximum(t, -onsets[j_on[ib]])
        kappa = _kappa((obs_b - coef_all[ib, 0] - coef_all[ib, 1] * z_b) * np.sqrt(w_b))
        v_mean = float(np.mean(s * s))  # the filter's mean variance over the bins (log units)
        # never fewer bins per independent one than the filter's own memory gives
        kappa = min(kappa, 1.0 / memory_factor(self.step_s, v_mean, self.drift_rate.get(q.name)))
        n_eff = max(kappa * n, 3.0)
        # BIC with the tempered likelihood: the Jacobian of u = exp(y) cancels against the weights (see module doc)
        bic = kappa * n * log_rss + k_par[j_on] * math.log(n_eff)
        evidence = kappa * n * math.log(max(rss_flat, 1e-300)) + math.log(n_eff) - float(bic.min())
        if not evidence >= self.evidence:
            return None
        logw = log_prior[j_on] - 0.5 * (bic - bic.min())
        wts = np.exp(logw - logw.max())
        wts /= wts.sum()
        w_exp = float(np.sum(wts[is_exp_all]))
        lo, hi = q.base.lo / q.base.value, q.base.hi / q.base.value
        nu = max(n_eff - 2.0, 1.0)
        # the twin's own slow level error, which no trend sees: a fraction of the bins' scatter about the trend, in
        # log units (the best candidate's residual variance at the bins' mean weight; the weights make both shapes'
        # residuals relative), and relative to the linear trend's level now
        d2 = self.discrepancy[q.name] ** 2 * float(rss_all[ib]) / max(n - 2.0, 1.0) * v_mean
        # the candidates that carry 99.9 % of the weight (neighbouring onsets share it), renormalised
        order = np.argsort(wts)[::-1]
        keep = order[:int(np.searchsorted(np.cumsum(wts[order]), 0.999)) + 1]
        is_exp = is_exp_all[keep]
        coef = coef_all[keep]
        # an exit counts within the reach of the stretch that supports each trend: from its onset
        grid = np.concatenate([np.broadcast_to(self._grid, (keep.size, self._grid.size)),
                               np.minimum(self.horizon_s, self.reach * onsets[j_on[keep]])[:, None]],
                              axis=1)
        F = (wts[keep] / wts[keep].sum()) @ _exit_cdf(
            coef, cov_all[keep], rss_all[keep], kappa, n, nu,
            np.where(is_exp, math.log(lo), lo), np.where(is_exp, math.log(hi), hi), grid,
            np.where(is_exp, d2, d2 * coef[:, 0] ** 2))
        p_alarm = float(F[-1])
        F = F[:-1]
        F = np.maximum.accumulate(F)
        qs: list[float | None] = []
        for p in _QUANTILES:
            if F[-1] < p:
                qs.append(None)
            elif F[0] >= p:
                qs.append(now)
            else:
                i = int(np.searchsorted(F, p))
                f0, f1, g0, g1 = F[i - 1], F[i], self._grid[i - 1], self._grid[i]
                qs.append(now + float(g0 + (g1 - g0) * (p - f0) / max(f1 - f0, 1e-300)))
        if qs[1] is None:  # the trend heads for no edge (or too slowly to say)
            return None
        # the time axis is resolved to one bin: the interval widened by a bin on either side
        qs[0] = max(now, qs[0] - self.step_s) if qs[0] is not None else None
        qs[2] = qs[2] + self.step_s if qs[2] is not None else None
        slope = float(coef_all[int(np.argmax(wts)), 1])
        return Forecast(q.name, now, t_ns, qs[1], qs[0], qs[2], p_alarm, w_exp, float(evidence),
                        "high" if slope > 0 else "low")

    # -- the early alarm ----------------------------------------------------------------------------------------
    def _level(self, q: _Param, fc: Forecast | None, now: float, t_ns: int) -> AlarmEvent | None:
        p = fc.p_within_horizon if fc is not None else 0.0
        if q.level == "ok":
            if fc is not None and p >= self.p_early:
                q.level = "early"
                q.clear_since = None
                return self._event(q, fc, "raised", now, t_ns)
            return None
        if p >= self.p_clear:
            q.clear_since = None
            return None
        if q.clear_since is None:
            q.clear_since = now
        if now - q.clear_since >= self.clear_s:
            q.level = "ok"
            q.clear_since = None
            return self._event(q, fc, "returned", now, t_ns)
        return None

    def _event(self, q: _Param, fc: Forecast | None, kind: str, now: float, t_ns: int,
               why: str = "") -> AlarmEvent:
        value, std = self._current(q)
        if kind == "raised":
            assert fc is not None
            msg = f"{q.name} leaves its band {describe(fc)}"
            level, stat = "early", fc.p_within_horizon
        else:
            msg = f"{q.name}: no exit from its band foreseen within {fmt_duration(self.horizon_s)}{why}"
            level, stat = "ok", (fc.p_within_horizon if fc is not None else 0.0)
        return AlarmEvent(rig=self.rig, parameter=q.name, level=level, kind=kind, t_ns=int(t_ns), t_s=float(now),
                          estimate=value, std=std, baseline=q.base.value, band_lo=q.base.lo, band_hi=q.base.hi,
                          statistic=float(stat), message=msg)

    def _current(self, q: _Param) -> tuple[float, float]:
        last = self._last_values
        if last is not None and q.name in last[2]:
            m = last[2].index(q.name)
            v, s = float(last[0][m]), float(last[1][m])
            if v > 0 and math.isfinite(v) and math.isfinite(s):
                return v, v * s
        return q.base.value, 0.0

    # -- resets, outputs, checkpoints -----------------------------------------------------------------------------
    def reset(self, names: Sequence[str] | None = None, why: str = "maintenance",
              record: Mapping[str, Any] | None = None) -> list[AlarmEvent]:
        """Forget the history of ``names`` (default all): a re-commissioning or a maintenance event. An ``early``
        alarm standing on a forgotten history returns (the events are returned). ``record``: the recorded
        maintenance event (``seq``, ``note``, ``wall_ns``), kept per parameter (:attr:`maintained`) and its
        ``seq`` as :attr:`maintenance_seq`."""
        events = []
        if record is not None:
            self.maintenance_seq = max(self.maintenance_seq, int(record.get("seq", 0)))
            now = self._bin_last[1] if self._bin_last is not None else None
            for n in (names if names is not None else list(self.params)):
                if n in self.params:
                    self.maintained[n] = {"t": now, "seq": int(record.get("seq", 0)),
                                          "note": str(record.get("note") or ""), "wall_ns": record.get("wall_ns")}
        for n in (names if names is not None else list(self.params)):
            q = self.params.get(n)
            if q is None:
                continue
            if q.level == "early" and self._bin_last is not None:
                t_ns, now = self._bin_last
                q.level = "ok"
                events.append(self._event(q, None, "returned", now, t_ns, why=f" (history reset: {why})"))
            self.params[n] = _Param(n, q.base, pts=q.pts)  # the same buffer, no bins in it
        return events

    def latest(self) -> dict[str, Forecast]:
        """The last forecast of each parameter that has one."""
        return {n: q.last for n, q in self.params.items() if q.last is not None}

    def levels(self) -> dict[str, str]:
        return {n: q.level for n, q in self.params.items()}

    def state(self) -> dict[str, Any]:
        """Plain data from which :meth:`restore` continues exactly: numbers, strings, lists, dicts and each
        parameter's bins as one float64 array ``[n, 4]`` (a checkpoint keeps it as raw bytes,
        :func:`twin.service.checkpoint_file.encode_state`: a full history is 1800 rows a parameter, taken every
        second, and a list of its numbers cost 20 times the CPU to write and twice the bytes)."""
        return {"version": 2, "origin": self._origin, "bin": self._bin, "maintenance_seq": self.maintenance_seq,
                "maintained": {n: dict(m) for n, m in self.maintained.items()},
                "bin_last": None if self._bin_last is None else list(self._bin_last),
                "params": {n: {"points": q.pts[:q.n].copy(), "acc": list(q.acc), "since": q.since,
                               "level": q.level, "clear_since": q.clear_since,
                               "last": None if q.last is None else dataclasses.asdict(q.last)}
                           for n, q in self.params.items()}}

    def restore(self, state: Mapping[str, Any]) -> None:
        """Continue from :meth:`state` of a monitor of the same rig (a state of another layout: start afresh)."""
        if state.get("version") != 2:
            return
        self._origin = state["origin"]
        self._bin = int(state["bin"])
        self.maintenance_seq = int(state.get("maintenance_seq", 0))
        self.maintained = {n: dict(m) for n, m in (state.get("maintained") or {}).items()}
        bl = state["bin_last"]
        self._bin_last = None if bl is None else (int(bl[0]), float(bl[1]))
        for n, d in state["params"].items():
            q = self.params.get(n)
            if q is None:
                continue
            pts = np.array(d["points"], dtype=float).reshape(-1, 4)  # an array, or a list of rows (earlier files)
            q.n = len(pts)
            if q.n <= len(q.pts):
                q.pts[:q.n] = pts
            else:  # a longer history than this monitor keeps: taken whole, merged at its next bin
                q.pts = pts
            q.acc = [float(v) for v in d["acc"]]
            q.since, q.level, q.clear_since = d["since"], d["level"], d["clear_since"]
            q.last = None if d["last"] is None else Forecast(**d["last"])


def _expit(z: float) -> float:
    """The logistic function, without overflow for any finite ``z``."""
    if z >= 0:
        return 1.0 / (1.0 + math.exp(-z))
    e = math.exp(z)
    return e / (1.0 + e)


_HINGE_STEPS = np.arange(HINGE_POINTS) / (HINGE_POINTS - 1)


def _geometric(lo: float, hi: float) -> np.ndarray:
    """:data:`HINGE_POINTS` points from ``lo`` to ``hi`` in geometric progression, both ends exact (``numpy.geomspace``
    without its generality: a quarter of a forecast's time went to it)."""
    out = lo * np.exp(_HINGE_STEPS * math.log(hi / lo))
    out[0], out[-1] = lo, hi
    return out


# -- closed-form pieces --------------------------------------------------------------------------------------------
@nb.njit(cache=True, nogil=True)
def _wls_hinges(t: np.ndarray, c: np.ndarray, k: np.ndarray, y: np.ndarray, w: np.ndarray):  # pragma: no cover
    """Weighted least squares of ``y = a + b z`` for each hinge at once, ``z = max(t, c_j)`` (row 0: ``z = t``), from
    running sums over the bins in time order: ``k_j`` bins lie before the hinge (``t < c_j``, where ``z`` is the
    constant ``c_j``), the rest after it (``z = t``). Each row costs O(1) after one O(n) pass, and no array of
    hinges x bins is made: the work and the memory are those of the history, not of the history times the hinges.
    Returns the coefficients ``[m, 2]``, their unscaled covariances ``(X'WX)^-1`` ``[m, 2, 2]`` and the weighted RSS
    ``[m]`` (a row without spread: infinite RSS, a candidate that never wins)."""
    n, m = t.size, c.size
    pw = np.zeros(n + 1)  # prefix sums: the bins before each hinge
    pwy = np.zeros(n + 1)
    for i in range(n):
        pw[i + 1] = pw[i] + w[i]
        pwy[i + 1] = pwy[i] + w[i] * y[i]
    s1 = np.zeros(n + 1)  # suffix sums, from the hinge on, summed from the end
    s2 = np.zeros(n + 1)
    s3 = np.zeros(n + 1)
    for i in range(n - 1, -1, -1):
        wt = w[i] * t[i]
        s1[i] = s1[i + 1] + wt
        s2[i] = s2[i + 1] + wt * t[i]
        s3[i] = s3[i + 1] + (w[i] * y[i]) * t[i]
    sw, sy = pw[n], pwy[n]
    ybar = sy / sw
    syy_c = 0.0
    for i in range(n):
        d = y[i] - ybar
        syy_c += w[i] * d * d
    coef = np.empty((m, 2))
    cov = np.empty((m, 2, 2))
    rss = np.empty(m)
    for j in range(m):
        kj = k[j]
        cj = c[j] if kj > 0 else 0.0  # row 0, or a hinge before every bin: z = t throughout
        st = cj * pw[kj] + s1[kj]
        stt = cj * cj * pw[kj] + s2[kj]
        sty = cj * pwy[kj] + s3[kj]
        det = sw * stt - st * st
        ok = det > 1e-12 * sw * max(stt, 1e-300)
        if not ok:
            det = 1.0
        b = (sw * sty - st * sy) / det
        coef[j, 0] = (sy - b * st) / sw
        coef[j, 1] = b
        cov[j, 0, 0] = stt / det
        cov[j, 0, 1] = -st / det
        cov[j, 1, 0] = -st / det
        cov[j, 1, 1] = sw / det
        # the residual sum about the line, from the centred sums (no cancellation against the level's square)
        rss[j] = max(syy_c - b * (sty - st * sy / sw), 0.0) if ok else np.inf
    return coef, cov, rss


#: the lags the autocorrelation is summed over directly before the FFT takes over (a long positive sequence)
KAPPA_DIRECT_LAGS = 64


@nb.njit(cache=True, nogil=True)
def _tau_direct(x: np.ndarray, max_lag: int) -> float:  # pragma: no cover
    """Geyer's initial positive sequence of the centred ``x`` summed lag by lag; -1 when it is still positive at
    ``max_lag`` (the caller then takes every lag at once by FFT)."""
    n = x.size
    c0 = 0.0
    for i in range(n):
        c0 += x[i] * x[i]
    if not c0 > 0:
        return 1.0
    kmax = (n - 1) // 2 * 2
    tau = 1.0
    lag = 1
    while lag + 1 <= kmax:
        if lag > max_lag:
            return -1.0
        a = 0.0
        for i in range(n - lag):
            a += x[i] * x[i + lag]
        b = 0.0
        for i in range(n - lag - 1):
            b += x[i] * x[i + lag + 1]
        p = (a + b) / c0
        if p <= 0.0:
            break
        tau += 2.0 * p
        lag += 2
    return tau


def _kappa(r: np.ndarray) -> float:
    """``n_eff / n = 1 / tau_int`` of the standardised residuals: the integrated autocorrelation time
    ``1 + 2 sum rho_k``, summed over Geyer's initial positive sequence (pairs ``rho_k + rho_k+1`` while positive),
    so a slow or periodic error (a bias that follows the excitation) counts as the few samples it is. The pairs
    are summed lag by lag while the sequence is short (most forecasts), else from the whole autocorrelation by
    FFT (the same sum)."""
    n = r.size
    if n < 4:
        return 1.0
    x = np.ascontiguousarray(r - r.mean(), dtype=np.float64)
    tau = _tau_direct(x, KAPPA_DIRECT_LAGS)
    if tau < 0.0:
        m = 1 << int(2 * n - 1).bit_length()
        f = np.fft.rfft(x, m)
        acf = np.fft.irfft(f * np.conj(f), m)[:n]
        rho = acf / acf[0]
        k = (n - 1) // 2 * 2
        pairs = rho[1:k + 1:2] + rho[2:k + 2:2] if k >= 2 else np.zeros(0)
        neg = np.flatnonzero(pairs <= 0.0)
        stop = int(neg[0]) if neg.size else pairs.size
        tau = 1.0 + 2.0 * float(np.sum(pairs[:stop]))
    return 1.0 / min(max(tau, 1.0), float(n))


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the forecast's compiled pieces on a small history (``twin warm``)."""
    t = np.arange(-30.0, 0.0)
    y = np.sin(t)
    _wls_hinges(t, np.array([-30.0, -10.0]), np.array([0, 20], dtype=np.intp), y, np.ones_like(t))
    _tau_direct(y - y.mean(), KAPPA_DIRECT_LAGS)


def _exit_cdf(coef: np.ndarray, cov: np.ndarray, rss: np.ndarray, kappa: float, n: int, nu: float, lo: np.ndarray,
              hi: np.ndarray, grid: np.ndarray, level_var: np.ndarray) -> np.ndarray:
    """For each of ``K`` trends (rows: ``coef [K, 2]``, ``cov [K, 2, 2]``, weighted ``rss [K]``, band edges ``lo``,
    ``hi`` and ``level_var [K]`` in the trend's own coordinates), P(the trend's level at ``grid [K, G]`` seconds from
    now is beyond ``lo`` or ``hi``) ``[K, G]``: Student t with ``nu`` degrees of freedom, scale from the residual
    variance over ``kappa n`` effective points plus ``level_var`` (the twin's slow level error, which the trend's
    average does not remove)."""
    s2 = (rss / max(n - 2.0, 1.0) / kappa)[:, None]
    m = coef[:, :1] + coef[:, 1:] * grid
    v = s2 * (cov[:, :1, 0] + 2.0 * grid * cov[:, :1, 1] + grid * grid * cov[:, 1:, 1]) + level_var[:, None]
    sd = np.sqrt(np.maximum(v, 1e-300))
    from scipy import special  # here, not at import: a worker that never forecasts does not pay for it

    hi, lo = hi[:, None], lo[:, None]
    return special.stdtr(nu, (m - hi) / sd) + special.stdtr(nu, (lo - m) / sd)
