"""The service's compiled drift test (``twin.online.drift._cusum_block``, one call per block) against the test
written out sample by sample in plain Python (the module docstring of ``twin.online.drift``): the same events,
statuses and guard on random streams with excursions, frozen, held and unresolved samples, whatever the
block sizes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from twin.models import get_model
from twin.online.baseline import default_baseline
from twin.online.drift import DriftMonitor
from twin.online.events import ALARM_LEVELS as LEVELS

BANDS = default_baseline("msp25")
NAMES = tuple(BANDS)


class PlainCusum:
    """The drift test of ``twin.online.drift`` evaluated one parameter and one instant at a time."""

    def __init__(self, kappa=1.0, h_warn=4.0, h_alarm=10.0, rate_hz=20.0, hold_s=1.0, resolve=0.5, settle_s=2.0,
                 max_ess=1000.0):
        self.kappa, self.h_warn, self.h_alarm, self.rate, self.hold_s = kappa, h_warn, h_alarm, rate_hz, hold_s
        self.resolve, self.settle_s, self.max_ess = resolve, settle_s, max_ess
        self.st = {n: {"s_hi": 0.0, "s_lo": 0.0, "level": "ok", "inside": None, "status": "ok"} for n in NAMES}
        self.next_t = None
        self.guard = "consistent"

    def statuses(self):
        return {n: (p["level"] if p["level"] != "ok" else p["status"]) for n, p in self.st.items()}

    def feed(self, t_s, est, log_std, frozen, hold, guard):
        """Events as (parameter, new level, sample index in the block, statistic)."""
        out = []
        if self.next_t is None:
            self.next_t = t_s[0] + self.settle_s
        i = int(np.searchsorted(t_s, self.next_t))
        while i < len(t_s):
            self.guard = str(guard[i]) if hold[i] else "consistent"
            for j, n in enumerate(NAMES):
                ev = self._one(n, float(t_s[i]), float(est[i, j]), float(log_std[i, j]), bool(frozen[i, j]),
                               bool(hold[i]))
                if ev is not None:
                    out.append((n, ev[0], i, ev[1]))
            self.next_t = float(t_s[i]) + 1.0 / self.rate
            i = int(np.searchsorted(t_s, self.next_t))
        return out

    def _one(self, n, t, value, sigma, frozen, held):
        p, b = self.st[n], BANDS[n]
        lo, hi = math.log(b.lo / b.value), math.log(b.hi / b.value)
        if frozen:
            p["status"] = "frozen"
            return None
        if held:
            p["status"] = "inconsistent"
            return None
        if not (sigma > 0 and math.isfinite(sigma)) or sigma > self.resolve * 0.5 * (hi - lo):
            p["status"] = "unresolved"
            return None
        p["status"] = "ok"
        z = math.log(value / b.value)
        tau = sigma * sigma / get_model("msp25").tracking(n).drift_rate ** 2
        r = math.exp(-1.0 / (self.rate * max(tau, 1e-9)))
        w = 1.0 / math.sqrt(min(self.max_ess, (1 + r) / max(1 - r, 1e-12)))
        cap = 3 * self.h_alarm
        p["s_hi"] = min(cap, max(0.0, p["s_hi"] + w * ((z - hi) / sigma - self.kappa)))
        p["s_lo"] = min(cap, max(0.0, p["s_lo"] + w * ((lo - z) / sigma - self.kappa)))
        stat = max(p["s_hi"], p["s_lo"])
        p["inside"] = (p["inside"] if p["inside"] is not None else t) if lo <= z <= hi else None
        new = p["level"]
        if stat >= self.h_alarm:
            new = "alarm"
        elif stat >= self.h_warn and p["level"] == "ok":
            new = "warning"
        elif p["level"] != "ok" and stat == 0.0 and p["inside"] is not None and t - p["inside"] >= self.hold_s:
            new = "ok"
        if new == p["level"]:
            return None
        p["level"] = new
        return new, stat


@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_drift_test_gives_the_events_of_the_plain_one(seed):
    rng = np.random.default_rng(seed)
    T = 20000
    t_ns = 5_000_000_000 + np.arange(T, dtype=np.int64) * 1_000_000
    t_s = (t_ns - t_ns[0]) * 1e-9
    base = np.array([BANDS[n].value for n in NAMES])
    # excursions out of the band and back (periods of 4-10 s) with a random walk on top
    swing = rng.uniform(0.2, 1.5, len(NAMES)) * np.sin(2 * np.pi * t_s[:, None] / rng.uniform(4, 10, len(NAMES)))
    est = base * np.exp(swing + np.cumsum(rng.normal(0, 0.003, (T, len(NAMES))), axis=0))
    log_std = np.abs(rng.normal(0.05, 0.04, (T, len(NAMES))))
    log_std[rng.random(log_std.shape) < 0.01] = np.nan
    frozen = rng.random(est.shape) < 0.05
    hold = rng.random(T) < 0.05
    guard = np.where(hold, "nis", "consistent")
    compiled, plain = DriftMonitor("r", BANDS), PlainCusum()
    got, want = [], []
    i = 0
    while i < T:
        k = int(rng.integers(1, 700))
        sl = slice(i, i + k)
        got += [(e.parameter, e.level, e.t_ns, e.statistic) for e in
                compiled.update_block(NAMES, t_ns[sl], t_s[sl], est[sl], log_std[sl], frozen[sl], hold[sl], guard[sl])]
        want += [(n, lev, int(t_ns[sl][j]), stat) for n, lev, j, stat in
                 plain.feed(t_s[sl], est[sl], log_std[sl], frozen[sl], hold[sl], guard[sl])]
        assert compiled.statuses() == plain.statuses() and compiled.guard == plain.guard
        i += k
    assert len(want) >= 10 and {lev for _, lev, _, _ in want} == set(LEVELS)
    assert [g[:3] for g in got] == [w[:3] for w in want]
    np.testing.assert_allclose([g[3] for g in got], [w[3] for w in want], rtol=1e-12)
