"""A corpus of bad configurations and invocations of ``twin serve`` and ``twin alarms``.

Each one must end with a non-zero exit and one line that names the file, key or
option and what was expected; never a traceback, never a silent default.
"""

from __future__ import annotations

import signal
import socket
from pathlib import Path

import pytest
import zenoh

from twin import cli
from fpdd.zenohconf import zenoh_config
from net_helpers import free_port

GOOD = """
[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:PORT"]

[service]
journal_dir = "JOURNAL"
estimate_every = 50

[[rig]]
name = "msp25-a"
source = "LOG"
speed = 1.0
track = ["Ffric", "CdAleak"]
[rig.params]
KP = 450
[rig.baseline.Ffric]
value = 60.0
rel_band = 0.5
"""


def edit(old: str, new: str):
    return lambda text: text.replace(old, new, 1)


# (id, edit of GOOD, expected message (regex), whether the message names the config file)
CASES = [
    ("top-level-typo", edit("[service]", "[servce]"), r"unknown key 'servce' \(did you mean 'service'\?\)"),
    ("zenoh-key-typo", edit("listen =", "lisen ="), r"zenoh: unknown key 'lisen' \(did you mean 'listen'\?\)"),
    ("service-key-typo", edit("estimate_every", "estimate_evry"),
     r"service: unknown key 'estimate_evry' \(did you mean 'estimate_every'\?\)"),
    ("rig-key-typo", edit("track =", "trak ="), r"rig 'msp25-a': unknown key 'trak' \(did you mean 'track'\?\)"),
    ("baseline-key-typo", edit("rel_band", "rel_bnd"),
     r"baseline\.Ffric: unknown key 'rel_bnd' \(did you mean 'rel_band'\?\)"),
    ("param-not-a-number", edit("KP = 450", 'KP = "abc"'), r"params\.KP: expected a number or a value with a unit, got 'abc'"),
    ("param-typo", edit("KP = 450", "KPP = 450"), r"params: unknown parameter 'KPP' of model msp25 \(did you mean 'KP'\?\)"),
    ("param-nan", edit("KP = 450", "KP = nan"), r"params\.KP: expected a finite number, got nan"),
    ("param-inf", edit("KP = 450", "KP = inf"), r"params\.KP: expected a finite number, got inf"),
    ("param-out-of-range", edit("KP = 450", "KP = -1"), r"params: KP \(=-1 V/m\) must be in \[0 \.\.\. 100000\] V/m"),
    ("rel-band-negative", edit("rel_band = 0.5", "rel_band = -1"), r"rel_band: must be > 0 \(the band is value/\(1\+rel_band\)"),
    ("rel-band-zero", edit("rel_band = 0.5", "rel_band = 0"), r"rel_band: must be > 0"),
    ("rel-band-nan", edit("rel_band = 0.5", "rel_band = nan"), r"rel_band: expected a finite number, got nan"),
    ("rel-band-string", edit("rel_band = 0.5", 'rel_band = "wide"'), r"rel_band: expected a number, got 'wide'"),
    ("baseline-value-zero", edit("value = 60.0", "value = 0.0"), r"baseline\.Ffric\.value: must be > 0, got 0"),
    ("baseline-band-outside", edit("rel_band = 0.5", "lo = 70.0\nhi = 90.0"),
     r"baseline\.Ffric: the band \[70, 90\] must contain the value 60"),
    ("baseline-both", edit("rel_band = 0.5", "rel_band = 0.5\nlo = 10.0\nhi = 90.0"),
     r"baseline\.Ffric: give either rel_band or lo and hi, not both"),
    ("baseline-untracked", edit("[rig.baseline.Ffric]", "[rig.baseline.Cd]"),
     r"baseline\.Cd: not a tracked parameter \(Ffric, CdAleak\)"),
    ("speed-negative", edit("speed = 1.0", "speed = -1.0"), r"speed: must be >= 0 \(0 = as fast as possible\), got -1"),
    ("speed-inf", edit("speed = 1.0", "speed = inf"), r"speed: expected a finite number, got inf"),
    ("speed-string", edit("speed = 1.0", 'speed = "fast"'), r"speed: expected a number, got 'fast'"),
    ("estimate-every-zero", edit("estimate_every = 50", "estimate_every = 0"), r"service\.estimate_every must be >= 1, got 0"),
    ("estimate-every-float", edit("estimate_every = 50", "estimate_every = 1.5"), r"estimate_every: expected an integer, got 1\.5"),
    ("estimate-every-bool", edit("estimate_every = 50", "estimate_every = true"), r"estimate_every: expected an integer, got True"),
    ("workers-negative", edit("estimate_every = 50", "workers = -1"), r"service\.workers: expected \"auto\" or an integer 0\.\.256"),
    ("workers-string", edit("estimate_every = 50", 'workers = "many"'), r"service\.workers: expected \"auto\" or an integer"),
    ("checkpoint-zero", edit("estimate_every = 50", "checkpoint_s = 0"), r"service\.checkpoint_s: must be > 0 seconds, got 0"),
    ("lag-warn-nan", edit("estimate_every = 50", "lag_warn_s = nan"), r"service\.lag_warn_s: expected a finite number, got nan"),
    ("stale-negative", edit("estimate_every = 50", "stale_s = -1"), r"service\.stale_s: must be >= 0\.05 seconds, got -1"),
    ("mode-unknown", edit('mode = "peer"', 'mode = "mesh"'), r"zenoh\.mode must be peer, client or router, got 'mesh'"),
    ("listen-not-a-list", edit('listen = ["tcp/127.0.0.1:PORT"]', 'listen = "tcp/127.0.0.1:7447"'),
     r"zenoh\.listen: expected a list, got 'tcp/127\.0\.0\.1:7447'"),
    ("listen-port-99999", edit('listen = ["tcp/127.0.0.1:PORT"]', 'listen = ["tcp/127.0.0.1:99999"]'),
     r"zenoh\.listen\[0\]: 'tcp/127\.0\.0\.1:99999': port '99999' is not in 0\.\.65535"),
    ("listen-no-port", edit('listen = ["tcp/127.0.0.1:PORT"]', 'listen = ["tcp/127.0.0.1"]'),
     r"zenoh\.listen\[0\]: 'tcp/127\.0\.0\.1' has no HOST:PORT"),
    ("connect-not-an-endpoint", edit("[service]", 'connect = ["nonsense"]\n[service]'),
     r"zenoh\.connect\[0\]: 'nonsense' is not an endpoint \(expected PROTOCOL/HOST:PORT"),
    ("connect-unknown-protocol", edit("[service]", 'connect = ["foo/1.2.3.4:7447"]\n[service]'),
     r"zenoh\.connect\[0\]: 'foo/1\.2\.3\.4:7447': unknown protocol 'foo'"),
    ("client-listens", edit('mode = "peer"', 'mode = "client"'), r"zenoh\.listen: a client cannot listen"),
    ("no-rig", lambda t: t.split("[[rig]]")[0], r"no \[\[rig\]\]: at least one rig is needed"),
    ("rig-not-an-array", edit("[[rig]]", "[rig]"), r"rig: write \[\[rig\]\] \(an array of tables\), not \[rig\]"),
    ("rig-without-name", edit('name = "msp25-a"\n', ""), r"rig\[0\]: missing key 'name'"),
    ("rig-name-slash", edit('name = "msp25-a"', 'name = "a/b"'), r"rig\[0\]\.name: 'a/b' must be unique"),
    ("rig-without-source", edit('source = "LOG"\n', ""), r"rig 'msp25-a': missing key 'source'"),
    ("source-unknown-format", edit('source = "LOG"', 'source = "rig.xyz"'),
     r"source: 'rig\.xyz' is not a log of a known format"),
    ("source-unknown-scheme", edit('source = "LOG"', 'source = "ftp://host/rig"'),
     r"source: 'ftp://host/rig' is not can://INTERFACE/CHANNEL or zenoh://KEYEXPR"),
    ("source-missing", edit('source = "LOG"', 'source = "MISSING.mcap"'), r"rig 'msp25-a'\.source: '.*missing\.mcap' does not exist"),
    ("track-empty", edit('track = ["Ffric", "CdAleak"]', "track = []"), r"track: the list is empty"),
    ("track-unknown", edit('track = ["Ffric", "CdAleak"]', 'track = ["Ffric", "CdAlek"]'),
     r"track: \['CdAlek'\] not among the trackable .* \(did you mean 'CdAleak'\?\)"),
    ("track-twice", edit('track = ["Ffric", "CdAleak"]', 'track = ["Ffric", "Ffric"]'), r"names a parameter twice"),
    ("model-unknown", edit('speed = 1.0', 'speed = 1.0\nmodel = "msp26"'),
     r"model: 'msp26' is not a model the online twin runs; it runs msp25"),
    ("model-params-of-another-model", edit('speed = 1.0', 'speed = 1.0\nmodel = "oscillator"'),
     r"rig 'msp25-a'\.params: unknown parameter 'KP' of model oscillator \(known: m, d, k\)"),
    ("commission-s-short", edit("speed = 1.0", "speed = 1.0\ncommission_s = 2"),
     r"rig 'msp25-a'\.commission_s: must be >= 5 seconds \(the commissioning fit needs a few periods of the "
     r"demand\), got 2"),
    ("commission-s-string", edit("speed = 1.0", 'speed = 1.0\ncommission_s = "2min"'),
     r"rig 'msp25-a'\.commission_s: expected a number, got '2min'"),
    ("commission-s-typo", edit("speed = 1.0", "speed = 1.0\ncommision_s = 60"),
     r"unknown key 'commision_s' \(did you mean 'commission_s'\?\)"),
    ("commission-both", edit("speed = 1.0", 'speed = 1.0\ncommission_s = 60\ncommission = "fit.json"'),
     r"rig 'msp25-a': give either commission \(a saved fit\) or commission_s \(commission on the first seconds in "
     r"service\), not both"),
    ("journal-dir-empty", edit('journal_dir = "JOURNAL"', 'journal_dir = ""'),
     r"service\.journal_dir: expected a directory path, got an empty string"),
    ("journal-dir-under-a-file", edit('journal_dir = "JOURNAL"', 'journal_dir = "AFILE/journal"'),
     r"service\.journal_dir: '.*afile/journal' cannot be a directory: '.*afile' is a file"),
    ("out-dir-under-a-file", edit("estimate_every = 50", 'out_dir = "AFILE/out"'),
     r"service\.out_dir: '.*afile/out' cannot be a directory: '.*afile' is a file"),
    # values that would start a service that never works (a dead thread, a hang, a band that cannot alarm)
    ("speed-1e308", edit("speed = 1.0", "speed = 1e308"),
     r"speed: 1e\+308; expected 0 \(as fast as possible\) or 0\.001 to 10000 times real time"),
    ("speed-1e-300", edit("speed = 1.0", "speed = 1e-300"), r"speed: 1e-300; expected 0 .* or 0\.001 to 10000"),
    ("controller-1e12", edit("speed = 1.0", 'speed = 1.0\ncontroller = "digital:1e12"'),
     r"controller: a digital controller at 1e\+12 Hz; at most 100000 Hz"),
    ("rel-band-1e308", edit("rel_band = 0.5", "rel_band = 1e308"),
     r"baseline\.Ffric: the band's upper edge 6e\+309|baseline\.Ffric: the band's (upper|lower) edge .* is beyond "
     r"what the twin can estimate"),
    ("rel-band-100", edit("rel_band = 0.5", "rel_band = 100.0"),
     r"baseline\.Ffric: the band's (upper|lower) edge .* is beyond what the twin can estimate .*: that side could "
     r"never alarm"),
    ("rig-name-300", edit('name = "msp25-a"', f'name = "{"r" * 300}"'), r"rig\[0\]\.name: 'r+'\.\.\. has 300 "
     r"characters, at most 64"),
    ("journal-dir-nul", edit('journal_dir = "JOURNAL"', 'journal_dir = "JOURNAL\\u0000x"'),
     r"service\.journal_dir: control character '\\x00' at position \d+ of the path"),
    ("journal-dir-5000", edit('journal_dir = "JOURNAL"', f'journal_dir = "JOURNAL/{"a" * 5000}"'),
     r"service\.journal_dir: path of \d+ characters, at most 4096"),
    ("source-nul", edit('source = "LOG"', 'source = "LOG\\u0000.mcap"'), r"\.source: control character '\\x00'"),
    ("source-component-300", edit('source = "LOG"', f'source = "{"s" * 300}.mcap"'),
     r"\.source: a path component of 305 bytes .*, at most 255"),
    ("can-unknown-interface", edit('source = "LOG"', 'source = "can://nosuchbus/0"'),
     r"\.source: can://nosuchbus/0: unknown CAN interface 'nosuchbus'; python-can knows .*socketcan"),
    ("can-interface-typo", edit('source = "LOG"', 'source = "can://virtul/rig1"'),
     r"unknown CAN interface 'virtul' \(did you mean 'virtual'\?\)"),
    ("zenoh-own-outputs", edit('source = "LOG"', 'source = "zenoh://fpdd/**"'),
     r"\.source: 'zenoh://fpdd/\*\*' would read the service's own outputs \(fpdd/\*/estimate\)"),
    ("zenoh-own-alarms", edit('source = "LOG"', 'source = "zenoh://fpdd/*/alarm/**"'),
     r"would read the service's own outputs \(fpdd/\*/alarm\)"),
    ("zenoh-bad-keyexpr", edit('source = "LOG"', 'source = "zenoh://a//b"'),
     r"\.source: 'zenoh://a//b': not a valid Zenoh key expression"),
    ("checkpoint-1e308", edit("estimate_every = 50", "checkpoint_s = 1e308"),
     r"service\.checkpoint_s: 1e\+308 seconds; at most 3600"),
    ("toml-nested-too-deep", lambda t: "a = " + "[" * 5000 + "]" * 5000 + "\n", r"nested too deeply"),
]


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    log = tmp_path / "rig.mcap"
    log.write_bytes(b"")  # exists: the configuration errors come first
    afile = tmp_path / "afile"
    afile.write_text("a regular file")
    return {"LOG": log, "JOURNAL": tmp_path / "journal", "AFILE": afile, "MISSING": tmp_path / "missing",
            "root": tmp_path}


