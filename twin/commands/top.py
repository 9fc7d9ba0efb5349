"""``twin top``: the running twins at a glance, live in the terminal.

Per rig: the service state, each tracked parameter's estimate ± standard
deviation in its display unit (wn in Hz, CdAleak in mm²) with its status and
when it leaves its healthy band (the early-warning forecast: median remaining
time and its 90 % interval, in s, min, h or d), the rig's soonest exit, and
the last alarm; refreshed as the twins publish (``rich``).  It subscribes over
Zenoh to ``fpdd/<rig>/{estimate,status,forecast,alarm}`` (the key space of
:mod:`twin.service.bus`), after fetching each twin's latest estimate, status and
forecast and its last journaled alarm, so the screen is filled at once.

A rig shared by several services (``[failover]`` of ``twin serve``) shows the service that runs it
(``owner``) and those standing by for it (``standby``), from their liveliness tokens.

Each rig's title says whether its twin is still there: ``gone`` when its
liveliness token ``fpdd/<rig>/twin`` went away (the process died or lost the
bus), ``stale`` when nothing came from it for :data:`STALE_PERIODS` status
periods, with the age of its last message either way.

``--once --json`` prints one snapshot as JSON and exits (for scripts).  When
no twin answers within ``--wait`` it exits with status 2 and one line
naming the endpoint.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from pathlib import Path
from collections.abc import Callable
from typing import Any

from fpdd.argtypes import positive_seconds
from fpdd import jsonio
from twin.models import DEFAULT_MODEL, MODELS
from twin.reports.units import Shown, pretty_unit

LEVEL_STYLE = {"alarm": "bold red", "warning": "bold yellow", "ok": "green"}
STATUS_STYLE = {"alarm": "bold red", "warning": "bold yellow", "ok": "green", "frozen": "cyan",
                "unresolved": "magenta", "inconsistent": "magenta"}
#: a twin publishes its status at least every STATUS_S; silent for this many periods it is shown ``stale``
STALE_PERIODS = 3
STATE_STYLE = {"running": "green", "finished": "blue", "degraded": "yellow", "stale_input": "yellow",
               "failed": "bold red", "stopped": "dim", "starting": "cyan"}


def add_top_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rig", default="*", help="rig id, or '*' for every rig (default)")
    p.add_argument("--connect", "--zenoh-connect", dest="connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; --zenoh-connect too, "
                   "as in replay); without it or --zenoh-config, twins are found by multicast scouting")
    p.add_argument("--mode", choices=("peer", "client"), default=None,
                   help="Zenoh session mode (default: the --zenoh-config file's, else peer)")
    p.add_argument("--zenoh-config", type=Path, metavar="FILE", help="Zenoh JSON5 configuration (TLS, credentials)")
    p.add_argument("--model", default=DEFAULT_MODEL, choices=MODELS,
                   help=f"the rigs' model, for display units (default {DEFAULT_MODEL})")
    p.add_argument("--wait", dest="wait", type=positive_seconds, default=10.0, metavar="S",
                   help="give up (exit status 2) when no twin answers within S seconds (default 10; as in "
                   "twin alarms)")
    p.add_argument("--once", action="store_true", help="print one snapshot and exit")
    p.add_argument("--json", action="store_true", help="with --once: the snapshot as JSON")
    p.add_argument("--for", "--timeout", dest="duration", type=positive_seconds, metavar="S",
                   help="exit after S seconds (default: until Ctrl-C; as twin alarms --for, --timeout too)")


class TopState:
    """The latest estimate, status and alarm of each rig (thread-safe; callbacks of Zenoh write here)."""

    def __init__(self, model: str = DEFAULT_MODEL, stale_s: float | None = None) -> None:
        from twin.service.rig import STATUS_S

        self.model = model
        self.stale_s = STALE_PERIODS * STATUS_S if stale_s is None else stale_s
        self.rigs: dict[str, dict[str, Any]] = {}
        self.seen: dict[str, float] = {}
        """rig -> wall-clock time [s] of its last message received here"""
        self.alive: dict[str, bool] = {}
        """rig -> whether its liveliness token is there (unknown rigs: not asked yet)"""
        self.roles: dict[str, dict[str, dict[str, int]]] = {}
        """rig -> role (owner, standby, prefer) -> {service_id: priority}: services sharing it (failover)"""
        self.lock = threading.Lock()
        self.changed = threading.Event()

    def token(self, key: str, alive: bool) -> None:
        """A failover token (``fpdd/<rig>/owner|standby|prefer/<priority>/<service_id>``) came or went."""
        from twin.service.ownership import ROLES, parse_token

        parsed = parse_token(key)
        if parsed is None:
            return
        rig, role, prio, sid = parsed
        with self.lock:
            held = self.roles.setdefault(rig, {r: {} for r in ROLES})[role]
            if alive:
                held[sid] = prio
            else:
                held.pop(sid, None)
        self.changed.set()

    def sharing(self, rig: str) -> dict[str, list[str]]:
        """``{"owner": [...], "standby": [...]}``: the services running and standing by for ``rig``, each by the
        failover rule's order (empty lists: not shared)."""
        with self.lock:
            roles = self.roles.get(rig, {})
            return {role: [s for _, s in sorted((p, s) for s, p in roles.get(role, {}).items())]
                    for role in ("owner", "standby")}

    def liveliness(self, rig: str, alive: bool) -> None:
        """The twin of ``rig`` declared (``True``) or lost (``False``) its liveliness token."""
        with self.lock:
            self.alive[rig] = alive
            if alive:
                self.seen.setdefault(rig, time.time())
        self.changed.set()

    def put(self, kind: str, d: dict) -> None:
        with self.lock:
            self.seen[d["rig"]] = time.time()
            r = self.rigs.setdefault(d["rig"], {"estimate": None, "status": None, "alarm": None, "forecast": None})
            old = r[kind]
            if kind == "alarm":
                if old is not None and d.get("seq", 0) < old.get("seq", 0):
                    return
            elif old is not None and d.get("t_ns", 0) < old.get("t_ns", 0):
                return
            r[kind] = d
        self.changed.set()

    def _order(self, name: str) -> tuple[int, str]:
        """Where ``name`` stands among the model's parameters (its declared order: the phenomenological ones as
        ``twin params`` lists them), names the model does not know last, alphabetically."""
        if self._names is None:
            try:
                from twin.models import DEFAULT_MODEL, get_model

                m = get_model(self.model or DEFAULT_MODEL)
                ps = m.params()
                self._names = [*m.PHENOMENOLOGICAL, *ps.names, *(n for e in m.EFFECTS.values() for n in e.names)]
            except Exception:  # an unknown model: alphabetical
                self._names = []
        return (self._names.index(name) if name in self._names else len(self._names), name)

    _names: list[str] | None = None

    def _shown(self, name: str, unit: str | None) -> Shown:
        return Shown(name, self.model, unit)

    def presence(self, rig: str, now: float | None = None) -> tuple[str, float | None]:
        """``("live" | "stale" | "gone", age of the last message [s])``."""
        now = time.time() if now is None else now
        with self.lock:
            seen, alive = self.seen.get(rig), self.alive.get(rig)
        age = None if seen is None else max(0.0, now - seen)
        if alive is False:
            return "gone", age
        if age is not None and age > self.stale_s:
            return "stale", age
        return "live", age

    def snapshot(self) -> dict:
        """JSON-ready: per rig its state, presence (live/stale/gone with the age of its last message),
        parameters (SI value, std, unit and the display text; ``forecast``: when it leaves its band), the
        soonest exit (``soonest_exit``: the parameter whose median exit comes first) and last alarm."""
        out = {}
        now = time.time()
        with self.lock:
            rigs = {k: dict(v) for k, v in self.rigs.items()}
        for rig in sorted(rigs):
            r = rigs[rig]
            est, st, al = r["estimate"], r["status"], r["alarm"]
            fcs = exits(r.get("forecast"))
            words = (st or {}).get("parameters", {})
            params = {}
            for name, p in ((est or {}).get("params") or {}).items():
                sh = self._shown(name, p.get("unit"))
                params[name] = {"value": p["value"], "std": p["std"], "unit": p.get("unit", ""),
                                "display_unit": pretty_unit(sh.unit), "display_value": sh(p["value"]),
                                "display_std": sh(p["std"]),
                                "shown": f"{sh.text(p['value'], 5, unit=False)} ± {sh.text(p['std'], 2)}",
                                "status": words.get(name, "")}
            for name, w in words.items():
                params.setdefault(name, {"status": w})
            for name, f in fcs.items():
                params.setdefault(name, {"status": ""})["forecast"] = f
            for name, m in ((r.get("forecast") or {}).get("maintenance") or {}).items():
                params.setdefault(name, {"status": ""})["maintenance"] = m
            params = {n: params[n] for n in sorted(params, key=self._order)}  # the model's order (payloads sort)
            soonest = min((f for f in fcs.values() if f["t_exit"] is not None),
                          key=lambda f: (f["t_exit"], f["parameter"]), default=None)
            presence, age = self.presence(rig, now)
            out[rig] = {"state": (st or {}).get("state"), "presence": presence, "age_s": age,
                        "message": (st or {}).get("message", ""),
                        "t_s": (est or {}).get("t_s"), "filter": (est or {}).get("status"),
                        "samples": ((st or {}).get("counters") or {}).get("samples"),
                        "params": params, "soonest_exit": soonest,
                        "last_alarm": self.alarm_text(al) if al else None,
                        "last_alarm_event": al, **self.sharing(rig)}
        return out

    def alarm_text(self, a: dict) -> str:
        sh = self._shown(a["parameter"], None)
        return (f"#{a['seq']} t={a['t_s']:.3f} s {a['level'].upper()} {a['kind']} {a['parameter']} = "
                f"{sh.text(a['estimate'], 4, unit=False)} ± {sh.text(a['std'], 2)} (band {sh.text(a['band_lo'], 4, unit=False)}"
                f" … {sh.text(a['band_hi'], 4)})")


