"""Rig signals over Zenoh for the live view: the key a service puts them on, their JSON, and the decimation
to the display rate."""

from __future__ import annotations

import json


def signals_key(rig: str = "*") -> str:
    """``fpdd/<rig>/signals``: a service's decimated rig signals (JSON, :func:`signals_to_json`)."""
    return f"fpdd/{rig}/signals"


def signals_to_json(rig: str, samples) -> bytes:
    """A block of samples as the service puts it on :func:`signals_key`: ``{"rig", "t_ns": [...], "signals":
    {name: [...]}, "units": {name: SI unit}}`` (SI; a non-finite sample is ``null``)."""
    from fpdd import jsonio
    from fpdd.units import SIGNAL_UNITS

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
