"""The user's rig, not only the paper's: a single-rod cylinder (two areas), an industrial PID (filtered
derivative, feed-forward, output limit) and time stamps with CAN jitter, on records of the independent
reference simulator (verification seeds >= 1000, truth drawn off the defaults, noise through the loop, starts
off the truth)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twin import cli
from fpdd.errors import DataError
from twin.estimation.fit import fit
from twin.models import get_model
from twin.models import msp25 as M
from twin.models.records import load_records
from twin.record import Record, records_from_samples
from replay.base import Samples

RIG = get_model("msp25")
FREE = RIG.PHENOMENOLOGICAL
#: a single-rod cylinder: the rod side's annulus half the piston's area, its chamber smaller; the P controller
#: tuned to it (at the paper's 400 V/m its retracting stroke's higher flow gain leaves some drawn rigs unstable)
SINGLE_ROD = {"AB": 960e-6, "V0B": 300e-6, "KP": 300.0}
#: the industrial PID of the issue: KP 300 V/m, KI 2000 V/(m s), KD 0.6 V s/m, derivative filter 1 ms
PID = {"KP": 300.0, "KI": 2000.0, "KD": 0.6}
DURATION = 8.0


def product_record(ref, name="reference") -> Record:
    return Record(ref.dt, {k: np.asarray(v, float) for k, v in ref.signals.items()}, name)


def off_truth(ref, seed):
    rng = np.random.default_rng(seed)
    return {k: ref.truth[k] * (1 + rng.choice([-1, 1]) * rng.uniform(0.1, 0.4)) for k in FREE}


def assert_within(res, ref, what):
    assert res.success, (what, res.message)
    for k in FREE:
        z = (res.estimate[k] - ref.truth[k]) / res.std[k]
        rel = res.estimate[k] / ref.truth[k] - 1
        assert abs(z) < 3.0, (what, k, res.estimate[k], ref.truth[k], res.std[k])
        if k != "CdAleak":  # the leak is resolved to its standard error only
            assert abs(rel) < 0.05, (what, k, rel)


@pytest.fixture(scope="module")
def single_rod(reference_records):
    from conftest import msp25_spec

    return reference_records([msp25_spec(1000, duration=DURATION, truth="draw", known=SINGLE_ROD)])[0]


@pytest.fixture(scope="module")
def pid_record(reference_records):
    from conftest import msp25_spec

    return reference_records([msp25_spec(1001, duration=DURATION, truth="draw", known=PID,
                                         pid={"Tf": 1e-3})])[0]


def test_single_rod_record_fits_within_three_standard_errors_with_its_two_areas(single_rod):
    pa, pb = single_rod.signals["pA"].mean(), single_rod.signals["pB"].mean()
    assert pb > 1.8 * pa  # the rest pressures sit in the inverse area ratio
    res = fit(RIG, product_record(single_rod), FREE, base=RIG.params(**SINGLE_ROD), start=off_truth(single_rod, 1000))
    assert_within(res, single_rod, "single rod")


def test_single_rod_record_is_refused_by_a_symmetric_model_naming_the_numbers(single_rod, tmp_path, capsys):
    with pytest.raises(DataError) as e:
        fit(RIG, product_record(single_rod), FREE)
    msg = str(e.value)
    assert "pA 9." in msg and "pB 18." in msg and "AB/A = 0.50" in msg and "\n" not in msg
    path = tmp_path / "single_rod.csv"
    single_rod.to_csv(path)
    assert cli.main(["fit", str(path), "--json", "-q"]) == 2
    err = capsys.readouterr().err
    assert "impossible for the stated cylinder" in err and "Traceback" not in err
    # the same record with its geometry stated passes the check (the tracker asks the same question)
    RIG.check_record(RIG.params(**SINGLE_ROD), single_rod.signals)
    RIG.check_record(RIG.params(Fext=-17.6e3), single_rod.signals)  # or a load that balances it


def test_filtered_pid_record_fits_within_three_standard_errors(pid_record):
    u = pid_record.signals["u"]
    assert np.max(np.abs(u)) < 10.0  # the output limit is not what this record tests
    res = fit(RIG, product_record(pid_record), FREE, base=RIG.params(**PID, Tf=1e-3),
              start=off_truth(pid_record, 1001))
    assert_within(res, pid_record, "filtered PID")


def test_symmetric_cylinder_stated_with_two_equal_areas_gives_the_same_numbers():
    from twin.models.simulate import excite

    _, xr = excite(RIG, 1.0, 1e-3, seed=1002)
    ps = RIG.params(KI=100.0, KD=0.4)
    a = RIG.simulate(ps, "x_ref", xr, 1e-3)
    b = RIG.simulate(ps.replace(AB=ps["A"], V0B=ps["V0"]), "x_ref", xr, 1e-3)
    np.testing.assert_array_equal(a.states, b.states)
    c = RIG.simulate(ps.replace(AB=0.5 * ps["A"]), "x_ref", xr, 1e-3)
    assert np.max(np.abs(c.states[:, 3] - a.states[:, 3])) > 1e6  # a single rod: chamber B at about twice pA


def test_controller_output_limit_derivative_filter_and_feed_forward():
    from twin.models.simulate import excite

    _, xr = excite(RIG, 1.0, 1e-3, seed=1003, amplitude=0.02)
    ps = RIG.params(KD=0.5)
    u = RIG.simulate(ps, "x_ref", xr, 1e-3).inputs["u"]
    lim = 0.5 * np.max(np.abs(u))
    ul = RIG.simulate(ps.replace(u_max=lim), "x_ref", xr, 1e-3).inputs["u"]
    assert np.max(np.abs(ul)) == pytest.approx(lim) and np.mean(np.abs(ul) >= lim) > 0.01
    # a derivative filter smooths the derivative of a noisy error: on a demand of noise alone the derivative
    # term dominates the raw output and shrinks about by h / (Tf + h) through a 5 ms filter
    rng = np.random.default_rng(1003)
    xn = rng.normal(0, 2e-6, 500)
    raw = RIG.simulate(ps.replace(KD=2.0), "x_ref", xn, 1e-3).inputs["u"]
    filt = RIG.simulate(ps.replace(KD=2.0, Tf=5e-3), "x_ref", xn, 1e-3).inputs["u"]
    assert np.std(filt) < 0.5 * np.std(raw)
    dmeas = RIG.simulate(ps.replace(KD=2.0, D_meas=1.0), "x_ref", xn, 1e-3).inputs["u"]
    assert np.std(dmeas) < 0.5 * np.std(raw)  # on the measurement: the demand's noise is not differentiated
    # feed-forward of the demand's rate: u grows by Kff times it (before the loop reacts, at the first samples)
    uf = RIG.simulate(ps.replace(Kff=50.0), "x_ref", xr, 1e-3).inputs["u"]
    rate = (xr[2] - xr[0]) / 2e-3
    assert uf[1] - u[1] == pytest.approx(50.0 * rate, rel=1e-3)
    # pressure feedback: the controller subtracts Kdp times the measured load pressure pA - pB AB/A
    init = {"pA0": 19e6, "pB0": 9e6}
    for extra in ({}, {"AB": 960e-6}):
        p0 = ps.replace(**extra)
        u0 = RIG.simulate(p0, "x_ref", xr, 1e-3, init=init).inputs["u"][0]
        ud = RIG.simulate(p0.replace(Kdp=1e-7), "x_ref", xr, 1e-3, init=init).inputs["u"][0]
        ratio = extra.get("AB", ps["A"]) / ps["A"]
        assert ud - u0 == pytest.approx(-1e-7 * (19e6 - 9e6 * ratio), rel=1e-9)
    with pytest.raises(Exception, match="u_max"):
        RIG.params(u_max=-1.0)


def _jittered(ref, jitter_s, seed):
    rng = np.random.default_rng(seed)
    t_ns = np.round((np.arange(len(ref.t)) * ref.dt + rng.uniform(0, jitter_s, len(ref.t))) * 1e9).astype(np.int64)
    return Samples(t_ns, {k: np.asarray(v, float) for k, v in ref.signals.items()})


def test_time_stamp_jitter_is_put_back_on_the_grid_and_real_gaps_stay_gaps(pid_record):
    s = _jittered(pid_record, 150e-6, 1004)
    (rec,) = records_from_samples(s, "jittered")
    assert len(rec) == len(pid_record.t) and rec.dt == pytest.approx(pid_record.dt, rel=1e-5)
    np.testing.assert_array_equal(rec.signals["x"], pid_record.signals["x"])
    keep = np.ones(len(s), bool)
    keep[3000] = False  # one sample lost: a gap, two records
    holed = Samples(s.t_ns[keep], {k: v[keep] for k, v in s.signals.items()})
    pieces = records_from_samples(holed, "holed")
    assert [len(p) for p in pieces] == [3000, len(s) - 3001]


def test_jittered_csv_fits_tracks_and_reads_consistently(pid_record, tmp_path, capsys):
    """The same file: replay info gap-free, twin fit one record on the grid, twin track processes it."""
    s = _jittered(pid_record, 150e-6, 1005)
    path = tmp_path / "jitter.csv"
    cols = ("x_ref", "u", "x", "pA", "pB")
    np.savetxt(path, np.column_stack([s.t_ns * 1e-9] + [s.signals[c] for c in cols]), delimiter=",",
               header=",".join(["t", *cols]), comments="", fmt=["%.9f"] + ["%.17g"] * len(cols))
    from replay import cli as replay_cli

    assert replay_cli.main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["report"]["gaps_ns"] == [] and 50e-6 < info["jitter_s"] <= 150e-6
    (rec,) = load_records(str(path))
    assert len(rec) == len(pid_record.t)
    sets = ",".join(f"{k}={v}" for k, v in {**PID, "Tf": "1ms"}.items())
    assert cli.main(["fit", str(path), "--set", sets, "--json", "-q", "--starts", "4"]) == 0
    out = json.loads(capsys.readouterr().out)
    for k in ("Cd", "wn"):
        v = out["params"][k]["value"]
        assert abs(v / pid_record.truth[k] - 1) < 0.05, (k, v)
    assert cli.main(["track", str(path), "--set", sets, "--json", "-q"]) == 0
    capsys.readouterr()


def test_tracker_lanes_with_two_areas_are_the_model_right_hand_side():
    """The tracker's side-by-side lanes compute the two-area physics with the model's own operations: each lane is
    the model's step, bit for bit."""
    from twin.models import msp25_lanes as F

    rng = np.random.default_rng(1006)
    for ab, v0b in ((0.0, 0.0), (960e-6, 300e-6)):
        p = RIG.vector(RIG.params(AB=ab, V0B=v0b))
        S = np.array([[rng.normal(0, 2e-4), rng.normal(0, 0.05), rng.uniform(2e6, 26e6), rng.uniform(2e6, 26e6),
                       rng.normal(0, 0.02), rng.normal(0, 0.05)] for _ in range(F.LANES)])
        u = rng.normal(0, 1, size=4)
        idx = np.array([RIG.kernel_index("Ffric")], dtype=np.int64)
        TH = np.full((F.LANES, 1), p[idx[0]])
        got = S.copy()
        F.lanes(got, TH, F.LANES, p.copy(), idx, u, 0, 1e-3, 2, np.empty(F.LANE_WORK))
        for ln in range(F.LANES):
            one = np.empty(6)
            M.step(S[ln], u[1], p, 1e-3, 2, one)
            np.testing.assert_array_equal(got[ln], one)