def exits(msg: dict | None) -> dict[str, dict]:
    """Per parameter of a forecast message (``fpdd/<rig>/forecast``): its exit time (record seconds, SI), the
    remaining time and its 90 % interval [s], ``p_within_horizon`` and ``shown``, the text a person reads
    (``in 6.1 min [4.0, 9.5]``)."""
    from twin.online.events.forecast import Forecast, describe

    if not msg:
        return {}
    out = {}
    for name, f in (msg.get("forecasts") or {}).items():
        t = f.get("t", msg.get("t_s"))
        fc = Forecast(name, t, msg["t_ns"], f["t_exit"], f["t_exit_lo"], f["t_exit_hi"], f["p_within_horizon"],
                      math.nan, math.nan, f.get("edge", ""))
        out[name] = {"parameter": name, "t": t, "t_exit": f["t_exit"], "t_exit_lo": f["t_exit_lo"],
                     "t_exit_hi": f["t_exit_hi"], "remaining_s": f.get("remaining_s"),
                     "remaining_lo_s": f.get("remaining_lo_s"), "remaining_hi_s": f.get("remaining_hi_s"),
                     "p_within_horizon": f["p_within_horizon"], "horizon_s": msg.get("horizon_s"),
                     "edge": f.get("edge"), "shown": describe(fc)}
    return out