def render(text: str, files: dict[str, Path], port: int) -> str:
    for key in ("LOG", "JOURNAL", "AFILE", "MISSING"):
        text = text.replace(key, str(files[key]))
    return text.replace("PORT", str(port))


def one_line_error(capsys, command: str) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith(f"twin {command}: error:")]
    assert "Traceback" not in err, err
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.parametrize("name, change, message", CASES, ids=[c[0] for c in CASES])
def test_bad_rigs_toml(files, capsys, name, change, message) -> None:
    path = files["root"] / "rigs.toml"
    path.write_text(render(change(GOOD), files, free_port()))
    assert cli.main(["serve", "--config", str(path)]) == 2
    line = one_line_error(capsys, "serve")
    assert str(path) in line
    assert __import__("re").search(message, line), line


def test_generated_configurations(tmp_path: Path) -> None:
    """The configuration corpus of ``python -m benchmarks.damage`` (>= 80): every valid one loads, every bad one
    is refused with one line naming the file and the key; none is accepted silently, none raises anything else."""
    from benchmarks import damage
    from fpdd.errors import ConfigError
    from twin.service.config import load_config

    log = tmp_path / "rig.mcap"
    log.write_bytes(b"")
    cases = damage.configs()
    assert len(cases) >= 80 and len({c.id for c in cases}) == len(cases)
    wrong = []
    for case in cases:
        path = tmp_path / f"{case.id}.toml"
        path.write_text(case.text.replace("JOURNAL", str(tmp_path / "journal")).replace("LOG", str(log))
                        .replace("ROOT", str(tmp_path)), encoding="utf-8")
        try:
            load_config(str(path))
        except ConfigError as exc:
            if case.valid or "\n" in str(exc) or str(path) not in str(exc):
                wrong.append(f"{case.id}: {exc}")
        else:
            if not case.valid:
                wrong.append(f"{case.id}: accepted")
    assert not wrong, "\n".join(wrong)


