"""The Python API example of the documentation (docs/reference/api.md) runs as written, and the curated API is
what it says."""

from __future__ import annotations

import pathlib
import re

import replay
import twin
from twin.reports import fit_report

API_PAGE = pathlib.Path(__file__).resolve().parents[1] / "docs" / "reference" / "api.md"


def test_documented_api_example_runs(capsys):
    text = API_PAGE.read_text()
    m = re.search(r"<!-- api-example -->\n```python\n(.*?)```", text, re.S)
    assert m, "docs/reference/api.md: the API example block is missing"
    exec(compile(m.group(1), "docs/reference/api.md:api-example", "exec"), {})
    out = capsys.readouterr().out
    assert "Ffric" in out and "zeta tracked:" in out


def test_every_public_name_resolves():
    for name in twin.__all__:
        assert getattr(twin, name) is not None, name
    for name in replay.__all__:
        assert getattr(replay, name) is not None, name
    assert twin.TwinError is replay.TwinError  # one error tree, at the bottom layer


def test_api_functions_survive_their_modules_being_imported():
    import importlib

    for mod in ("twin.estimation.fit", "twin.estimation.fit_checked", "twin.service.track",
                "twin.estimation.diagnose"):
        importlib.import_module(mod)
    assert callable(twin.fit) and callable(twin.track) and callable(twin.diagnose)
    # twin.fit is the fit with its adequacy test (what twin fit runs)
    assert twin.fit.__module__ == "twin.estimation.fit_checked" and twin.diagnose.__name__ == "diagnose"


def test_the_api_reads_like_the_command_line(tmp_path):
    """``load_records(map=...)`` in --map's direction (a dict or its strings), ``model.params`` with units as
    ``--set``, ``FitResult.save()`` read back as ``--params``, ``report()``, short reprs."""
    import dataclasses

    import numpy as np
    import pytest

    from twin.commands.common import load_params_file
    from twin.estimation.diagnose import Diagnosis
    from fpdd.errors import DataError, ParameterError

    here = pathlib.Path(__file__).parent
    lines = (here / "data" / "reference.csv").read_text(encoding="utf-8").splitlines()
    rows = [line.split(",") for line in lines[1:]]
    with open(tmp_path / "foreign.csv", "w", encoding="utf-8") as f:
        f.write("time,dem,u,pos_mm,pA,pB\n")
        for r in rows:
            f.write(",".join([r[0], r[1], r[2], repr(float(r[3]) * 1e3), r[4], r[5]]) + "\n")
    want = twin.load_records(str(here / "data" / "reference.csv"))[0]
    as_dict = twin.load_records(str(tmp_path / "foreign.csv"), map={"t": "time", "x_ref": "dem", "x": "pos_mm:mm"})
    as_text = twin.load_records(str(tmp_path / "foreign.csv"), map=["t=time", "x_ref=dem", "x=pos_mm:mm"])
    for got in (as_dict[0], as_text[0]):
        for k in ("x", "x_ref", "u", "pA", "pB"):
            np.testing.assert_allclose(got.signals[k], want.signals[k], rtol=1e-12)
    with pytest.raises(DataError, match="did you mean map x=pos_mm"):
        twin.load_records(str(tmp_path / "foreign.csv"), map="pos_mm=x")

    model = twin.get_model("msp25")
    ps = model.params(A="2000mm^2", wn="43Hz", Ffric="65 N")
    assert ps["A"] == pytest.approx(2e-3) and ps["wn"] == pytest.approx(2 * np.pi * 43) and ps["Ffric"] == 65.0
    with pytest.raises(ParameterError, match="A \\(='2 kg'\\) must be a number in m\\^2 or a value with a unit: '2 kg' is not in a unit of m\\^2"):
        model.params(A="2 kg")

    drive, x_ref = twin.excite(model, duration_s=4.0, seed=1003)
    record = twin.measure(model, model.params(Ffric=65.0), drive, x_ref, dt=1e-3,
                          noise={"x": 2e-6, "pA": 2e4, "pB": 2e4}, seed=1003)
    result = twin.fit(model, record, ["Ffric"], start={"Ffric": 40.0})
    text = repr(result)
    assert len(text) < 300 and text.startswith("FitResult(model='msp25', Ffric=") and "converged" in text
    saved = result.save(str(tmp_path / "fit.json"))
    back = load_params_file(model, saved)
    assert back["Ffric"] == pytest.approx(result.estimate["Ffric"])
    html = fit_report(result, [record], model, str(tmp_path / "report"))
    assert pathlib.Path(html).stat().st_size > 1000

    diag = Diagnosis(model="msp25", causes=["spool_deadband"], unexplained=False, nominal=None, final=None,  # type: ignore[arg-type]
                     path=[], screens=[[]] * 50, trials=[[]] * 50, gains={}, outputs=("x",), holdout=0.3, time_s=8.2,
                     records=[record] * 5)
    assert repr(diag) == ("Diagnosis(model='msp25', verdict='explained', causes=['spool_deadband'], records=5, "
                          "time_s=8.2)")
    assert dataclasses.is_dataclass(diag)


