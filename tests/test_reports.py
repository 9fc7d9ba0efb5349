"""Every command's HTML report, rendered by a real headless Chromium.

The reports are made from real results (an oscillator fit, paper cases, a
diagnosis, a tracked log), then Chromium loads each file: the DOM it builds
must hold the expected sections, every embedded PNG must decode, the console
must stay free of errors, and a screenshot must not be blank.  Chromium is
Debian's ``chromium`` package (``.ci/run`` installs it when missing); without
it these tests fail and say so, they never skip.
"""

from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from twin.reports import diagnose_report, fit_report, paper_report, track_report, track_summary
from twin.reports.units import Shown, label

sys.path.insert(0, os.path.dirname(__file__))

CHROMIUM_TIMEOUT_S = 120.0  # an upper bound on a loaded machine; a render takes about a second


def chromium() -> str:
    """The Chromium executable: ``$CHROMIUM``, else ``chromium``/``chromium-browser``/``google-chrome`` on PATH."""
    for name in (os.environ.get("CHROMIUM"), "chromium", "chromium-browser", "google-chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    pytest.fail("headless Chromium not found (tried $CHROMIUM, chromium, chromium-browser, google-chrome): "
                "install it with `apt-get install -y chromium` (.ci/run does this on CI)", pytrace=False)


def render(path: str, tmp_path) -> tuple[str, list[str], bytes]:
    """Load ``path`` in headless Chromium: (DOM after load, console messages, screenshot PNG)."""
    exe = chromium()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-extensions",
             "--disable-background-networking", "--hide-scrollbars", "--enable-logging=stderr", "--v=0"]
    url = "file://" + os.path.abspath(path)
    dom = subprocess.run([exe, *flags, "--dump-dom", url], capture_output=True, text=True,
                         timeout=CHROMIUM_TIMEOUT_S)
    assert dom.returncode == 0, dom.stderr[-2000:]
    console = [line for line in dom.stderr.splitlines() if ":CONSOLE" in line]
    shot = tmp_path / (os.path.basename(path) + ".png")
    r = subprocess.run([exe, *flags, f"--screenshot={shot}", "--window-size=1300,1800", url], capture_output=True,
                       text=True, timeout=CHROMIUM_TIMEOUT_S)
    assert r.returncode == 0 and shot.exists(), r.stderr[-2000:]
    console += [line for line in r.stderr.splitlines() if ":CONSOLE" in line]
    return dom.stdout, console, shot.read_bytes()


def check_page(path: str, tmp_path, sections: list[str], kind: str) -> str:
    from PIL import Image

    with open(path, encoding="utf-8") as f:
        text = f.read()
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", text), "the report must not load anything from the network"
    dom, console, shot = render(path, tmp_path)
    assert console == [], f"console messages: {console}"
    assert f'data-report="{kind}"' in dom
    for sid in sections:
        assert re.search(rf'<section id="{sid}"><h2>[^<]+</h2>', dom), f"section {sid!r} missing from the DOM"
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', dom)
    assert images, "no plot embedded"
    for data in images:
        im = Image.open(io.BytesIO(base64.b64decode(data)))
        im.load()
        assert im.size[0] > 300 and im.size[1] > 100
        assert np.asarray(im.convert("L")).std() > 5  # not a blank plot
    page = np.asarray(Image.open(io.BytesIO(shot)).convert("L"), dtype=float)
    assert page.shape[1] == 1300 and page.std() > 10, "the screenshot is blank"
    assert "[1]" not in dom, "a dimensionless quantity is labelled [1]"
    return dom


# --- the data of each report: real results, small -------------------------------------------
@pytest.fixture(scope="module")
def osc_fit():
    from twin.estimation.fit import fit
    from twin.models import get_model
    from twin.models.simulate import default_noise, excite, measure

    model = get_model("oscillator")
    name, drive = excite(model, 3.0, 1e-3, seed=3)
    rec = measure(model, model.params(), name, drive, 1e-3, noise=default_noise(model), seed=3, name="osc-3s")
    res = fit(model, [rec], ("d", "k"), start={"d": 0.15, "k": 3500.0}, seed=0)
    return model, rec, res


