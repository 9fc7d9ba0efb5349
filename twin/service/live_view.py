"""Live view of the twins in Foxglove: rig signals, estimates with their intervals and bands, statuses and alarms.

:class:`LiveView` serves the Foxglove WebSocket protocol (loopback ``127.0.0.1``
by default) under both subprotocol names: ``foxglove.websocket.v1`` (the
documented one, which Foxglove and most clients offer) and ``foxglove.sdk.v1``
(the name ``foxglove-sdk`` >= 0.30 servers answer to).  The SDK's server runs
on an internal loopback port; a small WebSocket front on the public port
accepts either name and relays the frames unchanged.  One JSON channel per
kind of message, each with its JSON schema:

* ``/rig/signals`` (``fpdd.live.Signals``): the rig's signals, decimated to
  ``signal_rate_hz``, in display units named in the field (``x_mm``,
  ``x_ref_mm``, ``u_V``, ``pA_MPa``, ``pB_MPa``: whatever the rig logs).
* ``/twin/estimate`` (``EstimateEvent``): the very message the twin puts on
  Zenoh and in its MCAP (:class:`twin.online.events.EstimateEvent`, SI with the
  unit beside each parameter: ``value``, ``std``, ``lo95``/``hi95``, ``band_lo``/
  ``band_hi``, ``baseline``; the same in the display unit under ``display``, which the layout's
  plots read), plus the Foxglove ``timestamp``.
* ``/twin/status`` (``StatusEvent``): service state, per-parameter status words, counters, message, as on
  Zenoh and in the MCAP.
* ``/twin/forecast`` (``fpdd.Forecast``): when each parameter leaves its band, as on Zenoh
  (``fpdd/<rig>/forecast``) and in the MCAP: per parameter the median exit time and its 90 % interval (record
  seconds) and the remaining time (``remaining_s``, ``remaining_lo_s``, ``remaining_hi_s``), SI with ``units``.
* ``/twin/alarm`` (``AlarmEvent``): every alarm event as on Zenoh and in the MCAP (SI, unit beside, the
  record's ``t_ns`` and the wall-clock ``wall_ns``).
* ``/twin/alarm_log`` (``foxglove.Log``): the same alarms as the lines a person reads (display units, the
  wall-clock time first); the Log panel lists them.

Every message carries ``rig`` (several rigs share the topics; Foxglove filters
with ``/twin/estimate{rig=="msp25-hall1-a"}``) and ``timestamp`` as Foxglove
time ``{sec, nsec}``; its log time is the sample's ``t_ns``.  The layout
``deploy/foxglove-layout.json`` plots each parameter's trend with its band and
interval, the remaining time until each parameter leaves its band with its 90 % interval, the rig's
position and pressures, and lists the alarms (open it in
Foxglove: Layouts, Import from file; connect to ``ws://127.0.0.1:PORT``);
``twin serve --foxglove`` writes one whose variable ``rig`` is the first rig served.

Feeding it: :meth:`LiveView.signals` with sample blocks, :meth:`estimate`,
:meth:`status`, :meth:`alarm` with the events of :mod:`twin.online.events` (or their
dicts), :meth:`payload` with the JSON the service puts on Zenoh;
:meth:`tee` wraps a :class:`twin.service.rig.RigTwin` publisher so everything it
publishes is shown too; :meth:`follow` subscribes to a Zenoh session's
``fpdd/<rig>/{estimate,status,forecast,alarm,signals}`` (any process, any number of twins;
a service puts ``signals`` when its ``signals_hz`` is set, as ``twin serve
--foxglove`` does).
"""

from __future__ import annotations

import json
import math
import threading
from typing import TYPE_CHECKING, Any
from collections.abc import Mapping

from twin.reports.units import Shown, signal_unit
from twin.models import DEFAULT_MODEL
from twin.service.publisher import Publisher

if TYPE_CHECKING:
    from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent
    from foxglove.websocket import WebSocketServer

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
"""The subprotocol names the live view accepts: the documented one first, then foxglove-sdk's own."""
EXAMPLE_RIG = "msp25-hall1-a"
"""The first rig of ``deploy/rigs.example.toml``: the shipped layout's default ``rig``."""

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


def _event_schema(kind: str) -> dict:
    """The schema of a twin event (``EstimateEvent``, ``StatusEvent``, ``AlarmEvent``) with the Foxglove
    ``timestamp``: as the twin's MCAP records it."""
    from replay.mcapio import with_time_schema
    from twin.online import events

    return dict(with_time_schema(getattr(events, kind).SCHEMA))


