"""A recorded log through the online twin, offline and as fast as it goes (the library of ``twin track``,
whose command line is :mod:`twin.commands.track`).

The same :class:`twin.service.rig.RigTwin` as the live service (tracker, drift
test), without Zenoh: estimates, alarms and statuses go to an MCAP file that
Foxglove plots (``/twin/estimate``, ``/twin/alarm``, ``/twin/status``), the
parameter trends with the healthy band to a PNG (like the paper's Fig. 4).
The healthy baseline is the rig configuration's values (the model's nominal ones, each band as wide as its
parameter's declared tracking band) unless ``--config`` or ``--baseline`` says otherwise.  Any registered model
the online twin runs (``model=``) is tracked the same way.

Offline there is no journal, so :class:`SequenceNumbers` stands in for the
service's publisher and numbers the alarm events 1, 2, 3, ... as the journal
would: the ``/twin/alarm`` messages carry the same ``seq`` field as on the bus
(``seq = 0`` means "never journaled" and is not a valid payload).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from types import SimpleNamespace
from typing import TYPE_CHECKING

from twin.service.publisher import Publisher

if TYPE_CHECKING:
    from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent


class SequenceNumbers(Publisher):
    """The publisher of a :class:`twin.service.rig.RigTwin` without a bus: numbers alarms 1, 2, 3, ..."""

    def __init__(self) -> None:
        self.seq = 0

    def publish_alarm(self, event: AlarmEvent) -> AlarmEvent:
        self.seq += 1
        return event.with_seq(self.seq)

    def publish_estimate(self, event: EstimateEvent) -> None:
        pass

    def publish_estimate_json(self, payload: str) -> bool:
        return True  # nothing to publish offline: no event is built for it

    def publish_status(self, event: StatusEvent) -> StatusEvent:
        return event


def _from_zero(blocks):
    """Blocks of a record whose times start below 0 (a pre-trigger record, times from the trigger) shifted to
    start at 0: events carry ingest times >= 0; ``t_s`` from the record's start is the same either way."""
    shift = None
    for block in blocks:
        if shift is None and len(block):
            shift = -int(block.t_ns[0]) if int(block.t_ns[0]) < 0 else 0
        if shift:
            block = type(block)(block.t_ns + shift, block.signals)
        yield block


def _blocks(source, chunk: int, dbc: str | None, reports: list | None = None, mapping=None):
    """Blocks of :class:`replay.base.Samples` from a path, a Record, Samples or an iterable of them (the read
    report of a path goes to ``reports``)."""
    from replay.base import Samples
    from replay.factory import open_source
    from twin.record import Record

    if isinstance(source, (str, os.PathLike)):
        opts: dict = {"dbc": dbc} if dbc else {}
        if mapping:  # a log's columns under other names or units, as --map
            from replay.csvio import parse_map
            from twin.estimation.fit_result import map_items

            opts["mapping"] = parse_map(map_items(mapping), option="map")
        with open_source(os.fspath(source), **opts) as src:
            try:
                yield from src.chunks(chunk)
            finally:  # the report of the reading itself (a CAN log's reader starts a fresh one for each reading)
                if reports is not None:
                    reports.append(src.report)
        return
    items = [source] if isinstance(source, (Record, Samples)) else source
    if not isinstance(items, Iterable):
        from fpdd.errors import DataError

        raise DataError(f"track reads a log path, a Record, Samples or an iterable of them, "
                        f"not {type(source).__name__}")
    for item in items:
        s = item.to_samples() if isinstance(item, Record) else item
        for i in range(0, len(s), chunk):
            yield s.slice(i, i + chunk)


