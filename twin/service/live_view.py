"""Live view of the twins in Foxglove: rig signals, estimates with their bands, statuses and alarms.

:class:`LiveView` runs a Foxglove WebSocket server (``foxglove-sdk``,
protocol ``foxglove.websocket.v1``; loopback ``127.0.0.1`` by default) with one
JSON channel per kind of message, each with its JSON schema:

================  ====================  ==============================================================
topic             schema                content (display units: x in mm, pressures in MPa, wn in Hz)
================  ====================  ==============================================================
``/rig/signals``  ``fpdd.live.Signals``  rig signals, decimated to ``signal_rate_hz``: ``x_mm``, ``x_ref_mm``,
                                         ``u_V``, ``pA_MPa``, ``pB_MPa`` (whatever the rig logs)
``/twin/estimate`` ``fpdd.live.Estimate`` per parameter ``value``, ``std``, ``lo95``/``hi95`` (95 % interval,
                                         log-normal as the tracker's), ``band_lo``/``band_hi`` (healthy band)
``/twin/status``  ``fpdd.live.Status``   service state, per-parameter status words, counters, message
``/twin/alarm``   ``fpdd.live.Alarm``    every alarm event: seq, level, kind, estimate ± std, band, message
``/twin/alarm_log`` ``foxglove.Log``     the same alarms as Foxglove log lines (the Log panel lists them)
================  ====================  ==============================================================

Every message carries ``rig`` (several rigs share the topics; Foxglove filters
with ``/twin/estimate{rig=="msp25-01"}``) and ``timestamp`` as Foxglove time
``{sec, nsec}``; its log time is the sample's ``t_ns``.  The layout
``deploy/foxglove-layout.json`` plots each parameter's trend with its band and
interval and lists the alarms (open it in Foxglove: Layouts, Import from file;
connect to ``ws://127.0.0.1:PORT``).

Feeding it: :meth:`LiveView.signals` with sample blocks, :meth:`estimate`,
:meth:`status`, :meth:`alarm` with the events of :mod:`twin.online.events` (or their
dicts), :meth:`payload` with the JSON the service puts on Zenoh;
:meth:`tee` wraps a :class:`twin.service.rig.RigTwin` publisher so everything it
publishes is shown too; :meth:`follow` subscribes to a Zenoh session's
``fpdd/<rig>/{estimate,status,alarm}`` (any process, any number of twins).
"""

from __future__ import annotations

import json
import math
import threading
from typing import TYPE_CHECKING, Any
from collections.abc import Mapping

from twin.reports.units import Shown, pretty_unit, signal_unit

if TYPE_CHECKING:
    from foxglove.websocket import WebSocketServer

Z95 = 1.959963984540054

_TIME = {"type": "object", "title": "time", "description": "Foxglove time: seconds and nanoseconds since the epoch "
         "(of the ingest clock: a replayed log's own time)",
         "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0,
                                                                          "maximum": 999999999}},
         "required": ["sec", "nsec"]}
_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}

SIGNALS_SCHEMA: dict = {
    "title": "fpdd.live.Signals", "type": "object",
    "description": "Rig signals in display units (field name = signal_unit), decimated for display",
    "properties": {"timestamp": _TIME, "rig": {"type": "string"}, "t_s": {**_NUM, "description": "s from the start"},
                   "x_mm": _NUM, "x_ref_mm": _NUM, "u_V": _NUM, "pA_MPa": _NUM, "pB_MPa": _NUM, "y_mm": _NUM},
    "additionalProperties": _NUM_OR_NULL, "required": ["timestamp", "rig", "t_s"],
}
_PARAM = {"type": "object", "properties": {
    "value": _NUM, "std": _NUM, "lo95": _NUM, "hi95": _NUM, "band_lo": _NUM_OR_NULL, "band_hi": _NUM_OR_NULL,
    "baseline": _NUM_OR_NULL, "unit": {"type": "string", "description": "display unit ('' for dimensionless)"}},
    "required": ["value", "std", "lo95", "hi95", "band_lo", "band_hi", "unit"]}
