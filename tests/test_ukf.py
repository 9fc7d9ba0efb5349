"""The compiled UKF kernel (twin.online.ukf): filterpy's filter as the reference on the paths test_tracker.py
does not cover (missing measurements, drive from x_ref), a linear Kalman oracle for the update, the
bounded parameter random walk across a long rest, unrepairable covariances and stale inputs."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints

from replay.base import Samples
from twin.online import ukf
from fpdd.errors import FilterError
from twin.models import msp25 as M
from twin.models.scenario import simulate_wear
from fpdd.units import NOMINAL_NOISE
from twin.models.simulate import excite
from twin.online.tracker import OnlineTracker
from tests.ukf_mirror import mirror, ours

NOISE = {k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}
WRONG = {"Ffric": 75.0, "CdAleak": 3.2863e-9 * 0.5, "Cd": 0.2191 * 1.5, "zeta": 0.3701 * 0.5,
         "wn": M.NOMINAL["wn"] * 1.5}
NAMES = ("x", "pA", "pB")
#: a single-rod cylinder (rod side's annulus half the piston's area, its chamber smaller)
SINGLE_ROD = {"AB": 960e-6, "V0B": 300e-6}


def _samples(duration, seed, xr=None, **params):
    if xr is None:
        _, xr = excite(M.MODEL, duration, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(**params), xr, 1e-3, (), noise=NOISE, seed=seed)
    return rec.to_samples()


def _prepared(samples, **kw):
    """A tracker that has read its initial state off ``samples`` (so a copy can start filterpy there)."""
    tr = OnlineTracker(**{"start": WRONG, "adapt_noise": False, **kw})
    tr.dt = 1e-3
    tr._start_from_data(samples)
    tr._started = True
    return tr


def _compare(samples, rtol=1e-7, atol=1e-9, **kw):
    tr = _prepared(samples, **kw)
    ref = copy.deepcopy(tr)
    out = tr.process(samples)
    expected = mirror(ref, samples, out)
    np.testing.assert_allclose(ours(tr, out), expected[:, :tr.nmod], rtol=rtol, atol=atol)
    return tr, out, expected


def test_same_as_filterpy_with_missing_measurements_per_sample():
    s = _samples(0.3, 21)
    T = len(s)
    rng = np.random.default_rng(21)
    sig = {k: v.copy() for k, v in s.signals.items()}
    for name, frac in (("x", 0.1), ("pA", 0.2), ("pB", 0.2)):
        sig[name][rng.random(T) < frac] = np.nan
    sig["x"][100:103] = sig["pA"][100:103] = sig["pB"][100:103] = np.nan  # nothing measured: prediction only
    holes = Samples(s.t_ns, sig)
    tr, out, _ = _compare(holes, excite=(0.0, 0.0, 0.0), gate_p=1e-300)
    assert list(out.status[100:103]) == ["stale_input"] * 3


def test_same_as_filterpy_on_a_single_rod_cylinder():
    """Two areas (AB, V0B): the lean path's physics against filterpy driving the model's own step."""
    s = _samples(0.3, 23, **SINGLE_ROD)
    assert np.mean(s.signals["pB"]) > 1.5 * np.mean(s.signals["pA"])
    tr, out, expected = _compare(s, excite=(0.0, 0.0, 0.0), gate_p=1e-300, params=SINGLE_ROD)
    assert ukf.functions_of(tr.model).lanes_applicable(tr.pvec) and tr.pvec[M.I_AB] == SINGLE_ROD["AB"]


def test_same_as_filterpy_with_coloured_noise_states_and_a_linear_input():
    """AR(1) noise states (a = 0.9 on x) and foh between the logged u samples: filterpy's algebra."""
    s = _samples(0.3, 22)
    tr, out, expected = _compare(s, excite=(0.0, 0.0, 0.0), gate_p=1e-300, noise_colour={"x": 0.9},
                                 timing="continuous")
    assert tr.timing.intersample_code(1e-3) == 2 and np.max(np.abs(expected[-1, 6:11] - expected[0, 6:11])) > 0.05


