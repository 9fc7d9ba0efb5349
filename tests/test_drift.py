"""The drift test (twin.online.drift) on synthetic estimate streams: levels, hysteresis, returns, what the filter
cannot resolve, frozen parameters, and baselines from the rig configuration or a commissioning fit."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

from twin.online.baseline import Baseline, default_baseline
from twin.online.baseline import baseline_from_fit
from twin.online.drift import DriftMonitor
from fpdd.errors import ParameterError
from twin.online.events import AlarmEvent
from twin.models import msp25 as M

FS = 1000.0
BAND = {"Ffric": Baseline(50.0, 50.0 / 1.5, 75.0), "CdAleak": Baseline(3.2863e-9, 3.2863e-9 / 3, 3 * 3.2863e-9)}
NAMES = ("Ffric", "CdAleak")


def _feed(dm, values, log_std, frozen=None, chunk=997, t0_ns=5_000_000_000):
    """Feed per-sample streams [T, p] to the monitor in blocks; returns the events."""
    values = np.asarray(values, dtype=float)
    T = values.shape[0]
    log_std = np.broadcast_to(np.asarray(log_std, dtype=float), values.shape)
    frozen = np.zeros(values.shape, bool) if frozen is None else np.broadcast_to(frozen, values.shape)
    t_ns = t0_ns + np.arange(T, dtype=np.int64) * 1_000_000
    t_s = (t_ns - t0_ns) * 1e-9
    ev = []
    for i in range(0, T, chunk):
        sl = slice(i, i + chunk)
        ev += dm.update_block(NAMES, t_ns[sl], t_s[sl], values[sl], log_std[sl], frozen[sl])
    return ev


def _stream(ffric, leak=3.2863e-9):
    ffric = np.asarray(ffric, dtype=float)
    return np.stack([ffric, np.full(ffric.shape, leak)], axis=1)


def test_default_baseline_is_table_9():
    b = default_baseline("msp25")
    for name in M.PHENOMENOLOGICAL:
        assert b[name].value == M.NOMINAL[name]
        assert b[name].lo < b[name].value < b[name].hi
    assert b["wn"].value == pytest.approx(2 * math.pi * 43.0)


def _ar1(n, tau_s, sd, seed):
    """An AR(1) stream at FS with correlation time ``tau_s`` (what a tracked estimate looks like)."""
    rng = np.random.default_rng(seed)
    a = math.exp(-1.0 / (FS * tau_s))
    w = rng.normal(0.0, sd * math.sqrt(1 - a * a), n)
    out = np.empty(n)
    out[0] = rng.normal(0.0, sd)
    for i in range(1, n):
        out[i] = a * out[i - 1] + w[i]
    return out


def test_autocorrelated_estimate_at_the_bands_edge_raises_nothing_only_with_the_weight():
    """A leakage estimate wandering about the band's top edge with its own standard deviation (0.3 log
    units, the filter's memory sigma^2 / q = 4 s): half of it lies outside, in excursions seconds long.
    Weighted by the effective sample size the test stays quiet; without the weight it alarms."""
    sd, q = 0.3, 0.15
    tau = sd * sd / q**2
    leak = 3 * 3.2863e-9 * np.exp(_ar1(120_000, tau, sd, 3))  # 2 minutes at the upper edge
    v = _stream(np.full(leak.size, 50.0), leak)
    std = [0.02, sd]
    assert _feed(DriftMonitor("r1", BAND, drift_rate={"Ffric": 0.3, "CdAleak": q}), v, std) == []
    naive = _feed(DriftMonitor("r1", BAND, drift_rate={"Ffric": 0.3, "CdAleak": q}, max_ess_factor=1.0), v, std)
    assert [e.parameter for e in naive if e.level == "alarm"][:1] == ["CdAleak"]


def test_effective_sample_factor_follows_the_filters_memory():
    dm = DriftMonitor("r1", BAND, drift_rate={"Ffric": 0.3, "CdAleak": 0.15})
    assert dm.ess_factor("Ffric", 0.001) == pytest.approx(1.0, abs=1e-9)  # sharp and fast: independent
    r = math.exp(-1.0 / (20.0 * 0.1**2 / 0.15**2))
    assert dm.ess_factor("CdAleak", 0.1) == pytest.approx((1 + r) / (1 - r))
    assert dm.ess_factor("CdAleak", 10.0) == dm.max_ess_factor


def test_held_samples_keep_the_statistic_and_say_inconsistent():
    dm = DriftMonitor("r1", BAND)
    v = _stream(np.full(20000, 200.0))  # far above the band
    hold = np.zeros(20000, bool)
    hold[:] = True
    t_ns = 5_000_000_000 + np.arange(20000, dtype=np.int64) * 1_000_000
    guard = np.full(20000, "inconsistent_nis")
    ev = dm.update_block(NAMES, t_ns, (t_ns - t_ns[0]) * 1e-9, v, np.full(v.shape, 0.02), np.zeros(v.shape, bool),
                         hold, guard)
    assert ev == [] and dm.statuses()["Ffric"] == "inconsistent" and dm.guard == "inconsistent_nis"
    ev = dm.update_block(NAMES, t_ns + 20_000_000_000, (t_ns - t_ns[0]) * 1e-9 + 20, v, np.full(v.shape, 0.02),
                         np.zeros(v.shape, bool), ~hold, guard)
    ff = [e for e in ev if e.parameter == "Ffric"]
    assert ff and ff[-1].level == "alarm" and ff[0].t_s < 20.2  # evidence counts again as soon as it is consistent


def test_step_out_warns_then_alarms_then_returns_with_hysteresis():
    dm = DriftMonitor("r1", BAND)
    T = 20000
    t = np.arange(T) / FS
    # 3.5 sigma above the band's top: the CUSUM grows by 2.5 per 20 Hz step, warning before alarm
    f = np.where((t >= 5.0) & (t < 12.0), 75.0 * math.exp(3.5 * 0.02), 50.0)
    f[(t >= 8.0) & (t < 8.3)] = 60.0  # a short dip back inside: no return (hold_s = 1 s)
    ev = _feed(dm, _stream(f), [0.02, 0.3])
    assert [(e.parameter, e.level, e.kind) for e in ev] == [
        ("Ffric", "warning", "raised"), ("Ffric", "alarm", "escalated"), ("Ffric", "ok", "returned")]
    warn, alarm, back = ev
    assert 5.0 <= warn.t_s < alarm.t_s <= 5.3  # 2 and 4 steps of 50 ms
    assert alarm.estimate == f[5000] and alarm.std == pytest.approx(f[5000] * 0.02)
    assert (alarm.baseline, alarm.band_lo, alarm.band_hi) == (50.0, BAND["Ffric"].lo, 75.0)
    assert alarm.rig == "r1" and alarm.statistic >= dm.h_alarm and "above" in alarm.message
    assert alarm.t_ns == 5_000_000_000 + round(alarm.t_s * 1e9)
    assert 13.0 <= back.t_s <= 13.5  # back at 12 s, held inside for 1 s
    assert all(isinstance(e, AlarmEvent) and e.seq == 0 for e in ev)  # numbered by the journal, not here
    assert dm.statuses()["Ffric"] == "ok"


def test_low_side_alarms_too_and_a_large_excursion_alarms_at_once():
    dm = DriftMonitor("r1", BAND)
    t = np.arange(8000) / FS
    ev = _feed(dm, _stream(np.where(t >= 4.0, 10.0, 50.0)), [0.02, 0.3])
    assert [(e.level, e.kind) for e in ev] == [("alarm", "raised")] and "below" in ev[0].message
    assert 4.0 <= ev[0].t_s <= 4.06
    assert dm.statuses()["Ffric"] == "alarm"


def test_an_estimate_at_the_edge_within_its_uncertainty_accumulates_nothing():
    dm = DriftMonitor("r1", BAND)
    # 1.5 % above the band's top with a 2 % std: less than the one-sigma allowance
    assert _feed(dm, _stream(np.full(30000, 75.0 * 1.015)), [0.02, 0.3]) == []


def test_weak_evidence_needs_more_time_than_strong_evidence():
    """Leakage out of its band by a factor 2 (log 0.69): with a 0.1 std the CUSUM grows by ~6 per
    step and alarms at once; with a 0.25 std (just resolved) it grows by ~1.8 and takes longer."""
    times = []
    for sd in (0.1, 0.25):
        dm = DriftMonitor("r1", BAND)
        t = np.arange(12000) / FS
        leak = np.where(t >= 4.0, 6 * 3.2863e-9, 3.2863e-9)
        ev = _feed(dm, np.stack([np.full(t.size, 50.0), leak], axis=1), [0.02, sd])
        alarm = [e for e in ev if e.level == "alarm"]
        assert alarm and alarm[0].parameter == "CdAleak"
        times.append(alarm[0].t_s)
    assert times[0] < times[1]


def test_unresolved_parameter_is_reported_and_never_alarmed():
    dm = DriftMonitor("r1", BAND)
    t = np.arange(15000) / FS
    leak = np.where(t >= 3.0, 30 * 3.2863e-9, 3.2863e-9)  # far out, but the filter cannot tell (std 0.9)
    ev = _feed(dm, np.stack([np.full(t.size, 50.0), leak], axis=1), [0.02, 0.9])
    assert ev == []
    assert dm.statuses()["CdAleak"] == "unresolved"


def test_frozen_parameter_is_reported_and_never_alarmed():
    dm = DriftMonitor("r1", BAND)
    frozen = np.array([True, False])
    ev = _feed(dm, _stream(np.full(10000, 200.0)), [0.02, 0.3], frozen=frozen)
    assert ev == []
    assert dm.statuses() == {"Ffric": "frozen", "CdAleak": "ok"}


def test_block_size_does_not_change_the_events():
    t = np.arange(16000) / FS
    v = _stream(np.where((t >= 4.0) & (t < 9.0), 120.0, 50.0))
    a = _feed(DriftMonitor("r1", BAND), v, [0.02, 0.3], chunk=16000)
    b = _feed(DriftMonitor("r1", BAND), v, [0.02, 0.3], chunk=37)
    assert [(e.level, e.kind, e.t_ns) for e in a] == [(e.level, e.kind, e.t_ns) for e in b]
    assert [(e.level, e.kind) for e in a] == [("alarm", "raised"), ("ok", "returned")]


def _fit(estimate, std):
    """What baseline_from_fit reads of a FitResult: the free names, estimates, standard errors, the model."""
    return types.SimpleNamespace(free=tuple(estimate), estimate=estimate, std=std,
                                 params=types.SimpleNamespace(model="msp25"))


def test_baseline_from_a_commissioning_fit():
    fit = _fit({"Ffric": 55.0, "CdAleak": 4e-9, "zeta": 0.36}, {"Ffric": 0.5, "CdAleak": 3e-9, "zeta": float("nan")})
    b = baseline_from_fit(fit)
    assert b["Ffric"] == Baseline(55.0, 55.0 / 1.5, 55.0 * 1.5)  # the configured band is wider than 3 sigma
    r = 3 * 3e-9 / 4e-9  # the fit's own uncertainty is wider than the configured band: 3 sigma
    assert b["CdAleak"].value == 4e-9 and b["CdAleak"].hi == pytest.approx(4e-9 * (1 + r))
    assert b["zeta"].lo == pytest.approx(0.36 / 1.3)  # no standard error (held at a bound): configured band
    assert set(baseline_from_fit(fit, names=("Ffric",))) == {"Ffric"}
    dm = DriftMonitor("r1", b)
    assert set(dm.statuses()) == {"Ffric", "CdAleak", "zeta"}
    with pytest.raises(ParameterError, match="did not estimate wn"):
        baseline_from_fit(fit, names=("wn",))
    with pytest.raises(ParameterError, match="not a positive number"):
        baseline_from_fit(_fit({"Cd": -1.0}, {"Cd": 0.1}))
