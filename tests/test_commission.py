"""Commissioning inside the service (``commission_s`` in rigs.toml): a rig of the independent reference
simulator (truth drawn off Table 9, noise through the loop) is replayed through ``twin serve``; its first
seconds are fitted in a worker process, the bands end up centred on the truth within the fit's stated
uncertainty, the statuses say ``commissioning`` then ``commissioned``, a restart reuses the saved
commissioning, and a rig that is not excited falls back to the configured baseline, saying so."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest
from mcap.reader import make_reader

from replay.base import Samples
from replay.mcapio import McapSink
from tests.conftest import get_records, msp25_spec
from twin.online.baseline import default_baseline
from twin.service.config import parse_config, with_commission_s
from twin.commands.demo import free_port
from fpdd.errors import ConfigError, LogFormatError
from twin.online.events import StatusEvent
from twin.service.serve import serve

TRACKED = ("Ffric", "CdAleak", "Cd", "zeta", "wn")
T0_NS = 1_700_000_000_000_000_000


def _write_log(path, rec) -> None:
    t_ns = T0_NS + np.round(rec.t * 1e9).astype(np.int64)
    with McapSink(str(path)) as sink:
        sink.write(Samples(t_ns, {k: np.asarray(v, float) for k, v in rec.signals.items()}))


def _config(tmp_path, log, commission_s=12.0, run="run1", **rig):
    return parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "out_dir": str(tmp_path / run), "workers": 0},
        "rig": [{"name": "rig-c", "source": str(log), "speed": 0.0, "commission_s": commission_s, **rig}],
    }, str(tmp_path / "rigs.toml"))


def _statuses(tmp_path, run):
    path = tmp_path / run / "rig-c.twin.mcap"
    with open(path, "rb") as f:
        return [StatusEvent.from_dict(json.loads(m.data))
                for _, _, m in make_reader(f).iter_messages(topics=["/twin/status"])]


def _alarms(tmp_path, run):
    with open(tmp_path / run / "rig-c.twin.mcap", "rb") as f:
        return [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/twin/alarm"])]


@pytest.fixture(scope="module")
def excited(tmp_path_factory):
    """A healthy reference rig with its truth drawn off Table 9, the default multisine demand, 30 s."""
    rec = get_records([msp25_spec(21, duration=30.0, truth="draw")])[0]
    path = tmp_path_factory.mktemp("logs") / "excited.mcap"
    _write_log(path, rec)
    return rec, path


@pytest.mark.slow
def test_a_rig_commissions_on_its_first_seconds_and_a_restart_reuses_it(tmp_path, excited):
    rec, log = excited
    twins: dict = {}
    summaries: dict = {}
    serve(_config(tmp_path, log), twins=twins, summaries=summaries)
    twin = twins["rig-c"]
    assert summaries["rig-c"].state == "finished"
    saved = tmp_path / "journal" / "rig-c.commission.json"
    doc = json.loads(saved.read_text())
    assert doc["commissioned"]["seconds"] == pytest.approx(12.0, abs=0.01)
    # the bands are centred on the truth within the fit's stated uncertainty
    for n in TRACKED:
        truth, band, std = float(rec.truth[n]), twin.rig.baseline[n], doc["params"][n]["std"]
        assert abs(band.value - truth) <= 4.0 * std, (n, band.value, truth, std)
        assert band.lo < truth < band.hi
        assert band.value != pytest.approx(default_baseline("msp25")[n].value, rel=0.01)  # not Table 9's
    # its noise levels and timing
    assert twin.tracker.noise_levels()["x"]["nominal"] == pytest.approx(doc["noise"]["x"]["value"])
    assert doc["noise"]["x"] == {"value": pytest.approx(2e-6, rel=0.2), "unit": "m"}
    assert doc["noise"]["pA"] == {"value": pytest.approx(2e4, rel=0.2), "unit": "Pa"}
    assert doc["params"]["Ffric"]["unit"] == "N" and "std" not in doc["params"]["A"]  # a known value has no std
    assert doc["timing"]["controller"] == "digital"
    # statuses: commissioning (gathering, then fitting; no alarms, parameters say so), then commissioned
    sts = _statuses(tmp_path, "run1")
    states = [s.state for s in sts]
    first_run = states.index("running")
    assert set(states[1:first_run]) == {"commissioning"} and "commissioning" not in states[first_run:]
    gathering = [s for s in sts[:first_run] if "gathered" in s.message]
    assert gathering and all(set(s.parameters.values()) == {"commissioning"} for s in gathering)
    assert all("no alarms before it ends" in s.message for s in sts[1:first_run])
    assert gathering[-1].counters["commission_needed_ms"] == 12000
    assert any("fitting its first 12.0 s" in s.message for s in sts[:first_run])
    done = sts[first_run]
    assert done.message.startswith("commissioned on its first 12.0 s: Ffric ") and "noise x " in done.message
    assert "WARNING" not in done.message and "warnings" not in doc  # the model represents this rig
    assert _alarms(tmp_path, "run1") == []  # a healthy rig against bands centred on its own fit
    assert twin.stats.samples == 30000
    # a restart reuses the saved commissioning: no new commissioning, same bands, the file untouched
    stamp = saved.stat().st_mtime_ns
    twins2: dict = {}
    serve(_config(tmp_path, log, run="run2"), twins=twins2)
    assert saved.stat().st_mtime_ns == stamp
    assert twins2["rig-c"].rig.baseline == twin.rig.baseline
    sts2 = _statuses(tmp_path, "run2")
    assert "commissioning" not in {s.state for s in sts2}
    assert any(s.message.startswith("commissioned by an earlier run (rig-c.commission.json): Ffric ") for s in sts2)
    # a journal gone from beside its checkpoint and commissioning is refused (alarm numbers never restart)
    os.replace(tmp_path / "journal" / "rig-c.db", tmp_path / "rig-c.db.aside")
    with pytest.raises(LogFormatError, match=r"rig-c\.db: the journal is missing, but its checkpoint"):
        serve(_config(tmp_path, log, run="run3"))
    os.replace(tmp_path / "rig-c.db.aside", tmp_path / "journal" / "rig-c.db")
    # a saved commissioning wins even without a checkpoint (the checkpoint moved aside)
    os.remove(tmp_path / "journal" / "rig-c.checkpoint.json")
    twins3: dict = {}
    serve(_config(tmp_path, log, run="run3"), twins=twins3)
    assert "commissioning" not in {s.state for s in _statuses(tmp_path, "run3")}
    assert twins3["rig-c"].rig.baseline == twin.rig.baseline and twins3["rig-c"].stats.samples == 30000


@pytest.mark.slow
@pytest.mark.slow
@pytest.mark.parametrize("seed", [1000, 1001, 1002, 1003])
def test_a_service_started_on_a_moving_rig_commissions_on_a_window_that_starts_mid_motion(seed):
    """The window a service gathers starts wherever the rig is: here 5.13 s into a reference record (truth
    drawn, noise through the loop), mid-motion. The fit's loop starts from a state read off the first samples
    and cannot read the rod's speed, the spool or a controller's integral there; its first half second is not
    counted (``BURN_S``). Counted, such windows were refused 16 times in 40 (leakage "too little excitation")."""
    from twin.online.commission import BURN_S, fit_window

    assert BURN_S > 0
    rec = get_records([msp25_spec(seed, duration=20.0, truth="draw")])[0]
    i0, i1 = 5130, 5130 + 12000
    t_ns = T0_NS + np.round(rec.t[i0:i1] * 1e9).astype(np.int64)
    window = Samples(t_ns, {k: np.asarray(v, float)[i0:i1] for k, v in rec.signals.items()})
    doc, why = fit_window(window, TRACKED)
    assert doc is not None, why
    for n in TRACKED:
        value, std = doc["params"][n]["value"], doc["params"][n]["std"]
        assert abs(value - rec.truth[n]) <= 4.0 * std, (n, value, rec.truth[n], std)


def test_a_rig_at_rest_cannot_commission_and_keeps_the_configured_baseline(tmp_path):
    """A demand of 10 um: the position hardly moves; the failure is one status line, the rig is tracked
    against its configured bands (here one set explicitly), nothing is saved, nothing crashes."""
    demand = {"kind": "multisine", "amplitude": 1e-5, "f_lo": 0.2, "f_hi": 15.0, "n_lines": 16}
    rec = get_records([msp25_spec(22, duration=10.0, demand=demand)])[0]
    log = tmp_path / "rest.mcap"
    _write_log(log, rec)
    twins: dict = {}
    summaries: dict = {}
    serve(_config(tmp_path, log, commission_s=5.0, baseline={"Ffric": {"value": 60.0, "rel_band": 0.4}}),
          twins=twins, summaries=summaries)
    assert summaries["rig-c"].state == "finished"
    twin = twins["rig-c"]
    assert twin.rig.baseline["Ffric"].value == 60.0
    assert twin.rig.baseline["wn"] == default_baseline("msp25")["wn"]
    assert not (tmp_path / "journal" / "rig-c.commission.json").exists()
    sts = _statuses(tmp_path, "run1")
    failed = [s for s in sts if s.message.startswith("commissioning failed: too little excitation: the position "
                                                     "moved 0.0")]
    assert failed and failed[0].state == "running"
    assert "tracking against the configured baseline" in failed[0].message
    assert twin.stats.samples == 10000 and twin.tracker.samples == 5000  # tracked after the window


def test_the_commission_s_flag_commissions_the_rigs_without_a_commissioning(tmp_path):
    log = tmp_path / "rig.mcap"
    cfg = parse_config({"rig": [{"name": "a", "source": str(log)},
                                {"name": "b", "source": str(log), "commission_s": 60.0}]}, "rigs.toml")
    assert [r.commission_s for r in cfg.rigs] == [None, 60.0]
    assert [r.commission_s for r in with_commission_s(cfg, 30.0).rigs] == [30.0, 60.0]
    assert with_commission_s(cfg, None) is cfg
    with pytest.raises(ConfigError, match=r"^--commission-s: must be >= 5 seconds, got 1$"):
        with_commission_s(cfg, 1.0)


@pytest.mark.slow
def test_a_rig_in_a_worker_process_commissions_too(tmp_path, excited):
    """Rigs spread over worker processes: the worker starts the fit's own process (workers are not daemonic
    for that, and die with the service all the same)."""
    rec, log = excited
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "out_dir": str(tmp_path / "run1"), "workers": 1},
        "rig": [{"name": "rig-c", "source": str(log), "speed": 0.0, "commission_s": 8.0}],
    }, str(tmp_path / "rigs.toml"))
    summaries: dict = {}
    serve(cfg, summaries=summaries)
    assert summaries["rig-c"].state == "finished" and summaries["rig-c"].samples == 30000
    doc = json.loads((tmp_path / "journal" / "rig-c.commission.json").read_text())
    ffric = doc["params"]["Ffric"]
    assert abs(ffric["value"] - float(rec.truth["Ffric"])) <= 4.0 * ffric["std"] and ffric["unit"] == "N"
    states = [s.state for s in _statuses(tmp_path, "run1")]
    assert "commissioning" in states and states.index("commissioning") < states.index("running")


@pytest.mark.slow
def test_a_rig_of_another_model_commissions_with_its_own_model(tmp_path, monkeypatch):
    """The commissioning fit runs the model the rig's configuration names, not the default one: a rig of the
    four-state actuator (``twin/models/actuator2.py``, registered for this test; the fit's own process registers
    it from the module the service names), its truth away from the model's defaults, is fitted in the fit's
    spawned process from those defaults, and the document is the actuator's, its estimates on the truth."""
    import twin.models as registry
    from twin.models import get_model
    from twin.models.simulate import measure
    from twin.service.spawn import FitJob

    monkeypatch.setitem(registry.REGISTRY, "actuator2", "twin.models.actuator2")
    monkeypatch.setattr(registry, "MODELS", tuple(registry.REGISTRY))
    model = get_model("actuator2")
    truth = {"Ffric": 65.0, "Kq": 4.3e-5}
    rng = np.random.default_rng(1005)
    t = np.arange(8000) * 1e-3
    f, ph = rng.uniform(0.2, 6.0, 8), rng.uniform(0, 2 * np.pi, 8)
    demand = 4e-3 * np.sum(np.sin(2 * np.pi * f[:, None] * t + ph[:, None]), axis=0) / np.sqrt(8)
    rec = measure(model, model.params(**truth), "x_ref", demand, 1e-3, noise={"x": 2e-6, "pA": 2e4, "pB": 2e4},
                  seed=1005)
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "out_dir": str(tmp_path / "run1"), "workers": 0},
        "rig": [{"name": "rig-a", "model": "actuator2", "source": str(tmp_path / "a.mcap"), "speed": 0.0,
                 "commission_s": 8.0, "track": list(truth)}],
    }, str(tmp_path / "rigs.toml"))
    rig = cfg.rigs[0]
    assert rig.model == "actuator2" and all(rig.params.get(n, model.NOMINAL[n]) != v for n, v in truth.items())
    job = FitJob(rig, rec.to_samples())
    while not job.done():
        time.sleep(0.05)
    doc, problem = job.result()
    assert problem == "" and doc is not None, problem
    assert doc["model"] == "actuator2" and doc["commissioned"]["rig"] == "rig-a"
    for n, v in truth.items():
        p = doc["params"][n]
        assert abs(p["value"] - v) <= 4.0 * p["std"] and abs(p["value"] / v - 1.0) < 0.05, (n, p)


