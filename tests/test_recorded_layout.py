"""Foxglove's layout on recorded files: every topic a panel of the layout reads is in the product's MCAP files
(``replay convert``, ``twin track``'s twin MCAP, the demo's), under the same name, JSON encoded, each message valid
against its channel's JSON schema, and every field a panel plots a number in the messages of the layout's rig."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from mcap.reader import make_reader

from replay import cli as replay_cli
from replay.base import Samples
from replay.mcapio import McapSource
from twin import cli
from twin.models import msp25 as M
from twin.models.scenario import Drift, simulate_wear
from twin.models.simulate import excite
from twin.online.events import validate
from twin.service.live_view.layout import foxglove_layout
from fpdd.units import NOMINAL_NOISE

NOISE = {k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}
_PATH = re.compile(r"^(/[\w/]+)(?:\{rig==\$rig\})?(?:\.(.+))?$")


def panels(layout: dict) -> dict[str, list[tuple[str, str | None]]]:
    """panel -> [(topic, field path or None)] of every message path the layout's panels read."""
    out: dict[str, list[tuple[str, str | None]]] = {}
    for pid, cfg in layout["configById"].items():
        paths = [p["value"] for p in cfg.get("paths", ())]
        paths += [cfg[k] for k in ("topicToRender", "topicPath") if k in cfg]
        for p in paths:
            m = _PATH.match(p)
            assert m, f"{pid}: path {p!r} not understood"
            out.setdefault(pid, []).append((m.group(1), m.group(2)))
    return out


def _field(msg: dict, path: str | None):
    for key in (path.split(".") if path else ()):
        if not isinstance(msg, dict) or key not in msg:
            return None
        msg = msg[key]
    return msg


def check_file(path: str, layout: dict, *, optional_panels: tuple[str, ...] = (), every: int = 1) -> dict:
    """Assert that the layout's panels fill on the MCAP file ``path`` (module docstring); panels in
    ``optional_panels`` may lack their topic. Every ``every``-th message of a channel is validated (all of the
    small ones). Returns {topic: messages of the layout's rig}."""
    rig = layout["globalVariables"]["rig"]
    wanted = panels(layout)
    topics = {t for ps in wanted.values() for t, _ in ps}
    counts: dict[str, int] = {t: 0 for t in topics}
    filled: dict[tuple[str, str | None], int] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {}
        for ch in summary.channels.values():
            if ch.topic in topics:
                sc = summary.schemas[ch.schema_id]
                assert ch.message_encoding == "json" and sc.encoding == "jsonschema", ch.topic
                schemas[ch.topic] = json.loads(sc.data)
        seen: dict[str, int] = {}
        for _, ch, m in reader.iter_messages(topics=sorted(topics)):
            seen[ch.topic] = seen.get(ch.topic, 0) + 1
            msg = json.loads(m.data)
            if seen[ch.topic] % every == 1 or every == 1 or seen[ch.topic] < 200:
                validate(msg, schemas[ch.topic], f"{path}:{ch.topic}")
            if ch.topic != "/twin/alarm_log" and msg.get("rig") != rig:
                continue
            counts[ch.topic] += 1
            for t, field in ((t, fp) for ps in wanted.values() for t, fp in ps if t == ch.topic):
                v = _field(msg, field)
                if field is None or (isinstance(v, (int, float)) and np.isfinite(v)):
                    filled[(t, field)] = filled.get((t, field), 0) + 1
    for pid, ps in wanted.items():
        if pid in optional_panels and not any(counts[t] for t, _ in ps):
            continue
        assert any(counts[t] for t, _ in ps), f"{path}: panel {pid} finds no message of {sorted({t for t, _ in ps})}"
        if pid.startswith("Plot!forecast"):  # one series per parameter: those with a forecast fill
            assert any(filled.get(p) for p in ps), f"{path}: {pid} has no number to plot"
        else:
            missing = [f"{t}.{fp}" for t, fp in ps if not filled.get((t, fp))]
            assert not missing, f"{path}: panel {pid} has nothing to plot at {missing}"
    return counts


