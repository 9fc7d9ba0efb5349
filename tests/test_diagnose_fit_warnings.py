"""``twin fit`` says what ``twin diagnose`` knows: a free parameter that an un-modelled effect of the catalogue
can mimic (a displacement transducer's gain and Cd) carries a caveat in the text, the JSON and the report (apart
from the warnings that say the fit or the model failed the record)."""

from __future__ import annotations

import json

import pytest

from diag_helpers import RIG, record
from twin import cli
from twin.estimation.fit_checked import fit, mimicry_warnings


@pytest.mark.slow
def test_a_free_cd_is_warned_as_mimicking_a_transducer_gain_and_absorbs_it():
    rec = record(RIG, ("position_sensor_gain",), seed=41, duration_s=2.0)  # the transducer reads 2 % high
    res = fit(RIG, rec, ("Cd",), n_starts=1, max_nfev=30, adequacy=False)
    cd0 = RIG.params()["Cd"]
    assert abs(res.estimate["Cd"] / cd0 - 1.02) < 0.01  # the gain went into Cd, as the warning says
    warned = [w for w in res.caveats if "position_sensor_gain" in w]
    assert len(warned) == 1 and warned[0].startswith("Cd can mimic position_sensor_gain")
    assert any("position_sensor_gain" in w for w in res.to_dict()["caveats"])
    assert "CAVEAT: Cd can mimic position_sensor_gain" in res.table()
    assert not any("position_sensor_gain" in w for w in res.warnings)  # not a failure of the fit


def test_no_mimicry_warning_when_the_parameter_is_held_or_the_effect_is_modelled():
    assert mimicry_warnings(RIG, ("c_visc", "Kleak")) == []
    assert mimicry_warnings(RIG, ("Cd",), effects=("position_sensor_gain",)) == []
    assert len(mimicry_warnings(RIG, ("Cd", "c_visc"))) == 1


@pytest.mark.slow
def test_cli_fit_json_and_report_carry_the_mimicry_warning(tmp_path, capsys):
    path = tmp_path / "rig.csv"
    assert cli.main(["-q", "simulate", "--model", "msp25", "-o", str(path), "--duration", "1", "--seed", "42"]) == 0
    capsys.readouterr()
    report = tmp_path / "report"
    assert cli.main(["-q", "fit", str(path), "--model", "msp25", "--free", "Cd", "--starts", "1", "--json",
                     "--no-adequacy", "--report", str(report)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert any(w.startswith("Cd can mimic position_sensor_gain") for w in out["caveats"])
    html = (report / "fit_report.html").read_text()
    assert "Cd can mimic position_sensor_gain" in html
