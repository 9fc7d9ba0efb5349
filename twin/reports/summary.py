"""What a fit is, in the words of MATLAB's ``present`` and ``compare``: estimates ± standard error with units,
Fit % per output with what the noise allows, a whiteness test of the residuals, k-step-ahead prediction
beside simulation, the identified servo-valve's Bode plot with its uncertainty band, and the comparison table
of several candidate models.

:func:`summarize` returns the summary as a JSON-ready dict (SI, the unit beside every value); :func:`text`
prints it in display units; :func:`add_sections` puts it, the Bode plot and the k-step table into a fit
report page; :func:`compare_text`, :func:`compare_json` and :func:`compare_report` show a
:func:`twin.estimation.compare.compare_models` result.

The signal-to-noise note: an output measured under white noise of standard deviation ``sigma`` cannot be
fitted above ``100 (1 - sigma / s)`` % (``s`` its standard deviation), even by the exact model: a Fit % far
below 100 on a record whose ceiling is low says the noise, not the model.  ``sigma`` is read off the residual's
sample-to-sample differences (:func:`twin.estimation.residuals.noise_level`).  The note appears when the ceiling
is below :data:`LOW_SNR_CEILING_PCT`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.special import chdtrc  # chi2.sf without importing scipy.stats

from twin.estimation import compare as C
from twin.models import DEFAULT_MODEL
from twin.estimation.residuals import ALPHA, ljung_box, noise_level
from twin.reports.units import Shown, fmt, signal_unit

#: the Fit % ceiling under which a summary says a low Fit % is the noise's: 90 % is a signal-to-noise ratio of
#: 10 (20 dB), the usual border of a "clean" measurement (a convention, not tuned on data)
LOW_SNR_CEILING_PCT = 90.0
#: lags of the whiteness (Ljung-Box) test, as the fit report's residual plot
WHITENESS_LAGS = 25
#: the normal quantile of the Bode plot's band (95 %)
Z95 = 1.959963984540054


def _signal_unit_si(o: str) -> str:
    from twin.units import SIGNAL_UNITS

    return SIGNAL_UNITS.get(o, "")


def _output_stats(o: str, records: Sequence, predicted: Sequence[Mapping], alpha: float, lags: int) -> dict:
    ys = [np.asarray(rec[o], dtype=np.float64) for rec in records]
    es = [y - np.asarray(p[o], dtype=np.float64) for y, p in zip(ys, predicted)]
    y = np.concatenate(ys)
    e = np.concatenate(es)
    n = y.size
    s = float(np.std(y))
    sig = math.sqrt(sum(noise_level(x) ** 2 * x.size for x in es) / n)
    rms = float(np.sqrt(np.mean(e * e)))
    ceiling = 100.0 * (1.0 - sig / s) if s > 0 else float("nan")
    q = df = 0.0
    for x in es:
        if x.size > lags + 1:
            lb = ljung_box(x, lags)
            q += lb["Q"]
            df += lb["df"]
    p = float(chdtrc(df, q)) if df else float("nan")
    unit = _signal_unit_si(o)
    return {"fit_pct": C.fit_percent(y, y - e),
            "rms_error": {"value": rms, "unit": unit},
            "noise": {"value": sig, "unit": unit},
            "spread": {"value": s, "unit": unit},
            "snr": s / sig if sig > 0 else float("inf"),
            "fit_ceiling_pct": ceiling,
            "error_to_noise": rms / sig if sig > 0 else float("inf"),
            "whiteness": {"test": "Ljung-Box", "lags": lags, "Q": q, "df": int(df), "p": p, "alpha": alpha,
                          "white": bool(p >= alpha) if math.isfinite(p) else None},
            "low_snr": bool(math.isfinite(ceiling) and ceiling < LOW_SNR_CEILING_PCT)}


def _cov(result: Any) -> np.ndarray:
    std = np.array([result.std[n] for n in result.free], dtype=np.float64)
    corr = np.asarray(result.corr, dtype=np.float64)
    return corr * np.outer(std, std)


def valve_bode(result: Any, freqs_hz: np.ndarray | None = None, points: int = 300) -> dict | None:
    """The identified servo-valve's frequency response ``wn^2 / (s^2 + 2 zeta wn s + wn^2)`` (spool per
    commanded spool position) from the fit's ``wn`` and ``zeta``, with the 95 % band of its magnitude and phase
    from the fit's covariance (delta method; a parameter held fixed adds nothing).  ``None`` for a model
    without a valve.  Arrays: ``f_hz``, ``mag_db``, ``phase_deg`` and their ``_lo``/``_hi`` bounds."""
    if "wn" not in result.params or "zeta" not in result.params:
        return None
    wn, zeta = float(result.params["wn"]), float(result.params["zeta"])
    f0 = wn / (2 * math.pi)
    f = np.logspace(math.log10(f0 / 20), math.log10(f0 * 10), points) if freqs_hz is None else np.asarray(freqs_hz)
    w = 2 * math.pi * f

    def resp(wn_: float, z_: float) -> tuple[np.ndarray, np.ndarray]:
        g = wn_ * wn_ / (wn_ * wn_ - w * w + 2j * z_ * wn_ * w)
        return 20 * np.log10(np.abs(g)), np.degrees(np.angle(g))

    mag, ph = resp(wn, zeta)
    names = [n for n in ("wn", "zeta") if n in result.free]
    var_m = np.zeros_like(f)
    var_p = np.zeros_like(f)
    if names:
        idx = [list(result.free).index(n) for n in names]
        cov = _cov(result)[np.ix_(idx, idx)]
        if np.all(np.isfinite(cov)):
            G_m, G_p = [], []
            for n in names:
                h = 1e-6 * (wn if n == "wn" else zeta)
                a = resp(wn + h, zeta) if n == "wn" else resp(wn, zeta + h)
                b = resp(wn - h, zeta) if n == "wn" else resp(wn, zeta - h)
                G_m.append((a[0] - b[0]) / (2 * h))
                G_p.append((a[1] - b[1]) / (2 * h))
            Gm, Gp = np.array(G_m), np.array(G_p)
            var_m = np.einsum("if,ij,jf->f", Gm, cov, Gm)
            var_p = np.einsum("if,ij,jf->f", Gp, cov, Gp)
    sm, sp = np.sqrt(np.clip(var_m, 0, None)), np.sqrt(np.clip(var_p, 0, None))
    # the -3 dB bandwidth and its standard error (delta method through the same covariance)
    bw, bw_std = _bandwidth(wn, zeta, result, names)
    return {"f_hz": f, "mag_db": mag, "mag_db_lo": mag - Z95 * sm, "mag_db_hi": mag + Z95 * sm,
            "phase_deg": ph, "phase_deg_lo": ph - Z95 * sp, "phase_deg_hi": ph + Z95 * sp,
            "wn": wn, "zeta": zeta, "uncertain": names, "bandwidth_hz": bw, "bandwidth_std_hz": bw_std}


def _bw(wn: float, zeta: float) -> float:
    """-3 dB frequency [Hz] of the normalised second-order low-pass (closed form)."""
    a = 1 - 2 * zeta * zeta
    return wn * math.sqrt(a + math.sqrt(a * a + 1)) / (2 * math.pi)


def _bandwidth(wn: float, zeta: float, result: Any, names: Sequence[str]) -> tuple[float, float]:
    bw = _bw(wn, zeta)
    if not names:
        return bw, 0.0
    idx = [list(result.free).index(n) for n in names]
    cov = _cov(result)[np.ix_(idx, idx)]
    if not np.all(np.isfinite(cov)):
        return bw, float("nan")
    g = []
    for n in names:
        h = 1e-6 * (wn if n == "wn" else zeta)
        g.append((_bw(wn + h, zeta) - _bw(wn - h, zeta)) / (2 * h) if n == "wn"
                 else (_bw(wn, zeta + h) - _bw(wn, zeta - h)) / (2 * h))
    gv = np.array(g)
    return bw, float(math.sqrt(max(float(gv @ cov @ gv), 0.0)))


def summarize(result: Any, records: Sequence, horizons: Sequence[float] = C.DEFAULT_HORIZONS,
              alpha: float = ALPHA, lags: int = WHITENESS_LAGS, drive: str = "auto") -> dict:
    """The ``present``-style summary of a :class:`~twin.estimation.fit.FitResult` on the ``records`` it was
    fitted to (JSON-ready: SI values with their units; module docstring)."""
    from twin.models import get_model

    model = get_model(result.model)
    specs = {s.name: s for s in result.params.specs}
    params = {n: {"value": float(result.estimate[n]), "std": float(result.std[n]), "unit": specs[n].unit}
              for n in result.free}
    predicted = list(result.predicted)
    outputs = {o: _output_stats(o, records, predicted, alpha, lags) for o in result.outputs}
    ahead = C.fit_by_horizon(model, result.params, records, horizons, drive, result.timing, result.init,
                             result.outputs)
    for o, d in outputs.items():
        d["fit_pct_ahead"] = {k: ahead[k][o] for k in ahead}
    notes = []
    for o, d in outputs.items():
        if d["low_snr"]:
            u, sc = signal_unit(o, result.model)
            notes.append(f"Fit({o}) = {d['fit_pct']:.1f} % is a low signal-to-noise ratio: {o} varies "
                         f"{fmt(d['spread']['value'] * sc, 3)} {u} rms under {fmt(d['noise']['value'] * sc, 3)} {u} "
                         f"of noise (SNR {d['snr']:.2g}), so even the exact model scores at most "
                         f"{d['fit_ceiling_pct']:.1f} %; the error is {d['error_to_noise']:.2f} x the noise")
    out: dict = {"model": result.model, "records": [getattr(r, "name", str(i)) for i, r in enumerate(records)],
                 "converged": bool(result.success), "params": params, "outputs": outputs,
                 "horizons": list(ahead), "criteria": {"aic": result.aic, "bic": result.bic, "fpe": result.fpe,
                                                       "n_obs": result.n_obs, "n_par": result.n_par},
                 "notes": notes}
    b = valve_bode(result)
    if b is not None:
        out["valve"] = {"wn": {"value": b["wn"], "unit": "rad/s"}, "zeta": {"value": b["zeta"], "unit": "1"},
                        "bandwidth_3db": {"value": 2 * math.pi * b["bandwidth_hz"],
                                          "std": 2 * math.pi * b["bandwidth_std_hz"], "unit": "rad/s"}}
    return out


def text(summary: Mapping, model: str | None = None) -> str:
    """The summary in display units, as MATLAB's ``present``."""
    model = model or summary["model"]
    lines = [f"{model}: {'converged' if summary['converged'] else 'NOT converged'}, "
             f"{len(summary['records'])} record(s), N = {summary['criteria']['n_obs']}"]
    lines.append("Free parameters (estimate ± std, HAC):")
    for n, d in summary["params"].items():
        sh = Shown(n, model, d["unit"])
        lines.append(f"  {n:<10} = {sh.text(d['value'], 6, unit=False)} ± {sh.text(d['std'], 3, unit=False)}"
                     + (f" {sh.unit_text}" if sh.unit_text else ""))
    ks = summary["horizons"]
    head = f"  {'output':<7}{'Fit %':>8}{'ceiling':>9}  " + "".join(f"{'k=' + k:>9}" for k in ks)
    lines.append("Outputs (Fit %: simulation; ceiling: the most the noise allows; k: k-step-ahead prediction):")
    lines.append(head + "   whiteness (Ljung-Box)")
    for o, d in summary["outputs"].items():
        w = d["whiteness"]
        verdict = "n/a" if w["white"] is None else (f"{'pass' if w['white'] else 'FAIL'} "
                                                     f"(p = {w['p']:.2g}, {w['lags']} lags)")
        lines.append(f"  {o:<7}{d['fit_pct']:8.2f}{d['fit_ceiling_pct']:9.2f}  "
                     + "".join(f"{d['fit_pct_ahead'][k]:9.2f}" for k in ks) + f"   {verdict}")
    c = summary["criteria"]
    lines.append(f"AIC = {c['aic']:.6g}, BIC = {c['bic']:.6g}, FPE = {c['fpe']:.4g} (N = {c['n_obs']}, "
                 f"p = {c['n_par']})")
    v = summary.get("valve")
    if v:
        lines.append(f"Servo-valve: wn = {v['wn']['value'] / (2 * math.pi):.4g} Hz, zeta = {v['zeta']['value']:.4g}, "
                     f"-3 dB bandwidth {v['bandwidth_3db']['value'] / (2 * math.pi):.4g} ± "
                     f"{v['bandwidth_3db']['std'] / (2 * math.pi):.2g} Hz")
    lines.extend(f"NOTE: {n}" for n in summary["notes"])
    return "\n".join(lines)


