"""The pure rigs.toml parser: TOML text in memory into plain dataclasses, no model consulted and no file opened
but the text; each bad key or value one line naming the file, the rig and the key."""

from __future__ import annotations

import pytest

from fpdd.errors import ConfigError
from twin.models import DEFAULT_MODEL
from twin.service.config import parse_config
from twin.service.config_parse import ParsedBand, parse_doc, parse_text

PATH = "/site/rigs.toml"
RIG = '[[rig]]\nname = "a"\nsource = "rig.csv"\n'


def parse(text: str):
    return parse_text(text, PATH)


def test_a_minimal_rig_takes_the_defaults():
    cfg = parse(RIG)
    assert (cfg.path, cfg.zenoh_mode, cfg.listen, cfg.connect) == (PATH, None, (), ())
    assert (cfg.estimate_every, cfg.workers, cfg.checkpoint_s, cfg.block_s, cfg.lag_warn_s, cfg.stale_s) == (
        50, None, 1.0, 0.1, 1.0, 1.0)
    assert cfg.journal_dir.endswith("fpdd-journal") and cfg.out_dir is None and cfg.failover is None
    (rig,) = cfg.rigs
    assert (rig.name, rig.model, rig.source, rig.where) == ("a", DEFAULT_MODEL, "rig.csv", f"{PATH}: rig 'a'")
    assert (rig.track, rig.params, rig.baseline, rig.noise, rig.timing) == (None, {}, {}, {}, None)
    assert (rig.speed, rig.dbc, rig.map, rig.commission, rig.commission_s, rig.forecast_horizon_s) == (
        1.0, None, (), None, None, 3600.0)


def test_values_are_kept_as_written_for_the_resolver():
    """Quantities stay as the text has them (a unit string, an integer): the model names their unit later."""
    cfg = parse('[zenoh]\nmode = "client"\nconnect = ["tcp/10.0.0.2:7447"]\n'
                '[service]\nworkers = 2\nestimate_every = 10\nsigning_keys = "keys"\n'
                '[[rig]]\nname = "hall-1.a"\nmodel = "oscillator"\nsource = "log.csv"\nspeed = 0\n'
                'track = ["d", "k"]\ncontroller = "digital:5000"\nintersample = "foh"\n'
                'map = { x = "pos_mm:mm", t = "time:ms" }\ncommission = "fit.json"\nforecast_horizon_s = 60\n'
                'noise = { x = "2um" }\n'
                '[rig.params]\nk = 400\nm = "2.5kg"\n'
                '[rig.baseline.k]\nlo = "300N/m"\nhi = 500.0\n[rig.baseline.d]\nvalue = 3.0\nrel_band = 0.5\n'
                '[[rig]]\nname = "b"\nsource = "can://socketcan/can0"\ncommission_s = 60\n')
    assert (cfg.zenoh_mode, cfg.connect, cfg.workers, cfg.estimate_every, cfg.signing_keys) == (
        "client", ("tcp/10.0.0.2:7447",), 2, 10, "keys")
    a, b = cfg.rigs
    assert (a.model, a.speed, a.track, a.commission, a.forecast_horizon_s) == ("oscillator", 0.0, ("d", "k"),
                                                                               "fit.json", 60.0)
    assert a.params == {"k": 400, "m": "2.5kg"} and type(a.params["k"]) is int
    assert a.noise == {"x": "2um"} and a.map == ("x=pos_mm:mm", "t=time:ms")
    assert a.baseline == {"k": ParsedBand(lo="300N/m", hi=500.0), "d": ParsedBand(value=3.0, rel_band=0.5)}
    assert a.timing is not None and (a.timing.controller, a.timing.rate_hz, a.timing.intersample) == (
        "digital", 5000.0, "foh")
    assert (b.source, b.commission_s, b.commission) == ("can://socketcan/can0", 60.0, None)


def test_the_parser_opens_no_file_and_asks_no_model():
    """What only the model or a file can judge passes the parser and is refused by the resolver."""
    text = (RIG + 'model = "nosuch"\ncommission = "missing.json"\ndbc = "missing.dbc"\ntrack = ["q"]\n'
            'noise = { q = "1 furlong" }\n[rig.params]\nnosuch = "7 parsecs"\n[rig.baseline.zz]\nvalue = -1\n')
    rig = parse(text).rigs[0]
    assert (rig.model, rig.commission, rig.dbc, rig.track) == ("nosuch", "missing.json", "missing.dbc", ("q",))
    assert rig.params == {"nosuch": "7 parsecs"} and rig.noise == {"q": "1 furlong"}
    assert rig.baseline == {"zz": ParsedBand(value=-1)}
    import tomllib

    with pytest.raises(ConfigError, match=r"^/site/rigs\.toml: rig 'a'\.model: 'nosuch' is not a model the online"):
        parse_config(tomllib.loads(text), PATH)