def track(source, rig_name: str = "rig", params: dict | None = None, tracked=None, baseline=None,
          out_dir: str | None = None, dbc: str | None = None, chunk: int = 10000, progress=None,
          estimate_every: int = 50, noise: dict | None = None, timing=None, commission=None,
          forecast_horizon_s: float | None = None, maintenance=(), model: str | None = None,
          map=None, confirm=None):  # noqa: A002
    """Run ``source`` through a :class:`RigTwin` (tracker and drift test); returns the twin.

    ``source``: a log path (any format :func:`replay.factory.open_source` reads), a
    :class:`twin.record.Record`, :class:`replay.base.Samples`, or an iterable of
    them in time order (a stream of blocks).  ``model``: the registered model to track (default
    :data:`twin.models.DEFAULT_MODEL`, or the commissioning fit's); ``params``: known parameters that
    differ from the model's nominal ones; ``tracked``: parameter names (default the model's
    phenomenological ones); ``baseline``: ``{name: twin.online.baseline.Baseline}``
    overriding the default bands; ``noise``: sensor noise standard deviations
    per output (SI); ``timing``: the loop's :class:`~twin.models.base.Timing`;
    ``commission``: a :class:`twin.online.commission.Commission` (or the path of a
    ``twin fit --save`` file): known values, healthy bands around the fitted
    values, noise and timing; ``forecast_horizon_s``: the early warning's horizon
    (default one hour); ``maintenance``: recorded maintenance events of the log, ``(t_s, [parameters], note)``
    with ``t_s`` in seconds from the start of the record (applied before the first sample at or after it, as
    ``twin maintenance`` is to a running rig).  With ``out_dir`` the estimates, alarms and
    statuses go to ``OUT_DIR/RIG.twin.mcap``, an estimate every ``estimate_every``
    samples.  The twin holds the results:
    ``alarms`` (events with ``t_s`` from the start of the record),
    ``final_estimates()``, ``history_arrays()``, ``drift.statuses()``,
    ``tracker.counters``, ``forecasts`` (:class:`twin.online.forecast.Forecast`, one per
    parameter per second of record while it has one; ``/twin/forecast`` in the MCAP); for a log path
    ``read_report`` (:class:`replay.base.ReadReport`: what its reader lost on the way, also logged as a warning).
    ``map``: a log's columns under other names or units, as ``--map`` (``{"x": "pos_mm:mm", "t": "time:ms"}`` or
    ``["x=pos_mm:mm"]``); default the map the commissioning fit was read with (``twin fit --map ... --save``).
    ``confirm``: alarms confirmed by window re-fits (:mod:`twin.online.confirm`; ``True`` or its options; false:
    the filter's drift test alone).
    """
    from twin.online.baseline import default_baseline
    from twin.service.live_view.record import TwinRecording
    from twin.service.config import RigConfig
    from twin.models import DEFAULT_MODEL, get_model
    from twin.service.rig import RigTwin

    from twin.online.commission import Commission, load_fit, tracker_for

    if isinstance(commission, (str, os.PathLike)):
        commission = load_fit(os.fspath(commission))
    if model is None:
        model = commission.model if isinstance(commission, Commission) else DEFAULT_MODEL
    tracked = tuple(tracked or get_model(model).PHENOMENOLOGICAL)
    base = default_baseline(model, params, tracked)
    if isinstance(commission, Commission):
        base.update(commission.baseline(tracked))
    base.update(baseline or {})
    where = os.fspath(source) if isinstance(source, (str, os.PathLike)) else f"<{type(source).__name__}>"
    rig = RigConfig(rig_name, model, where, dbc, 0.0, tracked, dict(params or {}), base,
                    forecast_horizon_s=3600.0 if forecast_horizon_s is None else float(forecast_horizon_s))
    rec = None
    if out_dir:
        os.makedirs(out_dir, exist_ok=True)
        rec = TwinRecording(os.path.join(out_dir, f"{rig_name}.twin.mcap"), rig_name, model, parameters=tracked,
                            layout=os.path.join(out_dir, f"{rig_name}.foxglove-layout.json"))
    every = max(1, int(estimate_every))
    twin = RigTwin(rig, SequenceNumbers(), rec, estimate_every=every, confirm=confirm)
    if noise or timing is not None or commission is not None:
        # the rig configuration plus what the command line adds
        r = SimpleNamespace(model=model, params=dict(params or {}), track=tracked,
                            noise=dict(noise or {}), timing=timing, commission=commission)
        twin.tracker = tracker_for(r)
    import numpy as np

    reports: list = []
    pending = sorted((float(t), list(ps), str(note)) for t, ps, note in maintenance)
    seq = 0
    t0_ns: int | None = None
    try:
        if map is None and isinstance(commission, Commission) and isinstance(source, (str, os.PathLike)):
            from replay import formats

            map = list(commission.map) if commission.map and formats.takes_map(os.fspath(source)) else None  # noqa: A001
        for block in _from_zero(_blocks(source, chunk, dbc, reports, map)):
            if t0_ns is None and len(block):
                t0_ns = int(block.t_ns[0])
            while pending and len(block) and t0_ns is not None:
                t_m, ps, note = pending[0]
                k = int(np.searchsorted(block.t_ns, t0_ns + int(round(t_m * 1e9)), side="left"))
                if k >= len(block):
                    break
                if k:
                    twin.write(block.slice(0, k))
                    block = block.slice(k, len(block))
                pending.pop(0)
                seq += 1
                twin.maintenance(ps, why=f"maintenance #{seq}" + (f": {note}" if note else ""),
                                 record={"rig": rig_name, "seq": seq, "parameters": ps, "note": note, "wall_ns": None})
            if len(block):
                twin.write(block)
            if progress:
                progress(f"{twin.stats.samples} samples, {twin.stats.alarms} alarm event(s)")
        twin.close()
    finally:
        if rec is not None:
            rec.close()
    twin.read_report = reports[0] if reports else None  # what the log's reader lost on the way (a path's)
    if twin.read_report is not None and twin.read_report.lossy:
        import logging

        logging.getLogger(__name__).warning("%s", twin.read_report.loss_line())
    return twin
