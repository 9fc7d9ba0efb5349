"""The online tracker: filterpy as the reference, convergence, faults, quiet rigs, covariance repair."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from replay.base import Samples
from twin import ukf
from twin.config import default_baseline
from twin.drift import DriftMonitor
from twin.errors import DataError, ParameterError
from twin.models import msp25 as M
from twin.scenario import Drift, simulate_wear
from twin.simulate import DEFAULT_NOISE, default_noise, excite, measure
from twin.tracker import OnlineTracker

NOISE = {k: DEFAULT_NOISE[k] for k in ("x", "pA", "pB")}
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
        events += dm.update_block(tr.tracked, out.t_ns, t_s, out.estimates, out.log_std, out.frozen)
    return tr, dm, events, outs


def test_same_estimates_as_filterpy_ukf():
    rec, _ = _record(0.4, 1)
    T = len(rec)
    tr = OnlineTracker(start=WRONG, excite=(0.0, 0.0, 0.0), gate_p=1e-300)
    n = tr.n
    pts = MerweScaledSigmaPoints(n, alpha=tr.alpha, beta=tr.beta, kappa=tr.kappa)
    np.testing.assert_allclose(pts.Wm, tr.Wm)
    np.testing.assert_allclose(pts.Wc, tr.Wc)

    def fx(x, dt, u):
        out = np.empty(n)
        ukf.fx_one(x, u, tr.pvec, tr.idx, tr.ref, tr.scale, dt, tr.substeps, out)
        return out

    def hx(x):
        return x[tr.meas_idx]

    ref = UnscentedKalmanFilter(dim_x=n, dim_z=3, dt=1e-3, hx=hx, fx=fx, points=pts)
    ref.x = tr.x.copy()
    ref.P = tr.P.copy()
    ref.Q = tr._q(1e-3)
    ref.R = np.diag(tr.R)
    Z = np.stack([rec["x"] / 1e-3, rec["pA"] / 1e6, rec["pB"] / 1e6], axis=1)
    expected = np.empty((T, n))
    for k in range(T):
        if k > 0:
            ref.predict(u=rec["u"][k - 1])
        else:  # the first sample is measured at the prior: no prediction, sigma points of the prior
            ref.sigmas_f = pts.sigma_points(ref.x, ref.P)
        ref.update(Z[k])
        expected[k] = ref.x
    out = tr.process(rec.to_samples())
    ours = np.concatenate([out.states / tr.scale, np.log(out.estimates / tr.ref)], axis=1)
    np.testing.assert_allclose(ours, expected, rtol=1e-7, atol=1e-9)
    assert np.max(np.abs(ours[-1, 6:] - ours[0, 6:])) > 0.05  # the parameters did move


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


def test_healthy_ten_minute_record_raises_no_alarm():
    _, xr = excite(M.MODEL, 600.0, 1e-3, seed=7)
    rec, _ = _record(600.0, 7, xr=xr)
    _, dm, events, _ = _run(rec, chunk=20000)
    assert events == []
    assert set(dm.statuses().values()) <= {"ok", "unresolved"}


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


def test_outlier_is_gated_and_missing_pressures_are_tolerated():
    rec, _ = _record(3.0, 10)
    s = rec.to_samples()
    x = s.signals["x"].copy()
    x[1500] += 5e-3  # a 5 mm spike
    pa = s.signals["pA"].copy()
    pa[2000:2100] = np.nan  # a dropout
    s2 = Samples(s.t_ns, {**s.signals, "x": x, "pA": pa})
    tr = OnlineTracker()
    out = tr.process(s2)
    assert out.status[1500] == "gated"
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
    xr = Samples(np.arange(10) * 1_000_000, {"x_ref": np.zeros(10), "x": np.zeros(10)})
    with pytest.raises(DataError, match="KI=5, KD=0; log the controller output u"):
        OnlineTracker(params={"KI": 5.0}).process(xr)


def test_julier_sigma_points_are_injectable_and_match_filterpy():
    from filterpy.kalman import JulierSigmaPoints

    rec, _ = _record(0.2, 12)
    tr = OnlineTracker(points=JulierSigmaPoints(11, kappa=-8.0), excite=(0.0, 0.0, 0.0), gate_p=1e-300)
    pts = tr.points

    def fx(x, dt, u):
        out = np.empty(tr.n)
        ukf.fx_one(x, u, tr.pvec, tr.idx, tr.ref, tr.scale, dt, tr.substeps, out)
        return out

    ref = UnscentedKalmanFilter(dim_x=tr.n, dim_z=3, dt=1e-3, hx=lambda x: x[tr.meas_idx], fx=fx, points=pts)
    ref.x, ref.P, ref.Q, ref.R = tr.x.copy(), tr.P.copy(), tr._q(1e-3), np.diag(tr.R)
    ref.sigmas_f = pts.sigma_points(ref.x, ref.P)
    Z = np.stack([rec["x"] / 1e-3, rec["pA"] / 1e6, rec["pB"] / 1e6], axis=1)
    out = tr.process(rec.to_samples())
    for k in range(len(rec)):
        if k > 0:
            ref.predict(u=rec["u"][k - 1])
        ref.update(Z[k])
    np.testing.assert_allclose(np.log(out.estimates[-1] / tr.ref), ref.x[6:], rtol=1e-7, atol=1e-10)
    with pytest.raises(ParameterError, match="sigma points for n=5"):
        OnlineTracker(points=JulierSigmaPoints(5))