BAD = [
    # the text and the tables
    ("[[rig]\nname=", r"not valid TOML"),
    ("", r"no \[\[rig\]\]: at least one rig is needed"),
    ("rig = []", r"at least one \[\[rig\]\] is needed"),
    ('[rig]\nname = "a"', r"rig: write \[\[rig\]\] \(an array of tables\), not \[rig\]"),
    ("rig = 3", r"rig: expected \[\[rig\]\] tables, got 3"),
    ("[zenoh]\nmod = 1\n" + RIG, r"zenoh: unknown key 'mod' \(did you mean 'mode'\?\)"),
    ("[rigs]\n" + RIG, r"unknown key 'rigs' \(did you mean 'rig'\?\)"),
    # [zenoh] and [service]
    ('[zenoh]\nmode = "mesh"\n' + RIG, r"zenoh\.mode must be peer, client or router, got 'mesh'"),
    ('[zenoh]\nmode = "client"\nlisten = ["tcp/127.0.0.1:7447"]\n' + RIG, r"zenoh\.listen: a client cannot listen"),
    ("[zenoh]\nlisten = [1]\n" + RIG, r"zenoh\.listen\[0\]: expected a string, got 1"),
    ("[service]\nestimate_every = 0\n" + RIG, r"service\.estimate_every must be >= 1, got 0"),
    ("[service]\nestimate_every = 2000000\n" + RIG, r"service\.estimate_every: 2000000 samples; at most 1000000"),
    ("[service]\nworkers = -1\n" + RIG, r"service\.workers: expected \"auto\" or an integer 0\.\.256"),
    ("[service]\nworkers = true\n" + RIG, r"service\.workers: expected \"auto\" or an integer 0\.\.256"),
    ('[service]\njournal_dir = " "\n' + RIG, r"service\.journal_dir: expected a directory path, got an empty"),
    ("[service]\nblock_s = 20\n" + RIG, r"service\.block_s: 20 seconds; at most 10 \(the latency"),
    ("[service]\ncheckpoint_s = 0\n" + RIG, r"service\.checkpoint_s: must be > 0 seconds, got 0"),
    ("[service]\nstale_s = nan\n" + RIG, r"service\.stale_s: expected a finite number, got nan"),
    # [[rig]]: name, keys, paths and sources
    ("[[rig]]\nname = \"a\"\n", r"rig 'a': missing key 'source'"),
    ("rig = [3]", r"rig\[0\]: expected a table"),
    ('[[rig]]\nname = "a/b"\nsource = "r.csv"\n', r"rig\[0\]\.name: 'a/b' must be unique"),
    (RIG + RIG, r"rig\[1\]\.name: 'a' must be unique"),
    (f'[[rig]]\nname = "{"n" * 65}"\nsource = "r.csv"\n', r"rig\[0\]\.name: 'nnnnnnnnnnnnnnnnnnnn'\.\.\. has 65 "),
    (RIG + "trak = []", r"rig 'a': unknown key 'trak' \(did you mean 'track'\?\)"),
    (RIG + "model = 3", r"rig 'a'\.model: expected a string, got 3"),
    ('[[rig]]\nname = "a"\nsource = ""\n', r"rig 'a'\.source: expected a log file, can://INTERFACE/CHANNEL or"),
    ('[[rig]]\nname = "a"\nsource = "rig.xyz"\n', r"rig 'a'\.source: 'rig\.xyz' is not a log of a known format"),
    ('[[rig]]\nname = "a"\nsource = "http://x/y"\n', r"rig 'a'\.source: 'http://x/y' is not can://INTERFACE"),
    ('[[rig]]\nname = "a"\nsource = "zenoh://fpdd/**"\n', r"rig 'a'\.source: 'zenoh://fpdd/\*\*' would read the "
                                                           r"service's own outputs"),
    ('[[rig]]\nname = "a"\nsource = "rig.mcap"\nmap = ["x=pos_mm:mm"]\n', r"rig 'a'\.map: maps the columns of CSV"),
    (RIG + "map = { x = 3 }", r"rig 'a'\.map\.x: expected \"COLUMN\[:UNIT\]\[\*GAIN\]\[\+OFFSET\]\", got 3"),
    (RIG + 'map = ["pos_mm=x:mm"]', r"rig 'a'\.map item 'pos_mm=x:mm': 'pos_mm' is not a signal name"),
    (RIG + 'dbc = "a\\u0001b.dbc"', r"rig 'a'\.dbc: control character '\\x01' at position 1 of the path"),
    (RIG + f'commission = "{"c" * 300}.json"', r"rig 'a'\.commission: a path component of 305 bytes"),
    # [[rig]]: numbers, lists, timing
    (RIG + "speed = -1", r"rig 'a'\.speed: must be >= 0 \(0 = as fast as possible\), got -1"),
    (RIG + "speed = 1e5", r"rig 'a'\.speed: 100000; expected 0 \(as fast as possible\) or 0\.001 to 10000"),
    (RIG + "forecast_horizon_s = 0", r"rig 'a'\.forecast_horizon_s: must be > 0 seconds"),
    (RIG + "commission_s = 1", r"rig 'a'\.commission_s: must be >= 5 seconds \(the commissioning fit needs"),
    (RIG + 'commission = "f.json"\ncommission_s = 60', r"rig 'a': give either commission \(a saved fit\) or"),
    (RIG + "track = [1]", r"rig 'a'\.track\[0\]: expected a string, got 1"),
    (RIG + 'track = "Ffric"', r"rig 'a'\.track: expected a list, got 'Ffric'"),
    (RIG + 'controller = "digital:abc"', r"rig 'a'\.controller: controller 'digital:abc': the rate after"),
    (RIG + 'controller = "digital:1e6"', r"rig 'a'\.controller: a digital controller at 1e\+06 Hz; at most 100000"),
    (RIG + "signing_key = 1", r"rig 'a'\.signing_key: expected a string, got 1"),
    # quantities: their form here, their unit and bounds the model's
    (RIG + "params = 3", r"rig 'a'\.params: expected a table, got 3"),
    (RIG + "[rig.params]\nKP = true", r"rig 'a'\.params\.KP: expected a number, got True"),
    (RIG + "[rig.params]\nKP = inf", r"rig 'a'\.params\.KP: expected a finite number, got inf"),
    (RIG + "noise = { x = [1] }", r"rig 'a'\.noise\.x: expected a number, got \[1\]"),
    (RIG + "[rig.baseline]\nFfric = 3", r"rig 'a'\.baseline\.Ffric: expected a table with value and rel_band"),
    (RIG + "[rig.baseline.Ffric]\nval = 3", r"rig 'a'\.baseline\.Ffric: unknown key 'val' \(did you mean 'value'"),
    (RIG + "[rig.baseline.Ffric]\nrel_band = 0.2\nlo = 1", r"baseline\.Ffric: give either rel_band or lo and hi"),
    (RIG + "[rig.baseline.Ffric]\nrel_band = 0", r"baseline\.Ffric\.rel_band: must be > 0 \(the band is value"),
    (RIG + '[rig.baseline.Ffric]\nrel_band = "wide"', r"baseline\.Ffric\.rel_band: expected a number, got 'wide'"),
    (RIG + "[rig.baseline.Ffric]\nvalue = false", r"baseline\.Ffric\.value: expected a number, got False"),
]


@pytest.mark.parametrize("text, message", BAD, ids=[m[:40] for _, m in BAD])
def test_a_bad_key_or_value_is_one_line_naming_the_file_and_the_key(text, message):
    with pytest.raises(ConfigError) as info:
        parse(text)
    line = str(info.value)
    assert "\n" not in line and line.startswith(f"{PATH}: "), line
    assert __import__("re").search(message, line), line


def test_a_document_parses_as_its_text_does():
    """``parse_doc`` (the tables of a TOML document, as tests and tools build them) and ``parse_text`` agree."""
    import tomllib

    text = RIG + 'track = ["Ffric"]\n[rig.baseline.Ffric]\nvalue = "50N"\nrel_band = 0.3\n'
    assert parse_doc(tomllib.loads(text), PATH) == parse(text)
