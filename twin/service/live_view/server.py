"""The live view's Foxglove WebSocket server (:class:`LiveView`), its front that accepts both subprotocol names,
and the tee that shows what a rig's twin publishes."""

from __future__ import annotations

import json
import threading
from typing import TYPE_CHECKING, Any
from collections.abc import Mapping

from twin.models import DEFAULT_MODEL
from twin.service.publisher import Publisher

if TYPE_CHECKING:
    from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent
    from foxglove.websocket import WebSocketServer
from twin.service.live_view.messages import (SUBPROTOCOLS, SignalFields, alarm_log_message, estimate_message,
                                             foxglove_time, topics)
from twin.service.live_view.signals import signals_from_json, signals_key


def _as_dict(ev: Any) -> dict:
    return ev.to_dict() if hasattr(ev, "to_dict") else dict(ev)


class LiveView:
    """A Foxglove WebSocket server showing the twins live (channels: :mod:`twin.service.live_view.messages`).

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
        self._fields: dict[str, SignalFields] = {}
        self._bands: dict[str, dict[str, tuple[float | None, float | None, float | None]]] = {}
        for rig, per in (bands or {}).items():
            for p, b in per.items():
                self.set_band(rig, p, b)
        self._lock = threading.Lock()
        self._subs: list = []
        channels = topics(model)
        self.counts = {k: 0 for k in channels}
        self._ctx = foxglove.Context()
        self._channels = {k: foxglove.Channel(topic, schema=schema, context=self._ctx)
                          for k, (topic, schema) in channels.items()}
        self._subscribed: dict[str, threading.Event] = {topic: threading.Event() for topic, _ in channels.values()}
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
        """A block of :class:`replay.base.Samples` (SI); returns how many messages it made (decimated): each
        sample's signals in SI with their units, and in display units under ``display``
        (:class:`~twin.service.live_view.messages.SignalFields`)."""
        t_ns = samples.t_ns
        if len(t_ns) == 0:
            return 0
        t0 = self._next_ns.setdefault(f"{rig}/t0", int(t_ns[0]))
        fields = self._fields.get(rig)
        if fields is None or fields.names != tuple(samples.signals):
            fields = self._fields[rig] = SignalFields(samples.signals, self.model)
        columns = [samples.signals[n] for n in fields.names]
        due = self._next_ns.get(rig, int(t_ns[0]))
        sent = 0
        with self._lock:
            for i in range(len(t_ns)):
                t = int(t_ns[i])
                if self._period_ns and t < due:
                    continue
                due = t + self._period_ns
                self._log("signals", fields.message(rig, t, (t - t0) * 1e-9, [c[i] for c in columns]), t)
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
        """A forecast message (:func:`twin.online.events.forecast.forecast_message`, as on Zenoh and in the MCAP) with
        its Foxglove ``timestamp``; one that does not follow its schema raises :class:`fpdd.errors.DataError`."""
        from twin.online.events import validate
        from twin.online.events.forecast import FORECAST_SCHEMA as SCHEMA

        d = dict(msg)
        validate(d, SCHEMA, "forecast")
        with self._lock:
            self._log("forecast", {**d, "timestamp": foxglove_time(d["t_ns"])}, d["t_ns"])

    def alarm(self, ev) -> None:
        """An :class:`~twin.online.events.AlarmEvent` (or its dict): on ``/twin/alarm`` the event's message (SI,
        unit beside, with the Foxglove ``timestamp``), on ``/twin/alarm_log`` the line a person reads (display
        units, :func:`twin.online.events.format_alarm`); its band becomes the rig's."""
        from twin.online.events import AlarmEvent

        e = ev if isinstance(ev, AlarmEvent) else AlarmEvent.from_dict(_as_dict(ev))
        self.set_band(e.rig, e.parameter, (e.band_lo, e.band_hi, e.baseline))
        stamp = foxglove_time(e.t_ns)
        log = alarm_log_message(e, self.model)
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
                from fpdd.errors import SourceError

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
