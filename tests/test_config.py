"""Rig configuration: defaults, bands, and errors that name the file and the key."""

from __future__ import annotations

import pytest

from twin.service.config import load_config, parse_config
from fpdd.errors import ConfigError

GOOD = """
[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:7447"]

[service]
journal_dir = "/tmp/j"

[[rig]]
name = "msp25-a"
source = "rig.mcap"
track = ["Ffric", "CdAleak"]
[rig.params]
KP = 450
[rig.baseline.Ffric]
value = 60.0
rel_band = 0.5
"""


def test_good_config_with_defaults(tmp_path):
    p = tmp_path / "rigs.toml"
    p.write_text(GOOD)
    cfg = load_config(str(p))
    rig = cfg.rigs[0]
    assert rig.model == "msp25" and rig.params == {"KP": 450.0} and rig.speed == 1.0
    assert rig.baseline["Ffric"].value == 60.0
    assert rig.baseline["Ffric"].lo == pytest.approx(40.0) and rig.baseline["Ffric"].hi == pytest.approx(90.0)
    assert rig.baseline["CdAleak"].value == pytest.approx(3.2863e-9)  # the paper's Table 9
    assert cfg.listen == ("tcp/127.0.0.1:7447",) and cfg.estimate_every == 50


@pytest.mark.parametrize("edit, message", [
    (lambda s: s.replace('name = "msp25-a"', 'name = "a/b"'), r"rig\[0\]\.name: 'a/b' must be unique"),
    (lambda s: s.replace('source = "rig.mcap"\n', ''), r"rig 'msp25-a': missing key 'source'"),
    (lambda s: s.replace('KP = 450', 'KP = -1'), r"rig 'msp25-a'\.params: KP \(=-1 V/m\) must be in"),
    (lambda s: s.replace('track = ["Ffric", "CdAleak"]', 'track = ["mass"]'), r"\.track: \['mass'\] not among"),
    (lambda s: s.replace('rel_band = 0.5', 'lo = 10.0\nhi = 40.0'), r"baseline\.Ffric: the band \[10, 40\] must contain the value 60"),
    (lambda s: s.replace('mode = "peer"', 'mode = "mesh"'), r"zenoh\.mode must be peer, client or router"),
    (lambda s: s.replace('rel_band = 0.5', 'rel_band = "wide"'), r"baseline\.Ffric\.rel_band: expected a number, got 'wide'"),
])
def test_bad_config_names_file_and_key(tmp_path, edit, message):
    p = tmp_path / "rigs.toml"
    p.write_text(edit(GOOD))
    with pytest.raises(ConfigError, match=message) as info:
        load_config(str(p))
    assert str(p) in str(info.value)


