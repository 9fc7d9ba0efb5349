"""Rig configuration: defaults, bands, and errors that name the file and the key."""

from __future__ import annotations

import pytest

from twin.config import load_config, parse_config
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
