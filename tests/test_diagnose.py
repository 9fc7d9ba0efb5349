"""``twin diagnose``: hide an effect, require finding it; name nothing when healthy; say "unexplained"
when the error is outside the catalogue.  Records are 8 s at 1 kHz with realistic noise."""

from __future__ import annotations

import json

import numpy as np
import pytest

from diag_helpers import OSC, RIG, oscillator_with_force_ripple, record, rig_with_pressure_sensor_drift
from twin import cli
from twin.estimation.diagnose import diagnose
from twin.record import Record
from twin.estimation.residuals import analyse, autocorrelation, cross_correlation, ljung_box, noise_level

# (model, effect, seed, excitation kind, excitation options).  The rig's catalogue is tested on the
# independent reference simulator (test_diagnose_reference.py); here the oscillator's, and on the product's
# own simulation the rig effects whose excitation needs a special drive (steps, a chirp).
CATALOGUE_CASES = [
    (RIG, "valve_null_bias", 5, "steps", {}),
    (RIG, "spool_deadband", 4, "chirp", {"f_lo": 0.5, "f_hi": 8.0}),
    (OSC, "coulomb_friction", 11, "multisine", {}),
    (OSC, "cubic_stiffness", 12, "chirp", {}),
    (OSC, "input_delay", 13, "steps", {"amplitude": 50.0}),
    (OSC, "input_offset", 14, "multisine", {}),
    (OSC, "output_offset", 15, "multisine", {}),
]


def test_catalogue_cases_cover_every_effect_of_the_oscillator():
    covered = {(m.name, e) for m, e, *_ in CATALOGUE_CASES if m is OSC}
    assert covered == {(OSC.name, e) for e in OSC.EFFECTS}


@pytest.mark.parametrize("model, effect, seed, kind, options",  # the rig's cases are long: CI (-m slow)
                         [pytest.param(*c, marks=pytest.mark.slow) if c[0] is RIG else c for c in CATALOGUE_CASES],
                         ids=[f"{m.name}-{e}" for m, e, *_ in CATALOGUE_CASES])
def test_hidden_effect_is_named_recovered_and_pays_off(model, effect, seed, kind, options):
    rec = record(model, (effect,), seed=seed, kind=kind, **options)
    d = diagnose(model, rec)
    assert d.causes == [effect], d.text()
    assert not d.unexplained, d.text()
    E = model.EFFECTS[effect]
    found = d.effect_params(effect)
    for name, truth in zip(E.names, E.typical):
        est, std = found[name]["value"], found[name]["std"]
        assert std > 0 and abs(est - truth) <= 3.0 * std, (name, est, std, truth)
    g = d.gains[effect]
    assert g["holdout_gain_interval"][0] > 0
    assert g["lr"] > 0 and g["p_adjusted"] < 1e-3 and g["delta_aicc"] < 0
    for o in d.outputs:  # held-out NRMSE not worse on any output, better on at least one
        assert g["holdout"]["after"][o]["nrmse"] <= g["holdout"]["before"][o]["nrmse"] * 1.001
    assert any(g["holdout"]["after"][o]["nrmse"] < g["holdout"]["before"][o]["nrmse"] for o in d.outputs)
    out = d.to_dict()
    assert out["causes"] == [effect] and out["unexplained"] is False
    assert set(out["effects"][effect]["params"]) == set(E.names)
    assert out["extended_params"]["effects"] == [effect]
    # the saved extended set is a valid parameter set of the model with the effect switched on by name
    ext = out["extended_params"]
    ps = model.params(effects=ext["effects"], **{k: v["value"] for k, v in ext["params"].items()})
    assert ps[E.names[0]] == pytest.approx(found[E.names[0]]["value"])


@pytest.mark.parametrize("model, seed, kind", [(RIG, 21, "multisine"), (RIG, 22, "steps"),
                                               (OSC, 23, "multisine"), (OSC, 24, "chirp")],
                         ids=["rig-multisine", "rig-steps", "oscillator-multisine", "oscillator-chirp"])
def test_healthy_record_names_nothing(model, seed, kind):
    d = diagnose(model, record(model, (), seed=seed, kind=kind))
    assert d.causes == [] and not d.unexplained, d.text()
    assert d.nominal.adequate
    assert d.to_dict()["effects"] == {}