def test_unreadable_and_invalid_toml(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(str(tmp_path / "missing.toml"))
    p = tmp_path / "bad.toml"
    p.write_text("[[rig]\nname=")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(str(p))
    with pytest.raises(ConfigError, match="at least one"):
        parse_config({"rig": []})


def test_the_shipped_example_configuration_validates():
    import os

    cfg = load_config(os.path.join(os.path.dirname(__file__), "..", "deploy", "rigs.example.toml"))
    assert [r.name for r in cfg.rigs] == ["msp25-hall1-a", "msp25-hall1-b"]
    assert cfg.zenoh_mode is None and cfg.journal_dir == "/var/lib/fpdd/journal"  # the mode comes from ZENOH_CONFIG


def test_commissioning_keys_bring_bands_noise_and_timing_from_a_saved_fit(tmp_path):
    """The operator's flow: twin fit --save, then rigs.toml names the file; bands centre on the fit."""
    import json
    import math

    from twin.online.commission import tracker_for

    fit = {"model": "msp25", "effects": [], "params": {"Ffric": 64.0, "CdAleak": 4.1e-9, "Cd": 0.23, "zeta": 0.41,
                                                       "wn": 2 * math.pi * 40},
           "std": {"Ffric": 0.5, "CdAleak": 4e-10, "Cd": 1e-5, "zeta": 3e-4, "wn": 0.2},
           "timing": {"controller": "continuous", "rate_hz": None, "intersample": "cubic"},
           "noise": {"x": 3e-6, "pA": 2.5e4, "pB": 2.5e4}}
    (tmp_path / "fit.json").write_text(json.dumps(fit))
    (tmp_path / "rigs.toml").write_text(
        '[service]\njournal_dir = "j"\n[[rig]]\nname = "a"\nsource = "rig.csv"\ncommission = "fit.json"\n'
        'noise = { x = "4um" }\n[rig.baseline.zeta]\nvalue = 0.4\nrel_band = 0.2\n')
    rig = load_config(str(tmp_path / "rigs.toml")).rigs[0]
    assert rig.commission == str(tmp_path / "fit.json")
    assert rig.baseline["Ffric"].value == 64.0 and rig.baseline["Ffric"].lo < 64.0 < rig.baseline["Ffric"].hi
    assert rig.baseline["zeta"].value == 0.4  # an explicit band still wins
    assert rig.noise == {"x": pytest.approx(4e-6)}
    tracker = tracker_for(rig)
    assert tracker.timing.controller == "continuous"  # from the fit: the rig's loop is analog
    assert tracker.ps["Ffric"] == 64.0


@pytest.mark.parametrize("rig_lines,message", [
    ('noise = { y = 1e-6 }', "noise: unknown output 'y'"),
    ('noise = { x = -1e-6 }', "noise.x: expected a positive standard deviation"),
    ('noise = { x = "2 N" }', "noise.x: x: '2 N' is not in a unit of m"),
    ('controller = "digital:abc"', "controller: controller 'digital:abc'"),
    ('intersample = "spline"', "intersample 'spline'"),
    ('commission = "missing.json"', "missing.json: cannot read the commissioning fit"),
])
def test_bad_commissioning_keys_name_the_key(tmp_path, rig_lines, message):
    (tmp_path / "rigs.toml").write_text(f'[[rig]]\nname = "a"\nsource = "rig.csv"\n{rig_lines}\n')
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        load_config(str(tmp_path / "rigs.toml"))


def _rig(tmp_path, lines: str, source: str = "rig.mcap"):
    p = tmp_path / "rigs.toml"
    p.write_text(f'[[rig]]\nname = "r"\nsource = "{source}"\n{lines}\n', encoding="utf-8")
    return load_config(str(p)).rigs[0]


def test_values_with_units_in_params_and_baselines(tmp_path):
    rig = _rig(tmp_path, '[rig.params]\nA = "2000mm^2"\nKP = 450\n[rig.baseline.CdAleak]\nvalue = "0.0033mm^2"\n'
                         'lo = "0.001 mm^2"\nhi = "0.01mm²"\n[rig.baseline.wn]\nvalue = "43Hz"\nrel_band = 0.2')
    assert rig.params == {"A": pytest.approx(2e-3), "KP": 450.0}
    b = rig.baseline["CdAleak"]
    assert (b.value, b.lo, b.hi) == pytest.approx((3.3e-9, 1e-9, 1e-8))
    assert rig.baseline["wn"].value == pytest.approx(2 * 3.141592653589793 * 43)


@pytest.mark.parametrize("lines, message", [
    ('[rig.baseline.CdAleak]\nvalue = 0.0033',
     r"baseline\.CdAleak\.value: value = 0\.0033: a bare number is ambiguous \(CdAleak is shown in mm\^2, kept in "
     r"m\^2\): write the unit, value = \"0\.0033mm\^2\" \(= 3\.3e-09m\^2\) or value = \"0\.0033m\^2\""),
    ('[rig.baseline.wn]\nvalue = 270.0\nlo = 200\nhi = 400', r"baseline\.wn\.value: value = 270: a bare number is "
     r"ambiguous \(wn is shown in Hz, kept in rad/s\): write the unit, value = \"270Hz\" \(= 1696\.46rad/s\) or "
     r"value = \"270rad/s\" \(= 42\.9718Hz\)"),
    ('noise = { x = 2e-6 }', r"noise\.x: x = 2e-06: a bare number is ambiguous \(x is shown in mm, kept in m\): write the "
     r"unit, x = \"2e-06mm\""),
    ('noise = { x = "0.6m" }', r"noise\.x: x=0\.6 m \(given as '0\.6m'\): implausible noise level for x: its physical "
     r"range -500 \.\. 500 mm allows a standard deviation of at most 0\.5 m"),
    ('[rig.baseline.Ffric]\nvalue = "50 bar"', r"baseline\.Ffric\.value: expected a number or a value with a unit, got '50 bar': '50 bar' is not in a unit of N"),
    ('[rig.params]\nA = "2000 kg"', r"params\.A: expected a number or a value with a unit, got '2000 kg': '2000 kg' is not in a unit of m\^2"),
    ('map = ["pos_mm=x:mm"]', r"rig 'r'\.map item 'pos_mm=x:mm': 'pos_mm' is not a signal name but 'x' is"),
    ('map = ["x=pos_mm:mm"]', r"rig 'r'\.map: maps the columns of CSV, .* the source 'rig.mcap' names its signals"),
    ('dbc = "missing.dbc"', r"rig 'r'\.dbc: .*missing\.dbc is not a file"),
])
def test_bad_units_maps_and_dbcs_name_the_key(tmp_path, lines, message):
    with pytest.raises(ConfigError, match=message):
        _rig(tmp_path, lines)


def test_a_csv_rig_with_foreign_columns_is_read_through_its_map(tmp_path):
    """rigs.toml ``map`` (a list as --map, or a table) and a ``dbc`` relative to the file; the service's reader
    of the rig reads the foreign CSV as the original."""
    import shutil

    import numpy as np

    from replay.factory import open_source
    from twin.service.inputs import open_rig_source

    here = __import__("pathlib").Path(__file__).parent
    text = (here / "data" / "reference.csv").read_text(encoding="utf-8").splitlines()
    cols = text[0].split(",")
    rows = [line.split(",") for line in text[1:]]
    foreign = ["time_ms", "dem", "valve_V", "pos_mm", "pa", "pb"]
    with open(tmp_path / "foreign.csv", "w", encoding="utf-8") as f:
        f.write(",".join(foreign) + "\n")
        for r in rows:
            t = (float(r[0]) - float(rows[0][0])) * 1e3
            f.write(",".join([repr(t), r[1], r[2], repr(float(r[3]) * 1e3), r[4], r[5]]) + "\n")
    shutil.copy(here.parent / "replay" / "data" / "msp25.dbc", tmp_path / "site.dbc")
    as_list = _rig(tmp_path, 'dbc = "site.dbc"\nmap = ["t=time_ms:ms", "x_ref=dem", "u=valve_V", "x=pos_mm:mm", '
                             '"pA=pa", "pB=pb"]', source=str(tmp_path / "foreign.csv"))
    assert as_list.dbc == str(tmp_path / "site.dbc")
    as_table = _rig(tmp_path, 'map = { t = "time_ms:ms", x_ref = "dem", u = "valve_V", x = "pos_mm:mm", pA = "pa", '
                              'pB = "pb" }', source=str(tmp_path / "foreign.csv"))
    with open_source(str(here / "data" / "reference.csv")) as src:
        want = src.read_all()
    for rig in (as_list, as_table):
        with open_rig_source(rig) as src:
            got = src.read_all()
        assert set(got.signals) >= set(cols[1:])
        for k in cols[1:]:
            np.testing.assert_allclose(got.signals[k], want.signals[k], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose((got.t_ns - got.t_ns[0]) * 1e-9, (want.t_ns - want.t_ns[0]) * 1e-9, atol=1e-6)


def test_a_spring_held_at_zero_is_held_not_tracked(tmp_path):
    """``k = 0`` in rigs.toml is the oscillator's free mass, as ``twin fit --set k=0``: accepted, held and left out
    of the default tracked parameters (before, the rig failed when it started: 'start value of k (0) is outside its
    physical bounds'); naming it in ``track`` is refused in one line."""
    from twin.models import get_model

    phen = get_model("oscillator").PHENOMENOLOGICAL
    for value in ("0", '"0N/m"'):
        rig = _rig(tmp_path, f'model = "oscillator"\n[rig.params]\nk = {value}\nm = 2.5', source="rig.csv")
        assert rig.params["k"] == 0.0
        assert rig.track == tuple(n for n in phen if n != "k") and "k" not in rig.baseline
    with pytest.raises(ConfigError, match=r"rig 'r'\.track: k is held at exactly 0 by params\.k; a parameter at 0 "
                                          r"is not tracked .*: drop it from track or give it a positive value"):
        _rig(tmp_path, 'model = "oscillator"\ntrack = ["d", "k"]\n[rig.params]\nk = 0', source="rig.csv")
    with pytest.raises(ConfigError, match=r"params: every trackable parameter \(d, k\) is held at 0"):
        _rig(tmp_path, 'model = "oscillator"\n[rig.params]\nk = 0\nd = 0', source="rig.csv")


@pytest.mark.slow
def test_serve_runs_a_free_mass_held_at_k_zero(tmp_path, capsys):
    """The rig with ``k = 0`` runs in the service: every sample read, estimates, no alarm on a record of that rig
    (the oscillator simulated with k = 0, m = 2.5 kg, d = 8 N s/m)."""
    import json

    from net_helpers import free_port

    from twin import cli
    from twin.service.serve import serve

    log = tmp_path / "free_mass.csv"
    assert cli.main(["simulate", "--model", "oscillator", "--set", "k=0,m=2.5,d=8", "--duration", "5",
                     "--seed", "3", "-o", str(log), "-q"]) == 0
    (tmp_path / "rigs.toml").write_text(
        f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{free_port()}"]\n'
        f'[service]\njournal_dir = "{tmp_path / "journal"}"\n'
        f'[[rig]]\nname = "mass"\nmodel = "oscillator"\nsource = "{log}"\nspeed = 0\n'
        '[rig.params]\nk = 0\nm = 2.5\nd = 8\n', encoding="utf-8")
    stats = serve(load_config(str(tmp_path / "rigs.toml")))
    assert stats["mass"].samples == 5000 and stats["mass"].estimates > 0 and stats["mass"].alarms == 0
    # twin track --set k=0 the same (before: 'start value of k (0) is outside its physical bounds')
    assert cli.main(["track", str(log), "--model", "oscillator", "--set", "k=0,m=2.5,d=8", "--out",
                     str(tmp_path / "out"), "--json", "-q"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["samples"] == 5000 and set(out["final"]) == {"d"} and not out["alarms"]
