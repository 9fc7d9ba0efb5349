"""Randomized campaigns of the online twin on the independent reference simulator (``python -m benchmarks.campaign``).

Each draw is a scenario drawn from its seed (:mod:`benchmarks.campaign_draw`: rig geometry and size,
controller, excitation and its order, noise level and colour, cold or commissioned start, and a wear, a
drifting sensor or a specimen that stiffens or cracks, or nothing), simulated by ``tests/reference``
(through its on-disk cache, ``$FPDD_REFCACHE``) and run through ``twin track``'s library
(:func:`twin.service.track.track`: tracker, drift test, early warning) as the rig's configuration would:
its geometry and controller stated, its timing, and for a commissioned start the commissioning fit of a
healthy 30-s record of the same rig (:func:`twin.online.commission.commission_from_samples`).

Calibration draws (``--set calibration``: seeds 0-999) are the ones any constant may be looked at on;
verification draws (``--set verification``: seeds from 1000) are the ones figures are quoted from.

Every figure is a rate with its 95 % interval (:mod:`benchmarks.campaign_stats`): Clopper-Pearson for a
proportion, the exact Poisson interval for events per hour, order statistics for a median delay:

* false alarm events per hour on the healthy draws (an event: a parameter raised to ``warning`` or
  ``alarm``; a healthy draw whose truth lies outside the bands its twin ran with, its commissioning refused and
  the default bands taken, is counted apart: an alarm there is right), per excitation kind (each event counted on the part of the demand running when it came, the
  hours of each kind summed likewise), and the share of healthy draws with any;
* per parameter, the detection rate of wear draws whose truth left the twin's band (a ``warning`` or
  ``alarm`` on that parameter after the wear's onset) and the delay from the truth leaving the band;
* wrong-parameter: wear draws with an event on another parameter after the onset;
* sensor-vs-parameter: sensor-drift draws with a parameter event after the drift's onset, and how often
  the drifting sensor was called faulty; specimen-vs-parameter: specimen draws with any parameter event;
  healthy sensors called faulty in any draw;
* early warning (as :mod:`benchmarks.forecast` measures it): the coverage of the forecasts in the last
  third before the true exit, pooled, and the share of wears whose first early alarm led the exit by a
  quarter of the wear or more; early alarms per hour on healthy draws.

Output: a progress line per draw on stderr, a text table (``--json``: everything, the draws included;
``--html DIR``: a page with plots). ``--merge`` re-summarises the ``--json`` outputs of several runs.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from benchmarks.campaign_draw import (COMMISSION_S, KINDS, SETS, commissioning_spec, describe, draw,
                                      product_params, reference, reference_spec, seeds, timing_spelling)
from benchmarks.campaign_stats import clopper_pearson, median_interval, poisson_rate

if not os.environ.get("FPDD_REFCACHE"):  # the tests' cache (tests/conftest.py): one record simulated once
    os.environ["FPDD_REFCACHE"] = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(
        os.path.expanduser("~"), ".cache"), "fpdd-twin", "refcache")

TRACKED = ("Ffric", "CdAleak", "Cd", "zeta", "wn")
#: the sensor events a confirmed twin raises (a transducer's offset) and the sensor each names
SENSOR_OF = {"pA_off": "pA", "pB_off": "pB"}
#: what a parameter event is: a raise to these levels (an escalation of a raised event is the same event)
EVENT_LEVELS = ("warning", "alarm")


def _samples(rec, t0_ns: int = 1_700_000_000_000_000_000):
    from replay.base import Samples

    t_ns = t0_ns + np.round(rec.t * 1e9).astype(np.int64)
    return Samples(t_ns, {k: np.asarray(v, float) for k, v in rec.signals.items()})


@contextlib.contextmanager
def _keeping_statuses() -> Iterator[list]:
    """The statuses the offline twin publishes, kept (``(t_ns, sensors)``): ``track`` builds its publisher from
    :class:`twin.service.track.SequenceNumbers`, swapped here for one that keeps what it is handed."""
    import twin.service.track as track_mod

    kept: list = []
    base = track_mod.SequenceNumbers

    class Keeping(base):  # type: ignore[misc, valid-type]
        def publish_status(self, event):
            kept.append((int(event.t_ns), dict(event.sensors)))
            return super().publish_status(event)

    track_mod.SequenceNumbers = Keeping  # type: ignore[misc]
    try:
        yield kept
    finally:
        track_mod.SequenceNumbers = base  # type: ignore[misc]


def parts_timeline(scn: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(kind, start s, end s) of each part of the demand; the rest before the first part counts to it."""
    out, t = [], float(scn["excitation"]["onset_s"])
    for i, p in enumerate(scn["excitation"]["parts"]):
        out.append((p["kind"], 0.0 if i == 0 else t, t + float(p["seconds"])))
        t += float(p["seconds"])
    if out:
        k, a, _ = out[-1]
        out[-1] = (k, a, max(t, float(scn["duration_s"])))
    return out