@pytest.mark.parametrize("model, effects, seed", [
    pytest.param(RIG, ("viscous_friction", "valve_null_bias"), 31, marks=pytest.mark.slow),  # found one after the other (greedy)
    pytest.param(RIG, ("stribeck_friction", "sensor_delay"), 32, marks=pytest.mark.slow),  # only recognisable together (pair step)
    (OSC, ("coulomb_friction", "input_delay"), 33),
], ids=["rig-viscous+bias", "rig-stribeck+delay", "oscillator-coulomb+delay"])
def test_two_hidden_effects_are_both_named(model, effects, seed):
    d = diagnose(model, record(model, effects, seed=seed))
    assert sorted(d.causes) == sorted(effects), d.text()
    assert not d.unexplained, d.text()
    for e in effects:
        E = model.EFFECTS[e]
        found = d.effect_params(e)
        for name, truth in zip(E.names, E.typical):
            assert abs(found[name]["value"] - truth) <= 3.0 * found[name]["std"], (name, found[name], truth)
        assert d.gains[e]["holdout_gain"] > 0 and d.gains[e]["p_adjusted"] < 1e-3
    assert d.final.adequate
    out = json.loads(json.dumps(d.to_dict(), allow_nan=False))
    assert sorted(out["effects"]) == sorted(effects)


def test_rig_pressure_sensor_drift_is_unexplained_not_forced_into_a_name():
    d = diagnose(RIG, rig_with_pressure_sensor_drift())
    assert d.causes == [] and d.unexplained, d.text()
    out = d.to_dict()
    sig = out["signature"]
    assert sig is not None and not sig["white"]["pA"]
    # the signature points at the drifting sensor: pA far above its noise floor, pB and x at it
    assert sig["excess"]["pA"] > 5 and sig["excess"]["pB"] < 1.5 and sig["excess"]["x"] < 1.5
    assert "UNEXPLAINED" in d.text()


@pytest.mark.slow
def test_a_named_effect_that_leaves_an_error_is_partly_explained():
    """Viscous friction (3x its typical size), and the chamber-A pressure sensor drifting 0.1 MPa during the
    record (outside the catalogue):
    the friction is named by its own signature, the drift is left over (the simulation's held-out error grows):
    "partly explained", with the residual signature beside the name.  The drifting transducer may be named too, as
    an offset of pA's (its mean; with the supply line in the catalogue the noise model regresses out three more
    directions and the offset's score passes), never of pB's; the drift stays unexplained."""
    rec = record(RIG, ("viscous_friction",), seed=35, values={"c_visc": 6000.0})
    sig = dict(rec.signals)
    sig["pA"] = sig["pA"] + 1e5 * rec.t_s / rec.t_s[-1]
    d = diagnose(RIG, Record(rec.dt, sig, "msp25+viscous_friction+pA-sensor-drift"))
    assert d.causes[0] == "viscous_friction" and d.unexplained, d.text()
    assert set(d.causes) <= {"viscous_friction", "pressure_sensor_offset"}, d.text()
    if "pressure_sensor_offset" in d.causes:  # the drifting transducer's mean, on pA
        off = d.effect_params("pressure_sensor_offset")
        assert 0 < off["pA_off"]["value"] < 1e5 and abs(off["pB_off"]["value"]) < 0.2 * off["pA_off"]["value"]
    assert d.verdict() == "partly explained" and "UNEXPLAINED" in d.text()
    out = d.to_dict()
    assert out["verdict"] == "partly explained" and out["signature"]["adequacy"]["adequate"] is False
    assert out["signature"]["excess"]["pA"] > out["signature"]["excess"]["pB"]
    assert d.effect_params("viscous_friction")["c_visc"]["value"] == pytest.approx(6000.0, rel=0.2)


@pytest.mark.xfail(strict=True, reason="a 1.5 % held-out gain of an input delay (z 2.6) leaves the model adequate "
                   "(the noise model's autoregression whitens the ripple's residual): named; the held-out test at "
                   "1e-3 with a Bonferroni count refused it but also a Stribeck curve on reference seed 1001 (open)")
def test_oscillator_force_ripple_is_unexplained_not_forced_into_a_name():
    d = diagnose(OSC, oscillator_with_force_ripple())
    assert d.causes == [] and d.unexplained, d.text()
    # the catalogue was screened; whatever was fitted was refused
    assert d.screens and not any(t.accepted for ts in d.trials for t in ts)
    assert d.to_dict()["signature"]["adequacy"]["adequate"] is False