def test_tracker_driven_by_the_demand_runs_the_rigs_filtered_pid():
    """No logged u: the tracker's controller drive is the rig's PID with its memory (integral, filtered
    derivative) carried from sample to sample; started off the truth, it settles near it with a consistent
    filter; forgetting the controller's memory (the tracker before) bends the valve's parameters."""
    from twin.models.simulate import excite, measure
    from twin.online.tracker import OnlineTracker

    params = {**PID, "Tf": 1e-3}
    ps = RIG.params(**params)
    _, xr = excite(RIG, 20.0, 1e-3, seed=1007)
    rec = measure(RIG, ps, "x_ref", xr, 1e-3, noise={"x": 2e-6, "pA": 2e4, "pB": 2e4}, seed=1007)
    s = rec.to_samples()
    demand_only = Samples(s.t_ns, {k: v for k, v in s.signals.items() if k != "u"})
    start = {"Ffric": 60.0, "CdAleak": 3.2863e-9 * 1.3, "Cd": 0.2191 * 1.1, "zeta": 0.3701 * 0.9,
             "wn": RIG.params()["wn"] * 1.1}
    out = OnlineTracker(params=params, start=start).process(demand_only)
    est = dict(zip(M.PHENOMENOLOGICAL, out.estimates[-1]))
    for k in ("Cd", "zeta", "wn"):
        assert abs(est[k] / ps[k] - 1) < 0.05, (k, est[k], ps[k])
    assert (out.guard[-5000:] == "consistent").mean() > 0.5


