"""Early warning measured on the reference simulator (``python -m benchmarks.forecast [--json] [--set S]``).

Slow wear of the independent reference simulator (``tests/reference``): leakage
(``CdAleak``), friction (``Ffric``) and valve bandwidth (``wn``) drifting
linearly or exponentially over 10-60 min of record at 1 kHz, default and doubled
sensor noise, the other parameters drawn within +-10 % of Table 9 (the tracker
starts at Table 9, away from the truth), the wearing one leaving its default
healthy band about three quarters into the record (10-min records in
``verify``, 30-60 min in ``long``: slower wear); healthy records (drawn truth,
nominal and doubled noise, a warming oil: the reference simulator's oil
temperature rises 20 K over the first 10 min and stays, its bulk modulus falling
12 % and its leakage rising 1.82 times by the simulator's own temperature laws,
the temperature logged as ``T_oil``; ``warming_ramp``/``warming`` are the older
leakage-only warming records of the calibration set) for false warnings.

Figures per wear record (``twin.online.forecast`` through the service's
:class:`twin.service.rig.RigTwin`, exactly as ``twin track`` runs it):

* coverage: the share of the forecasts published over the last third before
  the true exit whose 90 % interval ``[t_exit_lo, t_exit_hi]`` holds the true
  exit time (the first instant the truth leaves its band);
* lead: how long before the true exit the first ``early`` alarm of that
  parameter came, as a fraction of the wear's duration (from the start of the
  wear to the exit);
* false ``early`` alarms per hour on the healthy records (any parameter), and
  ``early`` alarms on a parameter that does not wear in the wear records.

Verification seeds are >= 1000 (``--set verify``, the table of docs/results/forecast.md);
``--set calib`` (seeds < 1000) is what any constant was looked at on (its last
line: ``twin.online.forecast.DISCREPANCY`` by its rule); ``--set unlogged``:
a warming oil whose temperature the log leaves out, which the twin cannot tell
from a worn seal (shown apart, not counted as healthy).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from typing import Any

import numpy as np

from benchmarks import add_guard_option, apply_guard

HERE = os.path.dirname(os.path.abspath(__file__))
_TESTS = os.path.join(os.path.dirname(HERE), "tests")

TWO_PI = 2.0 * math.pi


def _reference():
    if _TESTS not in sys.path:
        sys.path.insert(0, _TESTS)
    import reference

    return reference


#: default healthy bands (relative half-widths of the MSP25's tracking specs): hi = v (1 + r), lo = v / (1 + r)
BAND = {"Ffric": 0.5, "CdAleak": 2.0, "Cd": 0.15, "zeta": 0.3, "wn": 0.15}
#: which edge a wear heads for
EDGE = {"Ffric": "hi", "CdAleak": "hi", "wn": "lo"}


def wear_spec(param: str, shape: str, duration: float, seed: int, noise: float = 1.0,
              exit_frac: float = 0.75, t0: float = 0.0) -> dict:
    """The reference spec of a wear record: ``param`` wears from its drawn value from ``t0`` and leaves its default
    healthy band at ``t0 + exit_frac (duration - t0)``, ``shape`` ``linear`` (in the parameter) or ``exp``
    (exponential in the parameter)."""
    ref = _reference()
    nominal = ref.MSP25_FREE[param]
    truth = ref.draw_truth(seed, 0.1, "msp25")
    v0 = truth[param]
    r = BAND[param]
    edge = nominal * (1 + r) if EDGE[param] == "hi" else nominal / (1 + r)
    t_exit = t0 + exit_frac * (duration - t0)
    tt = np.arange(0.0, duration + 1.0, 1.0)
    if shape == "linear":
        rate = (edge - v0) / (t_exit - t0)
        vv = v0 + rate * np.clip(tt - t0, 0.0, None)
    elif shape == "exp":
        k = math.log(edge / v0) / (t_exit - t0)
        vv = v0 * np.exp(k * np.clip(tt - t0, 0.0, None))
    else:
        raise ValueError(f"shape must be linear or exp, got {shape!r}")
    tv = {param: {"kind": "table", "t": [-1.0, *tt.tolist()], "value": [v0, *vv.tolist()]}}
    nz = {"x": 2e-6 * noise, "pA": 2e4 * noise, "pB": 2e4 * noise}
    return ref.msp25_spec(seed, duration=duration, truth=truth, time_varying=tv, noise=nz)


#: the warming oil of ``warming_oil`` [K]: from the reference simulator's T0 by 20 K over the first 10 min, then
#: steady: its bulk modulus falls 12 % (0.006/K) and its leakage rises by exp(0.03 x 20) = 1.82 (viscosity), both
#: by the reference simulator's own temperature laws; the oil's temperature is logged (``T_oil``, as a rig logs it)
OIL_T0, OIL_DT = 313.15, 20.0


def healthy_spec(kind: str, duration: float, seed: int) -> dict:
    """A healthy record: ``plain`` (drawn truth), ``noisy`` (doubled sensor noise), ``warming`` (the oil warms: the
    leakage rises 30 % and Cd 3 % with a 400 s time constant, all inside their bands) or ``warming_ramp`` (the
    leakage rises 15 % over the first 10 min and stays: the leakage part of an oil warming by about 20 K; the
    oil's bulk modulus, which falls with it, is a known constant of the reference simulator), ``warming_oil`` (the
    reference simulator's temperature model: the oil warms 20 K over the first 10 min and stays, its bulk modulus
    falling 12 % and its leakage rising 1.82 times, ``T_oil`` logged) or ``warming_oil_unlogged`` (the same record
    replayed without ``T_oil``, :func:`logged`: the twin sees the leakage rise 1.82 times and level off, and the
    stiffness fall, with nothing to explain them)."""
    ref = _reference()
    truth = ref.draw_truth(seed, 0.1, "msp25")
    kw: dict[str, Any] = {}
    if kind == "noisy":
        kw["noise"] = {"x": 4e-6, "pA": 4e4, "pB": 4e4}
    elif kind == "warming":
        kw["time_varying"] = {
            "CdAleak": {"kind": "exp", "t0": 0.0, "tau": 400.0, "start": truth["CdAleak"],
                        "end": 1.3 * truth["CdAleak"]},
            "Cd": {"kind": "exp", "t0": 0.0, "tau": 400.0, "start": truth["Cd"], "end": 1.03 * truth["Cd"]}}
    elif kind == "warming_ramp":
        kw["time_varying"] = {"CdAleak": {"kind": "ramp", "t0": 0.0, "t1": 600.0, "start": truth["CdAleak"],
                                          "end": 1.15 * truth["CdAleak"]}}
    elif kind in ("warming_oil", "warming_oil_unlogged"):
        kw["temperature"] = {"T": {"kind": "ramp", "t0": 0.0, "t1": 600.0, "start": OIL_T0, "end": OIL_T0 + OIL_DT}}
    elif kind != "plain":
        raise ValueError(f"healthy kind must be plain, noisy, warming, warming_ramp or warming_oil, got {kind!r}")
    return ref.msp25_spec(seed, duration=duration, truth=truth, **kw)


#: (label, parameter, shape, duration s, seed, noise factor[, start of the wear s]); ``long``: verification records of 30-60 min (slower
#: wear, the same figures; their simulation takes about a tenth of their duration per record on one core)
WEAR: dict[str, list[tuple[Any, ...]]] = {
    "calib": [("leak_lin", "CdAleak", "linear", 600.0, 11, 1.0), ("leak_exp", "CdAleak", "exp", 600.0, 13, 2.0),
              ("fric_exp", "Ffric", "exp", 600.0, 14, 2.0), ("wn_exp", "wn", "exp", 900.0, 12, 1.0)],
    "verify": [("leak_lin", "CdAleak", "linear", 600.0, 1001, 1.0), ("leak_exp", "CdAleak", "exp", 600.0, 1002, 2.0),
               ("fric_lin", "Ffric", "linear", 600.0, 1003, 2.0), ("fric_exp", "Ffric", "exp", 600.0, 1004, 1.0),
               ("wn_lin", "wn", "linear", 600.0, 1005, 1.0), ("wn_exp", "wn", "exp", 600.0, 1006, 2.0),
               ("leak_lin", "CdAleak", "linear", 600.0, 1016, 2.0), ("leak_exp", "CdAleak", "exp", 600.0, 1017, 1.0),
               ("fric_lin", "Ffric", "linear", 600.0, 1018, 1.0), ("fric_exp", "Ffric", "exp", 600.0, 1019, 2.0),
               ("wn_lin", "wn", "linear", 600.0, 1020, 2.0), ("wn_exp", "wn", "exp", 600.0, 1021, 1.0)],
    "unlogged": [],
    # the rig healthy for 10 min, then the wear starts (the 7th field: its start [s]); 20-min records
    "late": [("leak_exp_late", "CdAleak", "exp", 1200.0, 1023, 2.0, 600.0),
             ("wn_lin_late", "wn", "linear", 1200.0, 1024, 1.0, 600.0),
             ("fric_lin_late", "Ffric", "linear", 1200.0, 1025, 1.0, 600.0)],
    "long": [("leak_exp", "CdAleak", "exp", 1800.0, 1007, 1.0), ("wn_lin", "wn", "linear", 1800.0, 1008, 2.0),
             ("fric_lin", "Ffric", "linear", 3600.0, 1009, 1.0)],
}
#: (label, kind, duration s, seed)
HEALTHY = {
    "calib": [("warming_ramp", "warming_ramp", 1200.0, 22), ("warming", "warming", 1200.0, 21)],
    "verify": [("plain", "plain", 1200.0, 1011), ("noisy", "noisy", 1200.0, 1012),
               ("warming_oil", "warming_oil", 1200.0, 1014)],
    "long": [("warming_oil", "warming_oil", 3600.0, 1015)],
    "late": [],
    # not healthy to the twin: the oil warms unlogged, so the twin's leakage takes up the oil's stiffness and the
    # drift test alarms (the early alarm before it is right about the estimate); shown apart, not counted
    "unlogged": [("warming_oil_unlogged", "warming_oil_unlogged", 1200.0, 23),
                 ("warming_oil_unlogged", "warming_oil_unlogged", 1200.0, 1022)],
}


def wear_start(row: tuple[Any, ...]) -> float:
    """The start of a :data:`WEAR` row's wear [s] (its optional seventh field; 0: from the record's start)."""
    return float(row[6]) if len(row) > 6 else 0.0


def logged(rec, kind: str):
    """The record as the rig logs it: a ``*_unlogged`` healthy kind without its oil temperature (``T_oil``)."""
    if not kind.endswith("_unlogged"):
        return rec
    import dataclasses

    return dataclasses.replace(rec, signals={k: v for k, v in rec.signals.items() if k != "T_oil"})


def specs(which: str) -> list[dict]:
    return ([wear_spec(row[1], row[2], row[3], row[4], row[5], t0=wear_start(row)) for row in WEAR[which]]
            + [healthy_spec(k, d, seed) for _, k, d, seed in HEALTHY[which]])


def build(which: str, workers: int = 1) -> None:
    """Fill the reference cache with the records of a set."""
    _reference().batch(specs(which), workers=workers)


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "build":
    for w in sys.argv[2:]:
        t = time.time()
        build(w)
        print(w, f"{time.time() - t:.0f} s", flush=True)


# --- the measurement ------------------------------------------------------------------------------------------------
def _samples(rec, t0_ns: int = 1_700_000_000_000_000_000):
    from replay.base import Samples

    t_ns = t0_ns + np.round(rec.t * 1e9).astype(np.int64)
    return Samples(t_ns, {k: np.asarray(v, float) for k, v in rec.signals.items()})


def run_record(rec, horizon_s: float = 3600.0, confirm: bool = False):
    """The record through ``twin track``'s library (tracker, drift test, forecast; ``confirm``: alarms confirmed by
    window re-fits, ``twin track --confirm``); returns the twin."""
    from twin.service.track import track

    return track(_samples(rec), "bench", forecast_horizon_s=horizon_s, confirm=True if confirm else None)


def _drift_alarms(twin) -> list[dict[str, Any]]:
    return [{"parameter": a.parameter, "level": a.level, "t_s": a.t_s} for a in twin.alarms
            if a.level in ("warning", "alarm") and a.kind in ("raised", "escalated")]


def true_exit(rec, twin, param: str) -> float:
    """The first record time at which the truth of ``param`` is outside the twin's band (inf: never)."""
    b = twin.rig.baseline[param]
    v = np.asarray(rec.hidden[param], float) if param in rec.hidden else np.full(rec.t.size, rec.truth[param])
    out = np.flatnonzero((v > b.hi) | (v < b.lo))
    return float(rec.t[out[0]]) if out.size else math.inf