def test_commission_s_flag_too_short(files, capsys) -> None:
    path = files["root"] / "rigs.toml"
    path.write_text(render(GOOD, files, free_port()))
    assert cli.main(["serve", "--config", str(path), "--commission-s", "1"]) == 2
    assert one_line_error(capsys, "serve") == "twin serve: error: --commission-s: must be >= 5 seconds, got 1"


@pytest.mark.parametrize("content, message", [
    ("missing", r"missing\.toml: cannot read the configuration \(No such file or directory\)"),
    ("directory", r"rigs\.toml: cannot read the configuration \(Is a directory\)"),
    ("utf16", r"rigs\.toml: the configuration is UTF-16 text; TOML must be UTF-8"),
    ("binary", r"rigs\.toml: not UTF-8 text \(byte 3: b'\\xff'\); TOML must be UTF-8"),
    ("toml", r"rigs\.toml: not valid TOML \(Expected ']]' at the end of an array declaration \(at line 1"),
], ids=["missing", "directory", "utf16", "binary", "toml"])
def test_unreadable_configurations(files, capsys, content, message) -> None:
    path = files["root"] / "rigs.toml"
    if content == "missing":
        path = files["root"] / "missing.toml"
    elif content == "directory":
        path.mkdir()
    elif content == "utf16":
        path.write_bytes(render(GOOD, files, 7447).encode("utf-16"))
    elif content == "binary":
        path.write_bytes(b"abc\xff\x80 garbage")
    else:
        path.write_text("[[rig]\nname =")
    assert cli.main(["serve", "--config", str(path)]) == 2
    assert __import__("re").search(message, one_line_error(capsys, "serve"))