ESTIMATE_SCHEMA: dict = _event_schema("EstimateEvent")
STATUS_SCHEMA: dict = _event_schema("StatusEvent")
ALARM_SCHEMA: dict = _event_schema("AlarmEvent")


def _forecast_schema() -> dict:
    from replay.mcapio import with_time_schema
    from twin.online.forecast import FORECAST_SCHEMA

    return dict(with_time_schema(FORECAST_SCHEMA))


FORECAST_SCHEMA: dict = _forecast_schema()
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
          "status": ("/twin/status", STATUS_SCHEMA), "forecast": ("/twin/forecast", FORECAST_SCHEMA),
          "alarm": ("/twin/alarm", ALARM_SCHEMA),
          "alarm_log": ("/twin/alarm_log", LOG_SCHEMA)}
LOG_LEVEL = {"ok": 2, "warning": 3, "alarm": 4, "early": 3}


def foxglove_time(t_ns: int) -> dict:
    """``{"sec", "nsec"}`` of integer nanoseconds."""
    t_ns = max(0, int(t_ns))
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def estimate_message(ev) -> dict:
    """The message of an :class:`~twin.online.events.EstimateEvent` on ``/twin/estimate``, live and in the
    twin's MCAP alike: the event's dict (SI, unit beside each parameter, 95 % interval, band, and the same in the
    display unit under ``display``) and its Foxglove
    ``timestamp``."""
    return {**ev.to_dict(), "timestamp": foxglove_time(ev.t_ns)}


# --------------------------------------------------------------------------- rig signals over Zenoh

def signals_key(rig: str = "*") -> str:
    """``fpdd/<rig>/signals``: a service's decimated rig signals (JSON, :func:`signals_to_json`)."""
    return f"fpdd/{rig}/signals"


def signals_to_json(rig: str, samples) -> bytes:
    """A block of samples as the service puts it on :func:`signals_key`: ``{"rig", "t_ns": [...], "signals":
    {name: [...]}, "units": {name: SI unit}}`` (SI; a non-finite sample is ``null``)."""
    from replay import jsonio
    from twin.units import SIGNAL_UNITS

    return jsonio.compact({"rig": rig, "t_ns": [int(t) for t in samples.t_ns],
                           "signals": {k: v.tolist() for k, v in samples.signals.items()},
                           "units": {k: SIGNAL_UNITS.get(k, "") for k in samples.signals}})


def signals_from_json(payload: bytes | str):
    """The :class:`replay.base.Samples` of a :func:`signals_to_json` payload."""
    import numpy as np

    from replay.base import Samples

    d = json.loads(payload)
    return Samples(np.asarray(d["t_ns"], dtype=np.int64),
                   {k: np.asarray([np.nan if x is None else x for x in v], dtype=float)
                    for k, v in d["signals"].items()})


