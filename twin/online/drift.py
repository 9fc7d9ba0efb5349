"""Drift detection: a sequential test of each tracked parameter against its healthy band.

The test is a two-sided CUSUM on the *standardised excursion beyond the band*,
in the filter's own log coordinates::

    d_hi = (log(theta) - log(hi)) / sigma,   d_lo = (log(lo) - log(theta)) / sigma
    S_hi <- max(0, S_hi + d_hi - kappa)       (likewise S_lo)

``sigma`` is the filter's standard deviation of ``log(theta)``, so evidence
accumulates only when the estimate sits outside the band by more than its own
uncertainty (``kappa`` = 1 standard deviation), and a weakly identifiable
parameter accumulates nothing until the data resolve it.  Why CUSUM: it is the
optimal sequential detector of a persistent shift (Page/Lorden), needs one
number of state per side, and its threshold trades delay against false-alarm
rate directly; a GLR would also estimate the change size, which the filter
already does.  The statistic is evaluated at ``rate_hz`` (20 Hz by default), and each
increment is weighted by ``1 / sqrt(g)`` with ``g`` the number of evaluation
steps per independent sample of the estimate: a parameter tracked as a random
walk of intensity ``q`` (log units^2 per s, the tracker's
the spec's tracking ``drift_rate`` squared) and known to ``sigma`` forgets with the
time constant ``tau = sigma^2 / q`` (the Kalman-Bucy filter's memory), so its
estimates at step ``1/rate`` are AR(1) with ``r = exp(-1 / (rate tau))`` and
``g = (1 + r) / (1 - r)`` (capped at ``max_ess_factor``).  With the weight the
sum of ``g`` correlated increments has the variance of one independent one:
a weakly identified, slowly forgetting parameter (the leakage) needs a longer
excursion before it warns than a sharp, fast one (the friction).

While the tracker's consistency guard says the filter does not agree with the
data (``hold``: model mismatch, noise not yet learnt, a sensor fault, a
re-initialisation or a recovery) the statistics keep their value and the
parameters say ``inconsistent``: nothing is raised on a guess.

Levels: ``warning`` at ``h_warn``, ``alarm`` at ``h_alarm``; hysteresis: a
parameter *returns* (event ``returned``, level ``ok``) only when its statistic
has decayed to zero and its estimate has stayed inside the band for
``hold_s``.  A parameter whose standard deviation exceeds ``resolve`` times the
half-width of its band is ``unresolved``: its statistic is frozen and nothing is
raised on a guess; a parameter the filter froze (no excitation) is ``frozen``.

Thresholds (defaults): ``kappa = 1`` sigma of allowance, ``h_warn = 4``,
``h_alarm = 10`` (sums of standardised excursions at 20 Hz): an estimate 3
sigma beyond the band warns after 0.1 s and alarms after 0.25 s; one hovering
at the band's edge within its own uncertainty accumulates nothing.  The
statistic is capped at ``3 h_alarm`` so a parameter that comes back is
declared returned within a bounded time.

Baselines (:class:`Baseline`) come from the rig's values (:func:`default_baseline`:
the paper's Table 9 for the MSP25, with each parameter's healthy band declared
beside its spec in the model, :class:`twin.params.Tracking`), the rig
configuration, or a commissioning fit (:func:`baseline_from_fit`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from twin.errors import ParameterError
from twin.models import get_model
from twin.online.events import AlarmEvent

#: relative band of a parameter whose spec declares none (not tracked online)
FALLBACK_BAND = 0.3


@dataclasses.dataclass(frozen=True)
class Baseline:
    """Healthy value of one parameter and its band [lo, hi] (SI units)."""

    value: float
    lo: float
    hi: float


def default_band(model_name: str, name: str) -> float:
    """The healthy band (relative half-width) of ``name``: its spec's tracking band, else
    :data:`FALLBACK_BAND`."""
    spec = get_model(model_name).params().spec(name) if name in get_model(model_name).kernel_names else None
    return spec.tracking.band if spec is not None and spec.tracking is not None else FALLBACK_BAND


def default_baseline(model_name: str, params: Mapping[str, float] | None = None,
                     names: Sequence[str] | None = None) -> dict[str, Baseline]:
    """Bands around the rig's values (the paper's Table 9 for the MSP25), each as wide as its spec's
    tracking band."""
    model = get_model(model_name)
    ps = model.params((), **dict(params or {}))
    out = {}
    for n in names or model.PHENOMENOLOGICAL:
        v = ps[n]
        r = default_band(model_name, n)
        out[n] = Baseline(v, v / (1 + r), v * (1 + r))
    return out


def baseline_from_fit(fit, names: Sequence[str] | None = None, rel_band: Mapping[str, float] | None = None,
                      k_sigma: float = 3.0) -> dict[str, Baseline]:
    """Healthy bands centred on a commissioning fit (:class:`twin.estimation.fit.FitResult`).

    Each band is ``[v / (1 + r), v (1 + r)]`` around the fitted value ``v`` with
    ``r`` the configured relative band (``rel_band``, default each parameter's
    tracking band in the model), widened to ``k_sigma`` standard errors of
    the fit when the fit itself is less certain than that.  ``names``: the
    parameters to take (default: all free parameters of the fit).
    """
    names = tuple(names or fit.free)
    missing = [n for n in names if n not in fit.estimate]
    if missing:
        raise ParameterError(f"the commissioning fit did not estimate {', '.join(missing)}; "
                             f"it estimated {', '.join(fit.free)}")
    model_name = fit.params.model
    bands = {**{n: default_band(model_name, n) for n in names}, **dict(rel_band or {})}
    out = {}
    for n in names:
        v = float(fit.estimate[n])
        if not (v > 0 and math.isfinite(v)):
            raise ParameterError(f"the commissioning fit's {n} (={v}) is not a positive number; no band around it")
        sd = float(fit.std.get(n, math.nan))
        r = float(bands.get(n, FALLBACK_BAND))
        if math.isfinite(sd):
            r = max(r, k_sigma * sd / v)
        out[n] = Baseline(v, v / (1.0 + r), v * (1.0 + r))
    return out


@dataclasses.dataclass
class _ParamState:
    name: str
    base: Baseline
    s_hi: float = 0.0
    s_lo: float = 0.0
    level: str = "ok"
    side: str = ""
    inside_since: float | None = None
    status: str = "ok"  # ok | frozen | unresolved (what the data say now)


class DriftMonitor:
    """Per-rig drift test; feed it the tracker's blocks with :meth:`update_block`.

    ``drift_rate``: each parameter's random-walk intensity in the filter (log
    units per sqrt(s), default the ``drift_rate`` of its spec's tracking in ``model``), from which the
    estimate's correlation time is derived (see the module docstring);
    ``max_ess_factor`` caps the autocorrelation correction.
    """

    def __init__(self, rig: str, baseline: Mapping[str, Baseline], kappa: float = 1.0, h_warn: float = 4.0,
                 h_alarm: float = 10.0, rate_hz: float = 20.0, hold_s: float = 1.0, resolve: float = 0.5,
                 settle_s: float = 2.0, drift_rate: Mapping[str, float] | None = None,
                 max_ess_factor: float = 1000.0, model: str = "msp25"):
        m = get_model(model)
        self.rig = rig
        self.kappa, self.h_warn, self.h_alarm = kappa, h_warn, h_alarm
        self.rate_hz, self.hold_s, self.resolve, self.settle_s = rate_hz, hold_s, resolve, settle_s
        self.params = {n: _ParamState(n, b) for n, b in baseline.items()}
        self.drift_rate = {**{n: m.tracking(n).drift_rate for n in baseline if n in m.trackable},
                           **dict(drift_rate or {})}
        self.max_ess_factor = float(max_ess_factor)
        self.guard = "consistent"
        self._next_t: float | None = None

    def statuses(self) -> dict[str, str]:
        """Per parameter: its alarm level when not ok, else what the data allow
        (ok / frozen / unresolved / inconsistent: the filter is not consistent with the data and the test holds)."""
        return {n: (p.level if p.level != "ok" else p.status) for n, p in self.params.items()}

    def update_block(self, names: Sequence[str], t_ns: np.ndarray, t_s: np.ndarray, est: np.ndarray,
                     log_std: np.ndarray, frozen: np.ndarray, hold: np.ndarray | None = None,
                     guard: np.ndarray | None = None) -> list[AlarmEvent]:
        """Evaluate the test on the samples of a block at ``rate_hz``; returns the events raised.

        ``hold[i]`` True (the tracker's consistency guard, :attr:`twin.online.tracker.TrackBlock.hold`): the
        filter is not consistent with the data at sample ``i``; the statistics keep their value and
        the parameters say ``inconsistent``; ``guard[i]`` is the reason.
        """
        events: list[AlarmEvent] = []
        if len(t_s) == 0:
            return events
        step = 1.0 / self.rate_hz
        if self._next_t is None:
            self._next_t = float(t_s[0]) + self.settle_s
        i = int(np.searchsorted(t_s, self._next_t))
        while i < len(t_s):
            held = bool(hold[i]) if hold is not None else False
            self.guard = str(guard[i]) if (guard is not None and held) else "consistent"
            for j, n in enumerate(names):
                if n in self.params:
                    ev = self._step(self.params[n], int(t_ns[i]), float(t_s[i]), float(est[i, j]),
                                    float(log_std[i, j]), bool(frozen[i, j]), step, held)
                    if ev is not None:
                        events.append(ev)
            self._next_t = float(t_s[i]) + step
            i = int(np.searchsorted(t_s, self._next_t))
        return events

    def ess_factor(self, name: str, sigma: float) -> float:
        """How many evaluation steps make one independent sample of the estimate: ``(1+r)/(1-r)``, with
        ``r = exp(-step / tau)`` and the filter's memory ``tau = sigma^2 / q`` (a random walk of
        intensity ``q`` observed to a standard deviation ``sigma``), at most ``max_ess_factor``."""
        q = self.drift_rate.get(name, 0.0) ** 2
        if not q > 0:
            return 1.0
        tau = sigma * sigma / q
        r = math.exp(-1.0 / (self.rate_hz * max(tau, 1e-9)))
        return min(self.max_ess_factor, (1.0 + r) / max(1.0 - r, 1e-12))

    def _step(self, p: _ParamState, t_ns: int, t_s: float, value: float, sigma: float, frozen: bool,
              step: float, held: bool = False) -> AlarmEvent | None:
        b = p.base
        lo, hi = math.log(b.lo / b.value), math.log(b.hi / b.value)
        z = math.log(value / b.value) if value > 0 else -math.inf
        if frozen:
            p.status = "frozen"
            return None
        if held:
            p.status = "inconsistent"
            return None
        if not (sigma > 0 and math.isfinite(sigma)) or sigma > self.resolve * 0.5 * (hi - lo):
            p.status = "unresolved"
            return None
        p.status = "ok"
        d_hi = (z - hi) / sigma
        d_lo = (lo - z) / sigma
        w = 1.0 / math.sqrt(self.ess_factor(p.name, sigma))
        cap = 3.0 * self.h_alarm
        p.s_hi = min(cap, max(0.0, p.s_hi + w * (d_hi - self.kappa)))
        p.s_lo = min(cap, max(0.0, p.s_lo + w * (d_lo - self.kappa)))
        stat = max(p.s_hi, p.s_lo)
        side = "high" if p.s_hi >= p.s_lo else "low"
        inside = lo <= z <= hi
        if inside:
            p.inside_since = t_s if p.inside_since is None else p.inside_since
        else:
            p.inside_since = None
        new = p.level
        if stat >= self.h_alarm:
            new = "alarm"
        elif stat >= self.h_warn and p.level == "ok":
            new = "warning"
        elif p.level != "ok" and stat == 0.0 and p.inside_since is not None and t_s - p.inside_since >= self.hold_s:
            new = "ok"
        if new == p.level:
            return None
        kind = "returned" if new == "ok" else ("escalated" if p.level == "warning" else "raised")
        old = p.level
        p.level = new
        p.side = side if new != "ok" else ""
        std = value * sigma
        msg = (f"{p.name} back inside its band" if new == "ok" else
               f"{p.name} {'above' if side == 'high' else 'below'} its healthy band "
               f"({old} -> {new}, CUSUM {stat:.1f})")
        return AlarmEvent(rig=self.rig, parameter=p.name, level=new, kind=kind, t_ns=t_ns, t_s=t_s,
                          estimate=value, std=std, baseline=b.value, band_lo=b.lo, band_hi=b.hi,
                          statistic=stat, message=msg)