def wear_figures(rec, twin, param: str, wear_start: float = 0.0) -> dict[str, Any]:
    """Coverage over the last third before the true exit, lead of the first early alarm, early alarms elsewhere."""
    te = true_exit(rec, twin, param)
    win0 = te - (te - wear_start) / 3.0
    fcs = [f for f in twin.forecasts if f.parameter == param and win0 <= f.t < te]
    hit = [f for f in fcs if f.t_exit_lo is not None and f.t_exit_lo <= te
           and (f.t_exit_hi is None or te <= f.t_exit_hi)]
    seconds = max(1, int(te - win0))
    early = [a for a in twin.alarms if a.level == "early" and a.kind == "raised"]
    first = next((a.t_s for a in early if a.parameter == param), None)
    lead = (te - first) if first is not None else None
    return {"parameter": param, "t_exit_true_s": te, "forecasts_in_window": len(fcs),
            "window_s": seconds, "coverage": (len(hit) / len(fcs)) if fcs else None,
            "first_early_s": first, "lead_s": lead,
            "lead_fraction": None if lead is None else lead / (te - wear_start),
            "early_other": [a.parameter for a in early if a.parameter != param],
            "early_before_exit": sum(1 for a in early if a.parameter == param and a.t_s < te),
            "drift_alarms": _drift_alarms(twin),
            # all-clears while the truth is outside its band (these wears only worsen past their exit)
            "returns_after_exit": sum(1 for a in twin.alarms if a.parameter == param and a.kind == "returned"
                                      and a.t_s >= te)}


