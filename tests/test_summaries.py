"""MATLAB-grade summaries of a fit, measured on records of the independent reference simulator (verification
seeds >= 1000, truth drawn off the defaults, noise through the loop, starts away from the truth): the
``present``-style summary, k-step-ahead prediction beside simulation, the valve's Bode plot with its band, and
the comparison of candidate models on held-out data (text, JSON, HTML)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from twin import cli
from twin.estimation import compare as C
from twin.estimation.fit import fit
from twin.models import get_model
from twin.record import Record
from twin.reports import summary as S

RIG = get_model("msp25")
FREE = RIG.PHENOMENOLOGICAL
#: the reference simulator's default sensor noise (standard deviations, SI)
REF_NOISE = {"x": 2e-6, "pA": 2e4, "pB": 2e4}


def product_record(ref, name: str = "reference") -> Record:
    return Record(ref.dt, {k: np.asarray(v, float) for k, v in ref.signals.items()}, name)


def write_csv(ref, path) -> str:
    names = [n for n in ("x_ref", "u", "x", "pA", "pB") if n in ref.signals]
    with open(path, "w", encoding="utf-8") as f:
        f.write("t," + ",".join(names) + "\n")
        for i in range(len(ref.t)):
            f.write(f"{float(ref.t[i])!r}," + ",".join(repr(float(ref.signals[n][i])) for n in names) + "\n")
    return str(path)


@pytest.fixture(scope="module")
def healthy(reference_records):
    """A 3 s record, truth drawn 3-20 % off Table 9, default noise through the loop."""
    from conftest import msp25_spec

    return reference_records([msp25_spec(1003, duration=3.0, truth="draw")])[0]


@pytest.fixture(scope="module")
def fitted(healthy):
    rec = product_record(healthy)
    start = {k: healthy.truth[k] * f for k, f in zip(FREE, (1.3, 0.6, 0.85, 1.2, 0.9))}
    return rec, fit(RIG, rec, FREE, start=start, n_starts=4, seed=1003)


def test_present_summary_names_units_and_says_the_pressures_low_fit_is_their_noise(fitted):
    rec, res = fitted
    s = S.summarize(res, [rec])
    json.dumps(s)  # JSON-ready
    assert set(s["params"]) == set(FREE)
    for n, d in s["params"].items():
        assert d["value"] == res.estimate[n] and d["std"] == res.std[n]
        assert d["unit"] == RIG.params().spec(n).unit  # SI, unit named
    for o in ("x", "pA", "pB"):
        d = s["outputs"][o]
        assert d["fit_pct"] == pytest.approx(res.fit_pct[o], abs=1e-9)
        assert d["noise"]["unit"] == {"x": "m", "pA": "Pa", "pB": "Pa"}[o]
        # the noise read off the residual is the reference's sensor noise
        assert d["noise"]["value"] == pytest.approx(REF_NOISE[o], rel=0.08)
        # the fitted model's error is the noise, to within a few per cent: the Fit sits at the noise's ceiling
        assert 0.97 < d["error_to_noise"] < 1.1, (o, d)
        assert d["fit_pct"] <= d["fit_ceiling_pct"] + 0.5
    # the pressures swing little under 20 kPa noise: a low Fit % the summary blames on the noise, not the model
    for o in ("pA", "pB"):
        assert s["outputs"][o]["low_snr"] and s["outputs"][o]["fit_pct"] < 80
        assert any(n.startswith(f"Fit({o})") and "signal-to-noise" in n for n in s["notes"])
    assert not s["outputs"]["x"]["low_snr"] and s["outputs"]["x"]["fit_pct"] > 99
    # a closed loop's displacement error is coloured by the sensor noise going round the loop: not white
    assert s["outputs"]["x"]["whiteness"]["white"] is False
    text = S.text(s)
    assert "wn" in text and "Hz" in text and "Ffric" in text and " N" in text and "±" in text
    assert "low signal-to-noise ratio" in text and "k=10" in text and "Ljung-Box" in text


def test_k_step_prediction_beats_simulation_only_where_the_error_is_coloured(fitted):
    """With a model error (wn held 15 % off) x's simulation error is slow: the 1- and 10-step predictions
    remove most of it.  No prediction beats the white sensor noise: every k-step Fit stays under the ceiling."""
    rec, res = fitted
    ok = C.fit_by_horizon(RIG, res.params, [rec], timing=res.timing, inits=res.init)
    s = S.summarize(res, [rec])
    for o in ("x", "pA", "pB"):
        assert ok["1"][o] >= ok["10"][o] - 0.05 and ok["10"][o] >= ok["inf"][o] - 0.05
        assert ok["1"][o] <= s["outputs"][o]["fit_ceiling_pct"] + 0.5
    wrong = res.params.update({"wn": res.params["wn"] * 0.85})
    bad = C.fit_by_horizon(RIG, wrong, [rec], timing=res.timing, inits=res.init)
    assert bad["inf"]["x"] < ok["inf"]["x"] - 0.05
    assert bad["1"]["x"] > bad["10"]["x"] > bad["inf"]["x"]
    # one step ahead the slow error is gone: back to the noise floor of x
    assert bad["1"]["x"] == pytest.approx(ok["inf"]["x"], abs=0.05)


def test_ar_disturbance_model_and_its_k_step_coefficients():
    """An AR(2) disturbance (seeded): Levinson-Durbin with AIC finds it, and the k-step predictor's error
    variance is the theory's sum of the first k impulse-response weights squared."""
    rng = np.random.default_rng(1001)
    a_true = np.array([1.5, -0.7])
    n = 40_000
    w = rng.normal(size=n)
    e = np.zeros(n)
    for t in range(2, n):
        e[t] = a_true[0] * e[t - 1] + a_true[1] * e[t - 2] + w[t]
    a = C.noise_model([e])
    assert a.size >= 2 and np.allclose(a[:2], a_true, atol=0.03) and np.all(np.abs(a[2:]) < 0.03)
    psi = [1.0, a_true[0]]  # impulse response of 1 / (1 - a1 q^-1 - a2 q^-2)
    for _ in range(20):
        psi.append(a_true[0] * psi[-1] + a_true[1] * psi[-2])
    for k in (1, 3, 10):
        b = C.ahead_coefficients(a, k)
        pred = np.convolve(e, b)[: n - k]
        err = e[k:] - pred
        assert np.var(err[100:]) == pytest.approx(sum(p * p for p in psi[:k]), rel=0.05)
    assert C.noise_model([rng.normal(size=5000)]).size == 0  # white: BIC keeps nothing