def test_listen_port_in_use(files, capsys) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        path = files["root"] / "rigs.toml"
        path.write_text(render(GOOD, files, port))
        handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
        assert cli.main(["serve", "--config", str(path)]) == 2
        assert {sig: signal.getsignal(sig) for sig in handlers} == handlers  # the caller's, as they were
    line = one_line_error(capsys, "serve")
    assert f"cannot listen on tcp/127.0.0.1:{port}: the address is already in use" in line


def test_router_unreachable_at_start(files, capsys) -> None:
    port = free_port()
    path = files["root"] / "rigs.toml"
    path.write_text(render(GOOD, files, 0).replace('mode = "peer"', 'mode = "client"')
                    .replace('listen = ["tcp/127.0.0.1:0"]', f'connect = ["tcp/127.0.0.1:{port}"]'))
    assert cli.main(["serve", "--config", str(path)]) == 2
    assert f"cannot reach tcp/127.0.0.1:{port}: nothing answers there" in one_line_error(capsys, "serve")


@pytest.mark.parametrize("zenoh_file, message", [
    (None, r"ZENOH_CONFIG=.*nothere\.json5: cannot read the Zenoh configuration: does not exist"),
    ("{mode: 'client', connect: {endpoints: [", r"ZENOH_CONFIG=.*zenoh\.json5: invalid Zenoh configuration"),
], ids=["missing", "garbage"])
def test_bad_zenoh_config_file_for_serve(files, capsys, monkeypatch, zenoh_file, message) -> None:
    target = files["root"] / ("zenoh.json5" if zenoh_file else "nothere.json5")
    if zenoh_file:
        target.write_text(zenoh_file)
    monkeypatch.setenv("ZENOH_CONFIG", str(target))
    path = files["root"] / "rigs.toml"
    path.write_text(render(GOOD, files, free_port()))
    assert cli.main(["serve", "--config", str(path)]) == 2
    assert __import__("re").search(message, one_line_error(capsys, "serve"))