def level_error(rec, twin, param: str, skip_s: float = 60.0, window_s: float = 60.0) -> dict[str, Any]:
    """The twin's level error against the truth: the forecast's 1-s bins of ``param`` (log of the estimate over the
    band's centre) less the log of the truth at each bin's time, averaged over ``window_s`` windows after the first
    ``skip_s`` (the filter converging); the windows' mean and RMS (log units). The RMS is what
    ``twin.online.forecast.DISCREPANCY`` stands for: an error of the level that no trend sees."""
    q = twin.forecast.params[param]
    pts = q.pts[:q.n]
    v = np.asarray(rec.hidden[param], float) if param in rec.hidden else np.full(rec.t.size, rec.truth[param])
    truth = np.log(np.interp(pts[:, 0], rec.t, v) / q.base.value)
    err = pts[:, 1] - truth
    keep = pts[:, 0] >= skip_s
    t, e = pts[keep, 0], err[keep]
    te = true_exit(rec, twin, param)
    keep = t < te  # up to the exit (the forecast's business)
    t, e = t[keep], e[keep]
    edges = np.arange(skip_s, (t[-1] if t.size else skip_s) + window_s, window_s)
    means = [float(np.mean(e[(t >= a) & (t < a + window_s)])) for a in edges[:-1]
             if np.any((t >= a) & (t < a + window_s))]
    m = np.asarray(means)
    out: dict[str, Any] = {"parameter": param, "windows": len(means), "mean": float(m.mean()) if m.size else None,
                           "rms": float(np.sqrt(np.mean(m * m))) if m.size else None,
                           "window_means": [round(x, 4) for x in means]}
    if m.size and e.size >= 4:
        # the part of the windows' level error that the bins' own scatter does not explain: a window mean of
        # errors with scatter sigma and integrated autocorrelation time tau (bins) varies by sigma^2 tau / window
        from twin.online.forecast import _kappa

        sigma = float(np.std(e))
        tau = 1.0 / _kappa(e)
        excess = math.sqrt(max(0.0, float(np.mean(m * m)) - sigma * sigma * tau / window_s))
        out.update(scatter=sigma, tau_bins=tau, excess=excess, excess_ratio=excess / sigma if sigma > 0 else None)
    return out


