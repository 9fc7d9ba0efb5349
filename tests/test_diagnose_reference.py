"""``twin diagnose`` on records of the independent reference simulator (``tests/reference``).

Verification seeds (>= 1000; the diagnosis's thresholds are set on seeds 0-999).  Truth drawn 3-20 % off
Table 9 per seed (the nominal fit starts at Table 9, not at the truth), effects in the reference's own
formulation with sizes drawn per seed, a digital controller reading the noisy measured displacement (so
output-error residuals are coloured even when the model is exact), white or AR(1) noise.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from diag_reference import IN_CATALOGUE, reference_record
from twin import cli
from fpdd.jsonio import finite_or_none
from twin.estimation.diagnose import CONTROLLER_RATE, _gain, _implausible, diagnose, holm
from twin.estimation.fit import fit
from twin.models import get_model
from twin.models.base import Timing
from fpdd.units import NOMINAL_NOISE
from twin.estimation.noise_model import block_bootstrap, fit_noise_model, long_run_variance

RIG = get_model("msp25")
DURATION = 6.0

#: product parameter -> (reference truth key, sign convention) where the two formulations share a meaning
COMPARABLE = {
    "c_visc": "viscous_friction.c", "K_lam": "laminar_leakage.G", "k_spec": "specimen_stiffness.k",
    "tau_x": "sensor_delay.delay", "k_xm": "position_sensor_gain.gain", "xs_max": "spool_saturation.xs_max",
}

_CACHE: dict = {}


def _diag(effects=(), seed=1001, controller="digital", tau=0.0, timing=None):
    key = (tuple(effects), seed, controller, tau, timing)
    if key not in _CACHE:
        rec, info = reference_record(effects, seed=seed, duration=DURATION, controller=controller, tau=tau)
        _CACHE[key] = (diagnose(RIG, rec, timing=Timing.parse(timing), seed=seed), info)
    return _CACHE[key]


#: known failures on the reference (strict: a fix makes the test fail until the mark is removed)
KNOWN: dict[str, str] = {}

#: effects a free nominal parameter mimics: not testable with the default free set (tested below with the
#: mimicking parameter held at a commissioned value)
MIMICKED = ("position_sensor_gain",)


#: the catalogue's effects but one (each diagnosis took 8-170 s in full runs of the suite): run by CI
#: (``pytest -m slow``); valve_null_bias stays in the default run
SLOW = tuple(e for e in IN_CATALOGUE if e != "valve_null_bias")


@pytest.mark.parametrize("effect", [pytest.param(e, marks=[*([pytest.mark.xfail(strict=True, reason=KNOWN[e])]
                                                               if e in KNOWN else []),
                                                             *([pytest.mark.slow] if e in SLOW else [])])
                                    for e in IN_CATALOGUE if e not in MIMICKED])
@pytest.mark.slow
def test_each_catalogue_effect_is_named_exactly(effect):
    d, info = _diag((effect,), seed=1001)
    assert d.causes == [effect], d.text()
    assert not d.unexplained, d.text()
    g = d.gains[effect]
    assert g["p_adjusted"] < d.alpha and g["delta_aicc"] < 0
    lo, hi = g["holdout_gain_interval"]
    assert 0 < lo <= g["holdout_gain"] <= hi
    for name, v in d.effect_params(effect).items():
        key = COMPARABLE.get(name)
        if key is not None:  # the same physical quantity in both formulations: the right size
            truth = info["truth"][key]
            assert v["value"] == pytest.approx(truth, rel=0.35), (name, v, truth)


@pytest.mark.slow
def test_a_position_sensor_gain_is_not_testable_while_cd_is_free_and_named_when_cd_is_commissioned():
    """In the measured displacement a gain g is the nominal rig with Cd x g (bulk modulus and moving mass / g
    leave the hydraulic resonance unchanged): with Cd free the diagnosis says so instead of testing it; with
    Cd held at a fit of the same rig's healthy record (a commissioning) the gain is named, at its size."""
    d, info = _diag(("position_sensor_gain",), seed=1001)
    assert d.causes == [] and "position_sensor_gain" in d.not_testable, d.text()
    assert d.not_testable["position_sensor_gain"]["mimicked_by"] == ["Cd"]
    assert all(r.effect != "position_sensor_gain" for s in d.screens for r in s)
    assert "not tested: position_sensor_gain" in d.text()
    out = json.loads(json.dumps(d.to_dict(), allow_nan=False))
    assert out["not_testable"]["position_sensor_gain"]["mimicked_by"] == ["Cd"]

    healthy, _ = reference_record((), seed=1001, duration=DURATION)
    cd = fit(RIG, healthy, RIG.PHENOMENOLOGICAL, seed=1001).estimate["Cd"]
    rec, _ = reference_record(("position_sensor_gain",), seed=1001, duration=DURATION)
    free = tuple(n for n in RIG.PHENOMENOLOGICAL if n != "Cd")
    d = diagnose(RIG, rec, free=free, base=RIG.params().update({"Cd": cd}), seed=1001)
    assert d.causes == ["position_sensor_gain"] and not d.unexplained and not d.not_testable, d.text()
    k = d.effect_params("position_sensor_gain")["k_xm"]
    truth = info["truth"]["position_sensor_gain.gain"]
    assert abs(k["value"] - truth) < 0.1 * (truth - 1.0)  # the gain's error within a tenth of its size


