"""The report of ``twin fit``: compare, resid, parameters with both standard errors, correlation, timing."""

from __future__ import annotations

import math
from typing import Any
from collections.abc import Mapping, Sequence

import numpy as np

from twin.models import get_model
from twin.reports import page as P
from twin.reports import views
from twin.reports.units import Shown, fmt, pct, pretty_unit, signal_unit

#: records shown in the compare view (the fit uses them all)
MAX_RECORDS_SHOWN = 3


def _get(result: Any, key: str, default=None):
    if isinstance(result, Mapping):
        return result.get(key, default)
    return getattr(result, key, default)


def _param_rows(result: Any, model: str) -> list[dict]:
    if isinstance(result, Mapping):  # FitResult.to_dict()
        items = [(n, d["value"], d.get("std"), d.get("std_white"), d.get("unit")) for n, d in result["params"].items()]
        specs = {}
    else:
        items = [(n, result.estimate[n], result.std.get(n), result.std_white.get(n), None) for n in result.free]
        specs = {s.name: s for s in result.params.specs}
    rows = []
    for n, v, s, sw, unit in items:
        sh = Shown(n, model, unit, spec=specs.get(n))
        rel = abs(s / v) * 100 if (s is not None and v and math.isfinite(s)) else None
        ratio = (s / sw) if (s is not None and sw and math.isfinite(s) and math.isfinite(sw)) else None
        lo = v - views.Z95 * s if s is not None and math.isfinite(s) else None
        hi = v + views.Z95 * s if s is not None and math.isfinite(s) else None
        rows.append({"parameter": n, "estimate": sh.text(v, 7, unit=False), "std (HAC)": sh.text(s, 3, unit=False),
                     "std (textbook)": sh.text(sw, 3, unit=False), "HAC / textbook": fmt(ratio, 3),
                     "relative std": pct(rel, 3),
                     "95 % interval": f"{sh.text(lo, 6, unit=False)} … {sh.text(hi, 6, unit=False)}",
                     "unit": sh.unit_text})
    return rows


def _timing_text(timing: Mapping | None) -> list[dict]:
    t = dict(timing or {})
    ctrl = t.get("controller", "digital")
    rate = t.get("rate_hz")
    inter = t.get("intersample")
    return [
        {"setting": "controller", "value": ctrl if ctrl == "continuous" else f"digital, {fmt(rate)} Hz" if rate
         else "digital, at the log's sample rate"},
        {"setting": "intersample behaviour of the logged inputs", "value": inter or "zero-order hold (default)"},
    ]


