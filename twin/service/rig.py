"""The online twin service: per rig, samples in, tracked parameters and drift alarms out over Zenoh.

``twin serve --config rigs.toml`` opens one Zenoh session and runs every rig
of the configuration (:mod:`twin.service.fleet`: a :class:`~twin.service.runner.RigRunner` per
rig, in threads of this process or spread over spawned worker processes).
Each rig's computing part is a :class:`RigTwin`: the tracker, the drift
detector, estimates in a bounded ring, and the events it hands to a publisher
(:class:`twin.service.publisher.Publisher`).

Per block of samples the rig twin

1. filters the block (``twin.online.tracker.OnlineTracker``);
2. feeds every published estimate to the drift detector (``twin.online.drift``);
3. hands each alarm event to its publisher (which journals it, then puts it
   on the bus; an alarm journaled before is recognised and not repeated);
4. publishes the latest estimate every ``estimate_every`` samples and a status
   on every change of the filter's or a parameter's status, and at least once
   a second;
5. optionally records estimates, alarms and statuses to MCAP.

Its state (tracker and detector objects, whole) is what the runner
checkpoints (:meth:`RigTwin.state` / :meth:`RigTwin.restore`).
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import logging
import time
from typing import Any
from collections.abc import Callable, Mapping

import numpy as np

from replay.base import ReadReport, Samples, Sink
from twin.service.config import RigConfig
from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent
from twin.online.events.forecast import FORECAST_SCHEMA
from twin.service.publisher import Publisher

log = logging.getLogger(__name__)

#: Estimates kept per rig by the service (at 20 per second: about 3 minutes); ``twin track`` keeps all.
SERVICE_HISTORY = 4096
#: Alarm events kept in memory per rig (the journal has them all).
ALARMS_KEPT = 10000
#: A rig's status is published at least this often [s], and a change of its message alone waits for it.
STATUS_S = 1.0
#: Forecasts kept in memory per rig by the service (one per parameter per second: with five parameters about the
#: span of its estimates, 3.4 minutes); the bus and the recording have them all, the service publishes only the
#: latest; ``twin track`` keeps all.
FORECASTS_KEPT = 1024
#: Samples that arrive while a rig's commissioning fit runs wait for it, at most this much sample time [s].
COMMISSION_PENDING_S = 60.0


@dataclasses.dataclass
class RigStats:
    samples: int = 0
    blocks: int = 0
    alarms: int = 0
    estimates: int = 0
    statuses: int = 0
    busy_s: float = 0.0
    duplicates: int = 0
    """Alarms raised again on data processed before (journaled already: not published again)."""


@dataclasses.dataclass
class Health:
    """What a rig's runner says about it; goes into every status the twin publishes."""

    state: str = "running"
    message: str = ""
    counters: dict[str, int] = dataclasses.field(default_factory=dict)


