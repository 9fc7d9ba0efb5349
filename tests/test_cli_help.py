"""``twin --help`` and every subcommand's ``--help`` build their parser without importing the heavy libraries
(numba, scipy, matplotlib, mcap, python-can): each command imports them when it runs."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from twin.cli import COMMANDS

HEAVY = ("numba", "scipy", "matplotlib", "mcap", "can", "filterpy")
PROBE = """
import json, sys
from twin import cli
try:
    cli.main({argv!r})
except SystemExit:
    pass
print(json.dumps(sorted(m for m in {heavy!r} if m in sys.modules)))
"""


@pytest.mark.parametrize("command", ["", *COMMANDS])
def test_help_imports_no_heavy_library(command):
    argv = [a for a in (command, "--help") if a]
    r = subprocess.run([sys.executable, "-c", PROBE.format(argv=argv, heavy=HEAVY)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    loaded = json.loads(r.stdout.strip().splitlines()[-1])
    assert loaded == [], f"twin {command} --help imported {loaded}"


@pytest.mark.parametrize("module", ["twin.online.tracker", "twin.service.fleet", "twin.service.rig"])
def test_the_online_path_imports_neither_filterpy_nor_scipy(module):
    """The tracker and a worker's start-up import numba but neither filterpy (its sigma-point weights are
    twin.online.sigma's) nor scipy's subpackages (the gate's chi-square quantile is twin.online.chi2's; numba
    itself imports only scipy's top level): every spawned worker would pay them again."""
    heavy = ("filterpy", "scipy.stats", "scipy.special", "scipy.optimize", "scipy.linalg", "scipy.signal",
             "scipy.interpolate", "matplotlib")
    probe = f"import json, sys, {module}; print(json.dumps(sorted(m for m in {heavy!r} if m in sys.modules)))"
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1]) == []


RST = __import__("re").compile(r"``|:(mod|func|class|meth|attr|data|ref):`|^\s*\.\. [a-z]+::", __import__("re").M)


@pytest.mark.parametrize("argv", [["twin", c] for c in ("", *COMMANDS)]
                         + [["replay", c] for c in ("", "info", "convert", "play", "record")])
def test_help_texts_are_plain_text(argv, capsys):
    """What --help prints is read in a terminal: no reStructuredText markup (``x``, :mod:`x`, .. note::)."""
    from replay import cli as replay_cli
    from twin import cli as twin_cli

    main = twin_cli.main if argv[0] == "twin" else replay_cli.main
    with pytest.raises(SystemExit) as info:
        main([a for a in (argv[1], "--help") if a])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage:") and RST.search(out) is None, RST.search(out)


def test_params_table_shows_bounds_in_display_units(capsys):
    from twin import cli

    assert cli.main(["params"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:5] == ["parameter", "value", "min", "max", "unit"]
    wn = next(line.split() for line in lines if line.startswith("wn "))
    assert wn[2:5] == ["1", "1000", "Hz"]  # bounds 2 pi .. 2000 pi rad/s, in Hz
    leak = next(line.split() for line in lines if line.startswith("CdAleak "))
    assert leak[2:5] == ["1e-08", "10", "mm^2"]


@pytest.mark.slow
def test_amplitude_takes_units(tmp_path, capsys):
    """--amplitude 5mm is the same experiment as --amplitude 0.005 (SI); a wrong unit is one line."""
    from twin import cli

    for name, amp in (("mm.csv", "5mm"), ("si.csv", "0.005")):
        assert cli.main(["-q", "simulate", "-o", str(tmp_path / name), "--duration", "0.5", "--amplitude", amp]) == 0
    assert (tmp_path / "mm.csv").read_text() == (tmp_path / "si.csv").read_text()
    capsys.readouterr()
    assert cli.main(["-q", "simulate", "-o", str(tmp_path / "x.csv"), "--amplitude", "5kg"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["twin simulate: error: --amplitude (x_ref): '5kg' is not in a unit of m (expected e.g. 2um)"]


@pytest.mark.parametrize("command", ["", "info", "convert", "play", "record"])
def test_replay_help_imports_no_heavy_library_nor_package_metadata(command):
    probe = ("import json, sys\nfrom replay import cli\ntry:\n    cli.main({argv!r})\nexcept SystemExit:\n    pass\n"
             "print(json.dumps(sorted(m for m in ('importlib.metadata', *{heavy!r}) if m in sys.modules)))")
    argv = [a for a in (command, "--help") if a]
    r = subprocess.run([sys.executable, "-c", probe.format(argv=argv, heavy=HEAVY)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1]) == [], f"replay {command} --help"


def test_one_flag_convention_in_both_commands(tmp_path, capsys):
    """--for (old name --timeout) runs for S seconds and --wait waits for the other side in twin alarms and
    twin top alike; replay play waits with --wait too; -q goes after any subcommand; -o/--out names the output;
    a Zenoh endpoint is --zenoh-connect everywhere."""
    from replay import cli as replay_cli
    from twin import cli as twin_cli

    def parsed(command: str, *flags: str):
        return twin_cli.build_parser([command]).parse_args([command, *flags])

    for command, run_for in (("alarms", "timeout"), ("top", "duration")):
        a = parsed(command, "--timeout", "7", "--wait", "3", "--zenoh-connect", "tcp/127.0.0.1:7447")
        b = parsed(command, "--for", "7", "--wait", "3", "--connect", "tcp/127.0.0.1:7447")
        assert getattr(a, run_for) == getattr(b, run_for) == 7.0 and a.wait == b.wait == 3.0, command
        assert a.connect == b.connect == ["tcp/127.0.0.1:7447"], command
    assert parsed("simulate", "--out", "a.csv").output == parsed("simulate", "-o", "a.csv").output == "a.csv"
    play = replay_cli.build_parser().parse_args(["play", "x.csv", "--to", "zenoh", "--wait", "0.5", "--speed", "0"])
    assert play.wait_s == 0.5 and play.speed == float("inf")  # --speed 0: as fast as possible, as twin demo
    assert parsed("demo", "--speed", "0").speed == 0.0
    log = tmp_path / "a.csv"
    log.write_text("t,x\n" + "".join(f"{i * 1e-3!r},{i * 1e-6!r}\n" for i in range(50)))
    for argv in (["info", str(log), "-q", "--json"], ["-q", "info", str(log), "--json"],
                 ["convert", str(log), str(tmp_path / "b.csv"), "-q"]):
        assert replay_cli.main(argv) == 0, argv
    assert capsys.readouterr().err == ""