def fit_report(result, records: Sequence, model, out_dir: str, *, title: str | None = None,
               filename: str = "fit_report.html", max_lag: int = 25) -> str:
    """Write the HTML report of a fit; returns its path.

    ``result``: a :class:`twin.estimation.fit.FitResult` (or its ``to_dict()`` plus a
    ``"predicted"`` list of ``{output: array}`` per record); ``records``: the
    :class:`twin.record.Record` objects fitted (order as in the fit);
    ``model``: the model or its name.
    """
    model_name = model if isinstance(model, str) else model.name
    outputs = list(_get(result, "outputs"))
    fit_pct = dict(_get(result, "fit_pct"))
    predicted = list(_get(result, "predicted") or [])
    success = bool(_get(result, "success"))
    facts = {"model": model_name, "records": ", ".join(getattr(r, "name", "?") for r in records),
             "outputs": ", ".join(outputs),
             "Fit": ", ".join(f"{o} {fit_pct[o]:.2f} %" for o in outputs),
             "converged": "yes" if success else "NO"}
    for i, w in enumerate(_get(result, "warnings") or []):
        facts[f"WARNING {i + 1}" if i else "WARNING"] = str(w)
    for i, c in enumerate(_get(result, "caveats") or []):
        facts[f"CAVEAT {i + 1}" if i else "CAVEAT"] = str(c)
    pg = P.Page(title or f"twin fit: {model_name}", facts, kind="fit")

    # compare
    body = []
    if predicted:
        for r, (rec, pred) in enumerate(zip(records[:MAX_RECORDS_SHOWN], predicted)):
            outs = []
            for o in outputs:
                unit, sc = signal_unit(o, model_name)
                rec_fit = _fit_pct(rec[o], pred[o])
                outs.append({"name": o, "unit": unit, "scale": sc, "measured": rec[o],
                             "models": [(f"simulated: Fit {rec_fit:.2f} %", pred[o])],
                             "title": f"{o}: measured vs simulated, Fit {rec_fit:.2f} % ({getattr(rec, 'name', r)})"})
            fig = views.compare_figure(rec.t_s, outs)
            body.append(P.figure(fig, f"Record {getattr(rec, 'name', r)}: measured (grey) and simulated (blue) "
                                 "output, the error (measured − simulated) under each; right: a zoom where the "
                                 f"error is largest, {views.zoom_text(fig)}."))
        if len(records) > MAX_RECORDS_SHOWN:
            body.append(P.note(f"{len(records) - MAX_RECORDS_SHOWN} more record(s) fitted, not drawn."))
    else:
        body.append(P.note("no simulated outputs in the result: compare view not available"))
    snr = snr_rows(result, records, model_name)
    body.append(P.table([{"output": o, "Fit": pct(fit_pct[o]), "best Fit the noise allows": pct(snr[o]["best_pct"], 3),
                          "NRMSE": fmt(_get(result, "nrmse")[o], 4),
                          "RMS error": f"{fmt(math.sqrt(_get(result, 'mse')[o]) * signal_unit(o, model_name)[1], 4)} "
                                       f"{signal_unit(o, model_name)[0]}",
                          "noise σ": f"{fmt(snr[o]['noise'] * signal_unit(o, model_name)[1], 3)} "
                                     f"{signal_unit(o, model_name)[0]}"} for o in outputs]))
    body.append(P.note("Fit = 100 (1 − ‖y − ŷ‖ / ‖y − mean y‖) over all records, as MATLAB's compare. Even an exact "
                       "model leaves the sensor noise: its best Fit is 100 (1 − σ √N / ‖y − mean y‖) (σ: the noise "
                       "level the fit weighted the output with)."))
    for o in outputs:
        if snr[o]["note"]:
            body.append(f'<p class="snr">{P.badge("MODEL MISSES" if snr[o]["model_misses"] else "LOW SNR", "warn" if snr[o]["model_misses"] else "info")} '
                        f"{P.esc(snr[o]['note'])}</p>")
    pg.add("compare", "Measured vs simulated (compare)", "\n".join(body))

    # resid
    if predicted:
        res = {o: np.concatenate([rec[o] - pred[o] for rec, pred in zip(records, predicted)]) for o in outputs}
        ins = {}
        for name in ("x_ref", "u"):
            if all(name in rec for rec in records):
                ins[name] = np.concatenate([rec[name] for rec in records])
        closed = ("u",) if get_model(model_name).CLOSED_LOOP else ()
        dt = float(records[0].dt)
        fig = views.resid_figure(res, ins, dt, max_lag=max_lag, closed_loop=closed)
        cap = (f"Residual analysis over {len(records)} record(s), lags up to {max_lag} samples: autocorrelation "
               "with the 99 % band ±2.58/√N (white residuals stay inside), cross-correlation with the inputs "
               "with Bartlett's 99 % band.")
        txt = [P.figure(fig, cap)]
        if closed:
            txt.append(P.note("Closed loop: u is computed from the measured x, so the residual correlates with u "
                              "at negative lags (feedback, shaded); only lags ≥ 0 point at a model error. "
                              "Output-error residuals of a closed loop are coloured by the sensor noise going "
                              "round the loop even for an exact model: the HAC standard errors account for that."))
        pg.add("resid", "Residual analysis (resid)", "\n".join(txt))
    else:
        pg.add("resid", "Residual analysis (resid)", P.note("no simulated outputs: residuals not available"))

    # parameters
    rows = _param_rows(result, model_name)
    body = [P.table(rows, ["parameter", "estimate", "std (HAC)", "std (textbook)", "HAC / textbook",
                           "relative std", "95 % interval", "unit"], text_columns=("parameter", "unit"))]
    body.append(P.note("std (HAC): Newey–West sandwich standard error, honest for coloured residuals; "
                       "std (textbook): s² (JᵀJ)⁻¹, valid only for white residuals. Values in display units."))
    figs = [{"figure": lbl, "value": fmt(_get(result, k), 8)}
            for k, lbl in (("aic", "AIC"), ("aicc", "AICc"), ("bic", "BIC"), ("fpe", "FPE"), ("loglik", "log-likelihood"))]
    figs += [{"figure": "samples × outputs (N)", "value": str(_get(result, "n_obs"))},
             {"figure": "estimated quantities (p)", "value": str(_get(result, "n_par"))},
             {"figure": "function evaluations", "value": str(_get(result, "nfev"))},
             {"figure": "time", "value": f"{fmt(_get(result, 'time_s'), 3)} s"},
             {"figure": "solver", "value": ("converged: " if success else "NOT converged: ") + str(_get(result, "message"))}]
    body.append(P.table(figs, text_columns=("figure", "value")))
    pg.add("parameters", "Parameters", "\n".join(body))

    # correlation
    corr = _get(result, "corr")
    names = list(_get(result, "free") or [])
    if isinstance(corr, Mapping):
        names, corr = corr["names"], np.array(corr["matrix"], dtype=float)
    corr = np.asarray(corr, dtype=float)
    if len(names) > 1:
        body = [P.figure(views.corr_figure(names, corr), "Correlation of the estimated parameters (|ρ| near 1: "
                         "the data hardly separate the pair).")]
        body.append(P.table([{"": a, **{b: fmt(corr[i, j], 4) for j, b in enumerate(names)}}
                             for i, a in enumerate(names)], text_columns=("",)))
    else:
        body = [P.note("one free parameter: no correlation to show")]
    pg.add("correlation", "Correlation matrix", "\n".join(body))

    # loop timing and the rest
    init = _get(result, "init") or []
    body = [P.table(_timing_text(_get(result, "timing")), text_columns=("setting", "value"))]
    if any(init):
        body.append(P.note("Initial state of each record (read off the data, refined where estimated):"))
        body.append(P.table([{"record": getattr(rec, "name", i), **{_init_label(k, model_name): _init_value(k, v, model_name)
                                                                     for k, v in d.items()}}
                             for i, (rec, d) in enumerate(zip(records, init))], text_columns=("record",)))
    pg.add("timing", "Loop timing used", "\n".join(body))

    hist = _get(result, "history") or []
    if hist:
        pg.add("convergence", "Convergence", P.figure(_convergence(hist), "Cost of each refined start per iteration."))
    if not isinstance(result, Mapping) and predicted:  # present-style summary, k-step prediction, valve Bode plot
        from twin.reports.summary import add_sections

        add_sections(pg, result, records)
    return pg.write(out_dir, filename)


