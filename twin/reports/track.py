"""The report of ``twin track``: parameter trends with their band and 95 % interval, alarms, statuses."""

from __future__ import annotations

from typing import Any
from collections.abc import Mapping

import numpy as np

from twin.reports import page as P
from twin.reports import views
from twin.reports.units import Shown, fmt

LEVEL_CLASS = {"alarm": "lvl-alarm", "warning": "lvl-warning", "ok": "lvl-ok"}


def track_summary(twin: Any, log: str | None = None) -> dict:
    """Plain data of a tracked log from a :class:`twin.service.rig.RigTwin` (what :func:`track_report` reads).

    ``{"rig", "model", "log", "samples", "t_s": [...], "params": {name: {"unit", "values", "stds",
    "band": [lo, hi], "baseline"}}, "alarms": [AlarmEvent dicts], "status": {name: word},
    "final": {name: {value, std, unit}}, "counters": {...}}`` (SI units, JSON-ready).
    """
    h = twin.history_arrays()
    names = list(twin.tracker.tracked)
    units = list(twin.tracker.units)
    base = twin.rig.baseline
    params = {}
    for j, n in enumerate(names):
        b = base.get(n)
        params[n] = {"unit": units[j], "values": h["values"][:, j].tolist(), "stds": h["stds"][:, j].tolist(),
                     "band": [b.lo, b.hi] if b is not None else None, "baseline": b.value if b is not None else None}
    return {"rig": twin.rig.name, "model": twin.rig.model, "log": log or twin.rig.source,
            "samples": int(twin.stats.samples), "t_s": h["t_s"].tolist(), "params": params,
            "alarms": [a.to_dict() for a in twin.alarms], "status": dict(twin.drift.statuses()),
            "final": twin.final_estimates(), "counters": {k: int(v) for k, v in twin.tracker.counters.items()}}


def interval95(value: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 95 % interval of a positive parameter tracked in log coordinates (log-normal): ``v·exp(±1.96 σ/v)``."""
    value = np.asarray(value, float)
    rel = np.asarray(std, float) / np.maximum(np.abs(value), 1e-300)
    return value * np.exp(-views.Z95 * rel), value * np.exp(views.Z95 * rel)


def track_report(track: Any, out_dir: str, *, log: str | None = None, title: str | None = None,
                 filename: str = "track_report.html") -> str:
    """Write the HTML report of a tracked log; returns its path.

    ``track``: :func:`track_summary`'s dict, or the :class:`twin.service.rig.RigTwin`
    that ``twin.service.track.track`` returns (converted with :func:`track_summary`).
    """
    s = track if isinstance(track, Mapping) else track_summary(track, log)
    model = s.get("model", "msp25")
    alarms = list(s.get("alarms") or [])
    status = dict(s.get("status") or {})
    facts = {"rig": s.get("rig", "rig"), "log": s.get("log", ""), "samples": str(s.get("samples", "")),
             "alarm events": str(len(alarms)),
             "now": ", ".join(f"{n} {w}" for n, w in status.items() if w not in ("ok",)) or "all ok"}
    pg = P.Page(title or f"twin track: {s.get('rig', 'rig')}", facts, kind="track")

    t = np.asarray(s.get("t_s") or [], float)
    rows = []
    for name, p in s["params"].items():
        sh = Shown(name, model, p.get("unit"))
        v = np.asarray(p["values"], float)
        lo, hi = interval95(v, np.asarray(p["stds"], float))
        band = p.get("band")
        span = [x for x in (*(band or ()), *(v[v > 0][-max(1, v.size // 2):] if v.size else ())) if x and x > 0]
        use_log = bool(span) and max(span) / min(span) > 8
        rows.append({"name": name, "label": sh.label, "value": sh(1.0) * v, "lo95": sh(1.0) * lo,
                     "hi95": sh(1.0) * hi, "band": None if band is None else (sh(band[0]), sh(band[1])),
                     "baseline": sh(p.get("baseline")), "log": use_log})
    if rows:
        body = [P.figure(views.trends_figure(t, rows, alarms),
                         "Each tracked parameter (display units): estimate (blue) with its 95 % interval "
                         "(shaded), the healthy band (green) and the alarm events (vertical lines).")]
    else:
        body = [P.note("no parameter tracked")]
    final = s.get("final") or {}
    frows = []
    for name, f in final.items():
        sh = Shown(name, model, f.get("unit"))
        lo, hi = interval95(np.array([f["value"]]), np.array([f["std"]]))
        band = (s["params"].get(name) or {}).get("band")
        frows.append({"parameter": name, "estimate": sh.text(f["value"], 5, unit=False),
                      "std": sh.text(f["std"], 3, unit=False),
                      "95 % interval": f"{sh.text(lo[0], 4, unit=False)} … {sh.text(hi[0], 4, unit=False)}",
                      "healthy band": "n/a" if not band else f"{sh.text(band[0], 4, unit=False)} … "
                                                             f"{sh.text(band[1], 4, unit=False)}",
                      "status": status.get(name, ""), "unit": sh.unit_text})
    body.append(P.table(frows, text_columns=("parameter", "status", "unit"),
                        flag=lambda r: r["status"] in ("warning", "alarm")))
    pg.add("trends", "Parameter trends", "\n".join(body))

    arows = []
    for a in alarms:
        sh = Shown(a["parameter"], model, None)
        arows.append({"seq": a.get("seq", ""), "t": f"{a['t_s']:.3f} s", "parameter": a["parameter"],
                      "level": f'<span class="{LEVEL_CLASS.get(a["level"], "")}">{P.esc(a["level"])}</span>',
                      "kind": a["kind"],
                      "estimate ± std": f"{sh.text(a['estimate'], 4, unit=False)} ± {sh.text(a['std'], 2, unit=False)}",
                      "healthy band": f"{sh.text(a['band_lo'], 4, unit=False)} … {sh.text(a['band_hi'], 4, unit=False)}",
                      "unit": sh.unit_text, "statistic": fmt(a.get("statistic"), 4), "message": a.get("message", "")})
    pg.add("alarms", "Alarms", P.table(arows, ["seq", "t", "parameter", "level", "kind", "estimate ± std",
                                               "healthy band", "unit", "statistic", "message"],
                                       text_columns=("parameter", "level", "kind", "unit"), raw_columns=("level",),
                                       wrap_columns=("message",)) if arows else P.note("no alarm: every parameter "
                                                                                        "stayed in its healthy band"))
    srows = [{"parameter": n, "status": w} for n, w in status.items()]
    counters = s.get("counters") or {}
    body = [P.table(srows, text_columns=("parameter", "status"), flag=lambda r: r["status"] in ("warning", "alarm")),
            P.note("ok: in the band; frozen: not excited by the recent data (held); unresolved: not identifiable "
                   "from the recent data; warning / alarm: the drift test's level.")]
    if counters:
        body.append(P.table([{"filter counter": k, "count": str(v)} for k, v in counters.items()],
                            text_columns=("filter counter",)))
    pg.add("status", "Statuses", "\n".join(body))
    return pg.write(out_dir, filename)
