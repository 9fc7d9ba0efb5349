"""The report of ``twin diagnose``: verdict, nominal vs extended model, gains with intervals, p-values."""

from __future__ import annotations

import math
from typing import Any
from collections.abc import Mapping, Sequence

import numpy as np

from twin.reports import page as P
from twin.reports import views
from twin.reports.units import Shown, fmt, pct, pretty_unit, signal_unit
from twin.reports.signatures import signature_data

VERDICT_BADGE = {"adequate": "ok", "explained": "info", "partly explained": "warn", "unexplained": "bad"}
VERDICT_TEXT = {
    "adequate": "The nominal model is adequate: its one-step prediction errors are white and no larger on "
                "held-out data; nothing in the catalogue is needed.",
    "explained": "The nominal model misses something; the named effect(s) explain it: with them the model is "
                 "adequate and predicts held-out data better.",
    "partly explained": "The named effect(s) improve the model, but what is left is still not adequate: "
                        "something outside the catalogue remains (see the residual signature).",
    "unexplained": "The nominal model is not adequate and no catalogue effect explains what is wrong: the "
                   "residual signature is shown instead of a forced name.",
}


def compare_data(diagnosis: Any) -> dict | None:
    """The arrays of the before/after view from a :class:`twin.estimation.diagnose.Diagnosis` (first record):
    ``t``, ``n_fit``, ``measured``, ``nominal``, ``extended`` (``{output: SI array}``); ``None`` from a dict."""
    try:
        rec = diagnosis.records[0]
        outs = list(diagnosis.outputs)
        return {"t": rec.t_s, "n_fit": int(diagnosis.n_fit[0]), "record": getattr(rec, "name", ""),
                "measured": {o: rec[o] for o in outs},
                "nominal": {o: diagnosis.nominal.predicted[0][o] for o in outs},
                "extended": {o: diagnosis.final.predicted[0][o] for o in outs} if diagnosis.causes else None}
    except (AttributeError, IndexError, KeyError, TypeError):
        return None


