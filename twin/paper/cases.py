"""The paper's numerical cases, regenerated: our estimate and error beside the paper's.

What the paper leaves ambiguous and what we chose (also in docs/results/fit.md):

* Oscillator excitation and record length are not given: a 10 s, 1 kHz
  Schroeder multisine force of 100 N peak on 1-30 Hz (the resonance is 10 Hz).
* Case B's label is garbled: it fits ``d`` with ``k`` known; the paper's table
  shows 0.10323 and "2 %" (0.10323 is in fact 3.2 % off); we compare with the
  printed 2 %.
* Case D's text says ``k`` is free, its table shows a value of ``d``
  (0.099987, 0.0013 %): we follow the text (``k`` free, ``d`` known) and compare
  with the printed 0.0013 %.
* The servo-hydraulic "true" values are the paper's Table 9 (its Tables 10-11
  use another parameterisation).  The rig is driven closed loop from a 10 s,
  1 kHz multisine demand (10 mm peak, 0.2-12 Hz) and fitted from x alone.
* Starts are deliberately wrong (x1.5 for single parameters; zeta 0.6 and
  CdAleak x3 for the hard case) and the multi-start screen is on.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping

from twin.estimation.fit import FitResult, fit
from twin.models import get_model
from twin.models.base import Timing
from twin.record import Record
from twin.models.simulate import default_noise, excite, measure


@dataclasses.dataclass(frozen=True)
class Case:
    case: str
    model: str
    free: tuple[str, ...]
    start: dict
    paper_estimate: dict
    paper_error_pct: dict
    note: str = ""


CASES: tuple[Case, ...] = (
    Case("osc-A", "oscillator", ("d", "k"), {"d": 0.15, "k": 3000.0},
         {"d": 0.099987, "k": 3949.9}, {"d": 0.0013, "k": 0.0532}, "System Identification Toolbox"),
    Case("osc-B", "oscillator", ("d",), {"d": 0.15}, {"d": 0.10323}, {"d": 2.0},
         "SI toolbox; k known (label garbled)"),
    Case("osc-C", "oscillator", ("d", "k"), {"d": 0.15, "k": 3000.0},
         {"d": 0.099987, "k": 3947.8}, {"d": 0.0014, "k": 0.0}, "Simulink PE, lsqnonlin"),
    Case("osc-D", "oscillator", ("k",), {"k": 3000.0}, {"k": 0.099987}, {"k": 0.0013},
         "Simulink PE; k free per the text (the table shows a d)"),
    *(Case(f"rig-A-{p}", "msp25", (p,), {p: f}, {p: None}, {p: 0.0}, "scenario A: one free parameter")
      for p, f in (("Ffric", 75.0), ("CdAleak", 3.2863e-9 * 1.5), ("Cd", 0.2191 * 1.5),
                   ("zeta", 0.3701 * 1.5), ("wn", 2 * 3.141592653589793 * 43.0 * 1.5))),
    Case("rig-B", "msp25", ("zeta", "CdAleak"), {"zeta": 0.6, "CdAleak": 3 * 3.2863e-9},
         {"zeta": None, "CdAleak": None}, {"zeta": 0.7, "CdAleak": 2.0},
         "scenario B: the hard two-parameter case, from x alone"),
)


def case_record(model_name: str, noisy: bool, seed: int = 0, duration_s: float = 10.0,
                timing: Timing | None = None):
    model = get_model(model_name)
    name, drive = excite(model, duration_s, 1e-3)
    noise = default_noise(model) if noisy else None
    return model, measure(model, model.params(), name, drive, 1e-3, noise=noise, seed=seed, name=model_name,
                          timing=timing)


def run_case(case: Case, noisy: bool = False, seed: int = 0, outputs=None,
             progress: Callable[[str], None] | None = None, record_cache: dict | None = None,
             timing: Timing | None = None, record: Record | None = None,
             truth: Mapping[str, float] | None = None) -> tuple[list[dict], FitResult]:
    """Fit one case.  By default on the product's own simulation of the case; ``record`` (with its
    ``truth``, the values the record was made with) fits a record made elsewhere instead.  Starts sit
    at the case's factor of the truth (x1.5, or the hard case's zeta 0.6 and CdAleak x3)."""
    model = get_model(case.model)
    if record is None:
        key = (case.model, noisy, seed)
        if record_cache is not None and key in record_cache:
            model, rec = record_cache[key]
        else:
            model, rec = case_record(case.model, noisy, seed, timing=timing)
            if record_cache is not None:
                record_cache[key] = (model, rec)
        truth_ps = model.params()
    else:
        rec = record
        truth_ps = model.params().update(dict(truth or {}))
    default = model.params()
    start = {p: truth_ps[p] * v / default[p] for p, v in case.start.items()}
    outs = outputs or model.OUTPUTS[:1]  # the paper fits each case from the displacement alone
    res = fit(model, rec, case.free, base=truth_ps, start=start, outputs=outs, progress=progress, timing=timing)
    rows = []
    for p in case.free:
        t = truth_ps[p]
        est = res.estimate[p]
        std = res.std[p]
        rows.append({
            "case": case.case, "model": case.model, "parameter": p, "true": t, "estimate": est,
            "std": std, "error_pct": abs(est - t) / abs(t) * 100.0,
            "z": abs(est - t) / std if std > 0 else (0.0 if est == t else float("inf")),
            "paper_estimate": case.paper_estimate[p], "paper_error_pct": case.paper_error_pct[p],
            "noisy": noisy, "outputs": list(outs), "fit_time_s": res.time_s, "converged": res.success,
            "unit": truth_ps.spec(p).unit, "note": case.note,
        })
    return rows, res


def run_all(noisy: bool = False, seed: int = 0, cases=CASES, progress=None,
            timing: Timing | None = None) -> tuple[list[dict], float]:
    t0 = time.perf_counter()
    cache: dict = {}
    rows = []
    for c in cases:
        if progress:
            progress(f"case {c.case}: fitting {', '.join(c.free)}")
        r, _ = run_case(c, noisy, seed, record_cache=cache, timing=timing)
        rows.extend(r)
    return rows, time.perf_counter() - t0


def format_rows(rows: list[dict]) -> str:
    out = [f"{'case':<14} {'param':<8} {'true':>12} {'estimate':>14} {'std':>10} {'error %':>10} "
           f"{'paper est':>11} {'paper err %':>11} {'time s':>7}"]
    for r in rows:
        pe = "-" if r["paper_estimate"] is None else f"{r['paper_estimate']:.6g}"
        out.append(f"{r['case']:<14} {r['parameter']:<8} {r['true']:>12.6g} {r['estimate']:>14.8g} "
                   f"{r['std']:>10.3g} {r['error_pct']:>10.2e} {pe:>11} {r['paper_error_pct']:>11.4g} "
                   f"{r['fit_time_s']:>7.2f}")
    return "\n".join(out)
