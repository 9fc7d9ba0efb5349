"""A rig the model cannot represent is fitted with a warning, never silently: ``twin fit``'s adequacy test
(:mod:`twin.estimation.diagnose.check`) on records of the independent reference simulator (verification seeds),
and what a commissioning keeps of it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import get_records
from reference import msp25_spec
from twin import cli
from twin.estimation.fit_checked import fit
from twin.models import get_model
from replay.base import Samples
from twin.online.commission import fit_window, from_dict
from twin.record import Record

#: out of the model's reach (as ``tests/chirp_divergence.py --unmodelled``): a 60 Hz load-train resonance; the
#: position sensor 3 ms late with 2 ms pressure transducers
UNMODELLED = {1020: {"mechanical_resonance": {"f": 60.0, "m2": 30.0, "zeta2": 0.02}},
              1021: {"sensor_delay": {"delay": 3e-3}, "pressure_sensor_lag": {"tau": 2e-3}}}


@pytest.fixture(scope="module")
def records():
    specs = [msp25_spec(s, duration=20.0, truth="draw", effects=e) for s, e in UNMODELLED.items()]
    specs += [msp25_spec(s, duration=20.0, truth="draw") for s in UNMODELLED]  # the same rigs without them
    refs = get_records(specs)
    return {k: r for k, r in zip(("resonance", "late_sensors", "healthy_1020", "healthy_1021"), refs)}


def _record(ref, name: str) -> Record:
    return Record(ref.dt, {k: np.asarray(v, float) for k, v in ref.signals.items()}, name)


@pytest.mark.slow
def test_a_rig_out_of_the_models_reach_is_fitted_with_a_warning_and_the_same_rig_without_it_is_not(records):
    rig = get_model("msp25")
    for name in ("resonance", "late_sensors"):
        res = fit(rig, _record(records[name], name), rig.PHENOMENOLOGICAL)
        assert res.success  # it converges: the fit alone would look fine
        off = max(abs(res.estimate[n] / float(records[name].truth[n]) - 1) for n in rig.PHENOMENOLOGICAL)
        assert off > 0.2, (name, res.estimate)  # and its values are biased, which the warning must say
        assert res.adequacy["adequate"] is False, name
        w = [x for x in res.warnings if "does not represent this record" in x]
        assert len(w) == 1 and "follow the drive" in w[0] and "twin diagnose" in w[0], res.warnings
        assert "WARNING the model does not represent" in res.message
    for name in ("healthy_1020", "healthy_1021"):
        res = fit(rig, _record(records[name], name), rig.PHENOMENOLOGICAL)
        assert res.adequacy["adequate"] is True and res.warnings == [], (name, res.warnings)


@pytest.mark.slow
def test_twin_fit_says_it_in_the_text_the_json_and_the_saved_file_and_a_commissioning_keeps_it(records, tmp_path,
                                                                                                 capsys):
    path = tmp_path / "resonance.csv"
    records["resonance"].to_csv(path)
    saved = tmp_path / "fit.json"
    assert cli.main(["fit", str(path), "--json", "--save", str(saved)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["adequacy"]["adequate"] is False and doc["adequacy"]["reasons"]
    assert any("does not represent this record" in w for w in doc["warnings"])
    kept = json.loads(saved.read_text())
    assert kept["warnings"] == doc["warnings"]
    com = from_dict(kept, str(saved))
    assert com.warnings == tuple(doc["warnings"])
    # tracked against bands centred on that fit: said again on stderr and in the JSON
    assert cli.main(["track", str(path), "--params", str(saved), "--json", "--out", str(tmp_path / "t")]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["commission_warnings"] == doc["warnings"]
    assert "WARNING (" in out.err and "does not represent this record" in out.err
    assert cli.main(["fit", str(path), "--no-adequacy", "--json"]) == 0  # asked not to judge: nothing said
    quiet = json.loads(capsys.readouterr().out)
    assert quiet["adequacy"] is None and quiet["warnings"] == []
    assert cli.main(["fit", str(path)]) == 0
    assert "WARNING: the model does not represent this record" in capsys.readouterr().out


@pytest.mark.slow
def test_a_commissioning_in_service_on_a_rig_out_of_reach_carries_the_warning(records):
    """The service's commissioning fit (``fit_window``, what the spawned fit process runs): the rig with the
    resonance is commissioned (its bands centred on the fit) and the document it saves says what the fit
    warned; the same rig without the resonance carries no warning."""
    names = ("Ffric", "CdAleak", "Cd", "zeta", "wn")
    for name, warned in (("resonance", True), ("healthy_1020", False)):
        ref = records[name]
        t_ns = 1_700_000_000_000_000_000 + np.round(ref.t * 1e9).astype(np.int64)
        samples = Samples(t_ns, {k: np.asarray(v, float) for k, v in ref.signals.items()})
        doc, problem = fit_window(samples, names, rig="rig-r")
        assert doc is not None and problem == "", problem
        says = [w for w in doc.get("warnings", []) if "does not represent this record" in w]
        assert bool(says) is warned, (name, doc.get("warnings"))
        assert from_dict(doc).warnings == tuple(doc.get("warnings", []))