@pytest.mark.slow  # filterpy's Python filter over 20 s of samples; the shorter comparisons above stay
def test_same_as_filterpy_with_the_production_settings_over_twenty_seconds():
    """Gating, excitation freezing and the consistency guard on (noise learning off): 20 s of a healthy
    record started away from the truth, filterpy following the same decisions, same numbers."""
    s = _samples(20.0, 26)
    sig = {k: v.copy() for k, v in s.signals.items()}
    sig["x"][5000] += 5e-3  # one output far off while the others agree: left out of the update
    for k, d in (("x", 1e-3), ("pA", 2e6), ("pB", -2e6)):
        sig[k][7000] += d  # all three: gated
    s = Samples(s.t_ns, sig)
    tr, out, expected = _compare(s, rtol=1e-6, atol=1e-7)
    assert out.frozen.any() and out.status[7000] == "gated" and not out.used[5000, 0]  # all paths exercised
    assert (out.guard == "consistent").mean() > 0.5
    truth = np.array([M.NOMINAL[n] for n in tr.tracked])
    assert np.all(np.abs(out.estimates[-1] / truth - 1) < 4 * out.log_std[-1] + 0.01)


def _random_pd(n, rng):
    A = rng.normal(size=(n, n))
    return A @ A.T / n + 0.1 * np.eye(n)


def _update_problem(seed: int):
    """A random 11-state prior measured at x, pA, pB: (n, meas_idx, H, R, x0, P0, z)."""
    rng = np.random.default_rng(seed)
    n = 11
    meas_idx = np.array([4, 2, 3], dtype=np.int64)
    H = np.zeros((3, n))
    H[np.arange(3), meas_idx] = 1.0
    R = np.array([0.04, 0.09, 0.01])
    x0 = rng.normal(size=n)
    P0 = _random_pd(n, rng)
    return n, meas_idx, H, R, x0, P0, H @ x0 + rng.normal(size=3)


