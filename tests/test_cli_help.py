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