class Ring:
    """The last ``capacity`` rows of (t, values[p], stds[p]) in preallocated arrays; ``None``: unbounded."""

    def __init__(self, p: int, capacity: int | None) -> None:
        self.p = p
        self.capacity = capacity
        size = capacity if capacity is not None else 256
        self._t = np.empty(size)
        self._v = np.empty((size, p))
        self._s = np.empty((size, p))
        self._n = 0  # rows ever added

    def add(self, t: float, v: np.ndarray, s: np.ndarray) -> None:
        if self.capacity is None and self._n == len(self._t):  # unbounded: grow
            self._t = np.concatenate([self._t, np.empty_like(self._t)])
            self._v = np.concatenate([self._v, np.empty_like(self._v)])
            self._s = np.concatenate([self._s, np.empty_like(self._s)])
        i = self._n % len(self._t)
        self._t[i], self._v[i], self._s[i] = t, v, s
        self._n += 1

    def __len__(self) -> int:
        return min(self._n, len(self._t))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows in time order (copies)."""
        n, size = len(self), len(self._t)
        idx = np.arange(self._n - n, self._n) % size
        return self._t[idx].copy(), self._v[idx].copy(), self._s[idx].copy()

    def last(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        if self._n == 0:
            return None
        i = (self._n - 1) % len(self._t)
        return float(self._t[i]), self._v[i].copy(), self._s[i].copy()


class Commissioning:
    """A rig's commissioning in progress: its first seconds gathered (:class:`twin.online.commission.Window`), then
    fitted in a worker process; samples that arrive meanwhile wait (at most ``pending_s`` of them, the
    oldest dropped and counted beyond that) and are tracked once the fit is done."""

    def __init__(self, seconds: float, pending_s: float = COMMISSION_PENDING_S) -> None:
        from twin.online.commission import Window

        self.seconds = float(seconds)
        self.window = Window(seconds)
        self.pending: collections.deque[Samples] = collections.deque()
        self.pending_s = float(pending_s)
        self.dropped = 0
        self.fitting = False

    def hold(self, samples: Samples) -> None:
        self.pending.append(samples)
        while len(self.pending) > 1 and (int(samples.t_ns[-1]) - int(self.pending[0].t_ns[0])) * 1e-9 > self.pending_s:
            self.dropped += len(self.pending.popleft())

    def note(self) -> str:
        if self.fitting:
            return (f"commissioning: fitting its first {self.window.gathered_s:.1f} s ({len(self.window)} samples) "
                    "in a worker process; no alarms before it ends")
        return (f"commissioning: {self.window.gathered_s:.1f} of {self.seconds:g} s gathered; "
                "no alarms before it ends")


def _forecast_monitor(rig: RigConfig):
    from twin.online.forecast import ForecastMonitor

    return ForecastMonitor(rig.name, rig.baseline, horizon_s=rig.forecast_horizon_s,
                           model=rig.model)


def make_twin(rig: RigConfig, publisher: Publisher | None = None, recorder=None, estimate_every: int = 50, *,
              history: int | None = SERVICE_HISTORY, dt: float | None = None) -> RigTwin:
    """The one place a rig's twin is built from its configuration (tracker, detector, publisher)."""
    return RigTwin(rig, publisher, recorder, estimate_every, dt=dt, history=history)


def fingerprint(rig: RigConfig, estimate_every: int) -> str:
    """What a checkpoint's state depends on: the rig's configuration except its replay speed."""
    d = dataclasses.asdict(rig)
    d.pop("speed")
    for key, default in (("commission_s", None), ("baseline_set", ()), ("map", ()),  # keys added later: their default is
                         ("forecast_horizon_s", 3600.0)):
        if d.get(key) == default:                                          # no change (checkpoints still match)
            d.pop(key, None)
    d["estimate_every"] = estimate_every
    return hashlib.sha256(repr(sorted(d.items())).encode()).hexdigest()[:16]


