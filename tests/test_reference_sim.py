"""The independent reference simulator (tests/reference): physics sanity, numerics, controllers,
effects, cache, CSV contract, and a cross-check against the product's simulator on shared physics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm

from conftest import get_records
from reference import (MSP25_EFFECTS, MSP25_FREE, MSP25_KNOWN, OSC_FREE, Record, draw_effects, draw_truth,
                       get_record, msp25_spec, oscillator_spec, replay_spec, spec_key)

KP = MSP25_KNOWN["KP"]
AREA = MSP25_KNOWN["A"]
QUIET = {"amplitude": 0.0}


def _rel_rms(a, b, ref=None):
    ref = b if ref is None else ref
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean((ref - np.mean(ref)) ** 2)))


# --- the specs of this module, simulated together (two processes) -------------------------------
SPECS = {
    "rest": msp25_spec(0, duration=1.0, demand=QUIET, truth={"CdAleak": 0.0}, noise=None),
    "loaded": msp25_spec(0, duration=1.0, demand=QUIET, Fext=15e3, noise=None),
    "analog": msp25_spec(1, duration=2.0, controller="analog", noise=None),
    "analog_tight": msp25_spec(1, duration=2.0, controller="analog", noise=None, rtol=1e-10, atol_scale=0.01),
    "digital1k": msp25_spec(1, duration=2.0, controller="digital", noise=None),
    "digital5k": msp25_spec(1, duration=2.0, controller="digital", rate_hz=5000, noise=None),
    "digital1k_radau": msp25_spec(1, duration=0.5, controller="digital", noise=None, driver="solve_ivp",
                                  method="Radau"),
    "digital1k_short": msp25_spec(1, duration=0.5, controller="digital", noise=None),
    "noisy_digital": msp25_spec(2, duration=2.0, controller="digital", intersample="zoh"),
    "noisy_digital5k": msp25_spec(2, duration=2.0, controller="digital", rate_hz=5000, intersample="foh"),
    "noisy_analog": msp25_spec(2, duration=2.0, controller="analog", intersample="cubic"),
    "ar1": msp25_spec(2, duration=2.0, controller="digital", noise={"tau": 5e-3}),
    "delay_digital": msp25_spec(3, duration=2.0, effects={"sensor_delay": {"delay": 2e-3}}, noise=None),
    "delay_analog": msp25_spec(3, duration=2.0, controller="analog", effects={"sensor_delay": {"delay": 2e-3}},
                               noise=None),
    "nodelay_digital": msp25_spec(3, duration=2.0, noise=None),
    "crosscheck": msp25_spec(4, duration=5.0, controller="digital", intersample="zoh", noise=None),
    "tv_step": msp25_spec(5, duration=2.0, noise=None, time_varying={
        "Ffric": {"kind": "step", "t0": 1.0, "before": 60.0, "after": 150.0}}),
    "tv_const60": msp25_spec(5, duration=2.0, noise=None, truth={"Ffric": 60.0}),
    "healthy": msp25_spec(6, duration=1.5, noise=None, demand={"amplitude": 8e-3}),
    **{f"demand_{k}": msp25_spec(7, duration=3.0, noise=None, demand={"kind": k, "amplitude": 8e-3, "f_hi": 12.0,
                                                                         "v_max": 0.2})
       for k in ("chirp", "sweep", "blocks", "road")},
    "demand_road_other_seed": msp25_spec(8, duration=3.0, noise=None, demand={"kind": "road", "amplitude": 8e-3,
                                                                              "f_hi": 12.0, "v_max": 0.2}),
    "rates_all": msp25_spec(9, duration=1.0, temperature={"T": 318.0}),
    "rates_500": msp25_spec(9, duration=1.0, temperature={"T": 318.0}, signal_rates={"pA": 500, "pB": 250,
                                                                                       "T_oil": 10}),
    # oil at T0 + 20 K against Table 8's oil and truth moved by the stated laws: the same rig
    "warm_oil": msp25_spec(10, duration=1.5, noise=None, temperature={"T": 333.15, "T0": 313.15, "a_bulk": 0.006,
                                                                      "b_visc": 0.03}),
    "warm_oil_by_law": msp25_spec(10, duration=1.5, noise=None, known={"B": 1.5e9 * (1 - 0.006 * 20.0)},
                                  truth={"CdAleak": MSP25_FREE["CdAleak"] * math.exp(0.03 * 20.0)}),
    "cold_oil": msp25_spec(10, duration=1.5, noise=None),
}
EFFECT_SPECS = {name: msp25_spec(6, duration=1.5, noise=None, demand={"amplitude": 8e-3}, effects=[name])
                for name in MSP25_EFFECTS}


@pytest.fixture(scope="module")
def rec() -> dict[str, Record]:
    names = list(SPECS) + [f"effect:{n}" for n in EFFECT_SPECS]
    specs = list(SPECS.values()) + list(EFFECT_SPECS.values())
    return dict(zip(names, get_records(specs)))


# --- physics sanity ---------------------------------------------------------------------------------
@pytest.mark.slow
def test_rig_at_rest_without_leak_keeps_its_pressures(rec):
    r = rec["rest"]
    assert r.meta["equilibrium"] == "rest"
    assert np.ptp(r.signals["pA"]) < 1e-3 and np.ptp(r.signals["pB"]) < 1e-3
    assert r.signals["pA"][0] == pytest.approx(14e6) and r.signals["pB"][0] == pytest.approx(14e6)
    assert np.max(np.abs(r.signals["x"])) < 1e-12 and np.max(np.abs(r.signals["u"])) < 1e-9


def test_loaded_rig_starts_settled_with_the_load_balanced(rec):
    r = rec["loaded"]
    pA, pB = r.signals["pA"], r.signals["pB"]
    assert r.meta["equilibrium"] == "solved"
    # the record does not start at rest with equal pressures: about 17.9 / 10.1 MPa
    assert pA[0] == pytest.approx(17.9e6, rel=2e-3) and pB[0] == pytest.approx(10.1e6, rel=2e-3)
    np.testing.assert_allclose((pA - pB) * AREA, 15e3, rtol=1e-7)
    np.testing.assert_allclose(pA + pB, MSP25_KNOWN["pP"], rtol=1e-7)  # symmetric valve feeds the leak
    assert np.ptp(pA) < 1.0 and np.ptp(r.hidden["x"]) < 1e-9
    # the valve stays open just enough to feed the leak: a small steady position error
    leak = MSP25_FREE["CdAleak"] * math.sqrt(2 * (pA[0] - pB[0]) / MSP25_KNOWN["rho"])
    g = MSP25_FREE["Cd"] * MSP25_KNOWN["b"] * math.sqrt(2 * (MSP25_KNOWN["pP"] - pA[0]) / MSP25_KNOWN["rho"])
    assert r.hidden["xs"][0] == pytest.approx(leak / g, rel=1e-6)


def test_tolerances_converge(rec):
    a, b = rec["analog"], rec["analog_tight"]
    assert np.max(np.abs(a.hidden["x"] - b.hidden["x"])) < 1e-6 * np.max(np.abs(b.hidden["x"]))
    assert np.max(np.abs(a.signals["pA"] - b.signals["pA"])) < 20.0
    # solve_ivp's Radau and odeint's LSODA agree tick by tick
    c, d = rec["digital1k_radau"], rec["digital1k_short"]
    assert np.max(np.abs(c.hidden["x"] - d.hidden["x"])) < 1e-9
    assert np.max(np.abs(c.signals["pB"] - d.signals["pB"])) < 20.0


def test_analog_and_digital_controllers_differ_and_5k_is_closer(rec):
    a, d1, d5 = rec["analog"], rec["digital1k"], rec["digital5k"]
    e1 = _rel_rms(d1.hidden["x"], a.hidden["x"])
    e5 = _rel_rms(d5.hidden["x"], a.hidden["x"])
    assert e1 > 1e-3  # far above the integration error (previous test: < 1e-9 m)
    assert e5 < 0.35 * e1


def test_sensor_delay_shifts_the_cross_correlation_peak(rec):
    def lag(r):
        x, xs = r.signals["x"] - np.mean(r.signals["x"]), r.hidden["x"] - np.mean(r.hidden["x"])
        d = np.diff(x), np.diff(xs)  # velocity-like, sharp peak
        c = np.correlate(d[0], d[1], mode="full")
        return int(np.argmax(c)) - (d[1].size - 1)

    assert lag(rec["nodelay_digital"]) == 0
    assert lag(rec["delay_digital"]) == 2
    assert lag(rec["delay_analog"]) == 2
    # the controller reads the late x too: the loop differs from the undelayed one
    assert _rel_rms(rec["delay_digital"].hidden["x"], rec["nodelay_digital"].hidden["x"]) > 1e-3


def test_noise_goes_through_the_loop(rec):
    for name in ("noisy_digital", "noisy_digital5k", "noisy_analog"):
        r = rec[name]
        s = r.signals
        # u at the log instants is the controller's reading of the logged (noisy) x
        np.testing.assert_allclose(s["u"], KP * (s["x_ref"] - s["x"]), rtol=0, atol=1e-9)
        noise = s["x"] - r.hidden["x_sensor"]
        assert np.std(noise) == pytest.approx(2e-6, rel=0.1)
        # and u carries it: u - KP (x_ref - true x) = -KP noise
        np.testing.assert_allclose(s["u"] - KP * (s["x_ref"] - r.hidden["x"]), -KP * noise, atol=1e-9)
        assert np.std(s["pA"] - r.hidden["pA"]) == pytest.approx(2e4, rel=0.1)


def test_coloured_noise_is_ar1():
    r = get_records([SPECS["ar1"]])[0]
    n = r.signals["x"] - r.hidden["x_sensor"]
    rho1 = np.corrcoef(n[:-1], n[1:])[0, 1]
    assert rho1 == pytest.approx(math.exp(-1e-3 / 5e-3), abs=0.05)


def test_open_loop_replay_of_logged_u_reproduces_x(rec):
    spec = SPECS["noisy_digital"]
    r = rec["noisy_digital"]
    zoh, foh = get_records([replay_spec(spec, r, "zoh"), replay_spec(spec, r, "foh")])
    assert np.max(np.abs(zoh.hidden["x"] - r.hidden["x"])) < 1e-10
    assert np.max(np.abs(zoh.signals["pA"] - r.hidden["pA"])) < 1.0
    np.testing.assert_array_equal(zoh.signals["u"], r.signals["u"])
    # the wrong intersample does not reproduce it
    assert np.max(np.abs(foh.hidden["x"] - r.hidden["x"])) > 1e-6


def test_time_varying_truth_steps_at_its_time(rec):
    r, c = rec["tv_step"], rec["tv_const60"]
    assert r.truth["Ffric"]["kind"] == "step"
    np.testing.assert_array_equal(r.hidden["Ffric"], np.where(r.t < 1.0, 60.0, 150.0))
    before, after = r.t < 1.0, r.t > 1.05
    assert np.max(np.abs(r.hidden["x"][before] - c.hidden["x"][before])) < 1e-10
    assert np.max(np.abs(r.hidden["x"][after] - c.hidden["x"][after])) > 1e-6


# --- effects ------------------------------------------------------------------------------------------
def test_every_effect_changes_the_record_with_its_drawn_size(rec):
    h = rec["healthy"]
    for name, ranges in MSP25_EFFECTS.items():
        r = rec[f"effect:{name}"]
        sizes = r.meta["effects"][name]
        for p, rg in ranges.items():
            if len(rg) == 2:
                assert rg[0] <= sizes[p] <= rg[1], (name, p)
            assert r.truth[f"{name}.{p}"] == sizes[p]
        changed = max(np.max(np.abs(r.signals[k] - h.signals[k])) / np.std(h.signals[k]) for k in ("x", "pA", "pB", "u"))
        assert changed > 1e-3, name
    # sizes are drawn per seed, not one typical value
    a, b = draw_effects(1, list(MSP25_EFFECTS)), draw_effects(2, list(MSP25_EFFECTS))
    assert a["viscous_friction"]["c"] != b["viscous_friction"]["c"]
    assert draw_effects(1, {"viscous_friction": {"c": 1234.0}})["viscous_friction"]["c"] == 1234.0


def test_sensor_effects_act_on_the_log(rec):
    g = rec["effect:position_sensor_gain"]
    np.testing.assert_allclose(g.signals["x"], g.meta["effects"]["position_sensor_gain"]["gain"] * g.hidden["x"],
                               rtol=1e-12, atol=1e-15)
    o = rec["effect:pressure_sensor_offset"]
    e = o.meta["effects"]["pressure_sensor_offset"]
    ch = e["channel"]
    other = "pB" if ch == "pA" else "pA"
    np.testing.assert_allclose(o.signals[ch] - o.hidden[ch], e["sign"] * e["offset"], atol=1e-6)
    np.testing.assert_allclose(o.signals[other], o.hidden[other], atol=1e-6)
    # friction drift: the hidden truth ramps by the drawn factor
    d = rec["effect:parameter_drift"]
    f = d.meta["effects"]["parameter_drift"]["factor"]
    assert d.hidden["Ffric"][0] == pytest.approx(50.0) and d.hidden["Ffric"][-1] == pytest.approx(50.0 * f, rel=1e-3)


# --- truth draws, cache, CSV -------------------------------------------------------------------------
def test_truth_is_drawn_off_the_defaults():
    draws = [draw_truth(s) for s in range(40)]
    for d in draws:
        for k, v in d.items():
            rel = abs(v / MSP25_FREE[k] - 1.0)
            assert 0.03 <= rel <= 0.2
    assert draw_truth(3) == draw_truth(3) and draw_truth(3) != draw_truth(4)
    assert len({round(d["Cd"], 9) for d in draws}) == 40
    o = draw_truth(1, model="oscillator")
    assert set(o) == set(OSC_FREE) and all(0.03 <= abs(o[k] / OSC_FREE[k] - 1) <= 0.2 for k in o)


def test_cache_hit_returns_identical_arrays(tmp_path, monkeypatch):
    monkeypatch.setenv("FPDD_REFCACHE", str(tmp_path))
    spec = msp25_spec(7, duration=0.3)
    a = get_record(spec)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1
    b = get_record(spec)
    assert list(tmp_path.glob("*.npz")) == files
    for k in a.signals:
        np.testing.assert_array_equal(a.signals[k], b.signals[k])
    assert a.truth == b.truth and a.meta == b.meta
    assert spec_key(msp25_spec(7, duration=0.3, Fext=1.0)) != spec_key(spec)
    assert spec_key(msp25_spec(7, duration=0.3)) == spec_key(spec)


def test_csv_is_read_by_the_product(rec, tmp_path):
    from replay.factory import open_source

    r = rec["noisy_digital"]
    path = tmp_path / "rig.csv"
    r.to_csv(path)
    assert path.read_text().splitlines()[0] == "t,x_ref,u,x,pA,pB"
    with open_source(path, required=("x_ref", "u", "x", "pA", "pB")) as src:
        got = src.read_all()
    assert len(got) == r.t.size
    np.testing.assert_array_equal(got.t_ns, np.round(r.t * 1e9).astype(np.int64))
    for k in ("x_ref", "u", "x", "pA", "pB"):
        np.testing.assert_array_equal(got.signals[k], r.signals[k])


# --- oscillator -----------------------------------------------------------------------------------------
def test_oscillator_zoh_matches_the_exact_discretisation():
    spec = oscillator_spec(8, duration=2.0, intersample="zoh", noise=None, truth="draw")
    r, ana = get_records([spec, oscillator_spec(8, duration=2.0, noise=None, truth="draw")], workers=1)
    d, k = r.truth["d"], r.truth["k"]
    A = np.array([[0.0, 1.0], [-k, -d]])
    M = expm(np.block([[A, np.array([[0.0], [1.0]])], [np.zeros((1, 3))]]) * r.dt)
    Ad, Bd = M[:2, :2], M[:2, 2]
    s = np.zeros(2)
    x = np.empty(r.t.size)
    for i, u in enumerate(r.signals["u"]):
        x[i] = s[0]
        s = Ad @ s + Bd * u
    assert np.max(np.abs(r.signals["y"] - x)) < 1e-5 * np.max(np.abs(x))
    assert d != OSC_FREE["d"] and k != OSC_FREE["k"]
    # a continuous force moves the oscillator differently
    np.testing.assert_array_equal(ana.signals["u"], r.signals["u"])
    assert _rel_rms(ana.signals["y"], r.signals["y"]) > 1e-3


def test_oscillator_coulomb_friction_and_noise():
    base, fr, noisy = get_records([
        oscillator_spec(9, duration=2.0, noise=None),
        oscillator_spec(9, duration=2.0, noise=None, effects=["coulomb_friction"]),
        oscillator_spec(9, duration=2.0)], workers=1)
    fc = fr.truth["coulomb_friction.Fc"]
    assert 0.5 <= fc <= 3.0
    assert np.std(fr.signals["y"]) < np.std(base.signals["y"])
    assert np.std(noisy.signals["y"] - base.signals["y"]) == pytest.approx(1e-6, rel=0.1)


# --- cross-check with the product's simulator, where both claim the same physics ----------------------
def test_product_simulator_agrees_on_shared_physics(rec):
    from twin.models import get_model

    r = rec["crosscheck"]
    model = get_model("msp25")
    overrides = {"dp_lam": 1e3}
    if "dp_lam_leak" in model.kernel_names:
        overrides["dp_lam_leak"] = 1e3
    ps = model.params(**overrides)
    res = model.simulate(ps, "x_ref", r.signals["x_ref"], r.dt)
    x_err = np.sqrt(np.mean((res.outputs["x"] - r.signals["x"]) ** 2)) / np.sqrt(np.mean(r.signals["x"] ** 2))
    assert x_err < 1e-4
    for p in ("pA", "pB"):
        assert _rel_rms(res.outputs[p], r.signals[p]) < 1e-2
    np.testing.assert_allclose(res.outputs["pA"], r.signals["pA"], rtol=1e-4)


# --- the test engineer's demands, signals at their own rates, oil temperature ------------------------
@pytest.mark.parametrize("kind", ["chirp", "sweep", "blocks", "road"])
def test_demands_stay_within_the_speed_limit_and_the_amplitude(rec, kind):
    r = rec[f"demand_{kind}"]
    xr = r.signals["x_ref"]
    v = np.gradient(xr, r.dt)
    assert np.max(np.abs(xr)) <= 8e-3 * (1 + 1e-9)
    assert np.max(np.abs(v)) <= 0.2 * 1.01
    if kind in ("chirp", "sweep"):  # the speed limit reached at the top of the sweep, not before the low end
        assert np.max(np.abs(v[r.t > 2.5])) > 0.19
        assert np.max(np.abs(xr[(r.t > 0.6) & (r.t < 1.0)])) > 7.5e-3
    assert np.max(np.abs(r.hidden["x"] - xr)) < 4e-3  # the rig follows it


def test_block_loading_has_blocks_of_different_amplitudes(rec):
    r = rec["demand_blocks"]
    xr = r.signals["x_ref"]
    peaks = [np.max(np.abs(xr[(r.t >= a) & (r.t < a + 2.0)])) for a in (0.0, 2.0)]
    assert abs(peaks[0] / peaks[1] - 1) > 0.05
    i = np.flatnonzero(r.t >= 2.0)[0]
    assert abs(xr[i]) < 1e-4  # faded to zero between blocks


def test_road_load_is_band_limited_and_drawn_per_seed(rec):
    a, b = rec["demand_road"].signals["x_ref"], rec["demand_road_other_seed"].signals["x_ref"]
    assert _rel_rms(a, b) > 0.5
    f = np.fft.rfftfreq(a.size, 1e-3)
    p = np.abs(np.fft.rfft(a * np.hanning(a.size))) ** 2
    assert p[f > 15.0].sum() < 1e-3 * p.sum()


def test_slow_signals_are_held_onto_the_log_grid(rec):
    full, slow = rec["rates_all"], rec["rates_500"]
    for name, every in (("pA", 2), ("pB", 4), ("T_oil", 100)):
        k = np.arange(full.t.size)
        fresh = k % every == 0
        assert np.array_equal(slow.hidden[f"fresh_{name}"] > 0, fresh)
        np.testing.assert_array_equal(slow.signals[name][fresh], full.signals[name][fresh])  # same draw
        np.testing.assert_array_equal(slow.signals[name], full.signals[name][k - k % every])  # held
    np.testing.assert_array_equal(slow.signals["x"], full.signals["x"])


def test_warm_oil_follows_the_stated_laws(rec):
    warm, law, cold = rec["warm_oil"], rec["warm_oil_by_law"], rec["cold_oil"]
    assert np.all(np.abs(warm.signals["T_oil"] - 333.15) <= 0.05 + 1e-9)  # logged, quantised at 0.1 K
    assert warm.hidden["B"][0] == pytest.approx(1.5e9 * 0.88)
    for k in ("x", "pA", "pB"):
        assert _rel_rms(warm.signals[k], law.signals[k], cold.signals[k]) < 1e-5
        assert _rel_rms(warm.signals[k], cold.signals[k]) > 100 * _rel_rms(warm.signals[k], law.signals[k],
                                                                           cold.signals[k])