def healthy_figures(rec, twin) -> dict[str, Any]:
    early = [a for a in twin.alarms if a.level == "early" and a.kind == "raised"]
    hours = float(rec.t[-1] - rec.t[0]) / 3600.0
    return {"hours": hours, "early": len(early), "early_parameters": [a.parameter for a in early],
            "forecasts": len(twin.forecasts), "drift_alarms": _drift_alarms(twin)}


def measure(which: str, say=print, part: str = "all", seeds: list[int] | None = None,
            confirm: bool = False) -> dict[str, Any]:
    """The figures of a set's records (``seeds``: only those of the set's records; ``confirm``: the alarms
    confirmed by window re-fits)."""
    ref = _reference()
    out: dict[str, Any] = {"set": which, "confirm": confirm, "wear": [], "healthy": []}
    for row, spec in zip(WEAR[which] if part != "healthy" else [], specs(which)):
        label, param, shape, dur, seed, nz = row[:6]
        t0 = wear_start(row)
        if seeds and seed not in seeds:
            continue
        rec = ref.get_record(spec)
        t = time.perf_counter()
        twin = run_record(rec, confirm=confirm)
        r = {"label": label, "shape": shape, "duration_s": dur, "seed": seed, "noise": nz,
             **wear_figures(rec, twin, param, wear_start=t0), "wear_start_s": t0, "track_s": time.perf_counter() - t,
             "level_error": {n: level_error(rec, twin, n) for n in twin.forecast.params}}
        out["wear"].append(r)
        say(json.dumps(r))
    hspecs = specs(which)[len(WEAR[which]):]
    for (label, kind, dur, seed), spec in zip(HEALTHY[which] if part != "wear" else [], hspecs):
        if seeds and seed not in seeds:
            continue
        rec = logged(ref.get_record(spec), kind)
        twin = run_record(rec, confirm=confirm)
        r = {"label": label, "duration_s": dur, "seed": seed, **healthy_figures(rec, twin),
             "level_error": {n: level_error(rec, twin, n) for n in twin.forecast.params}}
        out["healthy"].append(r)
        say(json.dumps(r))
    return summarise(out)


