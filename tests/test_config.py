"""Rig configuration: defaults, bands, and errors that name the file and the key."""

from __future__ import annotations

import pytest

from twin.service.config import load_config, parse_config
from twin.errors import ConfigError

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