@pytest.mark.slow
def test_fit_report(tmp_path, osc_fit):
    model, rec, res = osc_fit
    path = fit_report(res, [rec], model, str(tmp_path / "fit"))
    dom = check_page(path, tmp_path, ["compare", "resid", "parameters", "correlation", "timing"], "fit")
    assert f"{res.fit_pct['y']:.2f} %" in dom
    # both standard errors, in display units
    shown = Shown("k", "oscillator")
    assert shown.text(res.std["k"], 3, unit=False) in dom and shown.text(res.std_white["k"], 3, unit=False) in dom
    assert "digital" in dom  # the loop timing used


@pytest.mark.slow
def test_fit_report_from_the_command_line(tmp_path, osc_fit):
    from twin import cli

    _, rec, _ = osc_fit
    csv = tmp_path / "osc.csv"
    from replay.factory import open_sink

    with open_sink(str(csv)) as sink:
        sink.write(rec.to_samples())
    out = tmp_path / "report"
    assert cli.main(["-q", "fit", str(csv), "--model", "oscillator", "--free", "d,k", "--report", str(out)]) == 0
    check_page(str(out / "fit_report.html"), tmp_path, ["compare", "resid", "parameters"], "fit")


@pytest.mark.slow
def test_paper_report(tmp_path):
    from twin.paper.cases import CASES, run_all

    cases = [c for c in CASES if c.case in ("osc-A", "osc-D")]
    rows, elapsed = run_all(noisy=True, seed=1, cases=cases)
    path = paper_report(rows, str(tmp_path / "paper"), elapsed_s=elapsed)
    dom = check_page(path, tmp_path, ["cases", "errors", "zscores"], "paper")
    for r in rows:
        assert r["case"] in dom and f"{r['error_pct']:.2e} %" in dom
    assert "0.0532 %" in dom  # the paper's error of k in case A, beside ours
    # noise-free: no error bars, no z-scores
    rows0, _ = run_all(noisy=False, seed=1, cases=cases[:1])
    dom0 = check_page(paper_report(rows0, str(tmp_path / "paper0")), tmp_path, ["cases", "errors"], "paper")
    assert 'id="zscores"' not in dom0


@pytest.mark.slow
def test_diagnose_report_from_the_object_and_from_its_json(tmp_path):
    from diag_helpers import OSC, record
    from twin.estimation.diagnose import diagnose

    rec = record(OSC, ("coulomb_friction",), seed=1, duration_s=3.0)
    diag = diagnose(OSC, [rec], seed=0, candidates=["coulomb_friction", "cubic_stiffness"])
    assert diag.causes == ["coulomb_friction"]
    path = diagnose_report(diag, str(tmp_path / "diag"))
    dom = check_page(path, tmp_path, ["verdict", "compare", "gain", "pvalues", "models"], "diagnose")
    assert "EXPLAINED" in dom and "coulomb_friction" in dom and "p (Holm)" in dom
    assert dom.count("<figure>") >= 3  # before/after, gain, screen
    # the JSON of `twin diagnose --json` makes the same report, without the before/after plot
    d = json.loads(json.dumps(diag.to_dict()))
    dom2 = check_page(diagnose_report(d, str(tmp_path / "diag-json")), tmp_path, ["verdict", "gain", "pvalues"],
                      "diagnose")
    assert "pass the Diagnosis object" in dom2
    vc = diag.effect_params("coulomb_friction")["vc"]
    assert Shown("vc", "oscillator").unit == "mm/s" and Shown("vc", "oscillator").text(vc["value"], 6, unit=False) in dom2


