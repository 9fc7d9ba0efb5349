"""Values with units on the way in: pint conversion, Hz for angular frequencies, clear errors."""

from __future__ import annotations

import json
import math

import pytest

from twin import cli
from twin.commands.common import kv
from fpdd.errors import ParameterError
from twin.units import to_si


@pytest.mark.parametrize("name,text,si", [
    ("wn", "43Hz", 2 * math.pi * 43),
    ("wn", "270.2 rad/s", 270.2),
    ("wn", "0.043 kHz", 2 * math.pi * 43),
    ("CdAleak", "3.3mm^2", 3.3e-6),
    ("CdAleak", "3.3 mm²", 3.3e-6),
    ("Ffric", "0.05kN", 50.0),
    ("x", "2um", 2e-6),
    ("x", "2 µm", 2e-6),
    ("pA", "2 bar", 2e5),
    ("Bulk", "1.5 GPa", 1.5e9),
    ("KP", "0.4 V/mm", 400.0),
    ("V0", "480 cm^3", 480e-6),
    ("zeta", "0.37", 0.37),
    ("Ffric", "50", 50.0),  # a bare number is SI
])
def test_values_with_units_convert_to_si(name, text, si):
    assert to_si(name, text) == pytest.approx(si, rel=1e-12)


@pytest.mark.parametrize("text,unit", [
    ("43Hz", "rad/s"), ("0.043 kHz", "rad/s"), ("270.2rad/s", "rad/s"), ("0.0098589mm^2", "m^2"),
    ("3.3 mm²", "m^2"), ("4 mm**2", "m^2"), ("480 cm^3", "m^3"), ("20kPa", "Pa"), ("1.5 GPa", "Pa"), ("0.05kN", "N"),
    ("2um", "m"), ("2 µm", "m"), ("7 cm", "m"), ("1.5ms", "s"), ("-3.5e2 mm", "m"),
])
def test_a_prefixed_si_unit_is_read_without_pint_and_as_pint_reads_it(text, unit):
    """The common spellings (the SI unit with a prefix) skip pint's import, about a second of a command's start;
    each gives what pint gives. Anything else is pint's (``3ms`` for a length: not a prefixed metre)."""
    from fpdd import units

    fast = units._prefixed(text, unit)
    assert fast is not None
    pint_value = units._registry().Quantity(text.replace("²", "^2").replace("µ", "u"))
    if unit == "rad/s" and "Hz" in text:
        assert fast == pytest.approx(2 * math.pi * float(pint_value.to("Hz").magnitude), rel=1e-12)
    else:
        assert fast == pytest.approx(float(pint_value.to(unit).magnitude), rel=1e-12)
    for other, u in (("3ms", "m"), ("2 kg", "N"), ("1 bar", "Pa"), ("40degC", "K"), ("5 mm^3", "m^2"),
                     ("0.4 V/mm", "V/m")):
        assert units._prefixed(other, u) is None