@pytest.mark.slow
def test_a_fit_that_explains_almost_none_of_an_output_is_never_a_plain_success(single_rod):
    """The single-rod record passed off as a symmetric rig under a static load (which the plausibility check
    cannot tell apart): the pressures are not fitted, and the result says so in its message and JSON."""
    res = fit(RIG, product_record(single_rod), FREE, base=RIG.params(Fext=-17.6e3, KP=300.0), n_starts=4)
    bad = [o for o in res.outputs if res.fit_pct[o] <= 10.0]
    assert bad and all(f"Fit({o})" in " ".join(res.warnings) for o in bad)
    assert "WARNING" in res.message and res.to_dict()["warnings"] == res.warnings
    good = fit(RIG, product_record(single_rod), FREE, base=RIG.params(**SINGLE_ROD), start=off_truth(single_rod, 7),
               n_starts=2)
    assert good.warnings == [] and "WARNING" not in good.message


def test_a_rate_change_is_not_read_as_jitter():
    t = np.concatenate([np.arange(2000) * 1_000_000, 2000 * 1_000_000 + np.arange(1, 2001) * 1_250_000])
    s = Samples(t.astype(np.int64), {"x": np.zeros(t.size)})
    with pytest.raises(DataError, match="not jitter of a fixed sample rate"):
        records_from_samples(s, "two rates")