def test_healthy_record_with_loop_noise_names_nothing():
    d, _ = _diag((), seed=1002)
    assert d.causes == [] and not d.unexplained, d.text()
    # the output-error residuals are coloured (the sensor noise goes round the loop) ...
    assert d.nominal.analysis.ljung_box["x"]["p"] < 1e-6
    # ... the one-step prediction errors are not, and they do not follow x_ref
    assert d.nominal.adequacy["whiteness"]["x"]["p"] > 1e-4
    assert d.nominal.adequacy["exogenous"]["dependent"] is False
    assert d.nominal.noise.orders["x"] > 0


@pytest.mark.slow
def test_a_rig_of_another_geometry_gets_the_right_name_with_sizes_that_follow_it():
    """The reference rig with twice the piston area and three times the moving mass (the diagnosis told so by
    ``--set A=... m=...``): the effect is named, and the catalogue's sizes follow the rig (the flow the record
    draws doubles with the area, so do the spool opening passing it and the force range; a sample period is a
    sample period)."""
    A, m = 2.0 * 1920e-6, 3.0 * 45.0
    rec, info = reference_record(("valve_null_bias",), seed=1003, duration=DURATION, known={"A": A, "m": m})
    d = diagnose(RIG, rec, base=RIG.params(A=A, m=m), seed=1003)
    assert d.causes == ["valve_null_bias"], d.text()
    truth = abs(info["truth"]["valve_null_bias.offset"])
    assert abs(d.effect_params("valve_null_bias")["xs_bias"]["value"]) == pytest.approx(truth, rel=0.35)
    here = RIG.effect_typicals(d.nominal.params, rec.signals, d.nominal.predicted[0], rec.dt)
    half = RIG.effect_typicals(d.nominal.params.update({"A": 1920e-6}), rec.signals, d.nominal.predicted[0], rec.dt)
    assert here["valve_null_bias"][0] == pytest.approx(2.0 * half["valve_null_bias"][0], rel=1e-9)
    assert here["viscous_friction"][0] == pytest.approx(2.0 * half["viscous_friction"][0], rel=1e-9)
    assert here["supply_line_loss"][0] == pytest.approx(0.25 * half["supply_line_loss"][0], rel=1e-9)
    assert here["sensor_delay"] == half["sensor_delay"] == pytest.approx((1.5 * rec.dt,))  # 1.5 samples


@pytest.mark.slow
def test_a_long_healthy_record_is_adequate_though_its_slight_colour_is_detectable():
    """20 s at 1 kHz: the loop noise a finite autoregression leaves slightly coloured is detectable on this many
    samples (seed 1011: Ljung-Box p 2e-4, under the level on its own), yet predicts a negligible share of the
    prediction errors: nothing named, nothing unexplained; a resonance in a record as long stays unexplained."""
    rec, _ = reference_record((), seed=1011, duration=20.0, controller="digital")
    d = diagnose(RIG, rec, seed=1011)
    w = d.nominal.adequacy["whiteness"]["x"]
    assert w["p"] < d.alpha and w["r2"] < 0.01 and not w["material"]
    assert d.causes == [] and not d.unexplained, d.text()
    rec, _ = reference_record(("mechanical_resonance",), seed=1011, duration=20.0, controller="digital")
    d = diagnose(RIG, rec, seed=1011)
    assert d.causes == [] and d.unexplained, d.text()