def run_draw(seed: int, minutes: float, confirm: bool = False) -> dict[str, Any]:
    """One draw: simulate (or read from the cache), commission if its start says so, track; what happened."""
    from fpdd.errors import ConfigError
    from twin.models.base import Timing
    from twin.online.commission import commission_from_samples
    from twin.service.track import track

    from benchmarks.forecast import true_exit, wear_figures

    scn = draw(seed, minutes)
    ref = reference()
    t0 = time.perf_counter()
    (rec,) = ref.batch([reference_spec(scn)], workers=1)
    params = product_params(scn)
    ctrl, isamp = timing_spelling(scn)
    timing = Timing.parse(ctrl, isamp)
    com, refused = None, None
    cspec = commissioning_spec(scn)
    if cspec is not None:
        (crec,) = ref.batch([cspec], workers=1)
        try:
            com = commission_from_samples(_samples(crec), COMMISSION_S, TRACKED, params, timing)
        except ConfigError as exc:  # refused: the twin starts cold, as the service would leave it
            refused = str(exc)
    t1 = time.perf_counter()
    with _keeping_statuses() as kept:
        twin = track(_samples(rec), "campaign", params=params, timing=timing, commission=com,
                     forecast_horizon_s=3600.0, confirm=confirm)
    t2 = time.perf_counter()
    t_first = 1_700_000_000_000_000_000
    events = [{"t_s": float(a.t_s), "parameter": a.parameter, "level": a.level, "kind": a.kind}
              for a in twin.alarms]
    faulty: dict[str, dict[str, Any]] = {}
    for t_ns, sensors in kept:
        for name, state in sensors.items():
            if state != "ok" and name not in faulty:
                faulty[name] = {"t_s": (t_ns - t_first) * 1e-9, "state": state}
    out: dict[str, Any] = {
        "seed": seed, "kind": scn["kind"], "what": describe(scn), "scenario": scn,
        "duration_s": float(rec.t[-1] - rec.t[0]) + rec.dt, "commission_refused": refused,
        "events": events, "sensor_faulty": faulty,
        "sensor_fault_samples": int(twin.tracker.counters.get("sensor_fault", 0)),
        "parts": parts_timeline(scn), "prepare_s": t1 - t0, "track_s": t2 - t1,
        "bands": {n: [b.lo, b.hi] for n, b in twin.rig.baseline.items()},
    }
    w = scn["wear"]
    if w:
        p = w["parameter"]
        te = true_exit(rec, twin, p)
        out["exit_s"] = te if math.isfinite(te) else None
        if math.isfinite(te):
            fig = wear_figures(rec, twin, p, wear_start=w["t0"])
            out["forecast"] = {k: fig[k] for k in ("coverage", "forecasts_in_window", "lead_s", "lead_fraction")}
    return out


# --- the figures --------------------------------------------------------------------------------------------------
def _raised(d: dict[str, Any], after: float = -math.inf) -> list[dict[str, Any]]:
    """A draw's parameter events (raises to warning or alarm) at or after ``after`` s."""
    return [e for e in d["events"] if e["kind"] == "raised" and e["level"] in EVENT_LEVELS and e["t_s"] >= after]


def _outside(d: dict[str, Any]) -> list[str]:
    """The parameters whose truth at the start lies outside the band the draw's twin ran with."""
    truth, bands = d["scenario"]["truth"], d.get("bands") or {}
    return [p for p, (lo, hi) in bands.items() if p in truth and not lo <= truth[p] <= hi]


def _first_on(d: dict[str, Any], param: str, after: float) -> float | None:
    ts = [e["t_s"] for e in d["events"] if e["parameter"] == param and e["level"] in EVENT_LEVELS
          and e["kind"] in ("raised", "escalated") and e["t_s"] >= after]
    return min(ts) if ts else None


def _prop(k: int, n: int) -> dict[str, Any]:
    lo, hi = clopper_pearson(k, n)
    return {"k": k, "n": n, "rate": (k / n) if n else None, "lo": lo, "hi": hi}