def render(snap: dict, where: str, live: bool = True):
    """The rich renderable of a snapshot: one table per rig."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    parts: list[Text | Table] = [Text(f"twin top · {len(snap)} rig(s) via {where}" + (" · Ctrl-C to quit" if live else ""), style="dim")]
    for rig, r in snap.items():
        state = r["state"] or "?"
        presence, age = r.get("presence", "live"), r.get("age_s")
        mark: tuple[str, str] | str = ""
        if presence == "gone":
            mark = (f"  GONE (twin left the bus; last message {age:.0f} s ago)" if age is not None
                    else "  GONE (twin left the bus)", "bold red")
        elif presence == "stale":
            mark = (f"  STALE (no message for {age:.0f} s)", "bold yellow")
        title = Text.assemble(("rig ", "bold"), (rig, "bold"), "  ", (state, STATE_STYLE.get(state, "")), mark,
                              f"  t = {r['t_s']:.2f} s" if r["t_s"] is not None else "",
                              f"  samples {r['samples']}" if r["samples"] is not None else "",
                              f"  filter {r['filter']}" if r["filter"] else "",
                              f"  owner {', '.join(r['owner'])}" if r.get("owner") else "",
                              f"  standby {', '.join(r['standby'])}" if r.get("standby") else "")
        parts.append(title)
        t = Table(expand=False, show_edge=True)
        t.add_column("parameter")
        t.add_column("estimate", justify="right")
        t.add_column("± std", justify="right")
        t.add_column("unit")
        t.add_column("status")
        t.add_column("leaves band")
        soonest = r.get("soonest_exit")
        for name, p in r["params"].items():
            f = p.get("forecast")
            m = p.get("maintenance")
            exit_text = Text(f["shown"], "bold yellow" if soonest and soonest["parameter"] == name else "") if f \
                else Text(f"maintained #{m['seq']}" + (f" ({m['note']})" if m.get("note") else ""), "cyan") if m \
                else Text("")
            if "display_value" not in p:
                t.add_row(name, "", "", "", Text(p["status"], STATUS_STYLE.get(p["status"], "")), exit_text)
                continue
            t.add_row(name, f"{p['display_value']:.5g}", f"{p['display_std']:.2g}", p["display_unit"],
                      Text(p["status"] or "", STATUS_STYLE.get(p["status"], "")), exit_text)
        parts.append(t)
        if soonest:
            parts.append(Text.assemble("  soonest exit: ", (f"{soonest['parameter']} leaves its band {soonest['shown']}"
                                                              f" (p within {_horizon(soonest)} = "
                                                              f"{soonest['p_within_horizon']:.2f})", "bold yellow")))
        al = r["last_alarm_event"]
        if al:
            parts.append(Text.assemble("  last alarm: ", (r["last_alarm"], LEVEL_STYLE.get(al["level"], ""))))
        else:
            parts.append(Text("  last alarm: none", style="dim"))
        if r["message"]:
            parts.append(Text(f"  {r['message']}", style="yellow"))
    return Group(*parts)


def _horizon(f: dict) -> str:
    from twin.online.events.forecast import fmt_duration

    return fmt_duration(f["horizon_s"]) if f.get("horizon_s") else "the horizon"


def _fill(session, state: TopState, rig: str, timeout: float) -> None:
    """Latest estimate, status and forecast of every twin (queryables), and each rig's last journaled alarm."""
    import zenoh

    from twin.service.bus import RigKeys
    from twin.service.queries import fetch_forecasts, fetch_latest

    for kind in ("estimate", "status"):
        for ev in fetch_latest(session, kind, rig, timeout=timeout):
            state.put(kind, ev.to_dict())
    for msg in fetch_forecasts(session, rig, timeout=timeout):
        state.put("forecast", msg)
    with state.lock:
        known = {r: (v["status"] or {}).get("counters", {}).get("alarm_seq") for r, v in state.rigs.items()}
    for r, last in known.items():
        if last == 0:
            continue
        sel = RigKeys(r).history + (f"?since_seq={last}" if last else "")
        replies = session.get(sel, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                              timeout=timeout)
        for reply in replies:
            if reply.ok is not None:
                try:
                    state.put("alarm", json.loads(reply.ok.payload.to_string()))
                except (ValueError, KeyError):
                    continue