def diagnose_report(diagnosis: Any, out_dir: str, *, compare: Mapping | None = None, title: str | None = None,
                    filename: str = "diagnose_report.html") -> str:
    """Write the HTML report of a diagnosis; returns its path.

    ``diagnosis``: a :class:`twin.estimation.diagnose.Diagnosis` or its ``to_dict()`` (the
    JSON of ``twin diagnose --json``).  The before/after plot needs the records
    and predictions: they come from the object, or from ``compare`` (see
    :func:`compare_data`); from a bare dict the plot is replaced by a note.
    """
    d = diagnosis.to_dict() if hasattr(diagnosis, "to_dict") else dict(diagnosis)
    compare = compare if compare is not None else compare_data(diagnosis)
    model = d["model"]
    verdict = d["verdict"]
    outputs = list(d["outputs"])
    causes = list(d["causes"])
    alpha = float(d.get("alpha", 1e-3))
    facts = {"model": model, "outputs": ", ".join(outputs), "verdict": verdict,
             "causes": ", ".join(causes) or "none",
             "held out": f"last {100 * d.get('holdout_fraction', 0.25):.0f} % of each record",
             "α (family-wise)": fmt(alpha), "time": f"{fmt(d.get('time_s'), 3)} s"}
    pg = P.Page(title or f"twin diagnose: {model}", facts, kind="diagnose")

    # verdict
    body = [f"<p>{P.badge(verdict.upper(), VERDICT_BADGE.get(verdict, 'info'))} {P.esc(VERDICT_TEXT.get(verdict, ''))}</p>"]
    rows = []
    for c in causes:
        for name, v in d["effects"][c]["params"].items():
            if c == "controller_rate":
                rows.append({"cause": c, "parameter": "loop timing", "estimate": v.get("shown", ""), "std": "",
                             "unit": ""})
                continue
            sh = Shown(name, model, v.get("unit"))
            rows.append({"cause": c, "parameter": name, "estimate": sh.text(v["value"], 6, unit=False),
                         "std": sh.text(v.get("std"), 3, unit=False), "unit": sh.unit_text})
    if rows:
        body.append(P.table(rows, text_columns=("cause", "parameter", "unit")))
    ta, tf = d.get("timing_assumed") or {}, d.get("timing_final") or {}
    if ta != tf:
        body.append(P.note(f"loop timing assumed: {_timing(ta)}; found: {_timing(tf)}"))
    else:
        body.append(P.note(f"loop timing: {_timing(ta)}"))
    for e, v in (d.get("not_testable") or {}).items():
        body.append(P.note(f"not tested: {e}, mimicked by the free {', '.join(v.get('mimicked_by', []))}: "
                           f"{v.get('why', '')}"))
    pg.add("verdict", "Verdict", "\n".join(body))

    # nominal vs extended
    body = []
    if compare is not None:
        t = np.asarray(compare["t"])
        n_fit = int(compare["n_fit"])
        sl = slice(n_fit, t.size)
        outs = []
        for o in outputs:
            unit, sc = signal_unit(o, model)
            models = [("nominal", np.asarray(compare["nominal"][o])[sl])]
            if compare.get("extended") is not None:
                models.append(("extended: " + " + ".join(causes), np.asarray(compare["extended"][o])[sl]))
            outs.append({"name": o, "unit": unit, "scale": sc, "measured": np.asarray(compare["measured"][o])[sl],
                         "models": models, "title": f"{o}: held-out part, measured vs nominal"
                         + (" vs extended" if len(models) > 1 else "")})
        fig = views.compare_figure(t[sl], outs)
        lines = ("nominal model (blue), extended model (orange, dashed)" if compare.get("extended") is not None
                 else "nominal model (blue; no effect was found, so there is no extended model)")
        body.append(P.figure(fig, "Held-out part of the first record (not used by the fits): measured (grey), "
                             f"{lines}; errors under each. Right: a zoom where the error is largest, "
                             f"{views.zoom_text(fig)}."))
    else:
        body.append(P.note("the records are not in a diagnosis read from JSON: pass the Diagnosis object (or "
                           "compare=...) for the before/after plot"))
    before = (d.get("nominal") or {}).get("holdout", {})
    after = (d.get("extended") or {}).get("holdout", {}) if d.get("extended") else {}
    rows = []
    for o in outputs:
        b = before.get(o, {})
        a = after.get(o, {})
        rows.append({"output": o, "held-out Fit, nominal": pct(b.get("fit_pct")),
                     "held-out Fit, extended": pct(a.get("fit_pct")) if a else "—",
                     "NRMSE, nominal": fmt(b.get("nrmse"), 4), "NRMSE, extended": fmt(a.get("nrmse"), 4) if a else "—"})
    body.append(P.table(rows))
    pg.add("compare", "Nominal vs extended model (before / after)" if d.get("extended") else
           "The nominal model on held-out data (no extended model: nothing to add)", "\n".join(body))

    # the simulation error per output with its noise band
    noise = ((d.get("nominal") or {}).get("residuals") or {}).get("noise") or {}
    if compare is not None:
        t = np.asarray(compare["t"])
        n_fit = int(compare["n_fit"])
        outs = []
        for o in outputs:
            unit, sc = signal_unit(o, model)
            y = np.asarray(compare["measured"][o])
            errs = [("nominal", y - np.asarray(compare["nominal"][o]))]
            if compare.get("extended") is not None:
                errs.append(("extended", y - np.asarray(compare["extended"][o])))
            outs.append({"name": o, "unit": unit, "scale": sc, "errors": errs, "noise": _noise_of(o, noise, errs)})
        fig = views.error_figure(t, outs, t_split=float(t[n_fit]) if 0 < n_fit < t.size else None)
        rows = [{"output": o["name"], "noise σ": f"{fmt(o['noise'] * o['scale'], 3)} {pretty_unit(o['unit'])}",
                 **{f"RMS error, {lbl}": f"{fmt(float(np.sqrt(np.mean(e ** 2))) * o['scale'], 3)} "
                                         f"{pretty_unit(o['unit'])}" for lbl, e in o["errors"]}} for o in outs]
        body = [P.figure(fig, "Simulation error (measured − simulated) of each output over the whole record, "
                         "with the band ±1.96 σ of the sensor noise (σ: the residual's noise floor, from its "
                         "sample-to-sample differences): inside the band the error is the noise; dotted: the "
                         f"start of the held-out part. Right: a zoom where the error is largest, {views.zoom_text(fig)}."),
                P.table(rows, text_columns=("output",))]
    else:
        body = [P.note("the records are not in a diagnosis read from JSON: pass the Diagnosis object (or "
                       "compare=...) for the error panel")]
    pg.add("error", "Simulation error and the noise band", "\n".join(body))

    # gains
    body = []
    if causes:
        gains = [(c, d["effects"][c]["gain"]) for c in causes]
        body.append(P.figure(_gain_figure(gains), "Held-out gain of each accepted effect (relative reduction of "
                             "the held-out one-step prediction errors' sum of squares) with its 95 % "
                             "block-bootstrap interval; accepted only when the interval is above 0."))
        body.append(P.table([{"cause": c, "held-out gain": pct(_times100(g.get("holdout_gain")), 3),
                              "95 % interval": _interval(g.get("holdout_gain_interval")),
                              "LR": fmt(g.get("lr"), 5), "df": g.get("df"), "p": _p(g.get("p")),
                              "p (Holm)": _p(g.get("p_adjusted")), "ΔAICc": fmt(g.get("delta_aicc"), 5),
                              "share of the misfit removed": pct(100 * g["share"], 3) if g.get("share") is not None
                              else "n/a"} for c, g in gains], text_columns=("cause",)))
    else:
        body.append(P.note("no effect accepted: no gain to show"))
    pg.add("gain", "Gain and its interval", "\n".join(body))

    # each cause's signature
    if causes:
        sigs = signature_data(diagnosis)
        body = []
        for sig in sigs:
            cap = (f"Signature of {sig['cause']}: the residual of {sig['signal']} before it was added (binned by "
                   f"{sig['axis']}, mean ± 1.96 standard errors) and its contribution (red); the vertical scale is "
                   "the binned curves', the samples behind go beyond it.")
            if sig["flat"]:
                cap += (f" Flat in this view: {sig['cause']} changes the binned {sig['signal']} by "
                        f"{fmt(sig['span'] * sig['scale'], 3)} {pretty_unit(sig['unit'])}, less than twice a bin "
                        f"mean's scatter ({fmt(sig['scatter'] * sig['scale'], 3)} {pretty_unit(sig['unit'])}): its "
                        "evidence is the held-out gain and the likelihood ratio above, spread over the record.")
            body.append(P.figure(views.signature_figure(sig), cap))
        if not sigs:
            body.append(P.note("the records are not in a diagnosis read from JSON: pass the Diagnosis object for "
                               "each cause's signature"))
        pg.add("signatures", "What each cause changes (its signature)", "\n".join(body))

    # screens and trials: corrected p-values
    body = []
    for i, screen in enumerate(d.get("screens") or []):
        body.append(f"<h3>Screen {i + 1}</h3>")
        if screen:
            body.append(P.figure(_screen_figure(screen, alpha), f"Score test of every candidate effect, screen "
                                 f"{i + 1}: Holm-corrected p-value; bars beyond the line (α = {alpha:g}) are fitted."))
        body.append(P.table([{"effect": r["effect"], "LM": fmt(r["lm"], 5), "p": _p(r["p"]),
                              "p × probes": _p(r["p_effect"]), "p (Holm)": _p(r["p_adjusted"]),
                              "share": fmt(r.get("share"), 3), "probe": r.get("probe", "")}
                             for r in screen], text_columns=("effect", "probe"),
                            flag=lambda r: r["p (Holm)"] != "n/a" and float(r["p (Holm)"].lstrip("<")) < alpha))
        trials = (d.get("trials") or [])[i] if i < len(d.get("trials") or []) else []
        if trials:
            body.append(P.table([{"fitted": t["effect"], "LR": fmt(t["lr"], 5), "df": t["df"],
                                  "p (Holm)": _p(t["p_adjusted"]), "ΔAICc": fmt(t["delta_aicc"], 5),
                                  "held-out gain": pct(_times100(t.get("holdout_gain")), 3),
                                  "95 % interval": _interval(t.get("holdout_gain_interval")),
                                  "converged": "yes" if t.get("converged") else "NO",
                                  "decision": "ACCEPTED" if t["accepted"] else "rejected", "why": t.get("reason", "")}
                                 for t in trials], text_columns=("fitted", "decision"), wrap_columns=("why",),
                                flag=lambda r: r["decision"] == "ACCEPTED"))
    pg.add("pvalues", "Candidates and corrected p-values", "\n".join(body) or P.note("no screen was run"))

    # adequacy of the models
    rows = []
    for label, st in (("nominal", d.get("nominal")), ("extended", d.get("extended"))):
        if not st:
            continue
        a = st.get("adequacy") or {}
        row = {"model": label + (f" ({', '.join(st.get('effects') or [])})" if st.get("effects") else "")}
        for o, w in (a.get("whiteness") or {}).items():
            row[f"Ljung–Box p, {o}"] = _p(w.get("p"))
        h = a.get("holdout") or {}
        row["held-out / fitting innovation power"] = fmt(h.get("ratio"), 4)
        row["p (held-out)"] = _p(h.get("p"))
        row["adequate"] = "yes" if a.get("adequate") else "NO"
        rows.append(row)
    body = [P.table(rows, text_columns=("model",)),
            P.note("Adequate: the one-step prediction errors (output error filtered by the fitted noise model) "
                   "are white and no larger on held-out data, Bonferroni over the tests.")]
    prow = []
    for label, st in (("nominal", d.get("nominal")), ("extended", d.get("extended"))):
        for name, v in ((st or {}).get("params") or {}).items():
            sh = Shown(name, model, v.get("unit"))
            prow.append({"model": label, "parameter": name, "estimate": sh.text(v["value"], 7, unit=False),
                         "std (HAC)": sh.text(v.get("std"), 3, unit=False),
                         "std (textbook)": sh.text(v.get("std_white"), 3, unit=False), "unit": sh.unit_text})
    body.append(P.table(prow, text_columns=("model", "parameter", "unit")))
    pg.add("models", "The models: adequacy and parameters", "\n".join(body))
    if d.get("signature"):
        sig = d["signature"]
        rows = [{"output": o, "Ljung–Box p": _p(v.get("p")), "excess power": fmt((sig.get("excess") or {}).get(o), 4)}
                for o, v in (sig.get("ljung_box") or {}).items()]
        pg.add("signature", "Unexplained: residual signature", P.table(rows))
    return pg.write(out_dir, filename)


