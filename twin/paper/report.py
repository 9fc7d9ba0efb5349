"""The report of ``twin paper``: every case, our estimate and error beside the paper's."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from twin.reports import page as P
from twin.reports import views
from twin.reports.units import Shown, fmt, pct

FLOOR = 1e-14  # an error of exactly 0 is drawn here on the log axis


def paper_report(rows: Sequence[Mapping], out_dir: str, *, elapsed_s: float | None = None,
                 title: str | None = None, filename: str = "paper_report.html") -> str:
    """Write the HTML report of ``twin paper``'s rows (:func:`twin.paper.cases.run_all`); returns its path.

    Each row: ``case, model, parameter, true, estimate, std, error_pct, z,
    paper_estimate, paper_error_pct, noisy, converged, fit_time_s, note``.
    """
    rows = [dict(r) for r in rows]
    noisy = any(r.get("noisy") for r in rows)
    within = sum(1 for r in rows if r.get("z") is not None and r["z"] <= 3)
    at_most = sum(1 for r in rows if round(r["error_pct"], 4) <= r["paper_error_pct"] and r["error_pct"] <= 0.01)
    facts = {"cases": str(len({r["case"] for r in rows})), "parameters": str(len(rows)),
             "data": "with sensor noise (x: 2 µm, y: 1 µm)" if noisy else "noise-free, as the paper"}
    if noisy:
        facts["within 3 std of the truth"] = f"{within}/{len(rows)}"
    else:
        facts["at most the paper's error"] = f"{at_most}/{len(rows)}"
    if elapsed_s is not None:
        facts["all fits"] = f"{elapsed_s:.2f} s"
    pg = P.Page(title or "twin paper: the paper's cases regenerated", facts, kind="paper")

    table = []
    for r in rows:
        sh = Shown(r["parameter"], r.get("model"), r.get("unit"))
        std = r.get("std")
        est = sh.text(r["estimate"], 8, unit=False)
        if noisy and std is not None and math.isfinite(std):
            est += f" ± {sh.text(std, 2, unit=False)}"
        pe = r.get("paper_estimate")
        table.append({"case": r["case"], "parameter": r["parameter"], "unit": sh.unit_text,
                      "true": sh.text(r["true"], 7, unit=False),
                      "ours: estimate" + (" ± std" if noisy else ""): est,
                      "ours: error": f"{r['error_pct']:.2e} %",
                      "paper: estimate": "—" if pe is None else sh.text(pe, 6, unit=False),
                      "paper: error": pct(r["paper_error_pct"]),
                      **({"|error| / std": fmt(r.get("z"), 3)} if noisy else {}),
                      **({} if all(x.get("converged", True) for x in rows) else
                         {"converged": "yes" if r.get("converged", True) else "NO"}),
                      "fit time": f"{fmt(r.get('fit_time_s'), 3)} s",
                      "note": r.get("note", "")})

    def flag(row):
        if noisy:
            z = row.get("|error| / std")
            return z not in ("n/a", None) and float(z) > 3
        return False

    body = [P.table(table, text_columns=("case", "parameter", "unit"), wrap_columns=("note",), flag=flag)]
    body.append(P.note("The truth is the paper's Table 9 for the rig, m = 1, d = 0.1, k = 3947.8 for the "
                       "oscillator. Parameters in display units (wn in Hz, CdAleak in mm²). "
                       + ("With noise: highlighted rows lie more than 3 standard errors from the truth."
                          if noisy else "Noise-free data are simulated by the same model, as the paper's were: "
                          "errors are at round-off level.")))
    pg.add("cases", "Cases", "\n".join(body))
    pg.add("errors", "Errors: ours beside the paper's", P.figure(
        _errors_figure(rows, noisy),
        "Relative error of each estimate, log scale; " + (
            "the black mark is the 95 % bound of our error (1.96 std / true): a bar below it is within the noise; "
            if noisy else "") + f"an error of exactly 0 is drawn at {FLOOR:g} %."))
    if noisy:
        pg.add("zscores", "Deviation in standard errors", P.figure(
            _z_figure(rows), "(estimate − true) / std per estimate with its ±1 std bar; the band is ±3 std."))
    return pg.write(out_dir, filename)


def _labels(rows) -> list[str]:
    return [f"{r['case']}\n{r['parameter']}" for r in rows]


def _errors_figure(rows, noisy: bool):
    pl = views.plt()
    x = np.arange(len(rows))
    ours = np.array([max(r["error_pct"], FLOOR) for r in rows])
    paper = np.array([max(r["paper_error_pct"], FLOOR) for r in rows])
    with pl.rc_context(views.RC):
        fig, ax = pl.subplots(figsize=(max(8.0, 0.75 * len(rows) + 1.5), 3.8))
        ax.bar(x - 0.2, paper, 0.38, color="#9e9e9e", label="paper (printed)")
        ax.bar(x + 0.2, ours, 0.38, color=views.BLUE, label="fpdd-twin")
        if noisy:  # the 95 % bound of our error: a mark above (or in) our bar, legible on a log axis
            bound = np.array([1.96 * r["std"] / abs(r["true"]) * 100 if r.get("std") and r["true"] else np.nan
                              for r in rows])
            ax.plot(x + 0.2, bound, "_", color="#1f1f1f", ms=16, mew=2.0,
                    label="ours: 95 % bound of the error (1.96 std / true)")
        ax.set_yscale("log")
        ax.set_xticks(x, _labels(rows), fontsize=7)
        ax.set_ylabel("relative error [%]")
        ax.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), ncol=3, frameon=False)
        fig.tight_layout()
    return fig


def _z_figure(rows):
    pl = views.plt()
    x = np.arange(len(rows))
    z = np.array([(r["estimate"] - r["true"]) / r["std"] if r.get("std") else 0.0 for r in rows])
    with pl.rc_context(views.RC):
        fig, ax = pl.subplots(figsize=(max(8.0, 0.75 * len(rows) + 1.5), 3.0))
        ax.axhspan(-3, 3, color=views.GREEN, alpha=0.12, lw=0, label="±3 std")
        ax.errorbar(x, z, yerr=np.ones_like(z), fmt="o", color=views.BLUE, capsize=3, ms=4, label="estimate ± 1 std")
        ax.axhline(0, color="#4d4d4d", lw=0.7)
        ax.set_xticks(x, _labels(rows), fontsize=7)
        ax.set_ylabel("(estimate − true) / std")
        lim = max(3.5, float(np.max(np.abs(z))) + 1.2) if z.size else 3.5
        ax.set_ylim(-lim, lim)
        ax.legend(loc="upper right", ncol=2)
        fig.tight_layout()
    return fig
