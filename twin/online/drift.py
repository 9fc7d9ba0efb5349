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

Baselines (:class:`twin.online.baseline.Baseline`) come from the rig's values (:func:`~twin.online.baseline.default_baseline`:
the model's nominal values, with each parameter's healthy band declared
beside its spec in the model, :class:`twin.params.Tracking`), the rig
configuration, or a commissioning fit (:func:`~twin.online.baseline.baseline_from_fit`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numba as nb
import numpy as np

from twin.models import DEFAULT_MODEL, get_model
from twin.online.baseline import Baseline
from twin.online.events import ALARM_LEVELS, AlarmEvent


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


def drift_rates(model: str, names, given: Mapping[str, float] | None = None) -> dict[str, float]:
    """Each parameter's random-walk intensity in the filter (log units per sqrt(s)): ``given`` over the
    ``drift_rate`` of its spec's tracking in ``model`` (a name the model does not track and ``given`` does not
    name has none)."""
    m = get_model(model)
    return {**{n: m.tracking(n).drift_rate for n in names if n in m.trackable}, **dict(given or {})}


def memory_factor(step: float, variance: float, rate: float | None) -> float:
    """How many samples ``step`` seconds apart make one independent sample of an estimate that a filter tracks as a
    random walk of intensity ``rate`` (log units per sqrt(s)) and knows to ``variance`` (log units^2):
    ``(1 + r) / (1 - r)`` with ``r = exp(-step / tau)`` and the filter's memory ``tau = variance / rate^2`` (the
    Kalman-Bucy filter's time constant; the integrated autocorrelation time of AR(1) samples). 1 without a rate."""
    q = (rate or 0.0) ** 2
    if not q > 0:
        return 1.0
    r = math.exp(-step / max(variance / q, 1e-9))
    return (1.0 + r) / max(1.0 - r, 1e-12)


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
                 max_ess_factor: float = 1000.0, model: str = DEFAULT_MODEL):
        self.rig = rig
        self.kappa, self.h_warn, self.h_alarm = kappa, h_warn, h_alarm
        self.rate_hz, self.hold_s, self.resolve, self.settle_s = rate_hz, hold_s, resolve, settle_s
        self.params = {n: _ParamState(n, b) for n, b in baseline.items()}
        self.drift_rate = drift_rates(model, baseline, drift_rate)
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
        the parameters say ``inconsistent``; ``guard[i]`` is the reason. The whole block is one
        compiled call (:func:`_cusum_block`); Python builds an event only where a level changes.
        """
        T = len(t_s)
        if T == 0:
            return []
        if self._next_t is None:
            self._next_t = float(t_s[0]) + self.settle_s
        c = self._constants(tuple(names))
        if c is None:
            return []
        jj, ps, const, whole = c
        state = np.array([[q.s_hi, q.s_lo, ALARM_LEVELS.index(q.level),
                           math.nan if q.inside_since is None else q.inside_since, _STATUS_CODE[q.status]]
                          for q in ps]).T.copy()
        if whole:  # every column is a monitored parameter, in order: no copies
            E = np.ascontiguousarray(est, dtype=float)
            S = np.ascontiguousarray(log_std, dtype=float)
            F = np.ascontiguousarray(frozen, dtype=np.bool_)
        else:
            E = np.ascontiguousarray(est[:, jj], dtype=float)
            S = np.ascontiguousarray(log_std[:, jj], dtype=float)
            F = np.ascontiguousarray(frozen[:, jj], dtype=np.bool_)
        H = np.zeros(T, np.bool_) if hold is None else np.ascontiguousarray(hold, dtype=np.bool_)
        # at most one evaluation per sample (a time gap adds none): sized by samples, not by the time spanned
        ev = self._buffer(len(ps) * (min(T, int((float(t_s[-1]) - float(t_s[0])) * self.rate_hz) + 2)))
        cfg = np.array([self._next_t, 1.0 / self.rate_hz, self.rate_hz, self.kappa, self.h_warn, self.h_alarm,
                        3.0 * self.h_alarm, self.hold_s, self.resolve, self.max_ess_factor])
        n_ev, next_t, last_i = _cusum_block(np.ascontiguousarray(t_s, dtype=float), E, S, F, H, cfg, const, state, ev)
        self._next_t = float(next_t)
        if last_i >= 0:
            self.guard = str(guard[last_i]) if (guard is not None and H[last_i]) else "consistent"
        for k, q in enumerate(ps):
            q.s_hi, q.s_lo = float(state[0, k]), float(state[1, k])
            q.level = ALARM_LEVELS[int(state[2, k])]
            q.inside_since = None if math.isnan(state[3, k]) else float(state[3, k])
            q.status = _STATUSES[int(state[4, k])]
        events = []
        for e in range(n_ev):
            i, k = int(ev[e, 0]), int(ev[e, 1])
            q = ps[k]
            old, new = ALARM_LEVELS[int(ev[e, 2])], ALARM_LEVELS[int(ev[e, 3])]
            side = "high" if ev[e, 5] else "low"
            q.side = side if new != "ok" else ""  # the parameter's last change in the block stays
            kind = "returned" if new == "ok" else ("escalated" if old == "warning" else "raised")
            value = float(E[i, k])
            stat = float(ev[e, 4])
            msg = (f"{q.name} back inside its band" if new == "ok" else
                   f"{q.name} {'above' if side == 'high' else 'below'} its healthy band "
                   f"({old} -> {new}, CUSUM {stat:.1f})")
            events.append(AlarmEvent(rig=self.rig, parameter=q.name, level=new, kind=kind, t_ns=int(t_ns[i]),
                                     t_s=float(t_s[i]), estimate=value, std=value * float(S[i, k]),
                                     baseline=q.base.value, band_lo=q.base.lo, band_hi=q.base.hi, statistic=stat,
                                     message=msg))
        return events

    STATE_VERSION = 1

    def state(self) -> dict:
        """The test's statistics and levels as plain data (restore with :meth:`restore` into a monitor of the
        same rig and baselines)."""
        return {"version": self.STATE_VERSION, "guard": self.guard, "next_t": self._next_t,
                "params": {n: {"base": [q.base.value, q.base.lo, q.base.hi], "s_hi": q.s_hi, "s_lo": q.s_lo,
                               "level": q.level, "side": q.side, "inside_since": q.inside_since, "status": q.status}
                           for n, q in self.params.items()}}

    def restore(self, state: Mapping) -> None:
        """Continue from :meth:`state`.

        :raises ValueError: another version, other parameters or other baselines (nothing is changed then).
        """
        if state.get("version") != self.STATE_VERSION:
            raise ValueError(f"drift state: version {state.get('version')!r}, this program reads {self.STATE_VERSION}")
        params = state.get("params")
        if not isinstance(params, Mapping) or sorted(params) != sorted(self.params):
            raise ValueError(f"drift state: parameters {sorted(params) if isinstance(params, Mapping) else params}, "
                             f"this rig monitors {sorted(self.params)}")
        new = {}
        for n, q in self.params.items():
            d = params[n]
            if list(d["base"]) != [q.base.value, q.base.lo, q.base.hi]:
                raise ValueError(f"drift state: the band of {n} was {d['base']}, it is "
                                 f"{[q.base.value, q.base.lo, q.base.hi]} now")
            if d["level"] not in ALARM_LEVELS or d["status"] not in _STATUSES:
                raise ValueError(f"drift state: level {d['level']!r} / status {d['status']!r} of {n}")
            inside = d["inside_since"]
            new[n] = _ParamState(n, q.base, float(d["s_hi"]), float(d["s_lo"]), str(d["level"]), str(d["side"]),
                                 None if inside is None else float(inside), str(d["status"]))
        next_t = state.get("next_t")
        self.params = new
        self.guard = str(state.get("guard", "consistent"))
        self._next_t = None if next_t is None else float(next_t)
        vars(self).pop("_const", None)  # the cached rows refer to the states replaced

    def _constants(self, names: tuple[str, ...]):
        """Per tuple of tracked names: the monitored columns, their states, and ``const`` rows: baseline value,
        log band (lo, hi) relative to it, drift-rate intensity (log units^2 per s)."""
        cache = getattr(self, "_const", None)
        if cache is not None and cache[0] == names:
            return cache[1]
        cols = [(j, n) for j, n in enumerate(names) if n in self.params]
        if not cols:
            c = None
        else:
            ps = [self.params[n] for _, n in cols]
            val = np.array([q.base.value for q in ps])
            const = np.stack([val, np.log(np.array([q.base.lo for q in ps]) / val),
                              np.log(np.array([q.base.hi for q in ps]) / val),
                              np.array([self.drift_rate.get(q.name, 0.0) ** 2 for q in ps])])
            jj = [j for j, _ in cols]
            c = (jj, ps, const, jj == list(range(len(names))))
        self._const = (names, c)
        return c

    def _buffer(self, n: int) -> np.ndarray:
        """Room for ``n`` changes of level (reused from block to block)."""
        buf = getattr(self, "_buf", None)
        if buf is None or len(buf) < n:
            buf = np.empty((max(n, 64), 6))
            self._buf = buf
        return buf

    def ess_factor(self, name: str, sigma: float) -> float:
        """How many evaluation steps make one independent sample of the estimate: ``(1+r)/(1-r)``, with
        ``r = exp(-step / tau)`` and the filter's memory ``tau = sigma^2 / q`` (a random walk of
        intensity ``q`` observed to a standard deviation ``sigma``), at most ``max_ess_factor``."""
        return min(self.max_ess_factor, memory_factor(1.0 / self.rate_hz, sigma * sigma, self.drift_rate.get(name)))


_STATUSES = ("ok", "frozen", "unresolved", "inconsistent")
_STATUS_CODE = {name: code for code, name in enumerate(_STATUSES)}


@nb.njit(cache=True)
def _cusum_block(t_s, E, S, F, H, cfg, const, state, ev):
    """The drift test over one block, evaluated at the first sample at or after ``cfg[0]`` (``next_t``) and
    then every ``cfg[1]`` seconds of sample time.

    ``cfg``: next_t, step, rate, kappa, h_warn, h_alarm, cap, hold_s, resolve, max_ess; ``const`` rows
    per parameter: baseline value, log band lo and hi relative to it, random-walk intensity q (log units^2
    per s, for the effective-sample weight); ``state`` rows, updated in place: s_hi, s_lo, level (0/1/2 =
    ok/warning/alarm), inside (since when the estimate is inside its band, NaN: not), status (0..3 =
    ok/frozen/unresolved/inconsistent). Each change of level goes to a row of ``ev``: sample, parameter,
    old level, new level, statistic, high side. Returns (changes, next_t, last sample evaluated or -1)."""
    next_t, step, rate, kappa, h_warn, h_alarm, cap, hold_s, resolve, max_ess = (
        cfg[0], cfg[1], cfg[2], cfg[3], cfg[4], cfg[5], cfg[6], cfg[7], cfg[8], cfg[9])
    T = t_s.shape[0]
    p = E.shape[1]
    n = 0
    last = -1
    i = np.searchsorted(t_s, next_t)
    while i < T:
        last = i
        held = H[i]
        for j in range(p):
            value = E[i, j]
            sigma = S[i, j]
            lo = const[1, j]
            hi = const[2, j]
            if F[i, j]:
                state[4, j] = 1
                continue
            if held:
                state[4, j] = 3
                continue
            if not (sigma > 0.0 and np.isfinite(sigma)) or sigma > resolve * 0.5 * (hi - lo):
                state[4, j] = 2
                continue
            state[4, j] = 0
            z = np.log(value / const[0, j]) if value > 0.0 else -np.inf
            d_hi = (z - hi) / sigma
            d_lo = (lo - z) / sigma
            g = 1.0
            if const[3, j] > 0.0:
                tau = sigma * sigma / const[3, j]
                r = np.exp(-1.0 / (rate * max(tau, 1e-9)))
                g = min(max_ess, (1.0 + r) / max(1.0 - r, 1e-12))
            w = 1.0 / np.sqrt(g)
            s_hi = min(cap, max(0.0, state[0, j] + w * (d_hi - kappa)))
            s_lo = min(cap, max(0.0, state[1, j] + w * (d_lo - kappa)))
            state[0, j] = s_hi
            state[1, j] = s_lo
            stat = max(s_hi, s_lo)
            if lo <= z <= hi:
                if np.isnan(state[3, j]):
                    state[3, j] = t_s[i]
            else:
                state[3, j] = np.nan
            old = state[2, j]
            new = old
            if stat >= h_alarm:
                new = 2.0
            elif stat >= h_warn and old == 0.0:
                new = 1.0
            elif old != 0.0 and stat == 0.0 and not np.isnan(state[3, j]) and t_s[i] - state[3, j] >= hold_s:
                new = 0.0
            if new != old:
                ev[n, 0] = i
                ev[n, 1] = j
                ev[n, 2] = old
                ev[n, 3] = new
                ev[n, 4] = stat
                ev[n, 5] = 1.0 if s_hi >= s_lo else 0.0
                n += 1
                state[2, j] = new
        next_t = t_s[i] + step
        i = np.searchsorted(t_s, next_t)
    return n, next_t, last