def _noise_of(o: str, noise: Mapping, errs) -> float:
    """The noise std of output ``o`` (SI): the diagnosis's noise floor, else the sensor's default, else the
    error's own sample-to-sample scatter."""
    if noise.get(o):
        return float(noise[o])
    from fpdd.units import NOMINAL_NOISE

    if o in NOMINAL_NOISE:
        return float(NOMINAL_NOISE[o])
    e = np.asarray(errs[0][1], float)
    return float(np.std(np.diff(e)) / math.sqrt(2.0)) if e.size > 2 else 0.0


def _timing(t: Mapping) -> str:
    if not t:
        return "n/a"
    c = t.get("controller", "digital")
    s = "continuous controller" if c == "continuous" else (
        f"digital controller at {fmt(t['rate_hz'])} Hz" if t.get("rate_hz") else "digital controller at the log's rate")
    return s + (f", intersample {t['intersample']}" if t.get("intersample") else "")


def _p(p) -> str:
    if p is None:
        return "n/a"
    p = float(p)
    if not math.isfinite(p):
        return "n/a"
    return "<1e-300" if p == 0.0 else f"{p:.3g}"


def _times100(v) -> float | None:
    """A fraction as a percentage; ``None`` (a non-finite figure of a diverged candidate) stays ``None``."""
    return None if v is None or not math.isfinite(float(v)) else 100.0 * float(v)