def test_update_is_the_linear_kalman_update():
    n, meas_idx, H, R, x0, P0, z = _update_problem(5)
    kf = KalmanFilter(dim_x=n, dim_z=3)
    kf.x, kf.P, kf.H, kf.R = x0.copy(), P0.copy(), H, np.diag(R)
    kf.update(z)
    x, P = x0.copy(), P0.copy()
    innov, Sd = np.empty(3), np.empty(3)
    st, nis, ll, m = ukf._update(x, P, z, meas_idx, -1, R, np.ones(3, bool), np.zeros(n, dtype=np.bool_), np.inf,
                                 innov, Sd)
    assert (ukf.STATUS[st], m) == ("ok", 3)
    np.testing.assert_allclose(x, kf.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(P, kf.P, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(innov, kf.y, rtol=1e-12)
    np.testing.assert_allclose(Sd, np.diag(kf.S), rtol=1e-12)
    assert nis == pytest.approx(float(kf.y @ np.linalg.solve(kf.S, kf.y)), rel=1e-10)
    assert ll == pytest.approx(kf.log_likelihood, rel=1e-10)


def test_update_with_noise_states_is_the_linear_kalman_update_of_model_plus_noise():
    n, meas_idx, H, R, x0, P0, z = _update_problem(7)
    H2 = np.zeros((3, n))
    H2[np.arange(3), meas_idx] = 1.0
    H2[np.arange(3), 8 + np.arange(3)] = 1.0  # noise states 8, 9, 10
    use = np.array([True, False, True])
    kf = KalmanFilter(dim_x=n, dim_z=2)
    kf.x, kf.P, kf.H, kf.R = x0.copy(), P0.copy(), H2[use], np.diag(R[use])
    kf.update(z[use])
    x, P = x0.copy(), P0.copy()
    innov = np.full(3, np.nan)
    st, nis, ll, m = ukf._update(x, P, z, meas_idx, 8, R, use, np.zeros(n, dtype=np.bool_), np.inf, innov,
                                 np.empty(3))
    assert m == 2 and np.isnan(innov[1])
    np.testing.assert_allclose(x, kf.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(P, kf.P, rtol=1e-10, atol=1e-12)
    assert ll == pytest.approx(kf.log_likelihood, rel=1e-10)


def test_frozen_rows_get_no_gain_and_an_honest_covariance():
    n, meas_idx, H, R, x0, P0, z = _update_problem(6)
    freeze = np.zeros(n, dtype=np.bool_)
    freeze[[6, 8]] = True
    x, P = x0.copy(), P0.copy()
    st, _, _, _ = ukf._update(x, P, z, meas_idx, -1, R, np.ones(3, bool), freeze, np.inf, np.empty(3), np.empty(3))
    assert ukf.STATUS[st] == "frozen"
    assert x[6] == x0[6] and x[8] == x0[8]
    K = P0 @ H.T @ np.linalg.inv(H @ P0 @ H.T + np.diag(R))
    K[freeze] = 0.0
    IKH = np.eye(n) - K @ H
    np.testing.assert_allclose(P, IKH @ P0 @ IKH.T + K @ np.diag(R) @ K.T, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(x, x0 + K @ (z - H @ x0), rtol=1e-12, atol=1e-12)
    assert P[6, 6] == pytest.approx(P0[6, 6], rel=1e-12)  # no information on a frozen parameter
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_a_long_rest_does_not_blow_up_the_parameters():
    """At rest the parameters are frozen and only their random walk acts; it stops at PARAM_STD_CAP, so
    the first sigma points after the rest stay where the model is finite. A fast walk (20 log units per
    sqrt(s)) stands in for a night at the default rates: without the cap the std would reach 35."""
    _, xr = excite(M.MODEL, 8.0, 1e-3, seed=23)
    s = _samples(0.0, 23, xr=np.concatenate([np.zeros(3000), xr]))
    tr = OnlineTracker(q_rate={n: 20.0 for n in M.PHENOMENOLOGICAL})
    rest = tr.process(s.slice(0, 3000))
    assert rest.frozen[-1].all() and np.mean(rest.status[1000:] == "frozen") > 0.95
    # at the cap: the walk's addition stops there, in the logit coordinates at the estimate of the moment; the
    # first samples, before the rest was seen, move an estimate (and the logit's curvature) by a little
    np.testing.assert_allclose(rest.log_std[-1], ukf.PARAM_STD_CAP, rtol=0.02)
    np.testing.assert_allclose(rest.log_std[-1], rest.log_std[1000], rtol=1e-9)  # and stays there
    tr.q_rate[:] = [0.3, 0.15, 0.02, 0.05, 0.05]
    out = tr.process(s.slice(3000, len(s)))
    assert np.all(np.isfinite(out.estimates))
    j = tr.tracked.index("Cd")
    assert abs(out.estimates[-1, j] / 0.2191 - 1) < 3 * out.log_std[-1, j] + 1e-3
    assert out.log_std[-1, j] < 0.01


def test_unrepairable_covariance_goes_back_to_the_last_checkpoint_and_says_so():
    s = _samples(6.0, 24)
    tr = OnlineTracker()
    tr.process(s.slice(0, 4000))
    tr.P[7, 7] = np.nan
    out = tr.process(s.slice(4000, len(s)))
    # recovered at once; the watchdog may recover once more while it settles (with the pressure states' process
    # noise at 3e-7 MPa^2 per sample it does, 79 samples later), never again after it has settled
    assert out.status[0] == "recovered" and 1 <= tr.counters["recovered"] <= 2
    assert not np.any(out.status[1000:] == "recovered")
    assert set(out.guard[:1000]) <= {"settling", "diverged"}  # the drift test holds while it settles
    assert np.all(np.isfinite(out.estimates)) and np.all(np.isfinite(tr.P))
    j = tr.tracked.index("Cd")
    assert abs(out.estimates[-1, j] / 0.2191 - 1) < 0.01
    tr.x_ck[:] = np.nan  # no usable checkpoint: one line naming the sample
    tr.P[7, 7] = np.nan
    with pytest.raises(FilterError, match=r"at sample 6000 \(t_ns=6000000000\)"):
        tr.process(s.slice(0, 10).__class__(s.t_ns[-10:] + 10_000_000, {k: v[-10:] for k, v in s.signals.items()}))


def test_missing_input_is_held_and_reported_stale():
    s = _samples(1.0, 25)
    sig = {k: v.copy() for k, v in s.signals.items()}
    sig["u"][400:410] = np.nan
    sig["x_ref"][400:410] = np.nan
    out = OnlineTracker().process(Samples(s.t_ns, sig))
    assert set(out.status[400:410]) == {"stale_input"}
    assert "stale_input" not in set(out.status[411:])
    assert np.all(np.isfinite(out.estimates))


def test_sigma_point_weights_are_filterpys_with_a_small_alpha():
    tr = OnlineTracker()
    pts = MerweScaledSigmaPoints(tr.n, alpha=tr.alpha, beta=tr.beta, kappa=tr.kappa)
    np.testing.assert_allclose(tr.Wm, pts.Wm, rtol=1e-14)
    np.testing.assert_allclose(tr.Wc, pts.Wc, rtol=1e-14)
    assert tr.alpha <= 0.5  # wide sigma points through the tanh friction fling the parameters (model-spec)


@pytest.mark.parametrize("mode,params", [(0, {}), (1, {}), (2, {}), (0, SINGLE_ROD), (2, SINGLE_ROD)])
def test_sigma_points_propagated_together_are_the_models_step_exactly(mode, params):
    """The model's lanes integrate the sigma points side by side (vectorised): per point the same numbers as the
    model's own one-point ``advance`` (its right-hand side ``deriv``), bit for bit, on both sides of the valve's
    null and with a noise state in the last coordinates; a symmetric and a single-rod cylinder."""
    tr = OnlineTracker(params=params)
    F = ukf.functions_of(tr.model)
    predict = ukf.kernel_modules(tr.model)[0]  # the prediction compiled with the model's functions
    _lanes, fx_into = predict._lanes, predict.fx_into
    n, nm, ns = tr.n, tr.nmod, tr.ns
    rng = np.random.default_rng(31 + mode)
    x = np.concatenate([[0.01, 0.0, 11.0, 9.0, 2.0, 0.5], np.zeros(len(tr.tracked)), np.zeros(n - nm)])
    sig = x + rng.normal(size=(2 * n + 1, n)) * np.concatenate([[0.05, 0.5, 2.0, 2.0, 1.0, 1.0],
                                                                np.full(len(tr.tracked), 0.3), np.full(n - nm, 0.1)])
    assert (sig[:, 0] < 0).any() and (sig[:, 0] > 0).any()
    wnd = np.array([0.1, 0.2, 0.5, 0.5])
    rows = np.array([k for k in range(2 * n + 1) if k == 0 or (k - 1) % n < nm])
    m = 2 * nm + 1
    assert F.lanes_applicable(tr.pvec) and m <= F.LANES
    sf = np.full((2 * n + 1, n), np.nan)
    _lanes(sig, sf, rows, m, wnd, mode, tr.pvec.copy(), tr.idx, tr.lo_log, tr.width, tr.scale, 1e-3, 2, nm,
           np.empty((F.LANES, ns)), np.empty((F.LANES, len(tr.tracked))), np.empty(F.LANE_WORK))
    for r in rows[:m]:
        one = np.empty((2 * n + 1, n))
        fx_into(sig, r, wnd, False, 1, mode, tr.pvec.copy(), tr.idx, tr.lo_log, tr.width, tr.scale, 1e-3, 2,
                0.0, np.zeros(F.N_CTRL), F.N_CTRL, np.empty(ns), np.empty(ns), one, nm)
        np.testing.assert_array_equal(sf[r, :nm], one[r, :nm])
    assert np.isnan(sf[nm + 1:n + 1]).all()  # the points along noise states are not integrated


def test_the_oscillators_prediction_integrates_its_sigma_points_in_one_call_as_one_at_a_time():
    """The oscillator's filter takes the side-by-side path (its lanes apply to every parameter vector): per sigma
    point the same numbers as its one-point ``fx_into``, bit for bit."""
    tr = OnlineTracker(model="oscillator")
    F = ukf.functions_of(tr.model)
    predict = ukf.kernel_modules(tr.model)[0]
    n, nm, ns = tr.n, tr.nmod, tr.ns
    rng = np.random.default_rng(41)
    sig = rng.normal(size=(2 * n + 1, n)) * np.concatenate([[0.5, 2.0], np.full(len(tr.tracked), 0.3),
                                                            np.full(n - nm, 0.1)])
    rows = np.array([k for k in range(2 * n + 1) if k == 0 or (k - 1) % n < nm])
    m = 2 * nm + 1
    assert F.lanes_applicable(tr.pvec) and m <= F.LANES
    wnd = np.array([0.1, 0.2, 0.5, 0.5])
    sf = np.full((2 * n + 1, n), np.nan)
    predict._lanes(sig, sf, rows, m, wnd, 1, tr.pvec.copy(), tr.idx, tr.lo_log, tr.width, tr.scale, 1e-3, 2, nm,
                   np.empty((F.LANES, ns)), np.empty((F.LANES, len(tr.tracked))), np.empty(F.LANE_WORK))
    for r in rows[:m]:
        one = np.empty((2 * n + 1, n))
        predict.fx_into(sig, r, wnd, False, 1, 1, tr.pvec.copy(), tr.idx, tr.lo_log, tr.width, tr.scale, 1e-3, 2,
                        0.0, np.zeros(F.N_CTRL), F.N_CTRL, np.empty(ns), np.empty(ns), one, nm)
        np.testing.assert_array_equal(sf[r, :nm], one[r, :nm])


def test_a_models_kernel_is_the_filters_source_with_one_marked_import_swapped():
    """The kernel of a model is ``ukf_predict`` and ``ukf_loop`` as written, each with its one marked import naming
    the model's module (and the model's prediction) instead of the slot: no other line differs, and a source that
    lost its marker is refused in one line."""
    from pathlib import Path

    from twin.online import ukf_loop, ukf_predict

    tr = OnlineTracker()
    predict, loop = ukf.kernel_modules(tr.model)
    functions = tr.model.FILTER.functions
    for generated, original, slot, named in ((predict, ukf_predict, "twin.online.ukf_model", functions),
                                             (loop, ukf_loop, "twin.online.ukf_predict", predict.__name__)):
        new = Path(generated.__file__).read_text().splitlines()
        old = Path(original.__file__).read_text().splitlines()
        assert new[:len(old)] == [row.replace(f"from {slot} import ", f"from {named} import ") for row in old]
        assert sum(a != b for a, b in zip(new, old)) == 1
        tail = new[len(old):]
    assert any(row.startswith("def run(") for row in tail)  # the loop's copy: the kernel's entry, appended
    with pytest.raises(RuntimeError, match="ukf_loop.py: expected one line"):
        ukf._swap_import("from twin.online.ukf_predict import _predict\n", ukf._PREDICT_LINE, "x", "twin/online/ukf_loop.py")


def test_the_kernel_is_loaded_from_numbas_cache_in_a_fresh_process():
    """The per-model kernel is a generated module whose compiled code numba caches: a second process loads it."""
    import subprocess
    import sys

    code = ("from twin.online.tracker import OnlineTracker; from twin.online import ukf; import numpy as np;"
            "from replay.base import Samples;"
            "tr = OnlineTracker(dt=1e-3); t = np.arange(5, dtype=np.int64) * 1000000;"
            "tr.process(Samples(t, {'u': np.zeros(5), 'x': np.zeros(5), 'pA': np.full(5, 14e6), 'pB': np.full(5, 14e6)}));"
            "k = ukf.kernel_for(tr.model); print(sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values()))")
    tr = OnlineTracker(dt=1e-3)  # this process compiles (or loads) it on its first block: the cache is written
    t = np.arange(5, dtype=np.int64) * 1000000
    tr.process(Samples(t, {"u": np.zeros(5), "x": np.zeros(5), "pA": np.full(5, 14e6), "pB": np.full(5, 14e6)}))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True)
    assert out.stdout.split() == ["1", "0"], out.stdout + out.stderr


def test_two_threads_making_a_models_kernel_at_once_both_get_it():
    """A service starts its rigs in threads: the first two to make a model's kernel at once must both get it (a
    second thread had replaced the first one's half-executed module, and the first then failed to import
    ``_predict`` from it: CI's live-view test, a rig and an idle rig in one process)."""
    import sys
    import threading

    from twin.models import get_model
    from twin.online import ukf

    model = get_model("oscillator")
    name = model.FILTER.functions
    saved = ukf._KERNELS.pop(name, None)
    for mod in [m for m in sys.modules if m.startswith("ukf_") and name.replace(".", "_") in m]:
        del sys.modules[mod]
    got: list = []
    errors: list = []
    start = threading.Barrier(4)

    def make() -> None:
        start.wait(timeout=60.0)
        try:
            got.append(ukf.kernel_for(model))
        except Exception as exc:  # noqa: BLE001 - the failure is what the test reports
            errors.append(exc)

    threads = [threading.Thread(target=make) for _ in range(4)]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=300.0)
        assert not errors, errors
        assert len(got) == 4 and all(g is got[0] for g in got)
    finally:
        if saved is not None and name not in ukf._KERNELS:
            ukf._KERNELS[name] = saved