@pytest.mark.slow
def test_a_long_analog_record_is_named_controller_rate_by_refits_over_the_timings():
    """20 s of an analog loop diagnosed as digital at the log's rate: the nominal estimates bend to the assumed
    timing, so at them the closest alternative (digital at 2x) scores best; its refit alone leaves the drive
    explaining over 1 % of x's prediction errors.  The search refits the continuous timing from there."""
    rec, _ = reference_record((), seed=1011, duration=20.0, controller="analog")
    d = diagnose(RIG, rec, seed=1011)
    assert d.causes == [CONTROLLER_RATE] and not d.unexplained, d.text()
    assert d.final.timing.ticks(1e-3) >= 5 or d.final.timing.controller == "continuous"
    assert d.final.adequacy["exogenous"]["r2_excess"] < 0.01


@pytest.mark.slow
def test_a_noise_model_whose_errors_stay_predictable_gets_a_higher_order():
    """8 s, a spool overlap: after the deadband is named, the noise model's prediction errors are not materially
    predictable - AIC's order sufficed, or it was raised along the grid until they were not (a calibration
    record, seed 0, needed AR(30) after AIC's AR(20); on this verification seed AIC's AR(16) suffices)."""
    rec, _ = reference_record(("spool_deadband",), seed=1000, duration=8.0)
    d = diagnose(RIG, rec, seed=1000)
    assert d.causes == ["spool_deadband"] and not d.unexplained, d.text()
    n = d.n_fit[0]
    resid = [np.array([(rec[o][:n] - d.final.predicted[0][o][:n]) / NOMINAL_NOISE[o] for o in d.outputs])]
    by_aic = fit_noise_model(resid, d.outputs).orders["x"]
    white = d.final.adequacy["whiteness"]["x"]
    assert not white["material"] and white["ar_order"] >= by_aic, (white, by_aic)  # never below AIC's choice
    # an order given as a floor is respected
    B = [np.array([(rec[o][:200] - rec[o][:200].mean()) / np.std(rec[o][:200]) for o in ("x", "pA")])]
    assert fit_noise_model(B, ("x", "pA"), min_orders={"x": 6}).orders["x"] >= 6


@pytest.mark.slow
def test_healthy_record_with_coloured_noise_names_nothing():
    d, _ = _diag((), seed=1003, tau=0.005)
    assert d.causes == [] and not d.unexplained, d.text()
    assert all(n > 0 for n in d.nominal.noise.orders.values())


@pytest.mark.slow
def test_analog_controller_is_named_controller_rate_and_not_with_the_right_timing():
    d, _ = _diag((), seed=1001, controller="analog")
    assert d.causes == [CONTROLLER_RATE] and not d.unexplained, d.text()
    assert d.final.timing.ticks(1e-3) != 1  # a continuous controller, or a digital one faster than the log
    out = json.loads(json.dumps(d.to_dict(), allow_nan=False))
    assert out["timing_final"] == d.final.timing.to_dict() and out["timing_assumed"]["controller"] == "digital"
    right, _ = _diag((), seed=1001, controller="analog", timing="continuous")
    assert right.causes == [] and not right.unexplained, right.text()


#: x_transducer_lag's diagnosis took 285 s of a loaded suite run (the default run keeps parameter_drift): run by CI
@pytest.mark.parametrize("effect", [pytest.param("mechanical_resonance", marks=pytest.mark.slow),
                                    "parameter_drift", pytest.param("x_transducer_lag", marks=pytest.mark.slow)])
def test_out_of_catalogue_error_is_unexplained_without_a_name(effect):
    d, _ = _diag((effect,), seed=1001)
    assert d.unexplained and d.causes == [], d.text()
    sig = d.to_dict()["signature"]
    assert sig is not None and sig["adequacy"]["adequate"] is False
    assert "UNEXPLAINED" in d.text()
    if effect == "mechanical_resonance":
        # the noise model's autoregression soaks up the resonance; the innovations still follow x_ref
        exo = d.nominal.adequacy["exogenous"]
        assert exo["dependent"] and exo["p"] < 1e-6 and exo["r2_excess"] > 0.01
        # so no catalogue effect is named for it: each explains only a small share of the misfit
        fitted = [t for ts in d.trials for t in ts if t.effects[0] != CONTROLLER_RATE]
        assert fitted and all(not t.accepted for t in fitted)


