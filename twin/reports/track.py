"""The report of ``twin track``: parameter trends with their band and 95 % interval, alarms, statuses."""

from __future__ import annotations

from typing import Any
from collections.abc import Mapping

import numpy as np

from twin.reports import page as P
from twin.models import DEFAULT_MODEL
from twin.reports import views
from twin.reports.units import Shown, fmt

LEVEL_CLASS = {"alarm": "lvl-alarm", "warning": "lvl-warning", "early": "lvl-warning", "ok": "lvl-ok"}


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
            "final": twin.final_estimates(), "counters": {k: int(v) for k, v in twin.tracker.counters.items()},
            "forecasts": [dict(f.to_dict(), edge=f.edge) for f in sorted(getattr(twin, "forecasts", ()), key=lambda f: (f.t, f.parameter))],
            "forecast_horizon_s": float(getattr(getattr(twin, "forecast", None), "horizon_s", 3600.0)),
            "maintenance": _maintenance(getattr(getattr(twin, "forecast", None), "maintained", None) or {})}


def _maintenance(maintained: Mapping) -> list[dict]:
    """Each parameter's last recorded maintenance, grouped by event: ``[{"parameters", "t", "note"}]``."""
    by: dict[int, dict] = {}
    for name, m in sorted(maintained.items()):
        if m.get("t") is None:
            continue
        e = by.setdefault(int(m.get("seq", 0)), {"parameters": [], "t": float(m["t"]), "note": m.get("note", "")})
        e["parameters"].append(name)
    return [by[k] for k in sorted(by)]


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
    model = s.get("model", DEFAULT_MODEL)
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
    pg.add("forecast", "Early warning: forecast exit from the healthy band", _forecast_section(s, model, rows, t, alarms))

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