def run_top(args) -> int:
    import zenoh

    from twin.service.bus import RigKeys
    from fpdd.zenohconf import check_endpoint, config_endpoints, open_session, zenoh_config
    from fpdd.errors import SourceError
    from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent, validate
    from twin.online.events.forecast import FORECAST_SCHEMA

    for e in args.connect:
        check_endpoint(e, "--connect")
    if args.json and not args.once:
        from fpdd.errors import ConfigError

        raise ConfigError("--json needs --once (a snapshot); the live view is for a terminal")
    scouting = True if not args.connect and args.zenoh_config is None else None
    config = zenoh_config(mode=args.mode, connect=args.connect, multicast_scouting=scouting,
                          config_file=args.zenoh_config)
    _, connect = config_endpoints(config)
    where = ", ".join(connect) if connect else "multicast scouting"
    keys = RigKeys(args.rig)
    state = TopState(args.model)
    session = open_session(config, "twin top")
    subs = []
    try:
        def checked_forecast(d: dict) -> dict:
            validate(d, FORECAST_SCHEMA, "forecast")
            return d

        parse: dict[str, Callable[[Any], Any]] = {
            "estimate": lambda d: EstimateEvent.from_dict(d).to_dict(),
            "status": lambda d: StatusEvent.from_dict(d).to_dict(),
            "alarm": lambda d: AlarmEvent.from_dict(d).to_dict(), "forecast": checked_forecast}

        def handler(kind):
            def on_sample(sample) -> None:
                try:
                    d = parse[kind](json.loads(sample.payload.to_bytes()))
                except Exception:  # a malformed payload is not shown
                    return
                state.put(kind, d)
            return on_sample

        for kind, key in (("estimate", keys.estimate), ("status", keys.status), ("forecast", keys.forecast),
                          ("alarm", keys.alarm)):
            subs.append(session.declare_subscriber(key, handler(kind)))

        def on_token(sample) -> None:
            import zenoh

            try:
                rig = RigKeys.rig_of(sample.key_expr)
            except Exception:  # not a twin's token
                return
            state.liveliness(rig, sample.kind == zenoh.SampleKind.PUT)

        subs.append(session.liveliness().declare_subscriber(keys.twin, on_token, history=True))
        subs.append(session.liveliness().declare_subscriber(  # who runs and who stands by (failover)
            f"fpdd/{args.rig}/*/*/*", lambda s: state.token(str(s.key_expr), s.kind == zenoh.SampleKind.PUT),
            history=True))
        deadline = time.monotonic() + args.wait
        while True:
            _fill(session, state, args.rig, timeout=max(0.2, min(2.0, deadline - time.monotonic())))
            with state.lock:
                have = any(v["estimate"] or v["status"] for v in state.rigs.values())
            if have:
                break
            if time.monotonic() >= deadline:
                raise SourceError(f"no twin answered through {where} within {args.wait:g} s "
                                  f"(nothing on {keys.estimate} or {keys.status})")
            state.changed.wait(timeout=max(0.0, min(0.5, deadline - time.monotonic())))
        if args.once:
            snap = state.snapshot()
            if args.json:

                print(jsonio.dumps({"where": where, "rigs": snap}))
            else:
                from rich.console import Console

                Console().print(render(snap, where, live=False))
            return 0
        return _live(state, where, args.duration)
    finally:
        for s in subs:
            s.undeclare()
        session.close()


def _live(state: TopState, where: str, duration: float | None) -> int:
    from rich.console import Console
    from rich.live import Live

    console = Console()
    end = None if duration is None else time.monotonic() + duration
    try:
        with Live(render(state.snapshot(), where), console=console, refresh_per_second=4,
                  redirect_stderr=False) as live:
            while end is None or time.monotonic() < end:
                wait = 0.5 if end is None else max(0.0, min(0.5, end - time.monotonic()))
                if state.changed.wait(timeout=wait):
                    state.changed.clear()
                live.update(render(state.snapshot(), where))  # ages grow without messages too
    except KeyboardInterrupt:
        pass
    return 0
