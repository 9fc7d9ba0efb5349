"""An extended model is a model: a rig commissioned with an effect of the catalogue (``twin fit --effects
specimen_stiffness --save``) is tracked online with that effect (``twin track --params``, ``rigs.toml``
``commission = ...``), the effect's parameter held at its fitted value.  The record is the independent reference
simulator's MSP25 with a specimen spring drawn by its seed (verification seed 1011: truth drawn away from the
defaults, noise through the loop); the fit starts from the nominal values and the typical specimen stiffness."""

from __future__ import annotations

import json

import pytest

from net_helpers import free_port
from twin import cli

FREE = "Ffric,CdAleak,Cd,zeta,wn,k_spec"


def _run(capsys, *argv) -> tuple[int, dict, str]:
    capsys.readouterr()
    rc = cli.main(["-q", *argv])
    out, err = capsys.readouterr()
    return rc, (json.loads(out) if out.strip() else {}), err


@pytest.mark.slow
def test_a_specimen_stiffness_commissioned_is_tracked_with_it_and_raises_no_alarm(reference_records, tmp_path,
                                                                                 capsys):
    from conftest import msp25_spec

    rec = reference_records([msp25_spec(1011, duration=20.0, truth="draw", effects=("specimen_stiffness",))])[0]
    k_true = rec.truth["specimen_stiffness.k"]
    csv = tmp_path / "spec.csv"
    rec.to_csv(csv)
    fit_json = tmp_path / "fit.json"
    rc, fitted, err = _run(capsys, "fit", str(csv), "--effects", "specimen_stiffness", "--free", FREE, "--save",
                           str(fit_json), "--json")
    assert rc == 0, err
    assert abs(fitted["params"]["k_spec"]["value"] / k_true - 1) < 0.02, (fitted["params"]["k_spec"], k_true)
    rc, out, err = _run(capsys, "track", str(csv), "--params", str(fit_json), "--out", str(tmp_path / "track"),
                        "--json")
    assert rc == 0, err
    assert out["model"] == "msp25" and out["alarms"] == [] and out["consistency"] == "consistent", out["alarms"]
    for n, d in out["final"].items():
        v = rec.truth[n]
        assert abs(d["value"] / v - 1) < 0.10 or abs(d["value"] - v) < 3 * d["std"], (n, d, v)
    # the same through a rig configuration: rigs.toml names the commissioning file, the service runs it
    toml = tmp_path / "rigs.toml"
    toml.write_text(f"""
[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{free_port()}"]
[service]
journal_dir = "{tmp_path / 'journal'}"
[[rig]]
name = "spec"
source = "{csv}"
speed = 0
commission = "{fit_json}"
""")
    rc, served, err = _run(capsys, "serve", "--config", str(toml), "--json")
    assert rc == 0, err
    stats = served["spec"] if "spec" in served else served["rigs"]["spec"]
    assert stats["samples"] == out["samples"] and stats["alarms"] == 0, stats


def test_a_saved_fit_with_an_effect_reads_as_an_extended_model(tmp_path):
    """The effect's parameters are parameters of the extended model (not refused as unknown); an effect the
    model does not have is refused in one line naming the file."""
    from fpdd.errors import ConfigError
    from twin.online.commission import load_fit, tracker_for

    doc = {"model": "msp25", "effects": ["specimen_stiffness"],
           "params": {"Ffric": {"value": 50.0, "unit": "N", "std": 1.0}, "k_spec": {"value": 1.5e6, "unit": "N/m"}}}
    p = tmp_path / "fit.json"
    p.write_text(json.dumps(doc))
    com = load_fit(str(p))
    assert com.effects == ("specimen_stiffness",) and com.params["k_spec"] == 1.5e6

    class Rig:
        model, params, track, commission = "msp25", {}, ("Ffric", "wn"), com

    tr = tracker_for(Rig())
    assert tr.ps.effects == ("specimen_stiffness",) and tr.ps["k_spec"] == 1.5e6 and tr.tracked == ("Ffric", "wn")
    p.write_text(json.dumps({**doc, "effects": ["specimen_cracking"]}))
    with pytest.raises(ConfigError, match="'specimen_cracking' is no effect of the msp25 model"):
        load_fit(str(p))