ESTIMATE_SCHEMA: dict = {
    "title": "fpdd.live.Estimate", "type": "object",
    "description": "Tracked parameters in display units with their 95 % interval and healthy band",
    "properties": {"timestamp": _TIME, "rig": {"type": "string"}, "t_s": _NUM, "status": {"type": "string"},
                   "nis": _NUM_OR_NULL, "params": {"type": "object", "additionalProperties": _PARAM}},
    "required": ["timestamp", "rig", "t_s", "status", "params"],
}
STATUS_SCHEMA: dict = {
    "title": "fpdd.live.Status", "type": "object", "description": "Health of the twin serving one rig",
    "properties": {"timestamp": _TIME, "rig": {"type": "string"}, "state": {"type": "string"},
                   "parameters": {"type": "object", "additionalProperties": {"type": "string"}},
                   "counters": {"type": "object", "additionalProperties": {"type": "integer"}},
                   "message": {"type": "string"}},
    "required": ["timestamp", "rig", "state", "parameters", "counters", "message"],
}
ALARM_SCHEMA: dict = {
    "title": "fpdd.live.Alarm", "type": "object", "description": "A drift alarm event, values in display units",
    "properties": {"timestamp": _TIME, "rig": {"type": "string"}, "seq": {"type": "integer"},
                   "parameter": {"type": "string"}, "level": {"type": "string", "enum": ["ok", "warning", "alarm", "early"]},
                   "kind": {"type": "string"}, "t_s": _NUM, "estimate": _NUM, "std": _NUM, "baseline": _NUM,
                   "band_lo": _NUM, "band_hi": _NUM, "unit": {"type": "string"}, "statistic": _NUM,
                   "message": {"type": "string"}, "text": {"type": "string", "description": "one line"}},
    "required": ["timestamp", "rig", "seq", "parameter", "level", "kind", "t_s", "estimate", "std", "band_lo",
                 "band_hi", "unit", "message", "text"],
}
LOG_SCHEMA: dict = {
    "title": "foxglove.Log", "type": "object",
    "description": "Foxglove's well-known log message (the Log panel lists them): one line per alarm event",
    "properties": {"timestamp": _TIME, "level": {"type": "integer", "minimum": 0, "maximum": 5,
                                                 "description": "2 info (returned), 3 warning, 4 error (alarm)"},
                   "message": {"type": "string"}, "name": {"type": "string", "description": "the rig"},
                   "file": {"type": "string"}, "line": {"type": "integer", "minimum": 0}},
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}
TOPICS = {"signals": ("/rig/signals", SIGNALS_SCHEMA), "estimate": ("/twin/estimate", ESTIMATE_SCHEMA),
          "status": ("/twin/status", STATUS_SCHEMA), "alarm": ("/twin/alarm", ALARM_SCHEMA),
          "alarm_log": ("/twin/alarm_log", LOG_SCHEMA)}
LOG_LEVEL = {"ok": 2, "warning": 3, "alarm": 4, "early": 3}


def foxglove_time(t_ns: int) -> dict:
    """``{"sec", "nsec"}`` of integer nanoseconds."""
    t_ns = max(0, int(t_ns))
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def _finite(v) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


def _as_dict(ev: Any) -> dict:
    return ev.to_dict() if hasattr(ev, "to_dict") else dict(ev)


