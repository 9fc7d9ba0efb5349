"""The online twin service: per rig, samples in, tracked parameters and drift alarms out over Zenoh.

``twin serve --config rigs.toml`` opens one Zenoh session and, per rig, a
:class:`RigTwin`: the rig's source (a live CAN bus, a Zenoh key expression or
a log replayed in real time), the tracker, the drift detector, the alarm
journal and a :class:`twin.bus.TwinPublisher`.  Each rig runs in its own
thread (the compiled filter releases no Python state between samples, and a
block of samples is filtered in one compiled call).

Per block of samples the rig twin

1. filters the block (``twin.track.OnlineTracker``);
2. feeds every published estimate to the drift detector (``twin.drift``);
3. journals, then publishes each alarm event (reliable, blocking);
4. publishes the latest estimate every ``estimate_every`` samples and a status
   on every change of the filter's or a parameter's status, and at least once
   a second;
5. optionally records estimates, alarms and statuses to MCAP.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys
import threading
import time
from typing import Callable

import numpy as np

from replay.base import Samples, Sink
from twin.config import RigConfig, ServiceConfig, load_config
from twin.errors import TwinError
from twin.events import AlarmEvent, EstimateEvent, StatusEvent

log = logging.getLogger(__name__)


@dataclasses.dataclass
class RigStats:
    samples: int = 0
    blocks: int = 0
    alarms: int = 0
    estimates: int = 0
    statuses: int = 0
    busy_s: float = 0.0


class RigTwin(Sink):
    """One rig's twin: a :class:`~replay.base.Sink` that samples are written to."""

    def __init__(self, rig: RigConfig, publisher=None, recorder=None, estimate_every: int = 50,
                 on_alarm: Callable[[AlarmEvent], None] | None = None, dt: float | None = None):
        from twin.drift import DriftMonitor
        from twin.tracker import OnlineTracker

        self.rig = rig
        self.publisher = publisher
        self.recorder = recorder
        self.estimate_every = int(estimate_every)
        self.on_alarm = on_alarm
        self.tracker = OnlineTracker(rig.model, params=rig.params, tracked=rig.track, dt=dt)
        self.drift = DriftMonitor(rig.name, rig.baseline)
        self.stats = RigStats()
        self.alarms: list[AlarmEvent] = []
        self._t0_ns: int | None = None
        self._last_status = None
        self._last_status_wall = 0.0
        self._since_estimate = 0
        self._hist_t: list[float] = []
        self._hist_v: list[np.ndarray] = []
        self._hist_s: list[np.ndarray] = []

    # -- Sink ---------------------------------------------------------------------------
    def write(self, samples: Samples) -> None:
        if len(samples) == 0:
            return
        t_start = time.perf_counter()
        if self._t0_ns is None:
            self._t0_ns = int(samples.t_ns[0])
        out = self.tracker.process(samples)
        t_s = (out.t_ns - self._t0_ns) * 1e-9
        for ev in self.drift.update_block(self.tracker.tracked, out.t_ns, t_s, out.estimates, out.log_std,
                                          out.frozen):
            self._alarm(ev)
        # an estimate every estimate_every samples, wherever the block boundaries fall
        n = len(out.t_ns)
        first = self.estimate_every - 1 - self._since_estimate
        for i in range(first, n, self.estimate_every):
            self._estimate(out, t_s, i)
        self._since_estimate = (self._since_estimate + n) % self.estimate_every
        self._status(out)
        self.stats.samples += len(samples)
        self.stats.blocks += 1
        self.stats.busy_s += time.perf_counter() - t_start

    def close(self) -> None:
        self._status(None, force=True, state="stopped")

    # -- what the twin has seen -----------------------------------------------------------------
    def history_arrays(self) -> dict[str, np.ndarray]:
        """Published estimates: ``t_s [n]``, ``values [n, p]``, ``stds [n, p]`` (SI)."""
        p = len(self.tracker.tracked)
        return {"t_s": np.array(self._hist_t),
                "values": np.array(self._hist_v).reshape(-1, p), "stds": np.array(self._hist_s).reshape(-1, p)}

    def final_estimates(self) -> dict[str, dict]:
        if not self._hist_t:
            return {}
        return {n: {"value": float(self._hist_v[-1][j]), "std": float(self._hist_s[-1][j]),
                    "unit": self.tracker.units[j]} for j, n in enumerate(self.tracker.tracked)}

    # -- publishing ---------------------------------------------------------------------------
    def _alarm(self, ev: AlarmEvent) -> None:
        if self.publisher is not None:
            ev = self.publisher.publish_alarm(ev)
        self.alarms.append(ev)
        self.stats.alarms += 1
        if self.recorder is not None:
            self.recorder.write_message("/twin/alarm", ev.t_ns, ev.to_dict())
        if self.on_alarm is not None:
            self.on_alarm(ev)

    def _estimate(self, out, t_s, i: int) -> None:
        params = {n: {"value": float(out.estimates[i][j]), "std": float(out.stds[i][j]),
                      "unit": self.tracker.units[j]} for j, n in enumerate(self.tracker.tracked)}
        ev = EstimateEvent(rig=self.rig.name, t_ns=int(out.t_ns[i]), t_s=float(t_s[i]), params=params,
                           nis=float(out.nis[i]) if np.isfinite(out.nis[i]) else None,
                           status=str(out.status[i]))
        self._hist_t.append(float(t_s[i]))
        self._hist_v.append(np.array(out.estimates[i], dtype=float))
        self._hist_s.append(np.array(out.stds[i], dtype=float))
        if self.publisher is not None:
            self.publisher.publish_estimate(ev)
        if self.recorder is not None:
            self.recorder.write_message("/twin/estimate", ev.t_ns, ev.to_dict())
        self.stats.estimates += 1

    def _status(self, out, force: bool = False, state: str = "running") -> None:
        now = time.monotonic()
        per_param = self.drift.statuses()
        key = (state, tuple(sorted(per_param.items())))
        if not force and key == self._last_status and now - self._last_status_wall < 1.0:
            return
        self._last_status = key
        self._last_status_wall = now
        t_ns = int(out.t_ns[-1]) if out is not None and len(out.t_ns) else (self._t0_ns or 0)
        counters = {"samples": self.stats.samples, "alarms": self.stats.alarms,
                    **{k: int(v) for k, v in self.tracker.counters.items() if k != "ok"}}
        ev = StatusEvent(rig=self.rig.name, t_ns=t_ns, state=state, parameters=per_param, counters=counters,
                         message="")
        if self.publisher is not None:
            ev = self.publisher.publish_status(ev)
        if self.recorder is not None:
            self.recorder.write_message("/twin/status", ev.t_ns, ev.to_dict())
        self.stats.statuses += 1


