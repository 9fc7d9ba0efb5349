"""rigs.toml ``map`` wherever the source's reader takes one: CSV, text and MATLAB files, CAN logs and ``can://``
buses; refused, in one line naming the key, for sources that name their signals themselves (MCAP, ``zenoh://``).
``twin serve`` runs a BLF log (python-can's writer) of another vendor's DBC through the map, on loopback Zenoh."""

from __future__ import annotations

import json
import threading
import time

import pytest

from fpdd.errors import ConfigError
from twin.service.config import load_config

MAP = 'map = { x = "MyPosSignal:mm", x_ref = "MyDemand", u = "ValveCmd", pA = "ChamberA", pB = "ChamberB" }'


def _rig(tmp_path, source: str, lines: str = MAP):
    p = tmp_path / "rigs.toml"
    p.write_text(f'[[rig]]\nname = "r"\nsource = "{source}"\n{lines}\n', encoding="utf-8")
    return load_config(str(p)).rigs[0]


@pytest.mark.parametrize("source", ["rig.blf", "rig.asc", "rig.mat", "rig.txt", "rig.tsv", "rig.csv.gz",
                                    "can://virtual/vendor"])
def test_map_is_accepted_wherever_the_reader_takes_one(tmp_path, source):
    """Before, every source but a CSV file was refused ('renames CSV columns; the source is not a CSV log')."""
    rig = _rig(tmp_path, source)
    assert rig.map == ("x=MyPosSignal:mm", "x_ref=MyDemand", "u=ValveCmd", "pA=ChamberA", "pB=ChamberB")
    assert rig.source_options()["mapping"]["MyPosSignal"][0] == "x"


@pytest.mark.parametrize("source", ["rig.mcap", "zenoh://fpdd/r/samples"])
def test_map_is_refused_where_the_source_names_its_signals(tmp_path, source):
    with pytest.raises(ConfigError, match=rf"rig 'r'\.map: maps the columns of CSV, text and MATLAB files and the "
                                          rf"signals of CAN logs and can:// buses; the source '{source}' names its "
                                          r"signals itself"):
        _rig(tmp_path, source)


@pytest.mark.slow
def test_serve_tracks_a_vendor_can_log_mapped_in_rigs_toml(tmp_path, hub, endpoint, capsys):
    """A BLF of another vendor's DBC (names, mm, mV, bar) mapped in rigs.toml: ``twin serve`` reads every sample
    through the map and its estimates arrive on the bus (loopback, explicit endpoint, scouting off)."""
    from test_can_formats import _foreign_dbc, _foreign_log

    from twin import cli
    from twin.models import msp25 as M
    from twin.models.scenario import simulate_wear
    from twin.models.simulate import excite

    _, xr = excite(M.MODEL, 3.0, 1e-3, seed=5)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [], noise={"x": 2e-6, "pA": 2e4, "pB": 2e4}, seed=5)
    samples = rec.to_samples()
    dbc = _foreign_dbc(tmp_path / "vendor.dbc")
    log = _foreign_log(tmp_path / "vendor.blf", dbc, samples)
    (tmp_path / "rigs.toml").write_text(
        f'[zenoh]\nmode = "peer"\nconnect = ["{endpoint}"]\n'
        f'[service]\njournal_dir = "{tmp_path / "journal"}"\nestimate_every = 100\n'
        f'[[rig]]\nname = "vendor"\nsource = "{log}"\ndbc = "vendor.dbc"\nspeed = 2.0\n{MAP}\n',
        encoding="utf-8")
    got: list[dict] = []
    arrived = threading.Event()

    def on_estimate(s):
        got.append(json.loads(s.payload.to_string()))
        arrived.set()

    sub = hub.declare_subscriber("fpdd/vendor/estimate", on_estimate)
    try:
        assert cli.main(["serve", "--config", str(tmp_path / "rigs.toml"), "--json", "-q"]) == 0
        stats = json.loads(capsys.readouterr().out)
        assert arrived.wait(10.0), "no estimate arrived on fpdd/vendor/estimate"
        time.sleep(0.2)  # let the last ones in flight land (not asserted on)
    finally:
        sub.undeclare()
    assert stats["vendor"]["samples"] == len(samples)
    assert stats["vendor"]["estimates"] > 0
    assert {e["rig"] for e in got} == {"vendor"}
    assert set(got[-1]["params"]) == set(M.MODEL.PHENOMENOLOGICAL)
    assert all(p["value"] > 0 for p in got[-1]["params"].values())