# --- report sections ---------------------------------------------------------------------------------------
def bode_figure(b: Mapping):
    from twin.reports import views

    pl = views.plt()
    with pl.rc_context(views.RC):
        fig, (a1, a2) = pl.subplots(2, 1, figsize=(7.5, 4.6), sharex=True)
        f = b["f_hz"]
        a1.semilogx(f, b["mag_db"], color="#0072BD", label="identified")
        a1.fill_between(f, b["mag_db_lo"], b["mag_db_hi"], color="#0072BD", alpha=0.25, lw=0, label="95 % band")
        a1.set_ylabel("magnitude [dB]")
        a1.legend(loc="lower left")
        a2.semilogx(f, b["phase_deg"], color="#0072BD")
        a2.fill_between(f, b["phase_deg_lo"], b["phase_deg_hi"], color="#0072BD", alpha=0.25, lw=0)
        a2.set_ylabel("phase [deg]")
        a2.set_xlabel("frequency [Hz]")
        a2.set_yticks([0, -45, -90, -135, -180])
        fig.tight_layout()
    return fig


def add_sections(page, result: Any, records: Sequence, summary: Mapping | None = None) -> dict:
    """Add the summary (``present``), the k-step-ahead table and the valve's Bode plot to a fit report page;
    returns the summary."""
    from twin.reports import page as P

    summary = summary or summarize(result, records)
    model = summary["model"]
    rows = []
    for n, d in summary["params"].items():
        sh = Shown(n, model, d["unit"])
        rows.append({"parameter": n, "estimate ± std": f"{sh.text(d['value'], 6, unit=False)} ± "
                                                       f"{sh.text(d['std'], 3, unit=False)}", "unit": sh.unit_text})
    body = [P.table(rows, text_columns=("parameter", "unit"))]
    orow = []
    for o, d in summary["outputs"].items():
        u, sc = signal_unit(o, model)
        w = d["whiteness"]
        orow.append({"output": o, "Fit": f"{d['fit_pct']:.2f} %", "ceiling (noise)": f"{d['fit_ceiling_pct']:.2f} %",
                     "RMS error": f"{fmt(d['rms_error']['value'] * sc, 4)} {u}",
                     "noise": f"{fmt(d['noise']['value'] * sc, 4)} {u}",
                     "whiteness": "n/a" if w["white"] is None else
                     f"{'pass' if w['white'] else 'fail'} (p = {w['p']:.2g})"})
    body.append(P.table(orow, text_columns=("output", "whiteness")))
    for n in summary["notes"]:
        body.append(P.note(n))
    body.append(P.note(f"Ceiling: the Fit an exact model reaches under the measured noise, 100 (1 − σ/s). "
                       f"Whiteness: Ljung–Box over {WHITENESS_LAGS} lags at α = {ALPHA:g} (a closed loop's "
                       "output-error residual is coloured by the noise going round the loop even for an exact "
                       "model)."))
    page.add("summary", "Summary (present)", "\n".join(body))
    ks = summary["horizons"]
    krows = [{"output": o, **{("simulation" if k == "inf" else f"{k}-step"): f"{d['fit_pct_ahead'][k]:.2f} %"
                              for k in ks}} for o, d in summary["outputs"].items()]
    page.add("ahead", "k-step-ahead prediction (compare, k)",
             P.table(krows, text_columns=("output",)) +
             P.note("Fit % of the k-step-ahead prediction ŷ(t | t − k): the simulation plus an AR disturbance "
                    "model of its error (order by BIC) predicting k samples ahead; k = ∞ is the simulation."))
    b = valve_bode(result)
    if b is not None:
        cap = (f"Identified servo-valve wn²/(s² + 2ζ wn s + wn²): wn = {b['wn'] / (2 * math.pi):.4g} Hz, "
               f"ζ = {b['zeta']:.4g}, −3 dB at {b['bandwidth_hz']:.4g} ± {b['bandwidth_std_hz']:.2g} Hz; "
               + ("the band is the 95 % interval from the fit's covariance of " + " and ".join(b["uncertain"])
                  if b["uncertain"] else "wn and ζ held fixed: no band"))
        page.add("bode", "Servo-valve Bode plot", P.figure(bode_figure(b), cap))
    return dict(summary)


