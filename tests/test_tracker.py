"""The online tracker: filterpy as the reference, convergence, faults, quiet rigs, covariance repair."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from replay.base import Samples
from twin.online.baseline import default_baseline
from twin.online.drift import DriftMonitor
from fpdd.errors import DataError, ParameterError
from twin.models import msp25 as M
from twin.models.scenario import Drift, simulate_wear
from fpdd.units import NOMINAL_NOISE
from twin.models.simulate import excite
from twin.online.tracker import OnlineTracker

NOISE = {k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}
BASE = default_baseline("msp25")
WRONG = {"Ffric": 75.0, "CdAleak": 3.2863e-9 * 0.5, "Cd": 0.2191 * 1.5, "zeta": 0.3701 * 0.5,
         "wn": M.NOMINAL["wn"] * 1.5}


def _record(duration, seed, drifts=(), xr=None):
    if xr is None:
        _, xr = excite(M.MODEL, duration, 1e-3, seed=seed)
    rec, P = simulate_wear(M.MODEL.params(), xr, 1e-3, drifts, noise=NOISE, seed=seed)
    return rec, P


def _run(rec, tracker=None, chunk=None):
    tr = tracker or OnlineTracker()
    dm = DriftMonitor("rig", BASE)
    s = rec.to_samples()
    blocks = [s] if chunk is None else [s.slice(i, i + chunk) for i in range(0, len(s), chunk)]
    events, outs = [], []
    for b in blocks:
        out = tr.process(b)
        outs.append(out)
        t_s = (out.t_ns - s.t_ns[0]) * 1e-9
        events += dm.update_block(tr.tracked, out.t_ns, t_s, out.estimates, out.log_std, out.frozen, out.hold,
                                  out.guard)
    return tr, dm, events, outs


def test_converges_from_wrong_starts_to_the_truth_within_three_sigma():
    rec, _ = _record(20.0, 3)
    tr, dm, events, outs = _run(rec, OnlineTracker(start=WRONG))
    out = outs[-1]
    truth = M.MODEL.params()
    for j, name in enumerate(tr.tracked):
        z = (out.estimates[-1, j] - truth[name]) / out.stds[-1, j]
        assert abs(z) < 3.0, (name, out.estimates[-1, j], out.stds[-1, j])
    assert out.log_std[-1, tr.tracked.index("Cd")] < 0.01  # the well-identified directions are sharp
    assert not [e for e in events if e.level != "ok"]
    assert 1.0 < np.nanmean(out.nis[2000:]) < 6.0  # three measurements: NIS ~ chi2(3)


def test_block_size_does_not_change_the_result():
    rec, _ = _record(1.0, 4)
    _, _, _, whole = _run(rec)
    _, _, _, parts = _run(rec, chunk=37)
    np.testing.assert_allclose(np.concatenate([o.estimates for o in parts]), whole[0].estimates, rtol=1e-12)


FAULTS = [
    ("friction step 50 -> 150 N", Drift("Ffric", 3.0, 10.0, shape="step"), 2.0),
    ("valve wn 43 -> 30 Hz over 20 s", Drift("wn", 30.0 / 43.0, 5.0, 25.0, "ramp"), 2.0),
    ("worn seal: leakage x1 -> x30 over 20 s", Drift("CdAleak", 30.0, 5.0, 25.0, "ramp"), 5.0),
]


@pytest.mark.parametrize("label, drift, limit", FAULTS, ids=[f[0] for f in FAULTS])
def test_fault_alarms_the_right_parameter_in_time(label, drift, limit):
    rec, _ = _record(30.0, 5, [drift])
    _, dm, events, _ = _run(rec, chunk=1000)
    b = BASE[drift.parameter]
    t_cross = drift.crossing(M.NOMINAL[drift.parameter], b.lo, b.hi, rec.t_s)
    alarms = [e for e in events if e.level == "alarm"]
    assert alarms, f"{label}: no alarm"
    assert {e.parameter for e in events} == {drift.parameter}, [(e.parameter, e.level) for e in events]
    assert 0.0 <= alarms[0].t_s - t_cross <= limit, (alarms[0].t_s, t_cross)
    assert alarms[0].kind in ("raised", "escalated") and alarms[0].std > 0
    assert dm.statuses()[drift.parameter] == "alarm"


def test_quiet_rig_freezes_friction_and_says_so():
    xr = np.zeros(8000)
    rec, _ = _record(8.0, 8, xr=xr)
    tr, dm, events, outs = _run(rec, OnlineTracker(start={"Ffric": 120.0}))
    out = outs[0]
    j = tr.tracked.index("Ffric")
    assert out.frozen[-1, j] and dm.statuses()["Ffric"] == "frozen"
    assert out.estimates[-1, j] == pytest.approx(120.0, rel=1e-6)  # a quiet rig tells nothing about friction
    assert "frozen" in set(out.status)
    assert events == []


def test_broken_covariance_is_repaired_reported_and_recovered():
    rec, _ = _record(6.0, 9)
    tr = OnlineTracker()
    s = rec.to_samples()
    tr.process(s.slice(0, 2000))
    tr.break_covariance()
    out = tr.process(s.slice(2000, len(s)))
    assert out.status[0] == "repaired_covariance"
    assert tr.counters["repaired_covariance"] >= 1
    assert np.all(np.isfinite(out.estimates))
    assert np.all(np.linalg.eigvalsh(tr.P) > 0)
    j = tr.tracked.index("Cd")
    assert abs(out.estimates[-1, j] / 0.2191 - 1) < 0.01


def test_an_outlier_does_not_enter_the_update_and_missing_pressures_are_tolerated():
    rec, _ = _record(3.0, 10)
    s = rec.to_samples()
    x = s.signals["x"].copy()
    x[1500] += 5e-3  # a 5 mm spike
    pa = s.signals["pA"].copy()
    pa[2000:2100] = np.nan  # a dropout
    s2 = Samples(s.t_ns, {**s.signals, "x": x, "pA": pa})
    tr = OnlineTracker()
    out = tr.process(s2)
    # the spike does not enter the update: the filter is consistent and the pressures agree with it, so x alone
    # is set aside as an outlier and the pressures update the filter (a whole sample is gated only when no
    # output vouches for the model)
    assert not out.used[1500, 0] and out.used[1500, 1:].all()
    assert out.status[1500] in ("ok", "gated") and tr.sensor_status()["x"] == "ok"  # one spike is not a fault
    j = tr.tracked.index("Cd")
    assert abs(out.estimates[1501, j] / out.estimates[1499, j] - 1) < 1e-3  # and moves nothing
    assert np.all(np.isfinite(out.estimates))
    xonly = Samples(s.t_ns, {"u": s.signals["u"], "x": s.signals["x"]})
    out2 = OnlineTracker(outputs=("x",)).process(xonly)
    assert np.all(np.isfinite(out2.estimates))


def test_tracker_driven_from_x_ref_when_u_is_not_logged():
    rec, _ = _record(10.0, 11)
    s = rec.to_samples()
    no_u = Samples(s.t_ns, {k: v for k, v in s.signals.items() if k != "u"})
    out = OnlineTracker(start=WRONG).process(no_u)
    j = ("Ffric", "CdAleak", "Cd", "zeta", "wn").index("Cd")
    assert abs(out.estimates[-1, j] / 0.2191 - 1) < 3 * out.log_std[-1, j] + 0.01


def test_bad_tracker_input_is_rejected_clearly():
    with pytest.raises(ParameterError, match="cannot track"):
        OnlineTracker(tracked=("mass",))
    with pytest.raises(ParameterError, match="unknown measurement"):
        OnlineTracker(outputs=("F",))
    s = Samples(np.arange(10) * 1_000_000, {"x": np.zeros(10)})
    with pytest.raises(DataError, match="needs the controller output 'u' or the demand 'x_ref'"):
        OnlineTracker().process(s)


def test_julier_sigma_points_are_injectable_and_match_filterpy():
    from filterpy.kalman import JulierSigmaPoints

    from tests.ukf_mirror import mirror, ours

    rec, _ = _record(0.2, 12)
    s = rec.to_samples()
    tr = OnlineTracker(points=JulierSigmaPoints(14, kappa=-11.0), excite=(0.0, 0.0, 0.0), gate_p=1e-300,
                       adapt_noise=False, start=WRONG)
    tr.dt = 1e-3
    tr._start_from_data(s)
    tr._started = True
    ref = copy.deepcopy(tr)
    out = tr.process(s)
    np.testing.assert_allclose(ours(tr, out), mirror(ref, s, out)[:, :tr.nmod], rtol=1e-7, atol=1e-9)
    with pytest.raises(ParameterError, match="sigma points for n=5"):
        OnlineTracker(points=JulierSigmaPoints(5))


def test_estimates_stay_within_their_physical_bounds_whatever_the_data():
    """A record that no healthy rig produces (pressures swapped, x scaled) cannot push a parameter past its
    physical bound; the filter says what it thinks of the data instead."""
    rec, _ = _record(4.0, 13)
    s = rec.to_samples()
    bad = Samples(s.t_ns, {**s.signals, "pA": s.signals["pB"], "pB": s.signals["pA"], "x": 3 * s.signals["x"]})
    tr = OnlineTracker()
    out = tr.process(bad)
    lo = np.array([tr.bounds[n][0] for n in tr.tracked])
    hi = np.array([tr.bounds[n][1] for n in tr.tracked])
    assert np.all((out.estimates >= lo) & (out.estimates <= hi))
    assert (out.guard != "consistent").mean() > 0.5
    assert hi[tr.tracked.index("Ffric")] <= M.NOMINAL["pP"] * M.NOMINAL["A"]
    assert hi[tr.tracked.index("wn")] == pytest.approx(3 * M.NOMINAL["wn"])


def test_noise_levels_are_configurable_and_checked():
    tr = OnlineTracker(noise={"x": 4e-6})
    assert tr.noise_levels()["x"]["nominal"] == pytest.approx(4e-6)
    assert tr.noise_levels()["pA"]["nominal"] == pytest.approx(2e4)
    with pytest.raises(ParameterError, match="noise level of pB must be a positive number"):
        OnlineTracker(noise={"pB": -1.0})
    with pytest.raises(ParameterError, match="outside its physical bounds"):
        OnlineTracker(start={"wn": 10 * M.NOMINAL["wn"]})


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5, 8])
def test_gate_quantiles_are_scipys(k):
    from scipy import stats

    from twin.online import chi2

    for p in (1e-300, 1e-50, 1e-9, 1e-3, 0.05, 0.5):
        assert chi2.isf(p, k) == pytest.approx(stats.chi2.isf(p, k), rel=1e-12)
    assert chi2.isf(0.0, k) == float("inf") and chi2.isf(1.0, k) == 0.0
    with pytest.raises(ValueError, match="positive integer"):
        chi2.isf(0.1, 0)


def test_default_sigma_weights_are_filterpys_merwe_points():
    from filterpy.kalman import MerweScaledSigmaPoints

    from twin.online.sigma import MerweWeights, spread

    for n, a, b, kap in ((14, 0.3, 2.0, 0.0), (9, 1e-3, 2.0, 1.0), (20, 0.5, 0.0, -3.0)):
        ours_, theirs = MerweWeights(n, a, b, kap), MerweScaledSigmaPoints(n, alpha=a, beta=b, kappa=kap)
        np.testing.assert_array_equal(ours_.Wm, theirs.Wm)
        np.testing.assert_array_equal(ours_.Wc, theirs.Wc)
        assert spread(ours_) == pytest.approx(a * a * (n + kap), rel=1e-12)


@pytest.mark.slow
def test_a_warming_oil_with_its_temperature_logged_is_not_a_worn_seal():
    """The oil warms 20 K (bulk modulus -12 %, leakage +15 %: kB_T 0.006/K, b_visc ln(1.15)/20 K) and logs T_oil
    at the HPU's 10 Hz: the model carries both at the logged temperature, the tracked CdAleak (at T_ref) holds
    still and no alarm is raised; read without T_oil the same record moves the leakage estimate further."""
    b_visc = float(np.log(1.15) / 20.0)
    ps = M.MODEL.params(b_visc=b_visc)
    _, xr = excite(M.MODEL, 200.0, 1e-3, seed=1010)
    t_ref = ps["T_ref"]
    rec, P = simulate_wear(ps, xr, 1e-3, [Drift("T_oil", (t_ref + 20.0) / t_ref, 10.0, 190.0)], noise=NOISE,
                           seed=1010)
    bulk = P[:, M.I_BULK] * (1 - P[:, M.I_KBT] * (P[:, M.I_TOIL] - P[:, M.I_TREF]))
    assert bulk[-1] / bulk[0] == pytest.approx(0.88, rel=1e-6)
    s = rec.to_samples()
    t_oil = np.full(len(s), np.nan)
    t_oil[::100] = P[::100, M.I_TOIL]  # the HPU status at 10 Hz: fresh every 100th sample, NaN between
    logged = Samples(s.t_ns, {**s.signals, "T_oil": t_oil})
    j = M.PHENOMENOLOGICAL.index("CdAleak")
    moved = {}
    for name, samples in (("logged", logged), ("unlogged", s)):
        tr = OnlineTracker(params={"b_visc": b_visc})
        dm = DriftMonitor("rig", BASE)
        out = tr.process(samples)
        events = dm.update_block(tr.tracked, out.t_ns, out.t_ns * 1e-9, out.estimates, out.log_std, out.frozen,
                                 out.hold, out.guard)
        late = out.estimates[-20000:, j]
        moved[name] = float(np.max(np.abs(np.log(late / ps["CdAleak"]))))
        if name == "logged":
            assert [e for e in events if e.level == "alarm"] == []
            assert abs(np.log(np.median(late) / ps["CdAleak"])) < 3 * np.median(out.log_std[-20000:, j]) + 0.05
            assert tr.exo_last[0] == pytest.approx(P[-100, M.I_TOIL])
    assert moved["unlogged"] > moved["logged"], moved


@pytest.mark.slow
def test_a_warming_oil_on_the_reference_simulator_raises_no_leakage_alarm(reference_records):
    """The independent reference simulator's leakage rises 15 % over 100 s as its oil warms; its bulk modulus has
    no temperature law, so this rig states kB_T = 0, and the leakage law b_visc = ln(1.15) / 20 K.  T_oil, computed
    with that law from the reference's leakage trajectory, is logged at 10 Hz.  The tracker, started at Table 9
    (the truth is drawn 3-10 % away), tracks CdAleak at T_ref: it stays at the drawn value within its
    uncertainty and the drift test, bands centred on the truth, raises nothing."""
    from reference import msp25_spec
    from reference.tables import draw_truth
    from tests.track_reference import to_samples
    from twin.online.baseline import Baseline

    seed = 1012
    b_visc = float(np.log(1.15) / 20.0)
    truth = draw_truth(seed, 0.1, "msp25")
    leak0 = truth["CdAleak"]
    tv = {"CdAleak": {"kind": "ramp", "t0": 10.0, "t1": 110.0, "start": leak0, "end": 1.15 * leak0}}
    rec = reference_records([msp25_spec(seed, duration=120.0, truth=truth, time_varying=tv)])[0]
    s = to_samples(rec)
    leak = np.asarray(rec.hidden["CdAleak"], float)
    t_oil = np.full(len(s), np.nan)
    t_oil[::100] = M.NOMINAL["T_ref"] + np.log(leak[::100] / leak0) / b_visc
    s = Samples(s.t_ns, {**s.signals, "T_oil": t_oil})
    base = {n: Baseline(truth[n], truth[n] * b.lo / b.value, truth[n] * b.hi / b.value) for n, b in BASE.items()}
    tr = OnlineTracker(params={"b_visc": b_visc, "kB_T": 0.0})
    dm = DriftMonitor("rig", base)
    events = []
    for i in range(0, len(s), 10000):
        out = tr.process(s.slice(i, i + 10000))
        events += dm.update_block(tr.tracked, out.t_ns, (out.t_ns - s.t_ns[0]) * 1e-9, out.estimates, out.log_std,
                                  out.frozen, out.hold, out.guard)
    assert [(e.parameter, e.level) for e in events if e.level == "alarm"] == []
    j = tr.tracked.index("CdAleak")
    logged = float(np.log(np.median(out.estimates[-5000:, j]) / leak0))
    assert abs(logged) < 3 * out.log_std[-1, j] + 0.03, logged
    # read without T_oil, the estimate follows the warm oil's leakage instead (the tracker before the input)
    plain = OnlineTracker(params={"b_visc": b_visc, "kB_T": 0.0}).process(Samples(s.t_ns, {
        k: v for k, v in s.signals.items() if k != "T_oil"}))
    unlogged = float(np.log(np.median(plain.estimates[-5000:, j]) / leak0))
    assert unlogged - logged > 0.5 * np.log(1.15), (logged, unlogged)