#: initial-state quantity -> the signal whose display unit it is shown in (``v0`` as a velocity)
_INIT_SIGNAL = {"x0": "x", "v0": "v", "dp0": "pA", "pA0": "pA", "pB0": "pB", "u0": "u"}


def _init_label(name: str, model: str) -> str:
    """``x0 [mm]``, ``pA0 [MPa]``: an initial-state column with its display unit."""
    from twin.reports.units import label

    return label(name, signal_unit(_INIT_SIGNAL.get(name, name), model)[0])


def _init_value(name: str, value, model: str) -> str:
    """In the display unit, fixed point to 0.1 µm, 0.1 kPa, 0.1 mV (a start near zero reads 0.0000, not 6.8e-05)."""
    if value is None or not math.isfinite(float(value)):
        return "n/a"
    return f"{float(value) * signal_unit(_INIT_SIGNAL.get(name, name), model)[1]:.4f}"


#: a Fit % the noise alone keeps below this is explained in the report as a low signal-to-noise ratio (a
#: MATLAB user reads a Fit under 90 % as a poor model)
LOW_FIT_PCT = 90.0


def snr_rows(result, records: Sequence, model: str) -> dict[str, dict]:
    """Per output: the noise level ``noise`` (SI std: the fit's weighting noise, else the sensor's default),
    the best Fit % an exact model reaches under that noise ``best_pct`` (``100 (1 − σ √N / ‖y − mean y‖)``),
    the share of the signal's power above the noise that the model explains ``explained``
    (``1 − (mse − σ²) / (var y − σ²)``), and a ``note`` for the report when the best Fit is low (below
    ``LOW_FIT_PCT``): how far the signal swings against the noise, and whether the model explains most of
    what is above the noise (a low signal-to-noise ratio) or not (``model_misses``)."""
    from twin.estimation.fit import noise_levels

    given = _get(result, "noise") or {}
    if isinstance(_get(result, "noise_levels"), Mapping):
        given = {o: v.get("value") for o, v in _get(result, "noise_levels").items() if isinstance(v, Mapping)}
    outputs = list(_get(result, "outputs"))
    fallback = noise_levels(get_model(model), records, outputs) if records else {}
    fit_pct = dict(_get(result, "fit_pct"))
    mse = dict(_get(result, "mse") or {})
    out = {}
    for o in outputs:
        sigma = float(given.get(o) or fallback.get(o) or 0.0)
        ys = [np.asarray(r[o], float) for r in records if o in getattr(r, "signals", r)]
        y = np.concatenate(ys) if ys else np.zeros(0)
        den = float(np.linalg.norm(y - y.mean())) if y.size else 0.0
        best = 100.0 * (1.0 - sigma * math.sqrt(y.size) / den) if den > 0 and sigma > 0 else None
        above = float(np.var(y)) - sigma ** 2 if y.size else 0.0  # the signal's power above the noise
        m = float(mse.get(o, float("nan")))
        explained = 1.0 - max(m - sigma ** 2, 0.0) / above if above > 0 and math.isfinite(m) else None
        row = {"noise": sigma, "best_pct": best, "explained": explained, "note": "", "model_misses": False}
        if best is not None and best < LOW_FIT_PCT:
            unit, sc = signal_unit(o, model)
            u = pretty_unit(unit)
            misses = explained is not None and explained < 0.5
            row["model_misses"] = misses
            head = (f"Low signal-to-noise ratio: {o} swings {fmt(float(np.ptp(y)) * sc, 3)} {u} (peak to peak, "
                    f"standard deviation {fmt(float(np.std(y)) * sc, 3)} {u}) under {fmt(sigma * sc, 3)} {u} of "
                    f"sensor noise: the best achievable Fit is about {max(best, 0.0):.0f} %; this fit reaches "
                    f"{fit_pct[o]:.1f} %")
            if explained is None:
                row["note"] = head + f". {o} does not rise above its noise: no model can fit it."
            else:
                row["note"] = head + (f" and explains {100 * max(explained, 0.0):.0f} % of the signal's power above "
                                      "the noise. " + ("The model misses something in this output." if misses else
                                                       "A low Fit here is the sensor, not the model."))
        out[o] = row
    return out


def _fit_pct(y, yh) -> float:
    y = np.asarray(y, float)
    e = y - np.asarray(yh, float)
    den = float(np.linalg.norm(y - y.mean()))
    return 100.0 * (1.0 - float(np.linalg.norm(e)) / den) if den > 0 else float("nan")


def _convergence(hist: Sequence[dict]):
    pl = views.plt()
    with pl.rc_context(views.RC):
        fig, ax = pl.subplots(figsize=(7.5, 2.6))
        for s in sorted({h["start"] for h in hist}):
            hs = [h for h in hist if h["start"] == s]
            ax.semilogy([h["iteration"] for h in hs], [max(h["cost"], 1e-300) for h in hs], "o-", ms=3,
                        label=f"start {s}")
        ax.set_xlabel("iteration")
        ax.set_ylabel("cost ½‖r‖² (weighted)")
        ax.legend()
        fig.tight_layout()
    return fig
