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