def _interval(iv: Sequence | None) -> str:
    if not iv or any(v is None for v in iv):
        return "n/a"
    return f"{100 * iv[0]:.3g} … {100 * iv[1]:.3g} %"


def _gain_figure(gains):
    pl = views.plt()
    with pl.rc_context(views.RC):
        fig, ax = pl.subplots(figsize=(7.5, 0.55 * len(gains) + 1.3))
        y = np.arange(len(gains))
        g = np.array([_times100(x.get("holdout_gain")) or 0.0 for _, x in gains])
        iv = np.array([[_times100(v) or 0.0 for v in (x.get("holdout_gain_interval") or [0, 0])] for _, x in gains],
                      dtype=float)
        ax.errorbar(g, y, xerr=[np.maximum(g - iv[:, 0], 0), np.maximum(iv[:, 1] - g, 0)], fmt="o",
                    color=views.BLUE, capsize=4, ms=5, label="gain with 95 % interval")
        ax.axvline(0, color=views.RED, lw=0.9, ls="--", label="no gain")
        ax.set_yticks(y, [c for c, _ in gains])
        ax.set_ylim(-0.7, len(gains) - 0.3)
        ax.set_xlabel("held-out gain [%]")
        ax.legend(loc="lower right", fontsize=7)
        fig.tight_layout()
    return fig


