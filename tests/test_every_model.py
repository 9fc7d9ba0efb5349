"""Every registered model runs every command: simulate, fit (and its --compare), diagnose, track and serve, from
the command line, on a record the model's own simulator wrote with its phenomenological parameters 15 % above
the nominal ones; fits and the tracker start from the nominal values.  A model cannot be half supported: a new
registry line is tested here by the same assertions as the others."""

from __future__ import annotations

import json

import pytest

from net_helpers import free_port
from twin import cli
from twin.models import MODELS, get_model

#: seconds of record per model: enough for its slowest parameter to be known within a few per cent
DURATION = {"msp25": 6.0, "oscillator": 6.0, "axis": 10.0}
SEED = 1007
TRUTH_FACTOR = 1.15


def _truth(name: str) -> dict[str, float]:
    m = get_model(name)
    ps = m.params()
    return {n: ps[n] * TRUTH_FACTOR for n in m.PHENOMENOLOGICAL}


def _with_units(name: str, values: dict[str, float]) -> str:
    """``NAME=VALUE,...`` with each value in its SI unit spelled out (a bare number is refused where the display
    unit differs from the SI one)."""
    ps = get_model(name).params()
    return ",".join(f"{k}={v!r}{ps.spec(k).unit.replace(' ', '*')}" for k, v in values.items())


def _run(capsys, *argv) -> dict:
    capsys.readouterr()
    rc = cli.main(["-q", *argv])
    out, err = capsys.readouterr()
    assert rc == 0, (argv, err[-2000:])
    return json.loads(out)


@pytest.fixture(scope="module", params=MODELS)
def record(request, tmp_path_factory):
    """(model name, CSV path, truth) of a record simulated by the model's own default experiment."""
    name = request.param
    d = tmp_path_factory.mktemp(name)
    path = d / "rec.csv"
    truth = _truth(name)
    assert cli.main(["-q", "simulate", "--model", name, "-o", str(path), "--duration", str(DURATION.get(name, 6.0)),
                     "--seed", str(SEED), "--set", _with_units(name, truth)]) == 0
    return name, path, truth


def test_simulate_writes_the_models_signals_in_their_units(record):
    name, path, _ = record
    m = get_model(name)
    header = path.read_text().splitlines()[0].split(",")
    assert header[0] == "t[s]"
    cols = dict(c.rstrip("]").split("[") for c in header[1:])
    assert m.drive_name in cols and set(m.OUTPUTS) <= set(cols)
    assert all(cols[n] == m.signal_unit(n) for n in cols)


@pytest.mark.slow
def test_fit_compare_diagnose_track_and_serve_run_the_model(record, tmp_path, capsys):
    name, path, truth = record
    m = get_model(name)
    free = ",".join(m.PHENOMENOLOGICAL)
    fit_json = tmp_path / "fit.json"
    fitted = _run(capsys, "fit", str(path), "--model", name, "--free", free, "--save", str(fit_json), "--json")
    for n, v in truth.items():
        est = fitted["params"][n]
        assert abs(est["value"] / v - 1) < 0.05 or abs(est["value"] - v) < 4 * est["std"], (name, n, est, v)
    effect = next(iter(m.EFFECTS))
    cmp = _run(capsys, "fit", str(path), "--model", name, "--free", free, "--compare", f"none,{effect}", "--json")
    assert {r["name"] for r in cmp["rows"]} == {"none", effect} and cmp["best"] in ("none", effect)
    diag = _run(capsys, "diagnose", str(path), "--model", name, "--free", free, "--candidates", effect,
                "--no-timing-test", "--json")
    assert diag["causes"] == [], (name, diag["causes"])
    tr = _run(capsys, "track", str(path), "--params", str(fit_json), "--out", str(tmp_path / "track"), "--json")
    assert tr["model"] == name and tr["alarms"] == [] and tr["input_lost"] == []
    assert set(tr["final"]) == set(m.PHENOMENOLOGICAL)
    for n, v in truth.items():
        est = tr["final"][n]  # a weakly excited parameter (a leak on a short record): within its 3 sigma
        assert abs(est["value"] / v - 1) < 0.10 or abs(est["value"] - v) < 3 * est["std"], (name, n, est, v)
    port = free_port()
    toml = tmp_path / "rigs.toml"
    toml.write_text(f"""
[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{port}"]
[service]
journal_dir = "{tmp_path / 'journal'}"
[[rig]]
name = "rig-{name}"
model = "{name}"
source = "{path}"
speed = 0
commission = "{fit_json}"
""")
    served = _run(capsys, "serve", "--config", str(toml), "--json")
    stats = served[f"rig-{name}"] if f"rig-{name}" in served else served["rigs"][f"rig-{name}"]
    assert stats["samples"] == tr["samples"] and stats["alarms"] == 0, stats


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1002, 1003, 1004])
def test_twin_track_follows_the_papers_oscillator_on_a_reference_record(seed, reference_records, tmp_path, capsys):
    """The independent reference simulator's oscillator (truth drawn away from the defaults, 1 um noise), tracked
    from the defaults with ``twin track --model oscillator``: d within 3 standard errors and 10 %, k within 1 %,
    no alarm."""
    from conftest import oscillator_spec

    rec = reference_records([oscillator_spec(seed, duration=20.0, truth="draw")])[0]
    path = tmp_path / "osc.csv"
    rec.to_csv(path)
    out = _run(capsys, "track", str(path), "--model", "oscillator", "--out", str(tmp_path / "track"), "--json")
    d, k = out["final"]["d"], out["final"]["k"]
    truth = rec.truth
    assert abs(d["value"] - truth["d"]) < 3 * d["std"] and abs(d["value"] / truth["d"] - 1) < 0.10, (d, truth)
    assert abs(k["value"] / truth["k"] - 1) < 0.01, (k, truth)
    assert out["alarms"] == [] and out["consistency"] == "consistent", out["alarms"]


def test_no_generic_module_names_a_model():
    """The filter, the estimation, the service and the reports ask the model and name none: no registered model's
    name, class or module appears in their sources (comments included), so a new model runs there without an edit
    (a short name such as ``axis`` counts only where it names the model: quoted after ``model``, as its module, or
    as its class)."""
    import re
    from pathlib import Path

    import twin

    root = Path(twin.__file__).parent
    names, class_names = [], []
    for key in MODELS:
        m = get_model(key)
        class_names.append(type(m).__name__)
        names += [key, type(m).__name__, type(m).__module__, m.FILTER.functions if m.FILTER else key]
    words = sorted({n.rsplit(".", 1)[-1] for n in names})
    anycase = re.compile("|".join([rf"twin\.models\.{re.escape(w)}\b|model\W{{0,3}}[\"']{re.escape(w)}[\"']"
                                   for w in words] + [rf"\b{re.escape(w)}\b" for w in words if len(w) > 4]),
                         re.IGNORECASE)
    classes = re.compile("|".join(rf"\b{re.escape(c)}\b" for c in class_names))

    def names_a_model(line):
        return bool(anycase.search(line) or classes.search(line))

    assert names_a_model("the MSP25's kernel") and names_a_model('model="axis"') and names_a_model("an Axis")
    assert not names_a_model("np.sum(x, axis=0)")
    hits = []
    for part in ("online", "estimation", "service", "reports"):
        for f in sorted(f for f in (root / part).rglob("*.py") if "__pycache__" not in f.parts):
            for i, line in enumerate(f.read_text().splitlines(), 1):
                if names_a_model(line):
                    hits.append(f"{f.relative_to(root.parent)}:{i}: {line.strip()}")
    assert not hits, "\n".join(hits)