def test_import_twin_is_light_and_reaches_its_subpackages():
    """``import twin; twin.reports.fit_report(...)`` as written, without importing ``twin.reports`` first; ``import
    twin`` alone imports neither numpy nor a subpackage."""
    import subprocess
    import sys

    code = ("import sys, twin; heavy = [m for m in ('numpy', 'twin.reports', 'twin.estimation', 'twin.models') "
            "if m in sys.modules]; assert not heavy, heavy; "
            "f = twin.reports.fit_report; assert callable(f) and 'twin.reports' in sys.modules; "
            "assert 'reports' in dir(twin); print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_fit_takes_params_as_the_command_line_does_and_short_reprs(tmp_path):
    import pytest

    from fpdd.errors import ParameterError
    from twin.estimation.fit_result import FitResult

    model = twin.get_model("msp25")
    drive, x_ref = twin.excite(model, duration_s=2.0, seed=1005)
    truth = model.params(A="2100mm^2", Ffric=62.0)
    record = twin.measure(model, truth, drive, x_ref, dt=1e-3, noise={"x": 2e-6, "pA": 2e4, "pB": 2e4}, seed=1005)
    res = twin.fit(model, record, ["Ffric"], params={"A": "2100mm^2"}, start={"Ffric": 40.0}, n_starts=1)
    assert res.params["A"] == pytest.approx(2.1e-3) and abs(res.estimate["Ffric"] - 62.0) < 4 * res.std["Ffric"]
    old = twin.fit(model, record, ["Ffric"], base=model.params(A="2100mm^2"), start={"Ffric": 40.0}, n_starts=1)
    assert old.estimate["Ffric"] == pytest.approx(res.estimate["Ffric"], rel=1e-9)
    with pytest.raises(ParameterError, match="params= or its older name base=, not both"):
        twin.fit(model, record, ["Ffric"], params={"A": "2100mm^2"}, base=model.params())
    saved = res.save(str(tmp_path / "fit.json"))
    back = FitResult.load(saved)
    assert back.params.values == res.params.values and back.estimate == res.estimate and back.std == res.std
    assert back.free == ("Ffric",) and back.timing == res.timing and back.fit_pct == res.fit_pct
    again = twin.fit(model, record, ["Ffric"], params=saved, start={"Ffric": 40.0}, n_starts=1)
    assert again.params["A"] == pytest.approx(2.1e-3)
    (tmp_path / "bad.json").write_text('{"model": "msp25", "params": {"A": {"value": 2, "unit": "mm^2"}}}')
    with pytest.raises(twin.TwinError, match=r"bad\.json: params\.A\.unit is 'mm\^2', expected 'm\^2'"):
        FitResult.load(str(tmp_path / "bad.json"))
    # one line, what makes this set this rig, in display units
    text = repr(truth)
    assert text == "ParameterSet(model='msp25', changed: A=2100mm^2, Ffric=62N; 34 parameters)"
    assert repr(model.params()) == "ParameterSet(model='msp25', nominal; 34 parameters)"
    assert len(repr(res)) < 300 and "\n" not in repr(res)


def test_track_takes_a_map_as_load_records_does(tmp_path):
    here = pathlib.Path(__file__).parent / "data" / "reference.csv"
    lines = here.read_text(encoding="utf-8").splitlines()
    with open(tmp_path / "foreign.csv", "w", encoding="utf-8") as f:
        f.write("time,dem,u,pos_mm,pA,pB\n")
        for line in lines[1:]:
            r = line.split(",")
            f.write(",".join([r[0], r[1], r[2], repr(float(r[3]) * 1e3), r[4], r[5]]) + "\n")
    plain = twin.track(str(here))
    mapped = twin.track(str(tmp_path / "foreign.csv"), map={"t": "time", "x_ref": "dem", "x": "pos_mm:mm"})
    assert mapped.stats.samples == plain.stats.samples == len(lines) - 1
    a, b = plain.final_estimates(), mapped.final_estimates()
    for k in a:
        assert b[k]["value"] == __import__("pytest").approx(a[k]["value"], rel=1e-9), k