def test_a_command_with_prefixed_units_does_not_import_pint():
    import subprocess
    import sys

    code = ("import sys; from twin.units import to_si; "
            "v = [to_si('CdAleak', '3.3mm^2'), to_si('wn', '43Hz'), to_si('Ffric', '0.05kN')]; "
            "print('pint' in sys.modules, v)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split(" ", 1)
    assert out[0] == "False" and json.loads(out[1]) == pytest.approx([3.3e-6, 2 * math.pi * 43, 50.0], rel=1e-12)


@pytest.mark.parametrize("text,message", [
    ("wn=43N", "wn: '43N' is not in a unit of rad/s"),
    ("Ffric=abc", "Ffric: cannot read 'abc'"),
    ("Ffric=inf", "Ffric: 'inf' is not a finite number"),
    ("nosuch=3mm", "'nosuch' has no known unit"),
    ("Ffric", "expected NAME=VALUE"),
])
def test_bad_values_name_the_parameter_and_the_expectation(text, message):
    with pytest.raises(ParameterError, match=message.replace("(", r"\(")):
        kv(text)


def test_simulate_takes_display_units_the_params_table_shows(tmp_path, capsys):
    out = tmp_path / "r.csv"
    assert cli.main(["simulate", "-o", str(out), "--duration", "0.2", "--json",
                     "--set", "CdAleak=0.01mm^2,wn=40Hz,Ffric=0.08kN"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["params"]["CdAleak"] == {"value": pytest.approx(1e-8), "unit": "m^2"}
    assert info["params"]["wn"] == {"value": pytest.approx(2 * math.pi * 40), "unit": "rad/s"}
    assert info["params"]["Ffric"] == {"value": pytest.approx(80.0), "unit": "N"}
    assert info["dt"] == {"value": 1e-3, "unit": "s"} and info["noise"]["pA"]["unit"] == "Pa"


def test_a_value_with_the_wrong_unit_is_a_one_line_error(tmp_path, capsys):
    assert cli.main(["simulate", "-o", str(tmp_path / "r.csv"), "--duration", "0.2",
                     "--set", "CdAleak=0.01mm"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "CdAleak" in err[0] and "m^2" in err[0]


def test_fit_track_and_diagnose_read_foreign_csv_columns_with_map(tmp_path, capsys):
    """A CSV logged by another tool: other column names, position in mm; --map says which is which."""
    import numpy as np

    rec = tmp_path / "r.csv"
    assert cli.main(["-q", "simulate", "-o", str(rec), "--duration", "2", "--seed", "4"]) == 0
    header = rec.read_text().splitlines()[0]
    assert header == "t[s],x_ref[m],u[V],x[m],pA[Pa],pB[Pa]"  # SI, the unit of each column named
    data = np.genfromtxt(rec, delimiter=",", skip_header=1,
                         dtype=[(c.split("[")[0], float) for c in header.split(",")])
    foreign = tmp_path / "foreign.csv"
    np.savetxt(foreign, np.column_stack([data["t"], data["x_ref"], data["u"], data["x"] * 1e3, data["pA"],
                                         data["pB"]]),
               delimiter=",", header="time,demand,command,pos_mm,p_a,p_b", comments="", fmt="%.17g")
    maps = ["--map", "t=time", "--map", "x_ref=demand", "--map", "u=command", "--map", "x=pos_mm:mm",
            "--map", "pA=p_a", "--map", "pB=p_b"]
    capsys.readouterr()
    assert cli.main(["-q", "fit", str(foreign), "--free", "Ffric", "--start", "Ffric=70N", "--json", *maps]) == 0
    out = json.loads(capsys.readouterr().out)
    assert abs(out["params"]["Ffric"]["value"] - 50.0) < 3 * out["params"]["Ffric"]["std"]
    assert cli.main(["-q", "fit", str(foreign), "--free", "Ffric"]) == 2
    err = capsys.readouterr().err
    assert "pos_mm" in err and "--map" in err and len(err.strip().splitlines()) == 1
    assert cli.main(["-q", "track", str(foreign), "--out", str(tmp_path / "tr"), "--json", *maps]) == 0
    assert json.loads(capsys.readouterr().out)["samples"] == 2000
    mcap = tmp_path / "r.mcap"
    assert cli.main(["-q", "simulate", "-o", str(mcap), "--duration", "0.5"]) == 0
    capsys.readouterr()
    assert cli.main(["-q", "fit", str(mcap), "--free", "Ffric", "--map", "x=pos"]) == 2
    assert "not a CSV" in capsys.readouterr().err


def test_track_says_an_oscillator_record_is_not_a_rig_log(tmp_path, capsys):
    osc = tmp_path / "osc.csv"
    assert cli.main(["-q", "simulate", "--model", "oscillator", "-o", str(osc), "--duration", "0.5"]) == 0
    capsys.readouterr()
    assert cli.main(["-q", "track", str(osc), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "oscillator" in err[0] and "msp25" in err[0]


def test_a_signal_shown_by_a_factor_is_never_labelled_in_a_unit_with_an_offset():
    """Plots and the live view convert a signal by a factor only: 313.15 K of oil must not read 313.15 °C."""
    from twin.reports.units import SIGNALS

    assert SIGNALS["T_oil"] == ("K", 1.0)
    assert not [n for n, (unit, _) in SIGNALS.items() if unit in ("°C", "degC", "°F", "degF")]


@pytest.mark.slow
def test_simulate_writes_csv_units_that_every_reader_reads_back_to_the_same_numbers(tmp_path, capsys):
    """``twin simulate``'s CSV names each column's SI unit (``t[s],x[m],pA[Pa]``; the oscillator's ``u[N]``);
    ``replay info``, ``twin fit`` and ``twin track`` read it to the very numbers of the same record in MCAP and of
    the same CSV without units in its header."""
    import numpy as np

    from replay import cli as replay_cli
    from replay.factory import open_source
    from twin import load_records

    def out_of(rc: int) -> dict:
        assert rc == 0
        return json.loads(capsys.readouterr().out)

    paths = {k: str(tmp_path / f"r.{k}") for k in ("csv", "mcap")}
    for path in paths.values():
        assert cli.main(["-q", "simulate", "-o", path, "--duration", "1.5", "--seed", "1005",
                         "--set", "Ffric=80N"]) == 0
    text = (tmp_path / "r.csv").read_text()
    assert text.splitlines()[0] == "t[s],x_ref[m],u[V],x[m],pA[Pa],pB[Pa]"
    paths["plain"] = str(tmp_path / "plain.csv")
    (tmp_path / "plain.csv").write_text("t,x_ref,u,x,pA,pB\n" + text.split("\n", 1)[1])
    read = {}
    for k, path in paths.items():
        with open_source(path) as src:
            read[k] = src.read_all()
    for k in ("csv", "plain"):
        assert np.array_equal(read[k].t_ns, read["mcap"].t_ns), k
        for name, v in read["mcap"].signals.items():
            assert np.array_equal(read[k].signals[name], v), (k, name)
    assert float(read["csv"].signals["pA"].mean()) > 1e6  # Pa
    info = {k: out_of(replay_cli.main(["info", "--json", p])) for k, p in paths.items()}
    assert info["csv"]["ranges"] == info["mcap"]["ranges"] == info["plain"]["ranges"]
    assert info["csv"]["samples"] == 1500 and info["csv"]["ranges"]["x"]["unit"] == "m"
    fits = {k: out_of(cli.main(["fit", p, "--free", "Ffric", "--json"]))["params"]["Ffric"] for k, p in paths.items()}
    assert fits["csv"] == fits["mcap"] == fits["plain"] and fits["csv"]["unit"] == "N"
    assert abs(fits["csv"]["value"] - 80.0) < 4 * fits["csv"]["std"]
    tracks = {k: out_of(cli.main(["track", p, "--out", str(tmp_path / f"t-{k}"), "--json"]))["final"]
              for k, p in paths.items() if k != "plain"}
    assert tracks["csv"] == tracks["mcap"]
    # the oscillator's input is a force: its column says N, and its model's reader takes it
    osc = tmp_path / "osc.csv"
    assert cli.main(["-q", "simulate", "--model", "oscillator", "-o", str(osc), "--duration", "1",
                     "--seed", "1006"]) == 0
    assert osc.read_text().splitlines()[0] == "t[s],u[N],y[m]"
    (rec,) = load_records(str(osc), model="oscillator")
    rows = np.loadtxt(osc, delimiter=",", skiprows=1)
    assert np.array_equal(rec.signals["u"], rows[:, 1]) and np.array_equal(rec.signals["y"], rows[:, 2])


# --- no silent unit trap: a bare number where the display unit is not SI -----------------------------------------

def _ambiguous_specs():
    """Every parameter of every model whose declared display unit differs from its SI unit (effects included)."""
    from twin.models import MODELS
    from twin.units import _specs

    return [(m, s) for m in MODELS for s in _specs(m).values()
            if s.unit != "1" and ((s.display_unit or s.unit) != s.unit or s.display_scale != 1.0)]


def test_a_bare_number_is_refused_for_every_parameter_shown_in_another_unit():
    """Found from each spec's declared display unit: wn, CdAleak, the pressures, and every other such one."""
    from twin.models import get_model
    from twin.units import _specs

    found = _ambiguous_specs()
    assert {"wn", "CdAleak", "pP", "pA_off", "A", "Tf"} <= {s.name for _, s in found}
    for _model, spec in found:
        with pytest.raises(ParameterError, match=rf"{spec.name}=1\.5: a bare number is ambiguous"):
            to_si(spec.name, "1.5")
        with pytest.raises(ParameterError, match="a bare number is ambiguous"):
            spec.check("1.5")
        # with its unit it is read, in either spelling (a value within the bounds)
        si = math.sqrt(spec.lo * spec.hi) if spec.lo > 0 else 0.5 * spec.hi
        assert to_si(spec.name, f"{si * spec.display_scale!r}{spec.display_unit}") == pytest.approx(si, rel=1e-9)
        assert spec.check(f"{si * spec.display_scale!r}{spec.display_unit}") == pytest.approx(si, rel=1e-9)
        assert spec.check(f"{si!r}{spec.unit}") == pytest.approx(si, rel=1e-12)
    # a parameter shown in its SI unit takes a bare number; zero is zero in every unit; floats from Python are SI
    assert to_si("Ffric", "50") == 50.0 and to_si("zeta", "0.4") == 0.4 and to_si("AB", "0") == 0.0
    ps = get_model("msp25").params()
    assert ps.replace(wn=270.0)["wn"] == 270.0
    assert "Ffric" in _specs("msp25") and ps.replace(Ffric="60")["Ffric"] == 60.0


def test_the_refusal_gives_both_spellings_and_each_works():
    with pytest.raises(ParameterError) as exc:
        kv("wn=43")
    line = str(exc.value)
    assert "\n" not in line and "wn=43Hz (= 270.177rad/s)" in line and "wn=43rad/s (= 6.84366Hz)" in line
    for spelling in ("wn=43Hz", "wn=270.177rad/s"):
        assert kv(spelling)["wn"] == pytest.approx(2 * math.pi * 43, rel=1e-5)


@pytest.mark.parametrize("option,text,expected", [
    ("--set", "wn=43", "wn=43Hz (= 270.177rad/s) or wn=43rad/s"),
    ("--set", "CdAleak=3.3", "CdAleak=3.3mm^2 (= 3.3e-06m^2) or CdAleak=3.3m^2"),
    ("--set", "pP=21", "pP=21MPa (= 2.1e+07Pa) or pP=21Pa"),
    ("--noise-levels", "x=2", "x=2mm (= 0.002m) or x=2m"),
    ("--noise-levels", "x=2m", "implausible noise level for x: its physical range -500 .. 500 mm allows a "
                               "standard deviation of at most 0.5 m; give the unit, e.g. x=2um"),
    ("--noise-levels", "pA=2e4", "pA=20000MPa (= 2e+10Pa) or pA=20000Pa"),
])
def test_simulate_refuses_a_silent_unit_trap_in_one_line(tmp_path, capsys, option, text, expected):
    assert cli.main(["-q", "simulate", "-o", str(tmp_path / "r.csv"), "--duration", "0.2", option, text]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0], err
    assert not (tmp_path / "r.csv").exists()


def test_fit_start_and_track_noise_levels_refuse_bare_numbers(tmp_path, capsys):
    rec = tmp_path / "r.csv"
    assert cli.main(["-q", "simulate", "-o", str(rec), "--duration", "0.5", "--seed", "5"]) == 0
    assert cli.main(["-q", "fit", str(rec), "--free", "wn", "--start", "wn=40"]) == 2
    assert "wn=40Hz (= 251.327rad/s)" in capsys.readouterr().err
    assert cli.main(["-q", "track", str(rec), "--noise-levels", "x=2e-6", "--out", str(tmp_path / "o")]) == 2
    assert "x=2e-06mm (= 2e-09m) or x=2e-06m (= 0.002mm)" in capsys.readouterr().err
