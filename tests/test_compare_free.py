"""``twin fit --compare`` holds what ``--set`` holds and fits what ``--free`` names; the oscillator's spring
held at exactly 0 (a free mass with damping).

The record is the independent reference simulator's (``tests/reference``): a mass of 2.5 kg (not the model's
default 1 kg) with damping 8 N s/m and no spring, driven by a multisine force, measured with 1 um of noise.
"""

from __future__ import annotations

import json

import pytest

from twin import cli

#: each fits a few times (and the first compiles the oscillator's kernels): the slow suite's
pytestmark = pytest.mark.slow

MASS, DAMPING = 2.5, 8.0


@pytest.fixture(scope="module")
def free_mass(reference_records, tmp_path_factory):
    from conftest import oscillator_spec

    (rec,) = reference_records([oscillator_spec(31, duration=4.0, truth={"d": DAMPING, "k": 0.0},
                                                known={"m": MASS}, effects=(), intersample="zoh")])
    path = tmp_path_factory.mktemp("free_mass") / "free_mass.csv"
    rec.to_csv(path)
    return path


def test_set_k_zero_is_accepted_and_held(free_mass, capsys):
    """``--set k=0`` is a spring of exactly 0 N/m (the range starts at 0); the fit of m and d finds the truth."""
    code = cli.main(["fit", str(free_mass), "--model", "oscillator", "--set", "k=0", "--free", "m,d",
                     "--controller", "digital", "--json", "-q"])
    assert code in (0, 3)
    d = json.loads(capsys.readouterr().out)
    assert set(d["params"]) == {"m", "d"}
    assert d["params"]["m"]["value"] == pytest.approx(MASS, rel=0.02)
    assert d["params"]["d"]["value"] == pytest.approx(DAMPING, rel=0.05)


def test_compare_honours_free_and_set(free_mass, capsys):
    """Every candidate fits --free (m, d) and its effects' own parameters, never k (held by --set at 0): before,
    m stayed at 1 kg and k was freed."""
    code = cli.main(["fit", str(free_mass), "--model", "oscillator", "--set", "k=0", "--free", "m,d",
                     "--controller", "digital", "--compare", "none,input_offset", "--json", "-q"])
    assert code in (0, 3)
    d = json.loads(capsys.readouterr().out)
    rows = {r["name"]: r for r in d["rows"]}
    assert rows["none"]["free"] == ["m", "d"]
    assert rows["input_offset"]["free"] == ["m", "d", "u0"]
    for r in rows.values():
        assert "k" not in r["params"]
        assert r["params"]["m"]["value"] == pytest.approx(MASS, rel=0.05), r["name"]
    # without --free, the phenomenological parameters less those --set: d alone (m held at its value)
    code = cli.main(["fit", str(free_mass), "--model", "oscillator", "--set", f"k=0,m={MASS}",
                     "--controller", "digital", "--compare", "none", "--json", "-q"])
    d = json.loads(capsys.readouterr().out)
    assert d["rows"][0]["free"] == ["d"]
    assert d["rows"][0]["params"]["d"]["value"] == pytest.approx(DAMPING, rel=0.05)


def test_plain_fit_does_not_free_what_set_holds(free_mass, capsys):
    """``twin fit --set k=0,m=2.5`` without --free fits d alone (before, k was freed from 0 and went to 7e7 N/m)."""
    code = cli.main(["fit", str(free_mass), "--model", "oscillator", "--set", f"k=0,m={MASS}",
                     "--controller", "digital", "--json", "-q"])
    assert code in (0, 3)
    d = json.loads(capsys.readouterr().out)
    assert set(d["params"]) == {"d"}
    assert d["params"]["d"]["value"] == pytest.approx(DAMPING, rel=0.01)


def test_diagnose_holds_what_set_holds(free_mass, capsys):
    """``twin diagnose --set k=0`` keeps the spring at 0 in its nominal fit (before, k was freed); with every
    nominal parameter held and no --free it says so in one line."""
    code = cli.main(["diagnose", str(free_mass), "--model", "oscillator", "--set", "k=0", "--free", "m,d",
                     "--controller", "digital", "--json", "-q"])
    assert code in (0, 3)
    d = json.loads(capsys.readouterr().out)
    assert set(d["nominal"]["params"]) == {"m", "d"}
    assert d["nominal"]["params"]["m"]["value"] == pytest.approx(MASS, rel=0.05)
    assert cli.main(["diagnose", str(free_mass), "--model", "oscillator", "--set", "k=0,d=1", "-q"]) == 2
    assert "--set holds every nominal free parameter of oscillator (d, k)" in capsys.readouterr().err