def _foreign(src, dst, scale=1.0):
    """``src`` (the product's CSV, SI) rewritten as another logger writes it: ms, mm, bar, its own column names."""
    lines = src.read_text(encoding="utf-8").splitlines()
    with open(dst, "w", encoding="utf-8") as f:
        f.write("time_ms,dem_mm,valve,pos_mm,p_a_bar,p_b_bar\n")
        for line in lines[1:]:
            t, xr, u, x, pa, pb = (float(v) for v in line.split(","))
            f.write(f"{t * 1e3!r},{xr * 1e3 * scale!r},{u!r},{x * 1e3 * scale!r},{pa * 1e-5!r},{pb * 1e-5!r}\n")


FOREIGN_MAP = ["t=time_ms:ms", "x_ref=dem_mm:mm", "u=valve", "x=pos_mm:mm", "pA=p_a_bar:bar", "pB=p_b_bar:bar"]


@pytest.mark.slow
def test_the_commissioning_file_keeps_its_column_map_for_the_next_commands(tmp_path, capsys):
    """Step 5 of commissioning: ``twin track other.csv --params commissioning.json`` on a foreign CSV of the same
    logger reads it through the map (and units) the commissioning fit was given; so do ``twin fit --params``
    and the Python API (``twin.track(commission=...)``, ``FitResult.load``)."""
    import pathlib

    import twin
    from twin import cli
    from twin.estimation.fit_result import FitResult

    here = pathlib.Path(__file__).parent / "data" / "reference.csv"
    run, other = tmp_path / "run.csv", tmp_path / "other.csv"
    _foreign(here, run)
    _foreign(here, other)
    saved = tmp_path / "commissioning.json"
    maps = [a for m in FOREIGN_MAP for a in ("--map", m)]
    assert cli.main(["-q", "fit", str(run), "--free", "Ffric", "--starts", "1", *maps, "--save", str(saved)]) == 0
    capsys.readouterr()
    doc = json.loads(saved.read_text())
    assert doc["source"] == {"map": FOREIGN_MAP}
    assert cli.main(["-q", "track", str(other), "--params", str(saved), "--json", "--out", str(tmp_path / "o")]) == 0
    out = json.loads(capsys.readouterr().out)
    n = len(here.read_text().splitlines()) - 1
    assert out["alarms"] == [] and out["samples"] == n
    assert cli.main(["-q", "fit", str(other), "--free", "Ffric", "--starts", "1", "--params", str(saved),
                     "--json"]) == 0
    refit = json.loads(capsys.readouterr().out)
    loaded = FitResult.load(str(saved))
    assert refit["params"]["Ffric"]["value"] == pytest.approx(loaded.estimate["Ffric"], rel=1e-6)
    assert loaded.source == {"map": FOREIGN_MAP} and loaded.free == ("Ffric",)
    sd = doc["params"]["Ffric"]["std"]
    assert loaded.std["Ffric"] == pytest.approx(np.nan if sd is None else sd, nan_ok=True)
    assert loaded.noise == {o: pytest.approx(v["value"]) for o, v in doc["noise"].items()}
    tw = twin.track(str(other), commission=str(saved))
    assert tw.stats.samples == n
    # a --map given on the command line wins over the saved one
    assert cli.main(["-q", "track", str(other), "--params", str(saved), "--map", "x=pos_mm", "--out",
                     str(tmp_path / "o2")]) == 2
    capsys.readouterr()