# --- several models ----------------------------------------------------------------------------------------
def compare_json(cmp: Mapping) -> dict:
    """A :func:`~twin.estimation.compare.compare_models` result without the fit objects (JSON-ready)."""
    rows = []
    for r in cmp["rows"]:
        d = {k: v for k, v in r.items() if k != "result"}
        res = r.get("result")
        if res is not None:
            specs = {s.name: s for s in res.params.specs}
            d["params"] = {n: {"value": res.estimate[n], "std": res.std[n], "unit": specs[n].unit} for n in res.free}
        rows.append(d)
    return {**{k: v for k, v in cmp.items() if k != "rows"}, "rows": rows}


def _rows_display(cmp: Mapping, model: str) -> list[dict]:
    outs = list(cmp["rows"][0]["fit_pct"]) if cmp["rows"] else []
    rows = []
    for r in cmp["rows"]:
        d = {"model": r["name"] + (" (best)" if r["best"] else ""), "p": str(r["n_par"])}
        for o in outs:
            d[f"Fit {o}"] = f"{r['fit_pct'][o]:.2f} %"
        for o in outs:
            u, sc = signal_unit(o, model)
            d[f"held-out RMS {o}"] = f"{fmt(r['validation_rms'][o]['value'] * sc, 4)} {u}"
        d["AIC"] = f"{r['aic']:.6g}"
        d["BIC"] = f"{r['bic']:.6g}"
        rows.append(d)
    return rows