@pytest.mark.slow
def test_spool_saturation_is_probed_at_levels_the_record_reaches():
    d, info = _diag(("spool_saturation",), seed=1001)
    row = next(r for r in d.screens[0] if r.effect == "spool_saturation")
    assert row.probe.startswith("secant@") and row.p_adjusted < d.alpha
    level = row.estimate["xs_max"]
    spool = np.abs(d.nominal.predicted[0]["state:xs"][: d.n_fit[0]])
    assert 0 < level < spool.max()  # the probe clips part of the record, not all of it and not none
    assert 0.001 < np.mean(spool > level) < 0.3


def test_an_implausibly_large_effect_is_not_named():
    d, _ = _diag((), seed=1002)
    ps = RIG.params(effects=("position_sensor_gain",)).update(d.nominal.params.as_dict())
    for k_xm, expect in ((1.03, []), (0.73, ["k_xm=0.73"])):  # typical deviation 0.02: at most 0.2 is plausible
        st = dataclasses.replace(d.nominal, params=ps.update({"k_xm": k_xm}))
        assert _implausible(RIG, ("position_sensor_gain",), st) == expect


# --- statistics ----------------------------------------------------------------------------------
def test_noise_model_whitens_an_ar_process_and_keeps_an_offset():
    rng = np.random.default_rng(7)
    e = rng.normal(size=(2, 8000))
    r = np.empty_like(e)
    r[:, 0] = e[:, 0]
    for t in range(1, e.shape[1]):
        r[:, t] = np.array([0.8, -0.5]) * r[:, t - 1] + e[:, t]
    nm = fit_noise_model([r], ("a", "b"))
    assert nm.orders["a"] >= 1 and nm.A[0, 0, 0] == pytest.approx(0.8, abs=0.03)
    w = nm.whiten(r)
    assert np.std(w[0]) == pytest.approx(1.0, abs=0.03) and abs(np.corrcoef(w[0, 1:], w[0, :-1])[0, 1]) < 0.04
    # a constant offset is not absorbed as noise: it survives whitening (scaled by A(1))
    shifted = nm.whiten(r + np.array([[3.0], [0.0]]))
    assert np.mean(shifted[0] - w[0]) == pytest.approx(3.0 * (1 - nm.A[:, 0, 0].sum()) / math.sqrt(nm.sigma[0, 0]),
                                                       rel=1e-6)


def test_long_run_variance_and_block_bootstrap_see_autocorrelation():
    rng = np.random.default_rng(3)
    w = rng.normal(size=20000)
    ar = np.empty_like(w)
    ar[0] = w[0]
    for t in range(1, w.size):
        ar[t] = 0.7 * ar[t - 1] + w[t]
    # long-run variance of an AR(1) with unit innovations: 1 / (1 - 0.7)^2 = 11.1
    assert long_run_variance(w) == pytest.approx(1.0, rel=0.1)
    assert long_run_variance(ar) == pytest.approx(11.1, rel=0.25)
    sums = block_bootstrap(ar, 200, 400, seed=0)
    assert np.std(sums) / math.sqrt(ar.size) == pytest.approx(math.sqrt(11.1), rel=0.25)


def test_block_bootstrap_resamples_several_series_jointly():
    """An improvement that comes in rare bursts (a stroke limit reached now and then): the ratio of the
    removed to the total error resampled jointly stays a share (at most 1), its interval above zero."""
    rng = np.random.default_rng(3)
    n = 2000
    q0 = rng.chisquare(3, size=n)
    burst = np.zeros(n)
    for start in rng.choice(n - 30, size=4, replace=False):
        burst[start:start + 30] = 200.0
    q0 = q0 + burst
    d = 0.95 * burst + 0.01 * rng.normal(size=n)
    both = block_bootstrap(np.stack([d, q0]), 160, 1000, seed=0)
    assert both.shape == (1000, 2)
    # the same blocks for both series: the first column alone is the one-series bootstrap
    assert np.allclose(both[:, 0], block_bootstrap(d, 160, 1000, seed=0))
    ratio = both[:, 0] / both[:, 1]
    lo, hi = np.quantile(ratio, [0.025, 0.975])
    assert 0.0 < lo < d.sum() / q0.sum() < hi <= 1.0