def _forecast_section(s: Mapping, model: str, rows: list[dict], t: np.ndarray, alarms: list[dict]) -> str:
    """Per parameter with a forecast: its trend with the band and the last forecast's fan, the forecast remaining
    time (median and 90 % interval) over the record; a table of the last forecasts and the first early alarms."""
    from twin.online.events.forecast import fmt_duration

    fcs = list(s.get("forecasts") or [])
    horizon = float(s.get("forecast_horizon_s") or 3600.0)
    if not fcs:
        return P.note(f"no forecast: no tracked parameter showed a trend strong enough to extrapolate (a BIC "
                      f"difference of 10 to a flat line); horizon {fmt_duration(horizon)}")
    by: dict[str, list[dict]] = {}
    for f in fcs:
        by.setdefault(f["parameter"], []).append(f)
    shown = [r for r in rows if r["name"] in by]
    pl = views.plt()
    with pl.rc_context(views.RC):
        fig, axes = pl.subplots(len(shown), 2, figsize=(10.5, 2.3 * len(shown) + 0.6), squeeze=False)
        for (ax, ax2), r in zip(axes, shown):
            fs = by[r["name"]]
            ft = np.array([f["t"] for f in fs])
            med = np.array([np.nan if f["t_exit"] is None else f["t_exit"] - f["t"] for f in fs]) / 60.0
            lo = np.array([np.nan if f["t_exit_lo"] is None else f["t_exit_lo"] - f["t"] for f in fs]) / 60.0
            hi = np.array([np.nan if f["t_exit_hi"] is None else f["t_exit_hi"] - f["t"] for f in fs]) / 60.0
            if r["band"] is not None:
                ax.axhspan(*r["band"], color=views.GREEN, alpha=0.13, lw=0, label="healthy band")
            if t.size:
                ax.plot(t, r["value"], color=views.BLUE, lw=1.0, label="estimate")
            # the fan of the forecast at the first early alarm (what the planner was told), else of the last one
            # that still looked ahead; drawn from the estimate's median over the 10 s before it
            t_early = next((a["t_s"] for a in alarms if a.get("parameter") == r["name"] and a.get("level") == "early"),
                           None)
            ahead = [f for f in fs if f["t_exit"] is not None and f["t_exit"] > f["t"] + 1.0] or fs
            last = next((f for f in ahead if t_early is not None and f["t"] >= t_early - 0.5), ahead[-1])
            if r["band"] is not None and t.size and last["t_exit"] is not None:
                near = (t > last["t"] - 10.0) & (t <= last["t"])
                v0 = float(np.median(r["value"][near])) if near.any() else float(r["value"][-1])
                edge = r["band"][1] if last.get("edge", "high") == "high" else r["band"][0]
                for key, ls in (("t_exit_lo", ":"), ("t_exit", "-"), ("t_exit_hi", ":")):
                    if last[key] is not None:
                        ax.plot([last["t"], last[key]], [v0, edge], color=views.ORANGE, lw=1.2, ls=ls, zorder=4)
                ends = [last[k] for k in ("t_exit_lo", "t_exit_hi") if last[k] is not None]
                if len(ends) == 2:
                    ax.fill([last["t"], ends[0], ends[1]], [v0, edge, edge], color=views.ORANGE, alpha=0.35, lw=0, zorder=3,
                            label="forecast (median, 90 %)")
            if r.get("log"):
                ax.set_yscale("log")
            ax.set_ylabel(r["label"])
            ax.set_xlabel("t [s]")
            ax2.fill_between(ft, lo, hi, color=views.ORANGE, alpha=0.25, lw=0, label="90 % interval")
            ax2.plot(ft, med, color=views.ORANGE, lw=1.1, label="median")
            ax2.axhline(horizon / 60.0, color=views.RED, lw=0.8, ls="--", label="horizon")
            for a in alarms:
                if a.get("parameter") == r["name"] and a.get("level") == "early":
                    ax2.axvline(a["t_s"], color=views.RED, lw=1.0)
            for m in s.get("maintenance") or []:
                if r["name"] in m["parameters"]:
                    ax2.axvline(m["t"], color=views.GREEN, lw=1.2, ls="-.")
            top = np.nanmax(np.concatenate([med, [horizon / 60.0]]))
            ax2.set_ylim(0, 1.5 * top if np.isfinite(top) else None)
            ax2.set_ylabel(f"{r['name']} exit in [min]")
            ax2.set_xlabel("t [s]")
        axes[0, 0].legend(loc="best", fontsize="small", frameon=False)
        axes[0, 1].legend(loc="best", fontsize="small", frameon=False)
        fig.tight_layout()
    body = [P.figure(fig, "Left: each forecast parameter's estimate (display units), its healthy band (green) and "
                          "the forecast at its first early alarm (else the last one before the exit): straight to "
                          "the band's edge at the median exit time, the 90 % interval shaded. Right: the remaining time forecast at each second of the record "
                          "(median, 90 % interval shaded; minutes) against the horizon (dashed), early alarms as "
                          "red vertical lines, recorded maintenance as green dash-dot ones.")]
    trows = []
    for name, fs in by.items():
        last = fs[-1]
        first_early = next((a["t_s"] for a in alarms if a.get("parameter") == name and a.get("level") == "early"),
                           None)

        def rem(v, t0=last["t"]):
            return "never" if v is None else fmt_duration(max(0.0, v - t0))

        trows.append({"parameter": name, "forecast at": f"{last['t']:.0f} s",
                      "exit in (median)": rem(last["t_exit"]),
                      "90 % interval": f"{rem(last['t_exit_lo'])} … {rem(last['t_exit_hi'])}",
                      f"P(exit within {fmt_duration(horizon)})": f"{last['p_within_horizon']:.2f}",
                      "first forecast": f"{fs[0]['t']:.0f} s",
                      "first early alarm": "none" if first_early is None else f"{first_early:.0f} s"})
    body.append(P.table(trows, text_columns=("parameter",)))
    for m in s.get("maintenance") or []:  # recorded maintenance: those forecasts started afresh there
        body.append(P.note(f"maintenance at {m['t']:.0f} s: {', '.join(m['parameters'])}"
                           + (f" ({m['note']})" if m.get("note") else "") + ": the forecast started afresh"))
    return "\n".join(body)