def compare_text(cmp: Mapping) -> str:
    model = cmp["rows"][0]["model"] if cmp["rows"] else DEFAULT_MODEL
    rows = _rows_display(cmp, model)
    if not rows:
        return "no candidates"
    cols = list(rows[0])
    w = {c: max(len(c), *(len(r[c]) for r in rows)) for c in cols}
    out = ["  ".join(f"{c:<{w[c]}}" if c == "model" else f"{c:>{w[c]}}" for c in cols)]
    out += ["  ".join(f"{r[c]:<{w[c]}}" if c == "model" else f"{r[c]:>{w[c]}}" for c in cols) for r in rows]
    out.append(f"Fit on {', '.join(cmp['estimation'])}; held-out simulation on {', '.join(cmp['validation'])}; "
               f"best by {cmp['criterion']}: {cmp['best']}")
    return "\n".join(out)


def compare_report(cmp: Mapping, out_dir: str, filename: str = "compare_report.html") -> str:
    """The comparison as one self-contained HTML page; returns its path."""
    from twin.reports import page as P

    model = cmp["rows"][0]["model"] if cmp["rows"] else DEFAULT_MODEL
    pg = P.Page(f"twin compare: {model}", {"best": str(cmp["best"]), "criterion": cmp["criterion"],
                                           "estimation": ", ".join(cmp["estimation"]),
                                           "validation": ", ".join(cmp["validation"])}, kind="compare")
    pg.add("compare", "Candidate models", P.table(_rows_display(cmp, model), text_columns=("model",)) + P.note(
        "Fit on the estimation data (simulation); RMS of the simulation error on the held-out data; BIC = "
        "−2 ln L + p ln N, the lowest marked best."))
    return pg.write(out_dir, filename)