def test_holm_adjusts_step_down_and_monotone():
    assert holm([0.01, 0.04, 0.03, 0.5]) == pytest.approx([0.04, 0.09, 0.09, 0.5])


# --- every result serialises ---------------------------------------------------------------------
def _strict(obj):
    return json.loads(json.dumps(obj, allow_nan=False))


def _variant(d, causes, unexplained=False, converged=True):
    """``d`` as if it had named ``causes`` (each with the gain and parameters of a real step)."""
    model = RIG
    # a real gain's figures, with non-finite entries (a diverged or non-converged step) in the statistics
    one = dict(_gain(d.nominal, d.final), lr=float("nan"), p=1.0, df=1, p_adjusted=1.0, delta_aicc=float("inf"),
               holdout_gain=float("-inf"), holdout_gain_interval=[float("nan"), float("nan")])
    effects = tuple(c for c in causes if c != CONTROLLER_RATE)
    ps = model.params(effects=effects).update(d.final.params.as_dict())
    fit = dataclasses.replace(d.final.fit, params=ps, success=converged,
                              std={**d.final.fit.std, **{n: float("nan") for n in ps.names}})
    final = dataclasses.replace(d.final, params=ps, fit=fit, free=d.final.free + tuple(
        n for e in effects for n in model.EFFECTS[e].names if n not in d.final.free))
    return dataclasses.replace(d, causes=list(causes), unexplained=unexplained, final=final,
                               gains={c: dict(one, pair="+".join(causes)) for c in causes})


@pytest.mark.parametrize("causes, unexplained, converged", [
    ([], False, True), ([], True, True), (["viscous_friction"], False, True),
    (["spool_deadband", "stribeck_friction"], False, True),
    (["spool_deadband", "stribeck_friction", "valve_null_bias"], True, True),
    ([CONTROLLER_RATE, "pressure_sensor_offset"], False, False),
], ids=["none", "unexplained", "one", "two", "three+unexplained", "timing+offset, not converged"])
def test_every_kind_of_result_serialises_to_strict_json(causes, unexplained, converged):
    d, _ = _diag((), seed=1002)
    v = _variant(d, causes, unexplained, converged)
    out = _strict(v.to_dict())
    assert out["causes"] == causes and out["unexplained"] is unexplained
    assert set(out["effects"]) == set(causes)
    for c in causes:
        assert out["effects"][c]["params"]
    _strict(finite_or_none(v.extended_params()))
    assert ("UNEXPLAINED" in v.text()) is unexplained


@pytest.mark.slow
def test_cli_json_save_report_and_timing_flags(tmp_path, capsys):
    rec, _ = reference_record((), seed=1001, duration=DURATION, controller="analog")
    path = tmp_path / "analog.csv"
    cols = ["x_ref", "u", "x", "pA", "pB"]
    np.savetxt(path, np.column_stack([rec.t_s] + [rec[c] for c in cols]), delimiter=",",
               header=",".join(["t"] + cols), comments="", fmt="%.17g")
    report, save = tmp_path / "report", tmp_path / "ext.json"
    assert cli.main(["-q", "diagnose", str(path), "--model", "msp25", "--json", "--report", str(report),
                     "--save", str(save), "--controller", "continuous"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["causes"] == [] and out["unexplained"] is False and out["timing_assumed"]["controller"] == "continuous"
    for f in (report / "diagnosis.json", report / "extended_params.json", save):
        json.loads(f.read_text(), parse_constant=lambda c, f=f: pytest.fail(f"{f}: {c} is not strict JSON"))
    html = (report / "diagnose_report.html").read_text()
    assert "verdict" in html.lower() and "continuous" in html
    assert json.loads(save.read_text())["timing"]["controller"] == "continuous"
    rc = cli.main(["-q", "diagnose", str(path), "--model", "msp25", "--controller", "digital:1500"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and "1500" in err and len(err.strip().splitlines()) == 1