@pytest.mark.slow
def test_track_report(tmp_path):
    from twin.online.baseline import Baseline
    from twin.models import msp25 as M
    from twin.models.scenario import Drift, simulate_wear
    from fpdd.units import NOMINAL_NOISE
    from twin.models.simulate import excite
    from twin.service.track import track

    name, xr = excite(M.MODEL, 6.0, 1e-3, seed=0)
    noise = {k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [Drift("CdAleak", 30.0, 1.0, 4.0, "ramp")], noise=noise,
                           seed=0, name="wear")
    tight = {"CdAleak": Baseline(M.NOMINAL["CdAleak"], M.NOMINAL["CdAleak"] / 2, M.NOMINAL["CdAleak"] * 2)}
    twin = track(rec, "rig-7", baseline=tight)
    assert any(a.parameter == "CdAleak" for a in twin.alarms)
    s = json.loads(json.dumps(track_summary(twin, "wear.mcap")))
    path = track_report(s, str(tmp_path / "track"))
    dom = check_page(path, tmp_path, ["trends", "alarms", "status"], "track")
    assert "CdAleak" in dom and "mm²" in dom and "wn" in dom and "Hz" in dom
    assert re.search(r'class="lvl-(warning|alarm)"', dom)
    # the RigTwin itself is accepted too
    check_page(track_report(twin, str(tmp_path / "track2"), log="wear.mcap"), tmp_path, ["trends"], "track")


def test_units_never_label_a_dimensionless_axis_with_1():
    assert label("zeta", "1") == "zeta" and label("x", "mm") == "x [mm]" and label("CdAleak", "mm^2") == "CdAleak [mm²]"
    wn = Shown("wn", "msp25")
    assert wn.unit == "Hz" and wn.text(2 * np.pi * 43.0, 4) == "43 Hz"
    assert Shown("zeta", "msp25").text(0.37) == "0.37"
    assert Shown("unknown", "msp25", "N").text(3.0) == "3 N"


# --- what a report must explain: low Fit from noise, the error panel, a zoom on long records, signatures --------
@pytest.mark.slow
def test_fit_report_explains_a_low_pressure_fit_by_the_noise(tmp_path):
    """A healthy rig's pressure Fit is low because the pressures barely swing under 20 kPa of noise: the report
    says so with the best Fit the noise allows (computed here from the record), and that the fit reached it;
    a wrong model (wn held 30 % low) is told apart: its error is beyond the noise."""
    from diag_reference import reference_record
    from twin.estimation.fit import fit
    from twin.models import get_model

    model = get_model("msp25")
    rec, info = reference_record((), seed=1001, duration=2.0)
    res = fit(model, [rec], model.PHENOMENOLOGICAL, seed=0)
    path = fit_report(res, [rec], model, str(tmp_path / "fit"))
    dom = check_page(path, tmp_path, ["compare", "resid", "parameters"], "fit")
    for o in ("pA", "pB"):
        y = rec[o]
        best = 100.0 * (1.0 - 2e4 * np.sqrt(y.size) / np.linalg.norm(y - y.mean()))
        explained = 1.0 - (res.mse[o] - 2e4 ** 2) / (np.var(y) - 2e4 ** 2)  # of the signal above the noise
        assert best < 60.0 and explained > 0.8, (o, best, res.fit_pct[o], explained)  # the healthy fit: most
        assert f"{o} swings" in dom and f"the best achievable Fit is about {best:.0f} %" in dom
        assert f"explains {100 * explained:.0f} % of the signal" in dom
    assert dom.count("A low Fit here is the sensor, not the model") == 2 and "LOW SNR" in dom
    assert "0.02 MPa" in dom and "best Fit the noise allows" in dom  # the noise in display units, the column
    wrong = model.params(**{k: v for k, v in info["truth"].items() if k in model.params().names})
    wrong = wrong.update({"wn": 0.7 * wrong["wn"]})
    res2 = fit(model, [rec], ("Ffric",), base=wrong, seed=0)
    with open(fit_report(res2, [rec], model, str(tmp_path / "wrong")), encoding="utf-8") as f:
        dom2 = f.read()
    assert "MODEL MISSES" in dom2 and "The model misses something in this output" in dom2


