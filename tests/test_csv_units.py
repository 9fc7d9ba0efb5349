"""A CSV's units never read silently wrong: a length column in mm read as metres is refused against the rig's
stroke, a ';'-separated export with decimal commas is read as it is meant, a flow column is said to be no
signal."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from twin import cli

HERE = pathlib.Path(__file__).parent / "data" / "reference.csv"


def _rows():
    lines = HERE.read_text(encoding="utf-8").splitlines()
    return [[float(v) for v in line.split(",")] for line in lines[1:]]


def _write(path, header, rows, sep=",", decimal="."):
    with open(path, "w", encoding="utf-8") as f:
        f.write(sep.join(header) + "\n")
        for r in rows:
            f.write(sep.join(repr(v).replace(".", decimal) for v in r) + "\n")


@pytest.mark.slow
def test_a_length_column_in_mm_read_as_metres_is_refused_with_the_unit_to_give(tmp_path, capsys):
    """A position logged in mm about 0.3 mm from mid stroke (0.1 mm of motion): within the signal's table range
    when read as metres (0.3 m < 0.5 m), but beyond the msp25's stroke of +-250 mm; fit and track refuse it,
    naming the range and both ways to give the unit."""
    from twin.models import get_model
    from twin.models.records import load_records
    from twin.units import check_lengths

    rows = [[t, xr * 10 + 0.3, u, x * 10 + 0.3, pa, pb] for t, xr, u, x, pa, pb in _rows()]  # mm
    assert 0.25 < max(r[3] for r in rows) < 0.5
    path = tmp_path / "mm.csv"
    _write(path, ["t", "x_ref", "u", "x", "pA", "pB"], rows)
    for cmd in (["fit", str(path), "--free", "Ffric", "--starts", "1"], ["track", str(path), "--out", str(tmp_path)]):
        assert cli.main(["-q", *cmd]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "beyond the msp25 rig's physical range -250 .. 250 mm" in err[0], err
        assert "reads like a column in mm" in err[0] and "--map x_ref=x_ref:mm or a header x_ref[mm]" in err[0]
    # with the unit given either way, the same numbers read in metres and pass
    _write(tmp_path / "mm_header.csv", ["t", "x_ref[mm]", "u", "x[mm]", "pA", "pB"], rows)
    model = get_model("msp25")
    mapped = load_records(str(path), map=["x_ref=x_ref:mm", "x=x:mm"])[0]
    header = load_records(str(tmp_path / "mm_header.csv"))[0]
    for rec in (mapped, header):
        np.testing.assert_allclose(rec.signals["x"], [r[3] * 1e-3 for r in rows], rtol=1e-15)
        check_lengths(model, model.params(), rec.signals, rec.name)


def test_a_semicolon_csv_with_decimal_commas_reads_as_the_plain_one(tmp_path):
    from twin.models.records import load_records

    rows = _rows()
    _write(tmp_path / "semi.csv", ["t", "x_ref", "u", "x", "pA", "pB"], rows, sep=";", decimal=",")
    got = load_records(str(tmp_path / "semi.csv"))[0]
    want = load_records(str(HERE))[0]
    for k in ("x_ref", "u", "x", "pA", "pB"):
        np.testing.assert_array_equal(got.signals[k], want.signals[k])


def test_a_flow_column_is_said_to_be_no_signal(tmp_path, capsys):
    rows = [r + [1.5] for r in _rows()]
    path = tmp_path / "flow.csv"
    _write(path, ["t", "x_ref", "u", "x", "pA", "pB", "Q[l/min]"], rows)
    assert cli.main(["-q", "fit", str(path), "--free", "Ffric", "--starts", "1", "--map", "Q=Q[l/min]:l/min"]) == 2
    err = capsys.readouterr().err
    assert "'l/min' is a flow (a volume per time), and no signal of a record is a flow" in err
    from replay.csvio import CsvSource

    with CsvSource(path) as src:
        problems = [p.what for p in src.report.problems]
    assert any("a flow (volume per time) is no signal of a record" in p for p in problems), problems
    assert not any("--map" in p for p in problems), problems