def open_rig_source(rig: RigConfig, session=None):
    """The rig's source; a ``zenoh://`` input rides on the service's own Zenoh session."""
    from replay.factory import open_source

    opts = {"dbc": rig.dbc} if rig.dbc else {}
    if rig.source.startswith("zenoh://") and session is not None:
        opts["session"] = session
    return open_source(rig.source, **opts)


def is_live(uri: str) -> bool:
    return uri.startswith(("can://", "zenoh://"))


def run_rig(rig: RigConfig, twin: RigTwin, stop: threading.Event, chunk: int = 100, session=None) -> None:
    """Feed ``twin`` from the rig's source until it ends or ``stop`` is set."""
    from replay.play import play

    with open_rig_source(rig, session) as src:
        if is_live(rig.source):
            for block in src.chunks(chunk):
                if stop.is_set():
                    break
                twin.write(block)
        else:
            speed = rig.speed if rig.speed > 0 else float("inf")
            play(src, twin, speed, chunk=chunk, should_stop=stop.is_set)


def serve(cfg: ServiceConfig, stop: threading.Event | None = None,
          on_alarm: Callable[[AlarmEvent], None] | None = None, session=None,
          twins: dict[str, RigTwin] | None = None) -> dict[str, RigStats]:
    """Run every rig of ``cfg`` until their sources end or ``stop`` is set; returns per-rig stats.

    ``session``: an open Zenoh session to use (default: open one from ``cfg``);
    ``twins``: a dict that receives each rig's :class:`RigTwin` (for reports).
    """
    import zenoh

    from replay.mcapio import McapSink
    from twin.bus import TwinPublisher, zenoh_config
    from twin.journal import AlarmJournal

    stop = stop or threading.Event()
    own_session = session is None
    if own_session:
        conf = zenoh_config(cfg.zenoh_mode, cfg.listen, cfg.connect,
                            config_file=os.environ.get("ZENOH_CONFIG") or None)
        session = zenoh.open(conf)
    os.makedirs(cfg.journal_dir, exist_ok=True)
    if cfg.out_dir:
        os.makedirs(cfg.out_dir, exist_ok=True)
    errors: dict[str, BaseException] = {}
    stats: dict[str, RigStats] = {}

    def worker(rig: RigConfig) -> None:
        try:
            with AlarmJournal(os.path.join(cfg.journal_dir, f"{rig.name}.alarms.jsonl")) as journal, \
                    TwinPublisher(session, rig.name, journal) as pub:
                rec = McapSink(os.path.join(cfg.out_dir, f"{rig.name}.twin.mcap")) if cfg.out_dir else None
                twin = RigTwin(rig, pub, rec, cfg.estimate_every, on_alarm)
                if twins is not None:
                    twins[rig.name] = twin
                try:
                    run_rig(rig, twin, stop, session=session)
                finally:
                    twin.close()
                    if rec is not None:
                        rec.close()
                stats[rig.name] = twin.stats
        except BaseException as exc:  # reported by serve() after every rig has ended
            errors[rig.name] = exc
            log.error("rig %s stopped: %s", rig.name, exc)

    try:
        threads = [threading.Thread(target=worker, args=(r,), name=f"rig-{r.name}", daemon=True) for r in cfg.rigs]
        for t in threads:
            t.start()
        for t in threads:
            while t.is_alive():
                t.join(0.2)
    except KeyboardInterrupt:
        stop.set()
        for t in threads:
            t.join(5.0)
    finally:
        if own_session:
            session.close()
    if errors:
        name, exc = next(iter(errors.items()))
        if isinstance(exc, TwinError):
            raise exc
        raise TwinError(f"rig {name}: {exc}") from exc
    return stats


def add_serve_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, metavar="RIG.toml", help="rig configuration (see twin/config.py)")
    p.add_argument("--json", action="store_true", help="print per-rig statistics as JSON at the end")


def run_serve(args) -> int:
    import json

    cfg = load_config(args.config)

    def show(ev: AlarmEvent) -> None:
        print(f"[{ev.rig}] t={ev.t_s:9.3f}s {ev.level.upper():7s} {ev.kind:9s} {ev.parameter}: "
              f"{ev.estimate:.4g} +- {ev.std:.2g} (band {ev.band_lo:.4g}..{ev.band_hi:.4g}) seq {ev.seq}",
              file=sys.stderr, flush=True)

    stats = serve(cfg, on_alarm=show)
    if args.json:
        print(json.dumps({k: dataclasses.asdict(v) for k, v in stats.items()}, indent=2))
    return 0