class SignalDecimator:
    """At most ``rate_hz`` samples per second of a stream of blocks: the first sample of every new period
    (``t_ns // period``), across block boundaries."""

    def __init__(self, rate_hz: float) -> None:
        self.period_ns = max(1, int(round(1e9 / rate_hz)))
        self._last = None

    def __call__(self, samples):
        """The kept samples of one block (``None`` when none)."""
        import numpy as np

        if len(samples) == 0:
            return None
        k = np.asarray(samples.t_ns, dtype=np.int64) // self.period_ns
        keep = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        if self._last is not None:
            keep = keep[k[keep] > self._last]
        if len(keep) == 0:
            return None
        self._last = int(k[keep[-1]])
        return type(samples)(samples.t_ns[keep], {n: v[keep] for n, v in samples.signals.items()})


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
    :param model: the rigs' model (display units of its parameters), default :data:`twin.models.DEFAULT_MODEL`.
    :param signal_rate_hz: most signal messages per second and rig (the rest are decimated away).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, *, bands: Mapping | None = None,
                 model: str = DEFAULT_MODEL, signal_rate_hz: float = 100.0, name: str = "fpdd-twin") -> None:
        import foxglove

        self.model = model
        self._period_ns = int(1e9 / signal_rate_hz) if signal_rate_hz > 0 else 0
        self._next_ns: dict[str, int] = {}
        self._bands: dict[str, dict[str, tuple[float | None, float | None, float | None]]] = {}
        for rig, per in (bands or {}).items():
            for p, b in per.items():
                self.set_band(rig, p, b)
        self._lock = threading.Lock()
        self._subs: list = []
        self.counts = {k: 0 for k in TOPICS}
        self._ctx = foxglove.Context()
        self._channels = {k: foxglove.Channel(topic, schema=schema, context=self._ctx)
                          for k, (topic, schema) in TOPICS.items()}
        self._subscribed: dict[str, threading.Event] = {topic: threading.Event() for topic, _ in TOPICS.values()}
        self._server: WebSocketServer | None = foxglove.start_server(
            name=name, host="127.0.0.1", port=0, context=self._ctx, server_listener=_listener(self._subscribed))
        try:
            self._front: _Front | None = _Front(host, port, int(self._server.port))
        except BaseException:
            self._server.stop()
            raise

    # ------------------------------------------------------------------ life
    @property
    def port(self) -> int:
        """The public port (both subprotocols)."""
        assert self._front is not None, "the live view is closed"
        return self._front.port

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
        if self._front is not None:  # the clients first, then the server they were relayed to
            self._front.close()
            self._front = None
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
        """An :class:`~twin.online.events.EstimateEvent` (or its dict), shown as :func:`estimate_message` (a
        parameter without a band takes the one the view was given for the rig)."""
        from twin.online.events import EstimateEvent

        e = ev if isinstance(ev, EstimateEvent) else EstimateEvent.from_dict(_as_dict(ev))
        bands = self._bands.get(e.rig)
        if bands:
            e = e.with_bands(bands)
        msg = estimate_message(e)
        with self._lock:
            self._log("estimate", msg, e.t_ns)

    def status(self, ev) -> None:
        """A :class:`~twin.online.events.StatusEvent` (or its dict): its message with the Foxglove ``timestamp``."""
        from twin.online.events import StatusEvent

        e = ev if isinstance(ev, StatusEvent) else StatusEvent.from_dict(_as_dict(ev))
        with self._lock:
            self._log("status", {**e.to_dict(), "timestamp": foxglove_time(e.t_ns)}, e.t_ns)

    def forecast(self, msg: Mapping) -> None:
        """A forecast message (:func:`twin.online.forecast.forecast_message`, as on Zenoh and in the MCAP) with
        its Foxglove ``timestamp``; one that does not follow its schema raises :class:`twin.errors.DataError`."""
        from twin.online.events import validate
        from twin.online.forecast import FORECAST_SCHEMA as SCHEMA

        d = dict(msg)
        validate(d, SCHEMA, "forecast")
        with self._lock:
            self._log("forecast", {**d, "timestamp": foxglove_time(d["t_ns"])}, d["t_ns"])

    def alarm(self, ev) -> None:
        """An :class:`~twin.online.events.AlarmEvent` (or its dict): on ``/twin/alarm`` the event's message (SI,
        unit beside, with the Foxglove ``timestamp``), on ``/twin/alarm_log`` the line a person reads (display
        units, :func:`twin.online.events.format_alarm`); its band becomes the rig's."""
        from twin.online.events import AlarmEvent, format_alarm

        e = ev if isinstance(ev, AlarmEvent) else AlarmEvent.from_dict(_as_dict(ev))
        self.set_band(e.rig, e.parameter, (e.band_lo, e.band_hi, e.baseline))
        stamp = foxglove_time(e.t_ns)
        log = {"timestamp": stamp, "level": LOG_LEVEL.get(e.level, 2), "message": format_alarm(e, model=self.model),
               "name": e.rig, "file": "", "line": 0}
        with self._lock:
            self._log("alarm", {**e.to_dict(), "timestamp": stamp}, e.t_ns)
            self._log("alarm_log", log, e.t_ns)

    def payload(self, rig: str, kind: str, payload: str | bytes | Mapping) -> None:
        """A message as the service puts it on Zenoh: ``kind`` is ``estimate``, ``status``, ``forecast`` or
        ``alarm``, the payload its JSON (text, bytes or decoded)."""
        d = json.loads(payload) if isinstance(payload, (str, bytes, bytearray)) else dict(payload)
        d.setdefault("rig", rig)
        {"estimate": self.estimate, "status": self.status, "forecast": self.forecast, "alarm": self.alarm}[kind](d)

    # ------------------------------------------------------------------ hooks
    def tee(self, publisher: Publisher | None = None) -> _Tee:
        """A publisher for :class:`twin.service.rig.RigTwin` that hands every event to ``publisher`` (may be
        ``None``) and shows what was published."""
        return _Tee(self, publisher)

    def follow(self, session, rig: str = "*") -> None:
        """Show what the twins publish on a Zenoh session: ``fpdd/<rig>/{estimate,status,forecast,alarm,signals}``."""
        from twin.service.bus import RigKeys

        keys = RigKeys(rig)

        def handler(kind):
            def on_sample(sample) -> None:
                try:
                    rig_of = RigKeys.rig_of(sample.key_expr)
                    if kind == "signals":
                        self.signals(rig_of, signals_from_json(sample.payload.to_bytes()))
                    else:
                        self.payload(rig_of, kind, sample.payload.to_bytes())
                except Exception:  # a malformed payload is the subscriber's problem, not the view's
                    import logging

                    logging.getLogger(__name__).debug("live view: bad %s payload", kind, exc_info=True)
            return on_sample

        for kind, key in (("estimate", keys.estimate), ("status", keys.status), ("forecast", keys.forecast),
                          ("alarm", keys.alarm), ("signals", signals_key(rig))):
            self._subs.append(session.declare_subscriber(key, handler(kind)))


