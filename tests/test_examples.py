"""The scripts of ``examples/`` run as a user runs them (a subprocess each, seeded) and print what they say.

Each takes a few seconds to tens of seconds (a fit, a track, a diagnosis, a service on loopback Zenoh), so they
are marked slow: CI runs them with ``-m slow``; ``pytest -m "" tests/test_examples.py`` runs them here. That
every script has its test is checked in the default run.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"



def run(script: str, *args: str, timeout: float = 280.0) -> str:
    done = subprocess.run([sys.executable, str(EXAMPLES / script), *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)
    assert done.returncode == 0, f"{script} exited {done.returncode}:\n{done.stderr[-3000:]}"
    return done.stdout


def test_every_example_is_tested() -> None:
    here = Path(__file__).read_text(encoding="utf-8")
    scripts = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert scripts, "no examples"
    assert [s for s in scripts if f'"{s}"' not in here] == []


@pytest.mark.slow
def test_fit_a_record_finds_the_simulated_values() -> None:
    out = run("fit_a_record.py", "--seed", "1")
    assert re.search(r"^FitResult\(model='msp25', Ffric=.*converged", out, re.M), out
    for name in ("Ffric", "zeta"):
        m = re.search(rf"^{name}: \S+ \+- \S+ \(simulated with \S+; ([0-9.]+) std off\)$", out, re.M)
        assert m, out
        assert float(m.group(1)) < 4.0, out  # started 40 % and 30 % off


@pytest.mark.slow
def test_track_and_alarms_alarms_the_leakage_alone() -> None:
    out = run("track_and_alarms.py", "--seed", "2")
    assert "alarmed parameters: CdAleak\n" in out, out
    assert re.search(r"ALARM\s+escalated CdAleak", out), out
    m = re.search(r"^final CdAleak: (\S+) \+- (\S+) m\^2$", out, re.M)
    assert m, out
    value, std = float(m.group(1)), float(m.group(2))
    assert abs(value - 3e-8) < 4 * std, out  # the simulated leakage, tracked from the nominal (a tenth of it)


@pytest.mark.slow
def test_diagnose_a_record_names_the_viscous_friction() -> None:
    out = run("diagnose_a_record.py", "--seed", "3")
    assert "verdict: explained\n" in out and "named: viscous_friction\n" in out, out
    m = re.search(r"viscous_friction: c_visc = (\S+) \+- (\S+) N s/m \(simulated with 2000\)", out)
    assert m, out
    assert abs(float(m.group(1)) - 2000.0) < 4 * float(m.group(2)), out


@pytest.mark.slow
def test_commission_your_csv_fits_and_tracks_quietly(tmp_path: Path) -> None:
    out = run("commission_your_csv.py", "--seed", "4", "--dir", str(tmp_path))
    offs = re.findall(r"^(\w+): ([0-9.]+) std from the rig's value$", out, re.M)
    assert [name for name, _ in offs] == ["Ffric", "CdAleak", "Cd", "zeta", "wn"], out
    assert all(float(z) < 4.0 for _, z in offs), out  # the fit started at the nominal values, the rig away
    saved = json.loads((tmp_path / "commissioning.json").read_text(encoding="utf-8"))
    assert saved["params"]["Ffric"]["unit"] == "N" and saved["params"]["Ffric"]["std"] > 0
    assert "pos_mm" in (tmp_path / "run1.csv").read_text(encoding="utf-8").splitlines()[0]
    assert "alarms on the second run: 0\n" in out, out


@pytest.mark.slow
def test_subscribe_to_alarms_receives_them_numbered() -> None:
    out = run("subscribe_to_alarms.py", "--seed", "2", "--wait", "120")
    m = re.search(r"^received (\d+) alarm\(s\), numbered \[([0-9, ]+)\], on \['CdAleak'\]$", out, re.M)
    assert m, out
    seqs = [int(s) for s in m.group(2).split(",")]
    assert seqs == list(range(1, int(m.group(1)) + 1)), out  # journaled: 1, 2, ... without a gap
    assert re.search(r"rig-a #\d+ .*ALARM\s+(raised|escalated) CdAleak", out), out