class LiveView:
    """A Foxglove WebSocket server showing the twins live (see the module docstring).

    :param host: address to listen on (default loopback; ``0.0.0.0`` exposes it to the network).
    :param port: TCP port (0: any free port, see :attr:`port`).
    :param bands: ``{rig: {parameter: (lo, hi)}}`` or ``{rig: {parameter: twin.online.baseline.Baseline}}`` in SI:
        the healthy bands drawn with the estimates (an alarm's band updates them too).
    :param model: the rigs' model (display units of its parameters), default ``msp25``.
    :param signal_rate_hz: most signal messages per second and rig (the rest are decimated away).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, bands: Mapping | None = None,
                 model: str = "msp25", signal_rate_hz: float = 100.0, name: str = "fpdd-twin") -> None:
        import foxglove

        self.model = model
        self._period_ns = int(1e9 / signal_rate_hz) if signal_rate_hz > 0 else 0
        self._next_ns: dict[str, int] = {}
        self._bands: dict[str, dict[str, tuple[float | None, float | None, float | None]]] = {}
        for rig, per in (bands or {}).items():
            for p, b in per.items():
                self.set_band(rig, p, b)
        self._shown: dict[str, Shown] = {}
        self._lock = threading.Lock()
        self._subs: list = []
        self.counts = {k: 0 for k in TOPICS}
        self._ctx = foxglove.Context()
        self._channels = {k: foxglove.Channel(topic, schema=schema, context=self._ctx)
                          for k, (topic, schema) in TOPICS.items()}
        self._subscribed: dict[str, threading.Event] = {topic: threading.Event() for topic, _ in TOPICS.values()}
        # _Listener implements only on_subscribe of foxglove's ServerListener protocol, the one callback used
        self._server: WebSocketServer | None = foxglove.start_server(
            name=name, host=host, port=port, context=self._ctx,
            server_listener=_Listener(self._subscribed))  # type: ignore[arg-type]

    # ------------------------------------------------------------------ life
    @property
    def port(self) -> int:
        assert self._server is not None, "the live view is closed"
        return int(self._server.port)

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # the session may be closed already
                pass
        self._subs.clear()
        if self._server is not None:
            self._server.stop()
            self._server = None
        for ch in self._channels.values():
            ch.close()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def wait_subscribed(self, topic: str, timeout: float) -> bool:
        """Wait until a client subscribes to ``topic`` (e.g. ``/twin/alarm``); ``True`` if one did."""
        return self._subscribed[topic].wait(timeout)

    # ------------------------------------------------------------------ bands and units
    def set_band(self, rig: str, parameter: str, band) -> None:
        """The healthy band of one parameter of one rig: ``(lo, hi)``, ``(lo, hi, baseline)`` or a Baseline (SI)."""
        if hasattr(band, "lo"):
            band = (band.lo, band.hi, band.value)
        lo, hi, *rest = band
        self._bands.setdefault(rig, {})[parameter] = (lo, hi, rest[0] if rest else None)

    def _sh(self, name: str, unit: str | None) -> Shown:
        sh = self._shown.get(name)
        if sh is None:
            sh = self._shown[name] = Shown(name, self.model, unit)
        return sh

    def _log(self, kind: str, msg: dict, t_ns: int) -> None:
        self._channels[kind].log(msg, log_time=max(0, int(t_ns)))
        self.counts[kind] += 1

    # ------------------------------------------------------------------ inputs
    def signals(self, rig: str, samples) -> int:
        """A block of :class:`replay.base.Samples` (SI); returns how many messages it made (decimated)."""
        t_ns = samples.t_ns
        if len(t_ns) == 0:
            return 0
        t0 = self._next_ns.setdefault(f"{rig}/t0", int(t_ns[0]))
        names = [(n, *signal_unit(n, self.model)) for n in samples.signals]
        fields = [(f"{n}_{u}" if u else n, samples.signals[n], sc) for n, u, sc in names]
        due = self._next_ns.get(rig, int(t_ns[0]))
        sent = 0
        with self._lock:
            for i in range(len(t_ns)):
                t = int(t_ns[i])
                if self._period_ns and t < due:
                    continue
                due = t + self._period_ns
                msg = {"timestamp": foxglove_time(t), "rig": rig, "t_s": (t - t0) * 1e-9}
                for key, arr, sc in fields:
                    msg[key] = _finite(arr[i] * sc)
                self._log("signals", msg, t)
                sent += 1
            self._next_ns[rig] = due
        return sent

    def estimate(self, ev) -> None:
        """An :class:`~twin.online.events.EstimateEvent` (or its dict): values, 95 % interval and band, display units."""
        d = _as_dict(ev)
        rig = d["rig"]
        bands = self._bands.get(rig, {})
        params = {}
        for name, p in d["params"].items():
            sh = self._sh(name, p.get("unit"))
            v, s = float(p["value"]), float(p["std"])
            rel = s / abs(v) if v else 0.0
            lo, hi = (v * math.exp(-Z95 * rel), v * math.exp(Z95 * rel)) if v > 0 else (v - Z95 * s, v + Z95 * s)
            b = bands.get(name, (None, None, None))
            params[name] = {"value": sh(v), "std": sh(s), "lo95": sh(lo), "hi95": sh(hi), "band_lo": sh(b[0]),
                            "band_hi": sh(b[1]), "baseline": sh(b[2]), "unit": pretty_unit(sh.unit)}
        msg = {"timestamp": foxglove_time(d["t_ns"]), "rig": rig, "t_s": float(d["t_s"]),
               "status": str(d.get("status", "ok")), "nis": _finite(d.get("nis")), "params": params}
        with self._lock:
            self._log("estimate", msg, d["t_ns"])

    def status(self, ev) -> None:
        """A :class:`~twin.online.events.StatusEvent` (or its dict)."""
        d = _as_dict(ev)
        msg = {"timestamp": foxglove_time(d["t_ns"]), "rig": d["rig"], "state": d["state"],
               "parameters": dict(d.get("parameters") or {}), "counters": dict(d.get("counters") or {}),
               "message": d.get("message", "")}
        with self._lock:
            self._log("status", msg, d["t_ns"])

    def alarm(self, ev) -> None:
        """An :class:`~twin.online.events.AlarmEvent` (or its dict), in display units; its band becomes the rig's."""
        d = _as_dict(ev)
        name = d["parameter"]
        sh = self._sh(name, None)
        self.set_band(d["rig"], name, (d["band_lo"], d["band_hi"], d.get("baseline")))
        u = pretty_unit(sh.unit)
        text = (f"#{d.get('seq', 0)} t={d['t_s']:.3f} s {d['level'].upper()} {d['kind']} {name} = "
                f"{sh.text(d['estimate'], 4, unit=False)} ± {sh.text(d['std'], 2)} (band {sh.text(d['band_lo'], 4, unit=False)}"
                f" … {sh.text(d['band_hi'], 4)})")
        msg = {"timestamp": foxglove_time(d["t_ns"]), "rig": d["rig"], "seq": int(d.get("seq", 0)), "parameter": name,
               "level": d["level"], "kind": d["kind"], "t_s": float(d["t_s"]), "estimate": sh(d["estimate"]),
               "std": sh(d["std"]), "baseline": sh(d.get("baseline", float("nan"))) if d.get("baseline") is not None
               else None, "band_lo": sh(d["band_lo"]), "band_hi": sh(d["band_hi"]), "unit": u,
               "statistic": _finite(d.get("statistic")), "message": d.get("message", ""), "text": text}
        log = {"timestamp": msg["timestamp"], "level": LOG_LEVEL.get(d["level"], 2), "message": text,
               "name": d["rig"], "file": "", "line": 0}
        with self._lock:
            self._log("alarm", msg, d["t_ns"])
            self._log("alarm_log", log, d["t_ns"])

    def payload(self, rig: str, kind: str, payload: str | bytes | Mapping) -> None:
        """A message as the service puts it on Zenoh: ``kind`` is ``estimate``, ``status`` or ``alarm``, the
        payload its JSON (text, bytes or decoded)."""
        d = json.loads(payload) if isinstance(payload, (str, bytes, bytearray)) else dict(payload)
        d.setdefault("rig", rig)
        {"estimate": self.estimate, "status": self.status, "alarm": self.alarm}[kind](d)

    # ------------------------------------------------------------------ hooks
    def tee(self, publisher=None) -> _Tee:
        """A publisher for :class:`twin.service.rig.RigTwin` that hands every event to ``publisher`` (may be
        ``None``) and shows what was published."""
        return _Tee(self, publisher)

    def follow(self, session, rig: str = "*") -> None:
        """Show what the twins publish on a Zenoh session: ``fpdd/<rig>/{estimate,status,alarm}``."""
        from twin.service.bus import RigKeys

        keys = RigKeys(rig)

        def handler(kind):
            def on_sample(sample) -> None:
                try:
                    self.payload(RigKeys.rig_of(sample.key_expr), kind, sample.payload.to_bytes())
                except Exception:  # a malformed payload is the subscriber's problem, not the view's
                    import logging

                    logging.getLogger(__name__).debug("live view: bad %s payload", kind, exc_info=True)
            return on_sample

        for kind, key in (("estimate", keys.estimate), ("status", keys.status), ("alarm", keys.alarm)):
            self._subs.append(session.declare_subscriber(key, handler(kind)))


