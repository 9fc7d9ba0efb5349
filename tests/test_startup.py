"""What a command imports before it reads its input: its record is read (and a bad one refused) before the fit's or
the diagnosis's libraries are loaded, and a fit imports the diagnosis only to run its adequacy test.

Deterministic, not timed: the modules in ``sys.modules`` at the moment the process opens its input (an audit hook
on ``open``), and at the end of a short command.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

#: runs ``twin ARGV`` in a fresh interpreter; prints the heavy modules loaded when ``TARGET`` is first opened
#: (``at_open``) and at the end (``at_end``) as JSON on the last line of stdout
PROBE = r"""
import json, os, sys
target, argv, heavy = sys.argv[1], json.loads(sys.argv[2]), json.loads(sys.argv[3])
seen = {}

def loaded():
    return sorted(m for m in heavy if m in sys.modules)

def hook(event, args):
    if event == "open" and "at_open" not in seen and isinstance(args[0], (str, bytes)):
        if os.path.abspath(os.fsdecode(args[0])) == target:
            seen["at_open"] = loaded()

sys.addaudithook(hook)
from twin import cli
try:
    rc = cli.main(argv)
except SystemExit as exc:
    rc = exc.code
seen["at_end"] = loaded()
seen["rc"] = rc
sys.stdout.write("\n" + json.dumps(seen) + "\n")
"""

HEAVY = ["numba", "scipy.optimize", "scipy.stats", "scipy.signal", "twin.estimation.diagnose",
         "twin.estimation.diagnose.search", "twin.estimation.fit", "matplotlib"]


def _probe(target: str, argv: list[str]) -> dict:
    r = subprocess.run([sys.executable, "-c", PROBE, target, json.dumps(argv), json.dumps(HEAVY)],
                       capture_output=True, text=True, timeout=600)
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def record(tmp_path_factory) -> str:
    """A 0.3 s record of the default model, written by ``twin simulate``."""
    path = str(tmp_path_factory.mktemp("startup") / "rec.csv")
    r = subprocess.run([sys.executable, "-m", "twin.cli", "-q", "simulate", "-o", path, "--duration", "0.3",
                        "--seed", "7"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return path


@pytest.mark.parametrize("command", ["fit", "track", "diagnose"])
def test_help_imports_neither_numba_nor_scipy(command):
    seen = _probe("", [command, "--help"])
    assert seen["rc"] == 0
    assert seen["at_end"] == [], f"twin {command} --help imported {seen['at_end']}"


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_the_record_is_read_before_the_estimation_is_imported(tmp_path, command):
    """Up to reading its record the command loads the model (numba: the record's signals are the model's), but
    not the optimiser, the statistics or the diagnosis; a bad record is refused without paying for them."""
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x_ref,u,x\n0,0,0,not-a-number\n")
    seen = _probe(str(bad), [command, str(bad)])
    assert seen["rc"] not in (0, None)
    assert "numba" in seen["at_open"]
    for m in ("scipy.optimize", "scipy.stats", "scipy.signal", "twin.estimation.diagnose", "twin.estimation.fit"):
        assert m not in seen["at_end"], f"twin {command} on a bad record imported {m}"


@pytest.mark.slow
def test_a_fit_without_the_adequacy_test_imports_no_diagnosis(record):
    seen = _probe(record, ["-q", "fit", record, "--free", "zeta", "--outputs", "x", "--starts", "1", "--no-adequacy",
                           "--json"])
    assert seen["rc"] == 0
    assert "twin.estimation.fit" in seen["at_end"]  # the fit ran
    assert "twin.estimation.fit" not in seen["at_open"]
    assert "twin.estimation.diagnose" not in seen["at_end"]