def summarise(out: dict[str, Any]) -> dict[str, Any]:
    """The summary figures of a measurement (or of the wear and healthy parts measured apart, merged)."""
    cov = [w["coverage"] for w in out["wear"] if w["coverage"] is not None]
    leads = [w["lead_fraction"] for w in out["wear"]]
    hours = sum(h["hours"] for h in out["healthy"])
    out["summary"] = {
        "coverage_mean": float(np.mean(cov)) if cov else None, "coverage_min": min(cov) if cov else None,
        "lead_fraction_min": None if any(v is None for v in leads) or not leads else min(leads),
        "healthy_hours": hours, "false_early_per_hour": sum(h["early"] for h in out["healthy"]) / max(hours, 1e-9),
        "early_on_other_parameters": sum(len(w["early_other"]) for w in out["wear"]),
        "coverage_pooled": (sum(w["coverage"] * w["forecasts_in_window"] for w in out["wear"] if w["coverage"] is not None)
                            / max(1, sum(w["forecasts_in_window"] for w in out["wear"] if w["coverage"] is not None)))
        if cov else None,
        "discrepancy_rule": discrepancy_rule(out)}
    return out


def discrepancy_rule(out: dict[str, Any]) -> dict[str, float]:
    """``twin.online.forecast.DISCREPANCY`` by its rule: per parameter, the RMS of the records' excess level error
    over their scatter (``level_error``'s ``excess_ratio``) over the wear records where that parameter wears, or over
    every record of the set when none does."""
    wearing = {w["parameter"] for w in out["wear"]}
    ratios: dict[str, list[float]] = {}
    for r in out["wear"] + out["healthy"]:
        for n, le in (r.get("level_error") or {}).items():
            counts = r.get("parameter") == n if n in wearing else True
            if counts and le.get("excess_ratio") is not None:
                ratios.setdefault(n, []).append(le["excess_ratio"])
    return {n: float(np.sqrt(np.mean(np.square(v)))) for n, v in ratios.items()}


def _level(w: dict[str, Any]) -> str:
    le = (w.get("level_error") or {}).get(w["parameter"])
    if not le or le.get("rms") is None:
        return "-"
    return f"{le['mean']:+.4f}, {le['rms']:.4f}"


def _firsts(w: dict[str, Any]) -> str:
    """The first warning and the first alarm on the wearing parameter, each as seconds from the true exit."""
    out = []
    for level in ("warning", "alarm"):
        t = next((d["t_s"] for d in w.get("drift_alarms", []) if d["parameter"] == w["parameter"]
                  and d["level"] == level), None)
        out.append("none" if t is None else f"{t - w['t_exit_true_s']:+.0f} s")
    return ", ".join(out)


def _returns(w: dict[str, Any]) -> str:
    n = w.get("returns_after_exit")
    return "-" if n is None else str(n)


def _others(w: dict[str, Any]) -> str:
    other = [d for d in w.get("drift_alarms", []) if d["parameter"] != w["parameter"]]
    return ", ".join(f"{d['parameter']} {d['level']} {d['t_s']:.0f} s" for d in other) or "none"