class _Listener:
    """Server callbacks: notes which topics have a subscriber."""

    def __init__(self, events: dict[str, threading.Event]) -> None:
        self.events = events

    def on_subscribe(self, client, channel) -> None:
        ev = self.events.get(channel.topic)
        if ev is not None:
            ev.set()


class _Tee:
    """Publisher wrapper: forwards to the real publisher, then shows what it published."""

    def __init__(self, view: LiveView, inner) -> None:
        self.view = view
        self.inner = inner

    def publish_alarm(self, ev):
        out = self.inner.publish_alarm(ev) if self.inner is not None else ev
        if out is not None:
            self.view.alarm(out)
        return out

    def publish_estimate(self, ev):
        out = self.inner.publish_estimate(ev) if self.inner is not None else None
        self.view.estimate(ev)
        return out

    def publish_status(self, ev):
        out = self.inner.publish_status(ev) if self.inner is not None else ev
        self.view.status(out or ev)
        return out


# --------------------------------------------------------------------------- the Foxglove layout
PARAMETERS = ("Ffric", "CdAleak", "Cd", "zeta", "wn")


def _plot(title: str, series: list[tuple[str, str, str]], *, ylabel: str = "") -> dict:
    return {"title": title, "paths": [{"value": v, "enabled": True, "timestampMethod": "receiveTime", "label": lbl,
                                       "color": c} for v, lbl, c in series],
            "showXAxisLabels": True, "showYAxisLabels": True, "showLegend": True, "legendDisplay": "floating",
            "showPlotValuesInLegend": True, "isSynced": True, "xAxisVal": "timestamp", "followingViewWidth": 120,
            "sidebarDimension": 240, **({"yAxisLabel": ylabel} if ylabel else {})}