@pytest.mark.slow
def test_cli_json_contract_and_report(tmp_path, capsys):
    path = tmp_path / "rig.csv"
    assert cli.main(["-q", "simulate", "--model", "msp25", "-o", str(path), "--duration", "6",
                     "--effects", "supply_pressure_droop", "--seed", "41"]) == 0
    capsys.readouterr()
    report = tmp_path / "report"
    save = tmp_path / "extended.json"
    assert cli.main(["-q", "diagnose", str(path), "--model", "msp25", "--json", "--report", str(report),
                     "--save", str(save)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["causes"] == ["supply_pressure_droop"] and out["unexplained"] is False
    r_sup = out["effects"]["supply_pressure_droop"]["params"]["R_sup"]
    assert abs(r_sup["value"] - 1.5e10) < 3 * r_sup["std"]
    gain = out["effects"]["supply_pressure_droop"]["gain"]
    for key in ("holdout", "delta_aicc", "lr", "p", "p_adjusted", "holdout_gain", "holdout_gain_interval"):
        assert key in gain
    for o in ("x", "pA", "pB"):
        assert gain["holdout"]["after"][o]["fit_pct"] > gain["holdout"]["before"][o]["fit_pct"]
        assert gain["holdout"]["after"][o]["nrmse"] < gain["holdout"]["before"][o]["nrmse"]
    assert {"params", "aicc", "holdout", "residuals"} <= set(out["nominal"])
    names = {p.split("/")[-1] for p in out["plots"]}
    assert {"diagnose_response.png", "diagnose_residuals.png", "diagnose_signature_supply_pressure_droop.png",
            "diagnose_residual_signature.png"} <= names
    for name in names:
        assert (report / name).stat().st_size > 1000
    saved = json.loads(save.read_text())
    assert saved["effects"] == ["supply_pressure_droop"] and "std" in saved["params"]["R_sup"]
    assert json.loads((report / "extended_params.json").read_text()) == saved
    assert json.loads((report / "diagnosis.json").read_text())["causes"] == ["supply_pressure_droop"]
    # the human-readable form names the cause and its uncertainty
    assert cli.main(["-q", "diagnose", str(path), "--model", "msp25"]) == 0
    text = capsys.readouterr().out
    assert "causes: supply_pressure_droop" in text and "+/-" in text


def test_cli_rejects_a_record_without_the_outputs(tmp_path, capsys):
    path = tmp_path / "rig.csv"
    assert cli.main(["-q", "simulate", "--model", "msp25", "-o", str(path), "--duration", "2"]) == 0
    capsys.readouterr()
    rc = cli.main(["-q", "diagnose", str(path), "--model", "msp25", "--outputs", "y"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err and "'y'" in err


# --- residual statistics ------------------------------------------------------------------------
def test_ljung_box_and_autocorrelation_separate_white_from_coloured():
    rng = np.random.default_rng(0)
    white = rng.normal(size=6000)
    assert ljung_box(white, 25)["p"] > 1e-3
    coloured = np.convolve(white, np.ones(5) / 5, mode="same")
    assert ljung_box(coloured, 25)["p"] < 1e-10
    ac = autocorrelation(coloured, 6)
    assert ac[0] == pytest.approx(1.0) and ac[1] == pytest.approx(0.8, abs=0.05) and abs(ac[6]) < 0.06
    assert noise_level(white + np.linspace(0, 50, white.size)) == pytest.approx(1.0, rel=0.05)


def test_cross_correlation_lag_convention_and_band():
    rng = np.random.default_rng(1)
    s = rng.normal(size=5000)
    r = np.roll(s, 3) + rng.normal(size=5000)  # r[t] depends on s[t - 3]: the signal leads by 3
    lags, vals, band = cross_correlation(r, s, 10)
    assert lags[np.argmax(np.abs(vals))] == 3 and vals.max() > band
    lags, vals, band = cross_correlation(rng.normal(size=5000), s, 10)
    assert np.mean(np.abs(vals) > band) < 0.1


def test_closed_loop_feedback_lags_are_reported_but_not_counted_as_model_error():
    rec = record(RIG, (), seed=51, duration_s=4.0)
    u = rec["u"]
    # residual of x = the controller output 5 samples *later* (the residual leads u): what feedback does
    pred = {"x": rec["x"] - 1e-7 * np.roll(u, -5), "pA": rec["pA"], "pB": rec["pB"], "u": u}
    an = analyse("msp25", rec, pred, ("x",))
    xc = an.xcorr["x~u"]
    assert xc["lags"][np.argmax(np.abs(xc["values"]))] == -5
    assert xc["feedback_lags_outside_band"] > 0 and "feedback" in xc["note"]
    assert {row["regime"] for row in an.regimes["x"]} >= {"velocity", "reversal", "position", "dp",
                                                           "spool_opening"}
    assert [b["f_lo_hz"] for b in an.bands["x"]][:3] == [0.0, 1.0, 5.0]
    assert not an.adequate