def table(res: dict[str, Any]) -> str:
    """The results table (Markdown, as in docs/results/forecast.md)."""
    lines = ["| record | wear | true exit | forecasts in last third | 90 % coverage | first early alarm | lead / wear "
             "| level error (60-s means: mean, RMS; log) | first warning, alarm (its parameter) | returns after the exit "
             "| alarms on others |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for w in res["wear"]:
        lf, cov, first = w["lead_fraction"], w["coverage"], w["first_early_s"]
        cov_t = "n/a" if cov is None else f"{100 * cov:.0f} %"
        first_t = "none" if first is None else f"{first:.0f} s"
        lf_t = "n/a" if lf is None else f"{lf:.2f}"
        lines.append(f"| {w['label']} seed {w['seed']}, {w['duration_s'] / 60:.0f} min, noise x{w['noise']:g} | "
                     f"{w['parameter']} {w['shape']} | {w['t_exit_true_s']:.0f} s | {w['forecasts_in_window']} of "
                     f"{w['window_s']} s | {cov_t} | {first_t} | {lf_t} | {_level(w)} | {_firsts(w)} | "
                     f"{_returns(w)} | {_others(w)} |")
    for h in res["healthy"]:
        drift = "".join(f", {d['parameter']} {d['level']} at {d['t_s']:.0f} s" for d in h.get("drift_alarms", []))
        lines.append(f"| healthy {h['label']} seed {h['seed']}, {h['duration_s'] / 60:.0f} min | none | - | "
                     f"{h['forecasts']} forecasts | - | {h['early']} early{drift} | - | - | - | - | - |")
    s = res["summary"]
    if s["coverage_pooled"] is not None:
        lines.append(f"\ncoverage: pooled over the forecasts {100 * s['coverage_pooled']:.1f} %, mean of the records "
                     f"{100 * s['coverage_mean']:.1f} %; smallest lead / wear: "
                     + ("n/a" if s['lead_fraction_min'] is None else f"{s['lead_fraction_min']:.2f}"))
    lines.append(f"\nhealthy: {s['healthy_hours']:.2f} h, {s['false_early_per_hour']:.2f} early alarms per hour; "
                 f"early alarms on parameters that do not wear: {s['early_on_other_parameters']}")
    if s["discrepancy_rule"]:
        lines.append("\ndiscrepancy by its rule (RMS of the excess level error over the scatter): "
                     + ", ".join(f"{n} {v:.3f}" for n, v in s["discrepancy_rule"].items()))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.forecast", description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=sorted(WEAR), default="verify",
                    help="verify (seeds >= 1000, the table of docs/results/forecast.md), long (seeds >= 1000, 30-60 min records), "
                    "calib (seeds < 1000), late (seeds >= 1000, 10 min healthy before the wear starts) or "
                    "unlogged (a warming oil whose temperature is not logged: not healthy to the twin, shown apart)")
    ap.add_argument("--build", action="store_true", help="only fill the reference cache with the set's records")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    ap.add_argument("--part", choices=("all", "wear", "healthy"), default="all",
                    help="measure only the wear or the healthy records (two processes; merge with --merge)")
    ap.add_argument("--seed", type=int, action="append", metavar="N",
                    help="measure only the set's record of this seed (repeatable; default: all of the set)")
    ap.add_argument("--merge", nargs="+", metavar="JSON", help="print the table of --json outputs of the parts")
    ap.add_argument("--confirm", action="store_true",
                    help="alarms confirmed by window re-fits (twin track --confirm); the table adds each wear's "
                    "first warning and alarm on its parameter and the alarms on others")
    add_guard_option(ap)
    a = ap.parse_args(argv)
    refused = apply_guard(a.guard)
    if refused:
        print(refused, file=sys.stderr)
        return 2
    if a.build:
        build(a.set)
        return 0
    if a.merge:
        parts = []
        for path in a.merge:
            with open(path, encoding="utf-8") as f:
                parts.append(json.load(f))
        res = summarise({"set": parts[0]["set"], "confirm": parts[0].get("confirm", False),
                         "wear": [w for p in parts for w in p["wear"]],
                         "healthy": [h for p in parts for h in p["healthy"]]})
        print(json.dumps(res, indent=1) if a.json else table(res))
        return 0
    if a.seed:
        known = {r[4] for r in WEAR[a.set]} | {r[3] for r in HEALTHY[a.set]}
        bad = sorted(set(a.seed) - known)
        if bad:
            print(f"--seed: {bad[0]} is not a record of the {a.set} set (its seeds: "
                  f"{', '.join(str(k) for k in sorted(known))})", file=sys.stderr)
            return 2
    res = measure(a.set, say=(lambda m: print(m, file=sys.stderr, flush=True)), part=a.part, seeds=a.seed,
                  confirm=a.confirm)
    print(json.dumps(res, indent=1) if a.json else table(res))
    return 0


if __name__ == "__main__" and not (len(sys.argv) > 1 and sys.argv[1] == "build"):
    sys.exit(main())