def _screen_figure(screen, alpha: float):
    pl = views.plt()
    rows = sorted(screen, key=lambda r: r["p_adjusted"])
    v = np.array([-math.log10(max(r["p_adjusted"], 1e-300)) for r in rows])
    with pl.rc_context(views.RC):
        fig, ax = pl.subplots(figsize=(7.5, 0.3 * len(rows) + 1.2))
        y = np.arange(len(rows))[::-1]
        colours = [views.ORANGE if r["p_adjusted"] < alpha else "#9e9e9e" for r in rows]
        ax.barh(y, np.maximum(v, 0.02), color=colours)
        ax.axvline(-math.log10(alpha), color=views.RED, lw=0.9, ls="--", label=f"α = {alpha:g}")
        ax.set_yticks(y, [r["effect"] for r in rows])
        line = -math.log10(alpha)
        if v.size and float(np.max(v)) > 10 * line:
            ax.set_xscale("symlog", linthresh=10)
        else:
            ax.set_xlim(0, max(float(np.max(v)) if v.size else 0.0, line) * 1.15)
        ax.set_xlabel("−log₁₀ p (Holm-corrected)")
        ax.legend(loc="lower right")
        fig.tight_layout()
    return fig


def write_diagnosis(diagnosis: Any, out_dir: str) -> str:
    """The whole report of ``twin diagnose --report DIR``: the plots, the extended model
    (``extended_params.json``, for ``twin fit``/``track --params``), the diagnosis as JSON and the HTML page;
    returns the page's path."""
    import os

    from fpdd import jsonio
    from twin.reports.plots import diagnosis_plots

    diagnosis.plots = diagnosis_plots(diagnosis, out_dir)
    jsonio.write(os.path.join(out_dir, "extended_params.json"), diagnosis.extended_params())
    jsonio.write(os.path.join(out_dir, "diagnosis.json"), diagnosis.to_dict())
    return diagnose_report(diagnosis, out_dir)