def test_converted_rig_log_fills_the_signal_panels(tmp_path):
    t = np.arange(3000, dtype=np.int64) * 1_000_000
    rng = np.random.default_rng(7)
    x = 0.004 * np.sin(2 * np.pi * 0.7 * t * 1e-9)
    sig = {"x_ref": x, "u": 2.0 * x / 0.01, "x": x + 2e-6 * rng.standard_normal(len(t)),
           "pA": 8e6 + 1e5 * rng.standard_normal(len(t)), "pB": 7e6 + 1e5 * rng.standard_normal(len(t))}
    csv = tmp_path / "hall2-b.csv"
    np.savetxt(csv, np.column_stack([t * 1e-9, *sig.values()]), delimiter=",", header="t,x_ref,u,x,pA,pB",
               comments="", fmt="%.17g")
    out = tmp_path / "hall2-b.mcap"
    assert replay_cli.main(["convert", str(csv), str(out)]) == 0
    layout = foxglove_layout(rig="hall2-b")  # the file's name names the rig when nothing else does
    counts = check_file(str(out), layout, optional_panels=("Plot!param0", "Plot!param1", "Plot!param2",
                                                           "Plot!param3", "Plot!param4", "Plot!forecast",
                                                           "Log!alarms", "RawMessages!status"), every=50)
    assert counts["/rig/signals"] == 3000
    with open(out, "rb") as f:  # the display numbers are the SI ones in mm and MPa
        for _, _, m in make_reader(f).iter_messages(topics=["/rig/signals"]):
            row = json.loads(m.data)
            assert row["display"]["x"] == pytest.approx(row["x"] * 1e3, rel=1e-6, abs=1e-12)
            assert row["display"]["pA"] == pytest.approx(row["pA"] * 1e-6, rel=1e-6)
    with McapSource(str(out)) as src:  # and the file still reads back as the samples it was given
        back = Samples.concat(list(src.chunks()))
    assert back.names == tuple(sig) and np.array_equal(back.signals["x"], sig["x"])


@pytest.mark.slow
def test_twin_track_mcap_fills_every_panel_but_the_forecast(tmp_path):
    _, xr = excite(M.MODEL, 8.0, 1e-3, seed=3)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [Drift("Ffric", 3.0, 4.0, shape="step")], noise=NOISE,
                           seed=3)
    log = tmp_path / "rig.mcap"
    from replay.mcapio import McapSink

    with McapSink(str(log)) as sink:
        sink.write(rec.to_samples())
    out = tmp_path / "out"
    assert cli.main(["track", str(log), "--rig", "bay-3", "--out", str(out), "--json"]) == 0
    layout = json.loads((out / "bay-3.foxglove-layout.json").read_text(encoding="utf-8"))
    assert layout["globalVariables"]["rig"] == "bay-3"
    counts = check_file(str(out / "bay-3.twin.mcap"), layout, optional_panels=("Plot!forecast",))
    assert counts["/twin/alarm_log"] >= 1 and counts["/rig/signals"] >= 8 * 40  # 50 per second of record


@pytest.mark.slow
def test_the_layout_of_another_model_plots_its_own_signals(tmp_path):
    """twin track of the oscillator writes a layout whose panels are the oscillator's parameters and its signals
    u and y, and its MCAP fills them."""
    rec = tmp_path / "osc.csv"
    assert cli.main(["simulate", "--model", "oscillator", "-o", str(rec), "--duration", "6", "--seed", "4"]) == 0
    out = tmp_path / "out"
    assert cli.main(["track", str(rec), "--model", "oscillator", "--rig", "osc", "--out", str(out), "--json"]) == 0
    layout = json.loads((out / "osc.foxglove-layout.json").read_text(encoding="utf-8"))
    paths = {fp for ps in panels(layout).values() for _, fp in ps}
    assert {"display.u", "display.y"} <= paths and "display.pA" not in paths
    counts = check_file(str(out / "osc.twin.mcap"), layout, optional_panels=("Plot!forecast", "Log!alarms"))
    assert counts["/rig/signals"] >= 6 * 40