# --- signals at their own rates -----------------------------------------------------------------------
def test_fresh_mask_finds_held_signals_and_leaves_quantised_ones_alone():
    from twin.record import fresh_mask

    rng = np.random.default_rng(1010)
    n = 4000
    k = np.arange(n)
    fast = rng.normal(0.0, 1.0, n)
    for every in (2, 4, 100):
        held = fast[k - k % every]
        m = fresh_mask(held)
        assert m is not None and np.array_equal(m, k % every == 0)
    assert fresh_mask(fast) is None
    # quantised at 1 um with 0.4 um of noise at rest (most samples repeat): measured on every sample all the same
    q = np.round(rng.normal(0.0, 0.4e-6, n) / 1e-6) * 1e-6
    assert np.mean(q[1:] == q[:-1]) > 0.5 and fresh_mask(q) is None
    assert fresh_mask(np.zeros(n)) is None  # a constant signal holds nothing


def test_a_prediction_is_held_as_the_log_holds_its_signal():
    from twin.record import as_logged

    rng = np.random.default_rng(1011)
    k = np.arange(1000)
    p = rng.normal(0.0, 1.0, 1000)
    rec = Record(1e-3, {"x": rng.normal(0.0, 1.0, 1000), "pA": p[k - k % 2]})
    pred = np.arange(2000.0).reshape(2, 1000)
    np.testing.assert_array_equal(as_logged(rec, "pA", pred), pred[:, k - k % 2])
    assert as_logged(rec, "x", pred) is pred
    np.testing.assert_array_equal(as_logged(rec, "pA", pred[:, :7]), pred[:, [0, 0, 2, 2, 4, 4, 6]])


@pytest.fixture(scope="module")
def can_rate_record(reference_records):
    from conftest import msp25_spec

    return reference_records([msp25_spec(1008, duration=DURATION, truth="draw", known=PID, pid={"Tf": 1e-3},
                                         signal_rates={"pA": 500.0, "pB": 500.0}, time_jitter_s=150e-6)])[0]


def test_can_rate_pressures_fit_on_their_fresh_samples_only(can_rate_record):
    ref = can_rate_record
    s = Samples(np.round(ref.t * 1e9).astype(np.int64), {k: np.asarray(v, float) for k, v in ref.signals.items()})
    (rec,) = records_from_samples(s, "can")
    for o in ("pA", "pB"):
        np.testing.assert_array_equal(rec.fresh_of(o), ref.hidden[f"fresh_{o}"] > 0)
    assert rec.fresh_of("x") is None
    res = fit(RIG, rec, FREE, base=RIG.params(**PID, Tf=1e-3), start=off_truth(ref, 1008))
    assert_within(res, ref, "CAN-rate pressures")
    assert res.n_obs == len(rec) * 2  # x on every sample, each pressure on every other one


def test_tracker_takes_a_held_pressure_as_missing(can_rate_record):
    from twin.online.tracker import OnlineTracker

    ref = can_rate_record
    s = Samples(np.round(ref.t * 1e9).astype(np.int64), {k: np.asarray(v, float) for k, v in ref.signals.items()})
    out = OnlineTracker(params={**PID, "Tf": 1e-3}).process(s)
    held = ref.hidden["fresh_pA"] == 0
    j = ["x", "pA", "pB"].index("pA")
    assert not out.used[held, j].any()
    assert out.used[~held, j].mean() > 0.95 and out.used[:, 0].mean() > 0.95


def test_a_chirp_to_the_speed_limit_fits_within_three_standard_errors(reference_records):
    from conftest import msp25_spec

    ref = reference_records([msp25_spec(1009, duration=DURATION, truth="draw", demand={"kind": "chirp"})])[0]
    assert np.max(np.abs(np.gradient(ref.signals["x_ref"], ref.dt))) > 0.2  # it reaches the speed limit
    res = fit(RIG, product_record(ref), FREE, start=off_truth(ref, 1009))
    assert_within(res, ref, "chirp")