class RigTwin(Sink):
    """One rig's twin: a :class:`~replay.base.Sink` that samples are written to.

    ``publisher``: a :class:`~twin.service.publisher.Publisher` (its ``publish_alarm(ev)`` returns the
    journaled event, or ``None`` for an alarm journaled before). ``history``: how many published estimates to keep
    (``None``: all, for offline tracks of finite logs).
    """

    def __init__(self, rig: RigConfig, publisher: Publisher | None = None, recorder=None, estimate_every: int = 50,
                 on_alarm: Callable[[AlarmEvent], None] | None = None, dt: float | None = None,
                 history: int | None = None, confirm: Mapping[str, Any] | bool | None = None):
        from twin.online.commission import tracker_for
        from twin.online.drift import DriftMonitor

        self.rig = rig
        self.publisher = publisher
        self.recorder = recorder
        self.estimate_every = int(estimate_every)
        self.on_alarm = on_alarm
        self.tracker = tracker_for(rig, dt=dt)
        self.drift = DriftMonitor(rig.name, rig.baseline, model=rig.model)
        self._confirm_options = ({} if confirm is True else dict(confirm)) if confirm else None
        self.confirm = self._confirmed_drift()
        """Alarms confirmed by window re-fits (:mod:`twin.online.confirm`; ``None``: the filter's drift test
        raises them itself)."""
        self.forecast = _forecast_monitor(rig)
        self.forecasts: collections.deque = collections.deque(maxlen=history and FORECASTS_KEPT)
        self._forecast_shown = False
        self.stats = RigStats()
        self.health = Health()
        self.alarms: collections.deque[AlarmEvent] = collections.deque(maxlen=ALARMS_KEPT)
        self.last_t_ns: int | None = None
        self._t0_ns: int | None = None
        self._last_status: tuple | None = None
        self._last_status_wall = 0.0
        self._since_estimate = 0
        self._ring = Ring(len(self.tracker.tracked), history)
        self._last_row: tuple[np.ndarray, np.ndarray] | None = None
        self._encoder: tuple | None = None
        self.status_after_write = True
        """Check the status after every block (``False``: the caller does, as a runner does after its block)."""
        self.commissioning: Commissioning | None = None
        """Set while the rig commissions (``commission_s``): samples are gathered, not tracked."""
        self.read_report: ReadReport | None = None
        """What the reader of its log lost on the way (set by :func:`twin.service.track.track` for a log path)."""

    def _confirmed_drift(self):
        if self._confirm_options is None:
            return None
        from twin.online.confirm import ConfirmedDrift

        return ConfirmedDrift(self.rig.name, self.rig.baseline, self.rig.model, **self._confirm_options)

    # -- checkpoints ------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Everything the twin's future output depends on, as plain data (numbers, strings, lists, arrays)."""
        return {"tracker": self.tracker.state(), "drift": self.drift.state(), "t0_ns": self._t0_ns,
                "last_t_ns": self.last_t_ns, "since_estimate": self._since_estimate, "samples": self.stats.samples,
                "forecast": self.forecast.state()}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state` of an earlier twin of the same rig (raises DataError, ValueError or
        KeyError for a state of another configuration or version: discard the twin then)."""
        self.tracker.restore(state["tracker"])
        self.drift.restore(state["drift"])
        self._t0_ns = state["t0_ns"]
        self.last_t_ns = state["last_t_ns"]
        self._since_estimate = int(state["since_estimate"])
        self.stats.samples = int(state["samples"])
        if "forecast" in state:  # checkpoints from before the forecast: it starts afresh
            self.forecast.restore(state["forecast"])

    def restart_filter(self, start: dict[str, float] | None = None) -> None:
        """A fresh tracker starting from ``start`` (e.g. the last good estimates); the detector carries on.

        After an input gap or a diverged filter the model states cannot be
        carried over; the parameters restart from their last estimates with
        the prior's uncertainty (the detector calls them ``unresolved`` until
        the data resolve them again, so nothing is raised on a guess).
        """
        from twin.online.commission import tracker_for

        old = self.tracker
        self.tracker = tracker_for(self.rig, dt=old.dt, start=start or None)
        for k, v in old.counters.items():
            self.tracker.counters[k] = self.tracker.counters.get(k, 0) + v

    def step_clock(self, t_ns: int) -> None:
        """Go on from ``t_ns`` on a sample clock that stepped back: the next sample may be at or after it, and the
        record time ``t_s`` of events runs on from the last one (the drift test's schedule is in it)."""
        if self.last_t_ns is not None and self._t0_ns is not None:
            step = int(round((self.tracker.dt or 1e-3) * 1e9))
            self._t0_ns = int(t_ns) - (self.last_t_ns - self._t0_ns) - step
        self.last_t_ns = int(t_ns) - 1

    # -- commissioning ---------------------------------------------------------------------
    def _gather(self, samples: Samples) -> None:
        c = self.commissioning
        assert c is not None  # only while commissioning
        if self._t0_ns is None:
            self._t0_ns = int(samples.t_ns[0])
        rest = c.window.add(samples)
        if rest is not None:
            c.hold(rest)
        self.last_t_ns = int(samples.t_ns[-1])
        self.stats.samples += len(samples) - (len(rest) if rest is not None else 0)
        self._status(None)

    def finish_commissioning(self, com, problem: str = "") -> str:
        """End the commissioning: with ``com`` (a :class:`twin.online.commission.Commission`) the rig is tracked with
        its values, noise and timing against bands centred on it; without, against the configured bands
        (``problem`` says why). The samples that waited are tracked now. Returns the status line."""
        from twin.online.commission import apply_commission, describe, tracker_for
        from twin.online.drift import DriftMonitor

        c = self.commissioning
        assert c is not None  # only while commissioning
        self.commissioning = None
        if com is not None:
            self.rig = apply_commission(self.rig, com)
            self.tracker = tracker_for(self.rig)
            self.drift = DriftMonitor(self.rig.name, self.rig.baseline, model=self.rig.model)
            self.confirm = self._confirmed_drift()
            for ev in self.forecast.reset(why="re-commissioned"):
                self._alarm(ev)
            self.forecast = _forecast_monitor(self.rig)
            line = (f"commissioned on its first {c.window.gathered_s:.1f} s: "
                    f"{describe(com, self.rig.track)}")
            line += "".join(f"; WARNING {w}" for w in com.warnings)
        else:
            line = f"commissioning failed: {problem}; tracking against the configured baseline"
        if c.dropped:
            line += f" ({c.dropped} samples that arrived during the fit were dropped)"
            self.health.counters["commission_dropped"] = c.dropped
        self._last_status = None
        self.health.message = line
        if self.health.state == "starting":
            self.health.state = "running"
        for block in c.pending:
            self.write(block)
        self._status(None, force=True)
        return line

    def _split(self, samples: Samples) -> bool:
        """Write a block longer than the confirmation's step (:data:`twin.online.confirm.STEP_S`) in pieces of
        that length: its re-fits are decided at the end of each piece, whatever the reader's chunk (a log read
        in 10-s chunks is then decided as the live rig is).  False when the block is short enough."""
        from twin.online.confirm import STEP_S

        step = int(round(STEP_S * 1e9))
        t = samples.t_ns
        if int(t[-1]) - int(t[0]) < step:
            return False
        edges = np.searchsorted(t, int(t[0]) + step * np.arange(1, (int(t[-1]) - int(t[0])) // step + 1))
        bounds = [0, *[int(e) for e in edges if 0 < e < len(t)], len(t)]
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b > a:
                self.write(samples.slice(a, b))
        return True

    # -- Sink ---------------------------------------------------------------------------
    def write(self, samples: Samples) -> None:
        if len(samples) == 0:
            return
        if self.commissioning is not None:
            self._gather(samples)
            return
        if self.confirm is not None and self._split(samples):
            return
        t_start = time.perf_counter()
        if self._t0_ns is None:
            self._t0_ns = int(samples.t_ns[0])
        if self.recorder is not None and hasattr(self.recorder, "signals"):  # the live view's decimated signals
            self.recorder.signals(samples)
        out = self.tracker.process(samples)
        if len(out.t_ns):
            self._last_row = (out.estimates[-1], out.interval_stds[-1])
        self.last_t_ns = int(samples.t_ns[-1])
        t_s = (out.t_ns - self._t0_ns) * 1e-9
        raised = (self.confirm.update(samples, out, t_s, self.tracker) if self.confirm is not None else
                  self.drift.update_block(self.tracker.tracked, out.t_ns, t_s, out.estimates, out.log_std,
                                          out.frozen, out.hold, out.guard))
        for ev in raised:
            self._alarm(ev)
        early, fcs = self.forecast.update_block(self.tracker.tracked, out.t_ns, t_s, out.estimates, out.log_std,
                                                out.frozen, out.hold, out.held_log_std)
        for ev in early:
            self._alarm(ev)
        if fcs:
            self._forecast(fcs)
        elif self._forecast_shown and not self.forecast.latest():
            self._forecast_ended()
        # an estimate every estimate_every samples, wherever the block boundaries fall
        n = len(out.t_ns)
        first = self.estimate_every - 1 - self._since_estimate
        for i in range(first, n, self.estimate_every):
            self._estimate(out, t_s, i)
        self._since_estimate = (self._since_estimate + n) % self.estimate_every
        self.stats.samples += len(samples)
        self.stats.blocks += 1
        if self.status_after_write:
            self._status(out)
        self.stats.busy_s += time.perf_counter() - t_start

    def close(self) -> None:
        self._status(None, force=True, state="stopped")

    # -- what the twin has seen -----------------------------------------------------------------
    def history_arrays(self) -> dict[str, np.ndarray]:
        """Published estimates kept (the last ``history``): ``t_s [n]``, ``values [n, p]``, ``stds [n, p]`` (SI)."""
        t, v, s = self._ring.arrays()
        return {"t_s": t, "values": v, "stds": s}

    def sensor_status(self) -> dict[str, str]:
        """Each sensor's status: the filter's, with its model-based verdicts as the window re-fits decide them when
        the alarms are confirmed (:meth:`twin.online.confirm.ConfirmedDrift.sensor_status`)."""
        sensors = self.tracker.sensor_status()
        return self.confirm.sensor_status(sensors) if self.confirm is not None else sensors

    def last_estimate(self) -> dict[str, tuple[float, float]]:
        """(value, std) of every tracked parameter (SI) after the last block filtered ({} before the first)."""
        row = self._last_row
        if row is None:
            return {}
        return {n: (float(row[0][j]), float(row[1][j])) for j, n in enumerate(self.tracker.tracked)}

    def final_estimates(self) -> dict[str, dict]:
        last = self._ring.last()
        if last is None:
            return {}
        _, v, s = last
        return {n: {"value": float(v[j]), "std": float(s[j]), "unit": self.tracker.units[j]}
                for j, n in enumerate(self.tracker.tracked)}

    # -- publishing ---------------------------------------------------------------------------
    def _alarm(self, ev: AlarmEvent) -> None:
        if self.publisher is not None:
            published = self.publisher.publish_alarm(ev)
            if published is None:  # journaled before (data processed again after a restart)
                self.stats.duplicates += 1
                return
            ev = published
        self.alarms.append(ev)
        self.stats.alarms += 1
        if self.recorder is not None:
            self.recorder.write_message("/twin/alarm", ev.t_ns, ev.to_dict(), schema=ev.SCHEMA)
        if self.on_alarm is not None:
            self.on_alarm(ev)

    def maintenance(self, parameters=None, why: str = "maintenance", record: dict | None = None) -> None:
        """A recorded maintenance event: the forecasts of ``parameters`` (default all) forget their history
        (``record``: the event of :mod:`twin.service.maintenance`, kept in the forecast's state and messages)."""
        for ev in self.forecast.reset(parameters, why, record=record):
            self._alarm(ev)
        if record is not None and self.publisher is not None and self.last_t_ns is not None:
            from twin.online.events.forecast import FORECAST_UNITS, forecast_message, maintenance_field

            latest = self.forecast.latest()
            msgs = forecast_message(self.rig.name, list(latest.values()), self.forecast.horizon_s,
                                       self.forecast.maintained)
            t_s = (self.last_t_ns - (self._t0_ns or 0)) * 1e-9
            self.publisher.publish_forecast(msgs[-1] if msgs else {
                "rig": self.rig.name, "t_ns": self.last_t_ns, "t_s": t_s, "horizon_s": self.forecast.horizon_s,
                "forecasts": {}, "units": dict(FORECAST_UNITS), **maintenance_field(self.forecast.maintained)})

    def _forecast(self, fcs) -> None:
        """Forecasts of one or more completed bins: kept, recorded (``/twin/forecast``, one message per bin) and
        handed to the publisher's ``publish_forecast`` (a no-op where the publisher has no forecast key)."""
        from twin.online.events.forecast import forecast_message

        self.forecasts.extend(fcs)
        self._forecast_shown = True
        for msg in forecast_message(self.rig.name, fcs, self.forecast.horizon_s, self.forecast.maintained):
            if self.recorder is not None:
                self.recorder.write_message("/twin/forecast", msg["t_ns"], msg, schema=FORECAST_SCHEMA)
            if self.publisher is not None:
                self.publisher.publish_forecast(msg)

    def _forecast_ended(self) -> None:
        """No parameter has a forecast any more: the publisher is told by a message with none (the bus's latest
        value must not keep the last one); the MCAP records forecasts only."""
        self._forecast_shown = False
        if self.publisher is not None and self.last_t_ns is not None:
            from twin.online.events.forecast import FORECAST_UNITS, maintenance_field

            t_s = (self.last_t_ns - (self._t0_ns or 0)) * 1e-9
            self.publisher.publish_forecast({"rig": self.rig.name, "t_ns": self.last_t_ns, "t_s": t_s,
                                             "horizon_s": self.forecast.horizon_s, "forecasts": {},
                                             "units": dict(FORECAST_UNITS),
                                             **maintenance_field(self.forecast.maintained)})

    def _estimate(self, out, t_s, i: int) -> None:
        sd = out.interval_stds[i]
        self._ring.add(float(t_s[i]), out.estimates[i], sd)
        if self.publisher is None and self.recorder is None:
            self.stats.estimates += 1
            return
        if self.publisher is not None and self.recorder is None:  # the payload alone, without the event
            payload = self._estimate_json(int(out.t_ns[i]), float(t_s[i]), out.estimates[i], sd,
                                          float(out.nis[i]), str(out.status[i]))
            if payload is not None and self.publisher.publish_estimate_json(payload):
                self.stats.estimates += 1
                return
        ev = EstimateEvent.of_tracker(self.rig.name, int(out.t_ns[i]), float(t_s[i]), self.tracker.tracked,
                                      out.estimates[i], sd, self.tracker.units,
                                      float(out.nis[i]) if np.isfinite(out.nis[i]) else None, str(out.status[i]),
                                      self.rig.baseline, self.tracker.displays)
        if self.publisher is not None:
            self.publisher.publish_estimate(ev)
        if self.recorder is not None:
            self.recorder.write_message("/twin/estimate", ev.t_ns, ev.to_dict(), schema=ev.SCHEMA)
        self.stats.estimates += 1

    def _estimate_json(self, t_ns: int, t_s: float, values: np.ndarray, stds: np.ndarray, nis: float,
                       status: str) -> str | None:
        """The ``EstimateEvent`` payload (intervals and bands included) written straight from the numbers by
        :class:`twin.online.events.EstimateEncoder`; ``None`` when the event path must run."""
        enc = self._encoder
        if enc is None or enc[0] is not self.rig or enc[1].names != self.tracker.tracked:
            from twin.online.events import EstimateEncoder

            enc = self._encoder = (self.rig, EstimateEncoder(self.rig.name, self.tracker.tracked,
                                                             self.tracker.units, self.rig.baseline,
                                                             self.tracker.displays))
        return enc[1](t_ns, t_s, values, stds, nis, status)

    def publish_status(self, force: bool = False) -> None:
        """Publish a status now if it changed or a second has passed (``force``: now)."""
        self._status(None, force=force)

    def _status(self, out, force: bool = False, state: str | None = None) -> None:
        """Publish a status when the rig's state, a parameter's status, a sensor's status or the filter's
        consistency changed, else at most once a second (``STATUS_S``; a change of the message alone, such as
        the lag, waits for it); ``force``: now."""
        now = time.monotonic()
        drift = self.confirm if self.confirm is not None else self.drift
        per_param = drift.statuses()
        state = state or self.health.state
        com = self.commissioning
        if com is not None:
            if state in ("starting", "running"):
                state = "commissioning"
            per_param = {n: "commissioning" for n in per_param}
        sensors = self.sensor_status()
        guard = str(drift.guard or "consistent")
        key = (state, tuple(per_param.items()), tuple(sensors.items()), guard, com is not None and com.fitting)
        if not force and key == self._last_status and now - self._last_status_wall < STATUS_S:
            return
        self._last_status = key
        self._last_status_wall = now
        from twin.online.tracker import consistency_note

        message = "; ".join(m for m in (self.health.message, consistency_note(self.tracker, drift, sensors)) if m)
        if com is not None and state not in ("failed", "stopped", "finished"):
            message = "; ".join(m for m in (com.note(), message) if m)
        t_ns = int(out.t_ns[-1]) if out is not None and len(out.t_ns) else (self.last_t_ns or self._t0_ns or 0)
        counters = {"samples": self.stats.samples, "alarms": self.stats.alarms,
                    **{k: int(v) for k, v in self.tracker.counters.items() if k != "ok"},
                    **{k: max(0, int(v)) for k, v in self.health.counters.items()}}
        if com is not None:
            counters["commission_ms"] = int(com.window.gathered_s * 1000)
            counters["commission_needed_ms"] = int(com.seconds * 1000)
        if self.publisher is not None:  # the publisher's own counters (alarm_seq), so the event is built and checked once
            counters.update(self.publisher.status_counters())
        ev = StatusEvent(rig=self.rig.name, t_ns=max(0, t_ns), state=state, parameters=per_param,
                         counters=counters, message=message, sensors=sensors, consistency=guard,
                         tested={n: t for n, t in (self.confirm.tested if self.confirm is not None else {}).items()
                                 if t is not None and t >= 0})
        if self.publisher is not None:
            ev = self.publisher.publish_status(ev) or ev
        if self.recorder is not None:
            self.recorder.write_message("/twin/status", ev.t_ns, ev.to_dict(), schema=ev.SCHEMA)
        self.stats.statuses += 1