def foxglove_layout(parameters=PARAMETERS, model: str = "msp25", rig: str = "msp25-01") -> dict:
    """The Foxglove layout of the live view (``deploy/foxglove-layout.json``): per parameter its estimate,
    95 % interval and healthy band over time; the rig's signals; the alarms (Log panel) and the last status.
    The variable ``rig`` selects the rig shown."""
    sel = "{rig==$rig}"
    config: dict = {}
    plots = []
    for i, name in enumerate(parameters):
        sh = Shown(name, model)
        base = f"/twin/estimate{sel}.params.{name}"
        pid = f"Plot!param{i}"
        config[pid] = _plot(sh.label, [
            (f"{base}.value", "estimate", "#0072BD"), (f"{base}.lo95", "95 % low", "#4DBEEE"),
            (f"{base}.hi95", "95 % high", "#4DBEEE"), (f"{base}.band_lo", "band low", "#77AC30"),
            (f"{base}.band_hi", "band high", "#77AC30")])
        plots.append(pid)
    sig = f"/rig/signals{sel}"
    config["Plot!position"] = _plot("position x, demand x_ref [mm]", [(f"{sig}.x_mm", "x", "#0072BD"),
                                                                      (f"{sig}.x_ref_mm", "x_ref", "#8c8c8c")])
    config["Plot!pressures"] = _plot("chamber pressures [MPa]", [(f"{sig}.pA_MPa", "pA", "#D95319"),
                                                                 (f"{sig}.pB_MPa", "pB", "#7E2F8E")])
    config["Log!alarms"] = {"searchTerms": [], "minLogLevel": 1, "topicToRender": "/twin/alarm_log",
                            "nameFilter": {}, "fontSize": 12}
    config["RawMessages!status"] = {"topicPath": f"/twin/status{sel}", "diffEnabled": False, "diffMethod": "custom",
                                    "diffTopicPath": "", "showFullMessageForDiff": False, "expansion": "all"}

    def stack(ids: list[str], direction: str = "column"):
        if len(ids) == 1:
            return ids[0]
        return {"first": ids[0], "second": stack(ids[1:], direction), "direction": direction,
                "splitPercentage": 100.0 / len(ids)}

    layout = {"first": stack(plots), "second": {
        "first": stack(["Plot!position", "Plot!pressures"]),
        "second": {"first": "Log!alarms", "second": "RawMessages!status", "direction": "column",
                   "splitPercentage": 60},
        "direction": "column", "splitPercentage": 50}, "direction": "row", "splitPercentage": 55}
    return {"configById": config, "globalVariables": {"rig": rig}, "userNodes": {}, "playbackConfig": {"speed": 1},
            "layout": layout}


def write_layout(path: str) -> str:
    """Write :func:`foxglove_layout` as JSON (``python -m twin.service.live_view --layout deploy/foxglove-layout.json``)."""
    with open(path, "w", encoding="utf-8") as f:
        json.dump(foxglove_layout(), f, indent=2, ensure_ascii=False)
        f.write("\n")
    return path


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(prog="python -m twin.service.live_view", description="write the Foxglove layout of the "
                                 "live view")
    ap.add_argument("--layout", required=True, metavar="FILE", help="where to write it (deploy/foxglove-layout.json)")
    print(write_layout(ap.parse_args().layout))