def _per_hour(k: int, hours: float) -> dict[str, Any]:
    lo, hi = poisson_rate(k, hours)
    return {"events": k, "hours": hours, "rate": (k / hours) if hours > 0 else None, "lo": lo, "hi": hi}


def _kind_of(d: dict[str, Any], t: float) -> str:
    for k, a, b in d["parts"]:
        if a <= t < b:
            return str(k)
    return str(d["parts"][-1][0]) if d["parts"] else "none"


def summarise(draws: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The campaign's figures from its draws (see the module docstring); draws that stopped on an error are
    counted apart (``failed``)."""
    failed = [{"seed": d["seed"], "what": d["what"], "error": d["error"]} for d in draws if d.get("error")]
    draws = [d for d in draws if not d.get("error")]
    fig: dict[str, Any] = {"draws": len(draws), "failed": failed, "by_kind": {k: sum(d["kind"] == k for d in draws) for k in KINDS}}
    # a healthy rig whose truth lies outside the bands the twin runs with (its commissioning refused, the twin fell
    # back to the default bands, the truth drawn up to 20 % off them): an alarm on that parameter is right there
    off_band = [d for d in draws if d["kind"] == "healthy" and _outside(d)]
    fig["healthy_outside_band"] = {
        "draws": [d["seed"] for d in off_band],
        "right": sum(1 for d in off_band for e in _raised(d) if e["parameter"] in _outside(d)),
        "wrong": sum(1 for d in off_band for e in _raised(d) if e["parameter"] not in _outside(d))}
    healthy = [d for d in draws if d["kind"] == "healthy" and not _outside(d)]
    hours = sum(d["duration_s"] for d in healthy) / 3600.0
    ev = [e for d in healthy for e in _raised(d)]
    fig["false_alarms"] = _per_hour(len(ev), hours)
    fig["healthy_draws_with_event"] = _prop(sum(bool(_raised(d)) for d in healthy), len(healthy))
    per_kind_h: dict[str, float] = {}
    per_kind_k: dict[str, int] = {}
    for d in healthy:
        for k, a, b in d["parts"]:
            per_kind_h[k] = per_kind_h.get(k, 0.0) + (min(b, d["duration_s"]) - a) / 3600.0
        for e in _raised(d):
            k = _kind_of(d, e["t_s"])
            per_kind_k[k] = per_kind_k.get(k, 0) + 1
    fig["false_alarms_by_excitation"] = {k: _per_hour(per_kind_k.get(k, 0), h) for k, h in sorted(per_kind_h.items())}
    by_start: dict[str, Any] = {}
    for s in ("cold", "commissioned"):
        ds = [d for d in healthy if d["scenario"]["start"] == s]
        by_start[s] = _per_hour(sum(len(_raised(d)) for d in ds), sum(d["duration_s"] for d in ds) / 3600.0)
    fig["false_alarms_by_start"] = by_start
    by_ctrl: dict[str, Any] = {}
    for c in ("P", "PI", "PID"):
        ds = [d for d in healthy if d["scenario"]["controller"]["type"] == c]
        by_ctrl[c] = _per_hour(sum(len(_raised(d)) for d in ds), sum(d["duration_s"] for d in ds) / 3600.0)
    fig["false_alarms_by_controller"] = by_ctrl
    fig["false_alarm_parameters"] = {p: sum(e["parameter"] == p for e in ev) for p in TRACKED}
    # the rig is healthy too before a wear's or a sensor drift's onset (not a specimen's: it is there from the start)
    before = [d for d in draws if d["kind"] in ("wear", "sensor")]
    onset = {d["seed"]: d["scenario"][d["kind"]]["t0"] for d in before}
    k_before = sum(1 for d in before for e in _raised(d) if e["t_s"] < onset[d["seed"]])
    fig["false_alarms_with_onsets"] = _per_hour(len(ev) + k_before, hours + sum(onset.values()) / 3600.0)
    early = sum(1 for d in healthy for e in d["events"] if e["level"] == "early" and e["kind"] == "raised")
    fig["early_alarms_healthy"] = _per_hour(early, hours)
    # wear
    wears = [d for d in draws if d["kind"] == "wear"]
    det: dict[str, Any] = {}
    for p in TRACKED:
        ws = [d for d in wears if d["scenario"]["wear"]["parameter"] == p]
        left = [d for d in ws if d.get("exit_s") is not None]
        delays, hit = [], 0
        for d in left:
            t = _first_on(d, p, d["scenario"]["wear"]["t0"])
            if t is not None:
                hit += 1
                delays.append(t - d["exit_s"])
        inside = [d for d in ws if d.get("exit_s") is None]
        med, lo, hi = median_interval(delays)
        det[p] = {"left_band": _prop(hit, len(left)), "delay_s": {"median": med, "lo": lo, "hi": hi,
                                                                   "values": [round(v, 2) for v in delays]},
                  "inside_band": len(inside),
                  "inside_alarmed": sum(_first_on(d, p, d["scenario"]["wear"]["t0"]) is not None for d in inside)}
    fig["detection"] = det
    left_all = [d for d in wears if d.get("exit_s") is not None]
    fig["detection_all"] = _prop(sum(_first_on(d, d["scenario"]["wear"]["parameter"], d["scenario"]["wear"]["t0"])
                                     is not None for d in left_all), len(left_all))
    # the goal's deadline: one scheduled re-fit period plus one window after the exit; a draw whose record ends
    # before that cannot show it either way and is not counted here
    from twin.online.confirm import PERIOD_S, WINDOW_S

    due = [d for d in left_all if d["exit_s"] + PERIOD_S + WINDOW_S <= d["duration_s"]]

    def in_time(d) -> bool:
        t = _first_on(d, d["scenario"]["wear"]["parameter"], d["scenario"]["wear"]["t0"])
        return t is not None and t <= d["exit_s"] + PERIOD_S + WINDOW_S

    fig["detection_in_time"] = {**_prop(sum(in_time(d) for d in due), len(due)),
                                "deadline_s": PERIOD_S + WINDOW_S}
    wrong = [d for d in wears if any(e["parameter"] != d["scenario"]["wear"]["parameter"]
                                     for e in _raised(d, d["scenario"]["wear"]["t0"]))]
    fig["wrong_parameter"] = _prop(len(wrong), len(wears))
    # sensors and specimens
    sens = [d for d in draws if d["kind"] == "sensor"]
    # a sensor event (a transducer's offset, ``pA_off``) is what a drifting sensor should raise: apart from the
    # rig's parameters
    fig["sensor_vs_parameter"] = _prop(sum(any(e["parameter"] in TRACKED for e in
                                               _raised(d, d["scenario"]["sensor"]["t0"])) for d in sens), len(sens))

    def named(d) -> bool:
        s = d["scenario"]["sensor"]
        t0 = s["t0"]
        by_status = s["sensor"] in d["sensor_faulty"] and d["sensor_faulty"][s["sensor"]]["t_s"] >= t0
        return by_status or any(SENSOR_OF.get(e["parameter"]) == s["sensor"] for e in _raised(d, t0))

    fig["sensor_named"] = _prop(sum(named(d) for d in sens), len(sens))
    fig["sensor_events_elsewhere"] = _prop(sum(any(e["parameter"] in SENSOR_OF and SENSOR_OF[e["parameter"]] !=
                                                   d["scenario"]["sensor"]["sensor"] for e in _raised(d))
                                               for d in sens), len(sens))
    spec = [d for d in draws if d["kind"] == "specimen"]
    fig["specimen_vs_parameter"] = _prop(sum(bool(_raised(d)) for d in spec), len(spec))
    fig["specimen_after_change"] = _prop(sum(bool(_raised(d, d["scenario"]["specimen"]["t0"])) for d in spec),
                                         len(spec))

    def wrongly_faulty(d):
        drifted = d["scenario"]["sensor"]["sensor"] if d["scenario"].get("sensor") else None
        return any(name != drifted for name in d["sensor_faulty"])

    def states(d):
        drifted = d["scenario"]["sensor"]["sensor"] if d["scenario"].get("sensor") else None
        return [v["state"] for name, v in d["sensor_faulty"].items() if name != drifted]

    fig["healthy_sensor_called_faulty"] = _prop(sum(wrongly_faulty(d) for d in draws), len(draws))
    fig["healthy_sensor_states"] = {st: sum(st in states(d) for d in draws) for st in
                                    sorted({st for d in draws for st in states(d)})}
    fig["healthy_sensor_called_faulty_healthy_draws"] = _prop(sum(wrongly_faulty(d) for d in healthy), len(healthy))
    # early warning
    fc = [d["forecast"] for d in wears if d.get("forecast")]
    n_fc = sum(f["forecasts_in_window"] for f in fc if f["coverage"] is not None)
    k_fc = sum(round(f["coverage"] * f["forecasts_in_window"]) for f in fc if f["coverage"] is not None)
    fig["forecast_coverage"] = {**_prop(int(k_fc), int(n_fc)), "records": sum(f["coverage"] is not None for f in fc),
                                "note": "pooled over forecasts, which are correlated within a record"}
    leads = [f["lead_fraction"] for f in fc]
    fig["lead_quarter"] = _prop(sum(v is not None and v >= 0.25 for v in leads), len(leads))
    med, lo, hi = median_interval([v for v in leads if v is not None])
    fig["lead_fraction"] = {"median": med, "lo": lo, "hi": hi, "with_early_alarm": sum(v is not None for v in leads),
                            "records": len(leads)}
    fig["commission_refused"] = sum(d["commission_refused"] is not None for d in draws)
    fig["composition"] = composition(draws)
    return fig


def composition(draws: Sequence[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """How many draws had each controller, start, geometry, noise colour and excitation kind (a draw counts once
    per kind it runs)."""
    def count(key) -> dict[str, int]:
        out: dict[str, int] = {}
        for d in draws:
            for k in key(d["scenario"]):
                out[k] = out.get(k, 0) + 1
        return dict(sorted(out.items()))

    return {
        "controller": count(lambda s: [s["controller"]["type"] + " " + ("analog" if s["controller"]["timing"] == "analog"
                                                                         else f"{s['controller']['rate_hz'] / 1e3:g} kHz")]),
        "start": count(lambda s: [s["start"]]),
        "geometry": count(lambda s: [s["rig"]["geometry"]]),
        "noise": count(lambda s: ["AR(1)" if s["noise"]["tau"] > 0 else "white"]),
        "excitation": count(lambda s: sorted(set(s["excitation"]["order"]))),
        "event": count(lambda s: [s["wear"]["parameter"] + " " + s["wear"]["shape"] if s["wear"] else
                                  "sensor " + s["sensor"]["sensor"] + " " + s["sensor"]["term"] if s["sensor"] else
                                  "specimen " + s["specimen"]["change"] if s["specimen"] else "healthy"]),
    }


# --- output -------------------------------------------------------------------------------------------------------
def _pct(p: dict[str, Any]) -> str:
    if not p["n"]:
        return "n/a (0 draws)"
    return f"{100 * p['rate']:.1f} % [{100 * p['lo']:.1f}, {100 * p['hi']:.1f}] ({p['k']}/{p['n']})"


def _ph(r: dict[str, Any]) -> str:
    if not r["hours"]:
        return "n/a (0 h)"
    return f"{r['rate']:.2f} /h [{r['lo']:.2f}, {r['hi']:.2f}] ({r['events']} in {r['hours']:.2f} h)"


def table(res: dict[str, Any]) -> str:
    """The campaign's figures as text (95 % intervals in brackets)."""
    f = res["figures"]
    lines = [f"campaign: set {res['set']}, {f['draws']} draws of {res['minutes']:g} min (seeds {res['seed_range']}); "
             + ", ".join(f"{k} {n}" for k, n in f["by_kind"].items()),
             "figure                                   rate [95 % interval] (count)",
             f"false alarm events, healthy draws        {_ph(f['false_alarms'])}",
             f"healthy draws with any event             {_pct(f['healthy_draws_with_event'])}",
             f"  with the healthy stretch before onsets {_ph(f['false_alarms_with_onsets'])}"]
    for k, r in f["false_alarms_by_excitation"].items():
        lines.append(f"  during {k:<32} {_ph(r)}")
    for k, r in f["false_alarms_by_start"].items():
        lines.append(f"  {k + ' start':<38} {_ph(r)}")
    for k, r in f.get("false_alarms_by_controller", {}).items():
        lines.append(f"  {k + ' controller':<38} {_ph(r)}")
    lines.append("  parameters of the events               "
                 + ", ".join(f"{p} {n}" for p, n in f["false_alarm_parameters"].items()))
    lines.append(f"early alarms, healthy draws              {_ph(f['early_alarms_healthy'])}")
    lines.append(f"detection, truth left the band           {_pct(f['detection_all'])}")
    if "detection_in_time" in f:
        lines.append(f"  within {f['detection_in_time']['deadline_s']:g} s of the exit (records that long) "
                     f"{_pct(f['detection_in_time'])}")
    for p, r in f["detection"].items():
        dl = r["delay_s"]
        delay = ("" if dl["median"] is None else
                 f"; delay from the exit median {dl['median']:.1f} s [{dl['lo']:.1f}, {dl['hi']:.1f}]")
        lines.append(f"  {p:<38} {_pct(r['left_band'])}{delay}; inside the band {r['inside_band']}, "
                     f"alarmed {r['inside_alarmed']}")
    lines += [f"wrong-parameter (wear draws)             {_pct(f['wrong_parameter'])}",
              f"sensor drift -> parameter event          {_pct(f['sensor_vs_parameter'])}",
              f"sensor drift -> that sensor called faulty {_pct(f['sensor_named'])}",
              f"sensor drift -> event on another sensor  {_pct(f.get('sensor_events_elsewhere', _prop(0, 0)))}",
              f"specimen -> parameter event              {_pct(f['specimen_vs_parameter'])}",
              f"  after the specimen's change            {_pct(f['specimen_after_change'])}",
              f"healthy sensor called faulty, all draws  {_pct(f['healthy_sensor_called_faulty'])}",
              f"  healthy draws                          {_pct(f['healthy_sensor_called_faulty_healthy_draws'])}",
              "  first state called (draws)             "
              + (", ".join(f"{k} {n}" for k, n in f["healthy_sensor_states"].items()) or "-"),
              f"forecast coverage (last third, 90 %)     {_pct(f['forecast_coverage'])} over "
              f"{f['forecast_coverage']['records']} wears",
              f"first early alarm >= wear / 4 before exit {_pct(f['lead_quarter'])}"]
    lf = f["lead_fraction"]
    if lf["median"] is not None:
        lines.append(f"  lead / wear median {lf['median']:.2f} [{lf['lo']:.2f}, {lf['hi']:.2f}] over "
                     f"{lf['with_early_alarm']} of {lf['records']} wears with an early alarm")
    lines.append(f"commissioning refused (started cold)     {f['commission_refused']}")
    ob = f.get("healthy_outside_band", {"draws": [], "right": 0, "wrong": 0})
    lines.append(f"healthy, truth outside the fallback band {len(ob['draws'])} draws (not counted above; events on "
                 f"those parameters {ob['right']}, on others {ob['wrong']})")
    for k, c in f.get("composition", {}).items():
        lines.append(f"draws by {k}: " + ", ".join(f"{n} {v}" for n, v in c.items()))
    for d in f.get("failed", []):
        lines.append(f"failed draw: seed {d['seed']} ({d['what']}): {d['error']}")
    return "\n".join(lines)


def html(res: dict[str, Any], out_dir: str) -> str:
    """``OUT_DIR/index.html`` with the table and plots (PNG beside it); returns the page's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    f = res["figures"]
    imgs = []

    def save(fig, name, caption):
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, name), dpi=110)
        plt.close(fig)
        imgs.append((name, caption))

    # detection delay per parameter
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for i, r in enumerate(f["detection"].values()):
        v = r["delay_s"]["values"]
        ax.plot(np.full(len(v), i) + np.linspace(-0.15, 0.15, max(1, len(v)))[:len(v)], v, "o", ms=5)
        if r["delay_s"]["median"] is not None:
            ax.errorbar(i + 0.3, r["delay_s"]["median"], yerr=[[r["delay_s"]["median"] - r["delay_s"]["lo"]],
                                                               [r["delay_s"]["hi"] - r["delay_s"]["median"]]],
                        fmt="s", color="k", capsize=3)
    ax.axhline(0.0, color="grey", lw=0.8)
    for i, r in enumerate(f["detection"].values()):
        lb = r["left_band"]
        ax.annotate(f"{lb['k']}/{lb['n']} alarmed", (i, 0.0), xycoords=("data", "axes fraction"),
                    xytext=(0, 4), textcoords="offset points", ha="center", fontsize=8)
    ax.set_xlim(-0.5, len(f["detection"]) - 0.5)
    ax.set_xticks(range(len(f["detection"])), list(f["detection"]))
    ax.set_xlabel("worn parameter (-)")
    ax.set_ylabel("alarm delay after the truth left the band (s)")
    ax.set_title("detection delay (dots: draws; square: median, 95 % interval)")
    save(fig, "delay.png", "detection delay per parameter")
    # detection rate per parameter
    fig, ax = plt.subplots(figsize=(7, 3.2))
    names = list(f["detection"])
    for i, p in enumerate(names):
        r = f["detection"][p]["left_band"]
        if r["n"]:
            ax.errorbar(i, 100 * r["rate"], yerr=[[100 * (r["rate"] - r["lo"])], [100 * (r["hi"] - r["rate"])]],
                        fmt="o", capsize=4)
            ax.annotate(f"{r['k']}/{r['n']}", (i, 100 * r["rate"]), textcoords="offset points", xytext=(8, 0))
    ax.set_xticks(range(len(names)), names)
    ax.set_ylim(-5, 105)
    ax.set_xlabel("worn parameter (-)")
    ax.set_ylabel("detected (% of draws)")
    ax.set_title("detection rate of wears that left the band, 95 % interval")
    save(fig, "detection.png", "detection rate per parameter")
    # false alarms per excitation kind
    fig, ax = plt.subplots(figsize=(7, 3.4))
    ks = list(f["false_alarms_by_excitation"])
    for i, k in enumerate(ks):
        r = f["false_alarms_by_excitation"][k]
        if r["hours"]:
            ax.errorbar(i, r["rate"], yerr=[[r["rate"] - r["lo"]], [r["hi"] - r["rate"]]], fmt="o", capsize=4)
            ax.annotate(f"{r['events']} in {60 * r['hours']:.0f} min", (i, r["rate"]), textcoords="offset points",
                        xytext=(6, 4), fontsize=8)
    ax.set_xticks(range(len(ks)), ks)
    ax.set_xlabel("excitation running at the event (-)")
    ax.set_ylabel("false alarm events (1/h)")
    ax.set_title("false alarms on healthy draws per excitation kind, 95 % interval")
    save(fig, "false_alarms.png", "false alarm events per hour per excitation kind")
    body = "".join(f'<figure><img src="{n}" alt="{c}"><figcaption>{c}</figcaption></figure>' for n, c in imgs)
    import html as html_mod

    rows = "".join(f"<tr><td>{d['seed']}</td><td>{html_mod.escape(d['what'])}</td><td>"
                   + html_mod.escape(d.get("error") or ", ".join(f"{e['parameter']} {e['level']} {e['t_s']:.1f} s"
                                                                 for e in _raised(d))) + "</td></tr>"
                   for d in res["draws"])
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>campaign {res['set']}</title></head><body>"
            f"<h1>Campaign: {res['set']} draws</h1><pre>{html_mod.escape(table(res))}</pre>{body}"
            f"<h2>Draws</h2><table border=1 cellpadding=3><tr><th>seed</th><th>scenario</th>"
            f"<th>parameter events (raised)</th></tr>{rows}</table>"
            f"<p>command: <code>{html_mod.escape(res.get('command', ''))}</code></p></body></html>")
    path = os.path.join(out_dir, "index.html")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(page)
    return path


def _result(which: str, minutes: float, draws: list[dict[str, Any]], command: str) -> dict[str, Any]:
    ss = sorted(d["seed"] for d in draws)
    return {"set": which, "minutes": minutes, "seed_range": f"{ss[0]}-{ss[-1]}" if ss else "-", "command": command,
            "draws": draws, "figures": summarise(draws)}


def _one(args: tuple[int, float, bool]) -> dict[str, Any]:
    """:func:`run_draw`, or the draw with the error that stopped it (an unstable loop the simulator could not
    integrate, a twin that failed): counted apart, never silently dropped."""
    try:
        return run_draw(*args)
    except Exception as exc:  # noqa: BLE001 - reported per draw and counted
        scn = draw(*args[:2])
        return {"seed": args[0], "kind": scn["kind"], "what": describe(scn), "scenario": scn,
                "error": f"{type(exc).__name__}: {exc}"[:300]}


def _build_one(args: tuple[int, float, bool]) -> int:
    seed, minutes, _ = args
    scn = draw(seed, minutes)
    specs = [reference_spec(scn)] + [s for s in (commissioning_spec(scn),) if s is not None]
    reference().batch(specs, workers=1)
    return seed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.campaign", description=__doc__.split("\n\n")[0],
                                 epilog="Figures: see the module's docstring (python -m pydoc benchmarks.campaign).")
    ap.add_argument("--draws", type=int, default=20, help="number of draws (default 20)")
    ap.add_argument("--set", choices=sorted(SETS), default="verification",
                    help="calibration (seeds 0-999: for looking at constants) or verification (seeds from 1000: "
                    "for quoting figures; default)")
    ap.add_argument("--first", type=int, default=None, help="the first seed (default: the set's first)")
    ap.add_argument("--minutes", type=float, default=1.0, help="length of each draw's record [min] (default 1)")
    ap.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument("--kinds", default=",".join(KINDS),
                    help=f"only draws of these kinds, comma-separated (default all: {','.join(KINDS)})")
    ap.add_argument("--build", action="store_true", help="only simulate the draws' records into the cache")
    ap.add_argument("--confirm", action="store_true",
                    help="alarms confirmed by window re-fits (twin.online.confirm), not the filter's drift test alone")
    ap.add_argument("--json", action="store_true", help="print everything (draws and figures) as JSON")
    ap.add_argument("--html", metavar="DIR", help="also write DIR/index.html with plots")
    ap.add_argument("--log", metavar="FILE", help="append each draw's result to FILE as it finishes (JSON lines)")
    ap.add_argument("--merge", nargs="+", metavar="FILE",
                    help="summarise earlier runs: their --json outputs or --log files")
    a = ap.parse_args(argv)
    command = "python -m benchmarks.campaign " + " ".join(argv if argv is not None else sys.argv[1:])
    if a.merge:
        draws: list[dict[str, Any]] = []
        sets: set[str] = set()
        mins: set[float] = set()
        for path in a.merge:
            try:
                with open(path, encoding="utf-8") as fh:
                    text = fh.read()
                if text.lstrip().startswith("{\"seed\""):  # a --log file: a draw per line
                    got = [json.loads(line) for line in text.splitlines() if line.strip()]
                else:
                    got = list(json.loads(text)["draws"])
                seen = {d["seed"] for d in draws}
                draws += [d for d in got if d["seed"] not in seen]
                sets.update(d["scenario"]["set"] for d in got)
                mins.update(d["scenario"]["duration_s"] / 60.0 for d in got)
            except (OSError, ValueError, KeyError, TypeError) as exc:
                print(f"--merge: {path}: not a campaign --json output or --log file ({type(exc).__name__}: {exc})",
                      file=sys.stderr)
                return 2
        if len(sets) != 1 or len(mins) != 1:
            print(f"--merge: the files mix draw sets {sorted(sets)} or lengths {sorted(mins)} min; merge one set "
                  "and length at a time", file=sys.stderr)
            return 2
        draws.sort(key=lambda d: d["seed"])
        res = _result(sets.pop(), mins.pop(), draws, command)
    else:
        kinds = tuple(k.strip() for k in a.kinds.split(",") if k.strip())
        bad = [k for k in kinds if k not in KINDS]
        if bad or not kinds:
            print(f"--kinds: {','.join(bad) or '(empty)'} is not a kind; the kinds are {', '.join(KINDS)}",
                  file=sys.stderr)
            return 2
        if a.draws < 1 or a.workers < 1 or not (0.2 <= a.minutes <= 60.0):
            print("--draws and --workers must be at least 1, --minutes within 0.2-60", file=sys.stderr)
            return 2
        lo, hi = SETS[a.set]
        if a.first is not None and not lo <= a.first < hi:
            print(f"--first: {a.first} is not a seed of the {a.set} set ({lo}-{hi - 1})", file=sys.stderr)
            return 2
        chosen = seeds(a.set, a.draws, a.minutes, kinds, a.first)
        jobs = [(s, a.minutes, a.confirm) for s in chosen]
        fn = _build_one if a.build else _one
        draws = []
        t0 = time.time()
        if a.workers == 1:
            results: Any = map(fn, jobs)
        else:
            import concurrent.futures as cf
            import multiprocessing

            ex = cf.ProcessPoolExecutor(max_workers=a.workers, mp_context=multiprocessing.get_context("spawn"))
            results = ex.map(fn, jobs)
        for i, r in enumerate(results):
            if a.build:
                print(f"[{i + 1}/{len(jobs)}] seed {r}: record cached ({time.time() - t0:.0f} s)", file=sys.stderr,
                      flush=True)
                continue
            r["confirm"] = bool(a.confirm)
            draws.append(r)
            if a.log:
                with open(a.log, "a", encoding="utf-8") as fh:
                    fh.write(json.dumps(r, default=float) + "\n")
            if r.get("error"):
                print(f"[{i + 1}/{len(jobs)}] seed {r['seed']}: {r['what']} -> FAILED: {r['error']}", file=sys.stderr,
                      flush=True)
                continue
            ev = "; ".join(f"{e['parameter']} {e['level']} {e['t_s']:.1f} s" for e in _raised(r)) or "no event"
            print(f"[{i + 1}/{len(jobs)}] seed {r['seed']}: {r['what']} -> {ev} "
                  f"(track {r['track_s']:.1f} s, {time.time() - t0:.0f} s)", file=sys.stderr, flush=True)
        if a.workers > 1:
            ex.shutdown()
        if a.build:
            return 0
        res = _result(a.set, a.minutes, draws, command)
    if a.html:
        print(f"html: {html(res, a.html)}", file=sys.stderr)
    print(json.dumps(res, indent=1, default=float) if a.json else table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
