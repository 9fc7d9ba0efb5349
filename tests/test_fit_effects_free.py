"""``twin fit --effects E`` fits E's own parameters without naming them in ``--free``; ``--set`` holds them and an
explicit ``--free`` is taken exactly as listed.

The record is the independent reference simulator's (``tests/reference``): the paper's oscillator with its damping
and stiffness drawn away from the defaults and a Coulomb friction force drawn in 0.5-3 N, measured with 1 um of
noise.
"""

from __future__ import annotations

import json

import pytest

from twin import cli
from twin.commands.fit import free_names
from twin.models import get_model


def test_free_names_rule():
    """The rule on every registered model's first effect: its own parameters join the phenomenological ones, less
    what --set holds; an explicit --free list is kept as is."""
    from twin.models import MODELS

    for name in MODELS:
        model = get_model(name)
        if not model.EFFECTS:
            continue
        effect = next(iter(model.EFFECTS))
        own = model.EFFECTS[effect].names
        assert free_names(model, (), {}, ()) == tuple(model.PHENOMENOLOGICAL)
        assert free_names(model, (), {}, (effect,)) == (*model.PHENOMENOLOGICAL, *own), name
        held = {own[0]: 1.0, model.PHENOMENOLOGICAL[0]: 1.0}
        got = free_names(model, (), held, (effect,))
        assert own[0] not in got and model.PHENOMENOLOGICAL[0] not in got and set(own[1:]) <= set(got), name
        assert free_names(model, (model.PHENOMENOLOGICAL[0],), {}, (effect,)) == (model.PHENOMENOLOGICAL[0],)


@pytest.fixture(scope="module")
def friction_record(reference_records, tmp_path_factory):
    from conftest import oscillator_spec

    (rec,) = reference_records([oscillator_spec(7, duration=4.0, truth="draw", effects=("coulomb_friction",),
                                                intersample="zoh")])
    path = tmp_path_factory.mktemp("friction") / "friction.csv"
    rec.to_csv(path)
    return rec, path


@pytest.mark.slow
def test_effects_parameters_are_fitted(friction_record, capsys):
    """Without --free, ``--effects coulomb_friction`` fits Fc (before: Fc stayed at its neutral 0 and only d, k
    were fitted) and finds the drawn friction force."""
    rec, path = friction_record
    fc = rec.truth["coulomb_friction.Fc"]
    code = cli.main(["fit", str(path), "--model", "oscillator", "--effects", "coulomb_friction",
                     "--controller", "digital", "--json", "-q"])
    assert code in (0, 3)
    d = json.loads(capsys.readouterr().out)
    assert {"d", "k", "Fc"} <= set(d["params"])
    assert d["params"]["Fc"]["value"] == pytest.approx(fc, rel=0.1)
    assert d["params"]["k"]["value"] == pytest.approx(rec.truth["k"], rel=0.01)


@pytest.mark.slow
def test_set_and_free_hold_the_effects_parameters(friction_record, capsys):
    """``--set Fc=...`` holds the friction at the value given; ``--free d,k`` fits d and k alone."""
    rec, path = friction_record
    fc = rec.truth["coulomb_friction.Fc"]
    code = cli.main(["fit", str(path), "--model", "oscillator", "--effects", "coulomb_friction",
                     "--set", f"Fc={fc}", "--controller", "digital", "--json", "-q"])
    assert code in (0, 3)
    d = json.loads(capsys.readouterr().out)
    assert "Fc" not in d["params"] and {"d", "k", "vc"} <= set(d["params"])
    code = cli.main(["fit", str(path), "--model", "oscillator", "--effects", "coulomb_friction",
                     "--free", "d,k", "--controller", "digital", "--json", "-q"])
    assert code in (0, 3)
    d = json.loads(capsys.readouterr().out)
    assert set(d["params"]) == {"d", "k"}