def _listener(events: dict[str, threading.Event]):
    """Server callbacks: notes which topics have a subscriber; every other callback of foxglove's
    ``ServerListener`` (``on_unsubscribe`` when a client leaves or the server stops, ...) is its no-op."""
    from foxglove.websocket import ServerListener

    class _Listener(ServerListener):
        def on_subscribe(self, client, channel) -> None:
            ev = events.get(channel.topic)
            if ev is not None:
                ev.set()

    return _Listener()


class _Front:
    """The public WebSocket endpoint: accepts both subprotocol names (:data:`SUBPROTOCOLS`) and relays every
    frame unchanged, both ways, to the SDK's server on an internal loopback port (``foxglove.sdk.v1``).
    Its asyncio loop runs in a daemon thread; :meth:`close` ends the connections and the thread."""

    def __init__(self, host: str, port: int, inner_port: int) -> None:
        import asyncio

        self.inner_url = f"ws://127.0.0.1:{inner_port}"
        self.port = 0
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._server: Any = None
        self._stopped: Any = None
        self._thread = threading.Thread(target=self._run, args=(host, port), name="foxglove-front", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self._thread.join()
            if isinstance(self._error, OSError):  # a port in use, an address not here: one line
                from twin.errors import SourceError

                raise SourceError(f"Foxglove live view: cannot listen on {host}:{port}: "
                                  f"{self._error.strerror or self._error}") from None
            raise self._error

    def _run(self, host: str, port: int) -> None:
        import asyncio

        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._main(host, port))
        except BaseException as exc:  # a port in use: raised in the caller's thread
            self._error = exc
            self._ready.set()
        finally:
            self._loop.close()

    async def _main(self, host: str, port: int) -> None:
        import asyncio

        from websockets.asyncio.server import serve

        self._stopped = asyncio.Event()
        async with serve(self._relay, host, port, subprotocols=list(SUBPROTOCOLS),  # type: ignore[arg-type]
                         max_size=None, compression=None, ping_interval=None) as server:
            self._server = server
            self.port = int(server.sockets[0].getsockname()[1])
            self._ready.set()
            await self._stopped.wait()
            server.close()
            await server.wait_closed()

    async def _relay(self, client) -> None:
        import asyncio

        from websockets.asyncio.client import connect
        from websockets.exceptions import WebSocketException

        async def pump(a, b) -> None:
            async for frame in a:
                await b.send(frame)

        try:
            async with connect(self.inner_url, subprotocols=["foxglove.sdk.v1"],  # type: ignore[list-item]
                               max_size=None, compression=None, ping_interval=None) as inner:
                tasks = {asyncio.ensure_future(pump(client, inner)), asyncio.ensure_future(pump(inner, client))}
                _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                for t in pending:
                    t.cancel()
                # every pump's end is collected, the finished one's too: a side closed mid-send is a normal end
                await asyncio.gather(*tasks, return_exceptions=True)
        except (OSError, WebSocketException):  # one side went away: the other is closed with it
            pass

    def close(self) -> None:
        if self._thread.is_alive() and self._stopped is not None:
            self._loop.call_soon_threadsafe(self._stopped.set)
            self._thread.join(timeout=10.0)


class _Tee(Publisher):
    """Publisher wrapper: forwards to the real publisher, then shows what it published (it takes estimates as
    events, :meth:`~twin.service.publisher.Publisher.publish_estimate_json` keeps its default)."""

    def __init__(self, view: LiveView, inner: Publisher | None) -> None:
        self.view = view
        self.inner = inner

    def publish_alarm(self, event: AlarmEvent) -> AlarmEvent | None:
        out = self.inner.publish_alarm(event) if self.inner is not None else event
        if out is not None:
            self.view.alarm(out)
        return out

    def publish_estimate(self, event: EstimateEvent) -> None:
        if self.inner is not None:
            self.inner.publish_estimate(event)
        self.view.estimate(event)

    def publish_status(self, event: StatusEvent) -> StatusEvent:
        out = self.inner.publish_status(event) if self.inner is not None else event
        self.view.status(out or event)
        return out or event

    def publish_forecast(self, message: dict) -> None:
        if self.inner is not None:
            self.inner.publish_forecast(message)
        self.view.forecast(message)