def test_whiteness_verdict_on_known_residuals():
    """White residuals pass the Ljung-Box test at alpha 1e-3, an AR(1) one at 0.3 fails (seeded)."""
    rng = np.random.default_rng(1002)
    n = 4000
    y = np.sin(np.arange(n) * 0.01)
    white = rng.normal(0, 0.05, n)
    ar = np.zeros(n)
    for t in range(1, n):
        ar[t] = 0.3 * ar[t - 1] + white[t]
    rec = Record(1e-3, {"y": y + white}, "w")
    d = S._output_stats("y", [rec], [{"y": y}], 1e-3, 25)
    assert d["whiteness"]["white"] is True and d["noise"]["value"] == pytest.approx(0.05, rel=0.05)
    rec = Record(1e-3, {"y": y + ar}, "ar")
    assert S._output_stats("y", [rec], [{"y": y}], 1e-3, 25)["whiteness"]["white"] is False


def test_valve_bode_at_resonance_and_its_band_matches_monte_carlo(fitted):
    _, res = fitted
    b = S.valve_bode(res, freqs_hz=np.array([res.params["wn"] / (2 * math.pi)]))
    zeta = res.params["zeta"]
    assert b["phase_deg"][0] == pytest.approx(-90.0, abs=1e-9)
    assert b["mag_db"][0] == pytest.approx(20 * math.log10(1 / (2 * zeta)), abs=1e-9)
    # the delta-method band against draws from the fit's covariance (seeded)
    i = [list(res.free).index(n) for n in ("wn", "zeta")]
    cov = S._cov(res)[np.ix_(i, i)]
    draws = np.random.default_rng(1004).multivariate_normal([res.params["wn"], zeta], cov, size=20_000)
    f = 0.8 * res.params["wn"] / (2 * math.pi)  # on the resonance's flank, where both parameters matter
    bb = S.valve_bode(res, freqs_hz=np.array([f]))
    w = 2 * math.pi * f
    g = draws[:, 0] ** 2 / (draws[:, 0] ** 2 - w * w + 2j * draws[:, 1] * draws[:, 0] * w)
    half = (bb["mag_db_hi"][0] - bb["mag_db_lo"][0]) / 2
    assert half == pytest.approx(S.Z95 * np.std(20 * np.log10(np.abs(g))), rel=0.1)
    half_p = (bb["phase_deg_hi"][0] - bb["phase_deg_lo"][0]) / 2
    assert half_p == pytest.approx(S.Z95 * np.std(np.degrees(np.angle(g))), rel=0.1)
    assert b["bandwidth_hz"] > res.params["wn"] / (2 * math.pi)  # an underdamped valve peaks before -3 dB