@pytest.mark.slow
def test_diagnose_report_has_the_error_panel_and_a_visible_signature_per_cause(tmp_path):
    from diag_helpers import OSC, record
    from twin.estimation.diagnose import diagnose
    from twin.reports import views
    from twin.reports.diagnose import signature_data

    rec = record(OSC, ("coulomb_friction",), seed=1002, duration_s=3.0)
    diag = diagnose(OSC, [rec], seed=0, candidates=["coulomb_friction", "cubic_stiffness"])
    assert diag.causes == ["coulomb_friction"]
    dom = check_page(diagnose_report(diag, str(tmp_path / "diag")), tmp_path,
                     ["verdict", "compare", "error", "gain", "signatures", "pvalues", "models"], "diagnose")
    assert "noise band" in dom and "±1.96 σ" in dom and "RMS error, extended" in dom and " mm" in dom
    assert re.search(r"zoom where the error is largest, t = [\d.]+ … [\d.]+ s \(0\.\d+ s\)", dom)
    # the signature: in display units, not flat, scaled so that the cause's curve fills the axis
    (sig,) = signature_data(diag)
    assert sig["cause"] == "coulomb_friction" and sig["axis"] == "velocity" and not sig["flat"]
    fig = views.signature_figure(sig)
    ax = fig.axes[0]
    assert ax.get_xlabel() == "velocity [mm/s]" and ax.get_ylabel() == "residual of y [mm]"
    lo, hi = ax.get_ylim()
    red = [ln for ln in ax.get_lines() if "coulomb_friction" in str(ln.get_label())][0].get_ydata()
    assert np.ptp(red) > 0.3 * (hi - lo), "the signature is drawn flat"
    assert "Signature of coulomb_friction" in dom and "Flat in this view" not in dom
    # a signature within the bins' scatter is said to be flat, and why
    rng = np.random.default_rng(1003)
    x = rng.normal(size=4000)
    flat = dict(sig, x=x, residual=rng.normal(size=4000) * 1e-6, contribution=1e-9 * x)
    flat["flat"], flat["span"], flat["scatter"] = views.signature_flatness(x, flat["contribution"], flat["residual"])
    assert flat["flat"] and "flat" in views.signature_figure(flat).axes[0].get_title(loc="left")
    # the error panel's axes carry their units
    efig = views.error_figure(rec.t_s, [{"name": "y", "unit": "mm", "scale": 1e3, "noise": 1e-6,
                                         "errors": [("nominal", rec["y"] - diag.nominal.predicted[0]["y"])]}])
    assert efig.axes[0].get_ylabel() == "error of y [mm]" and efig.axes[0].get_xlabel() == "t [s]"


@pytest.mark.slow
def test_a_long_record_is_shown_with_a_short_zoom_beside_it(tmp_path):
    """60 s at 1 kHz is a solid band at full width: the compare and error views show a zoom of at most 0.5 s."""
    from diag_helpers import OSC, record
    from twin.estimation.diagnose import diagnose

    rec = record(OSC, (), seed=1004, duration_s=2.0)
    d = diagnose(OSC, [rec], seed=0, candidates=["coulomb_friction"]).to_dict()
    rng = np.random.default_rng(1004)
    t = np.arange(60_000) * 1e-3
    y = 1e-3 * np.sin(2 * np.pi * 7 * t)
    compare = {"t": t, "n_fit": 45_000, "measured": {"y": y + 1e-6 * rng.normal(size=t.size)},
               "nominal": {"y": 0.98 * y}, "extended": None}
    dom = check_page(diagnose_report(d, str(tmp_path / "long"), compare=compare), tmp_path,
                     ["compare", "error"], "diagnose")
    spans = [float(s) for s in re.findall(r"t = [\d.]+ … [\d.]+ s \(([\d.]+) s\)", dom)]
    assert len(spans) >= 2 and all(0.2 <= s <= 0.5 for s in spans), spans  # compare and error views