# --------------------------------------------------------------------------- the Foxglove layout
PARAMETERS = ("Ffric", "CdAleak", "Cd", "zeta", "wn")


def _plot(title: str, series: list[tuple[str, str, str]], *, ylabel: str = "") -> dict:
    return {"title": title, "paths": [{"value": v, "enabled": True, "timestampMethod": "receiveTime", "label": lbl,
                                       "color": c} for v, lbl, c in series],
            "showXAxisLabels": True, "showYAxisLabels": True, "showLegend": True, "legendDisplay": "floating",
            "showPlotValuesInLegend": True, "isSynced": True, "xAxisVal": "timestamp", "followingViewWidth": 120,
            "sidebarDimension": 240, **({"yAxisLabel": ylabel} if ylabel else {})}


def foxglove_layout(parameters=PARAMETERS, model: str = DEFAULT_MODEL, rig: str = EXAMPLE_RIG) -> dict:
    """The Foxglove layout of the live view (``deploy/foxglove-layout.json``): per parameter its estimate,
    95 % interval and healthy band over time (the ``display`` numbers of each parameter, in the display units
    of ``twin params``, the unit in the title: ``wn [Hz]``, ``CdAleak [mm²]``); the time
    until each parameter leaves its band with its 90 % interval (``/twin/forecast``, seconds); the rig's
    position and pressures (display units); the alarms (Log panel) and the last status.
    The variable ``rig`` selects the rig shown (default: the first rig of ``deploy/rigs.example.toml``)."""
    sel = "{rig==$rig}"
    config: dict = {}
    plots = []
    for i, name in enumerate(parameters):
        sh = Shown(name, model)
        base = f"/twin/estimate{sel}.params.{name}.display"
        pid = f"Plot!param{i}"
        config[pid] = _plot(sh.label, [
            (f"{base}.value", "estimate", "#0072BD"), (f"{base}.lo95", "95 % low", "#4DBEEE"),
            (f"{base}.hi95", "95 % high", "#4DBEEE"), (f"{base}.band_lo", "band low", "#77AC30"),
            (f"{base}.band_hi", "band high", "#77AC30")])
        plots.append(pid)
    colors = ("#0072BD", "#D95319", "#EDB120", "#7E2F8E", "#77AC30", "#4DBEEE", "#A2142F")
    fc = f"/twin/forecast{sel}.forecasts"
    series = []
    for i, name in enumerate(parameters):
        c = colors[i % len(colors)]
        series += [(f"{fc}.{name}.remaining_s", f"{name} median", c),
                   (f"{fc}.{name}.remaining_lo_s", f"{name} 5 %", c), (f"{fc}.{name}.remaining_hi_s", f"{name} 95 %", c)]
    config["Plot!forecast"] = _plot("time until each parameter leaves its band, median and 90 % interval [s]",
                                    series, ylabel="remaining time [s]")
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
        "first": stack(["Plot!forecast", "Plot!position", "Plot!pressures"]),
        "second": {"first": "Log!alarms", "second": "RawMessages!status", "direction": "column",
                   "splitPercentage": 60},
        "direction": "column", "splitPercentage": 50}, "direction": "row", "splitPercentage": 55}
    return {"configById": config, "globalVariables": {"rig": rig}, "userNodes": {}, "playbackConfig": {"speed": 1},
            "layout": layout}


def write_layout(path: str, rig: str = EXAMPLE_RIG, model: str = DEFAULT_MODEL) -> str:
    """Write :func:`foxglove_layout` as JSON (``python -m twin.service.live_view --layout deploy/foxglove-layout.json``)."""
    with open(path, "w", encoding="utf-8") as f:
        json.dump(foxglove_layout(model=model, rig=rig), f, indent=2, ensure_ascii=False)
        f.write("\n")
    return path


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(prog="python -m twin.service.live_view", description="write the Foxglove layout of the "
                                 "live view")
    ap.add_argument("--layout", required=True, metavar="FILE", help="where to write it (deploy/foxglove-layout.json)")
    print(write_layout(ap.parse_args().layout))