# --------------------------------------------------------------------------- twin alarms


@pytest.mark.parametrize("argv, message", [
    (["--connect", "nonsense"], r"--connect: 'nonsense' is not an endpoint \(expected PROTOCOL/HOST:PORT"),
    (["--connect", "tcp/127.0.0.1:99999"], r"--connect: 'tcp/127\.0\.0\.1:99999': port '99999' is not in 1\.\.65535"),
    (["--zenoh-config", "/nonexistent/observer.json5"], r"/nonexistent/observer\.json5: cannot read the Zenoh configuration"),
    (["--rig", "a/b", "--connect", "tcp/127.0.0.1:1"], r"rig: 'a/b' is not a valid rig id"),
], ids=["endpoint", "port", "zenoh-file", "rig"])
def test_bad_alarms_invocations(capsys, argv, message) -> None:
    assert cli.main(["alarms", *argv]) == 2
    assert __import__("re").search(message, one_line_error(capsys, "alarms"))


@pytest.mark.parametrize("argv, message", [
    (["--since", "yesterday"], r"--since: 'yesterday' is not an ISO 8601 time"),
    (["--count", "0"], r"--count: 0 must be >= 1"),
    (["--wait", "-1"], r"--wait: -1\.0 must be a number of seconds >= 0"),
    (["--mode", "router"], r"--mode: invalid choice: 'router'"),
], ids=["since", "count", "wait", "mode"])
def test_bad_alarms_options_are_usage_errors(capsys, argv, message) -> None:
    with pytest.raises(SystemExit) as info:
        cli.main(["alarms", *argv])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and __import__("re").search(message, err.splitlines()[-1])


def test_alarms_with_a_file_in_client_mode_and_no_router(capsys, tmp_path) -> None:
    """The file's mode is kept (no --mode default overrides it): a client that finds no router says where."""
    port = free_port()
    observer = tmp_path / "observer.json5"
    observer.write_text(f'{{mode: "client", connect: {{endpoints: ["tcp/127.0.0.1:{port}"]}}, '
                        'scouting: {multicast: {enabled: false}}}')
    assert cli.main(["alarms", "--zenoh-config", str(observer)]) == 2
    assert f"cannot reach tcp/127.0.0.1:{port}: nothing answers there" in one_line_error(capsys, "alarms")


def test_alarms_with_no_twin_gives_up_after_the_wait(capsys) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config(listen=[endpoint])):
        assert cli.main(["alarms", "--connect", endpoint, "--wait", "0.3"]) == 2
    line = one_line_error(capsys, "alarms")
    assert f"no twin reachable through {endpoint} within 0.3 s (no liveliness token on fpdd/*/twin)" in line