@pytest.mark.slow
def test_fit_command_prints_the_summary_and_writes_the_bode_plot(healthy, tmp_path, capsys):
    csv = write_csv(healthy, tmp_path / "rig.csv")
    base = ["-q", "fit", csv, "--starts", "2", "--seed", "1003"]
    assert cli.main(base) == 0
    out = capsys.readouterr().out
    assert "Free parameters (estimate ± std, HAC):" in out and "NOTE: Fit(pA)" in out
    assert cli.main([*base, "--report", str(tmp_path / "rep"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)["summary"]
    assert s["params"]["wn"]["unit"] == "rad/s" and s["valve"]["bandwidth_3db"]["unit"] == "rad/s"
    assert set(s["outputs"]["x"]["fit_pct_ahead"]) == {"1", "10", "inf"}
    html = (tmp_path / "rep" / "fit_report.html").read_text(encoding="utf-8")
    for sid in ("summary", "ahead", "bode"):
        assert f'<section id="{sid}">' in html
    assert "Servo-valve Bode plot" in html and "data:image/png;base64," in html.split('id="bode"')[1]


@pytest.fixture(scope="module")
def stiff(reference_records):
    """A rig loaded by a specimen spring (size drawn by the reference), 4 s."""
    from conftest import msp25_spec

    return reference_records([msp25_spec(1005, duration=4.0, truth="draw", effects=("specimen_stiffness",))])[0]


def test_compare_picks_the_effect_the_rig_has_on_held_out_data(stiff, tmp_path):
    rec = product_record(stiff, "stiff")
    cmp = C.compare_models([C.Candidate.parse("none"), C.Candidate.parse("specimen_stiffness")], [rec],
                           n_starts=2, seed=1005)
    rows = {r["name"]: r for r in cmp["rows"]}
    assert cmp["best"] == "specimen_stiffness" and rows["specimen_stiffness"]["best"]
    assert rows["specimen_stiffness"]["bic"] < rows["none"]["bic"]
    for o in ("pA", "pB"):  # the spring's load is in the pressures: held-out error falls
        assert (rows["specimen_stiffness"]["validation_rms"][o]["value"]
                < rows["none"]["validation_rms"][o]["value"])
        assert rows["specimen_stiffness"]["validation_rms"][o]["unit"] == "Pa"
    assert cmp["validation"] == ["stiff (second half)"]
    text = S.compare_text(cmp)
    assert "specimen_stiffness (best)" in text and "MPa" in text and "BIC" in text
    page = S.compare_report(cmp, str(tmp_path))
    with open(page, encoding="utf-8") as f:
        assert "specimen_stiffness (best)" in f.read()


def test_fit_compare_command_json_and_bad_candidate(stiff, tmp_path, capsys):
    csv = write_csv(stiff, tmp_path / "stiff.csv")
    base = ["-q", "fit", csv, "--starts", "2", "--seed", "1005"]
    assert cli.main([*base, "--compare", "none,specimen_stiffness", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["best"] == "specimen_stiffness" and [r["name"] for r in d["rows"]] == ["none", "specimen_stiffness"]
    assert d["rows"][1]["params"]["k_spec"]["unit"] == "N/m"
    assert cli.main([*base, "--compare", "none,no_such_effect"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "no_such_effect" in err
