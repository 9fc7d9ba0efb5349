"""A measured record on a uniform time grid: what fits and diagnoses work on.

Sources deliver :class:`replay.base.Samples` with integer-nanosecond times;
:func:`records_from_samples` checks the grid and splits it at gaps (a fit never
bridges a gap: each piece becomes a record and parameters are shared across
them).  Inside a record time is float seconds from its first sample.

Signals at their own rates: a reader delivers a signal refreshed more slowly
than the grid (CAN pressures at 500 Hz on the 1 kHz grid of x, the oil
temperature at 10 Hz) held, its last value repeated (:mod:`replay.can.decode`).
:func:`fresh_mask` says which samples are measurements (see there for the one
rule); fit, noise model and diagnosis weigh only those.

A record knows no model: reading a file into the records of a model (its signals checked against the
model's inputs and outputs) is :mod:`twin.models.records`.
"""

from __future__ import annotations

import dataclasses
import numpy as np

from fpdd.errors import DataError


@dataclasses.dataclass
class Record:
    """Uniformly sampled signals (SI units), time first; ``dt`` in seconds."""

    dt: float
    signals: dict[str, np.ndarray]
    name: str = "record"
    t0_ns: int = 0
    #: per signal refreshed more slowly than the grid: True where a sample is fresh (a measurement), False
    #: where it holds an earlier one; ``None``: read off the values by :func:`fresh_mask` when asked
    fresh: dict[str, np.ndarray] | None = None

    def __post_init__(self) -> None:
        if not (self.dt > 0 and np.isfinite(self.dt)):
            raise DataError(f"{self.name}: sample time dt (={self.dt}) must be a positive number of seconds")
        n = None
        for k, v in list(self.signals.items()):
            v = np.ascontiguousarray(v, dtype=np.float64)
            if v.ndim != 1:
                raise DataError(f"{self.name}: signal {k!r} must be 1-D, has shape {v.shape}")
            if n is None:
                n = v.shape[0]
            elif v.shape[0] != n:
                raise DataError(f"{self.name}: signal {k!r} has {v.shape[0]} samples, others have {n}")
            bad = ~np.isfinite(v)
            if bad.any():
                raise DataError(f"{self.name}: signal {k!r} has {int(bad.sum())} non-finite values "
                                f"(first at sample {int(np.flatnonzero(bad)[0])}); clean the record first")
            self.signals[k] = v

    def fresh_of(self, name: str) -> np.ndarray | None:
        """Which samples of ``name`` are measurements (``None``: all of them); see :func:`fresh_mask`."""
        if self.fresh is None:
            self.fresh = {}
        if name not in self.fresh:
            m = fresh_mask(self.signals[name])
            self.fresh[name] = np.ones(0, bool) if m is None else m
        m = self.fresh[name]
        return None if m.size == 0 else m

    def burn_start(self, seconds: float, names) -> None:
        """Count no measurement of ``names`` in the record's first ``seconds`` (at most half the record).

        A fit's simulation starts from a state read off the first samples; what it cannot read there (a moving
        rod's speed, the spool, a controller's integral) makes its first residuals large and systematic, and
        they pull the fit. The samples stay in the record: the simulation still runs through them."""
        n = len(self)
        k = min(int(round(seconds / self.dt)), n // 2) if seconds > 0 else 0
        if k == 0:
            return
        for name in names:
            if name in self.signals:
                m = self.fresh_of(name)
                m = np.ones(n, dtype=bool) if m is None else m.copy()
                m[:k] = False
                assert self.fresh is not None
                self.fresh[name] = m

    def __len__(self) -> int:
        return 0 if not self.signals else next(iter(self.signals.values())).shape[0]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.signals[name]

    def __contains__(self, name: str) -> bool:
        return name in self.signals

    @property
    def t_s(self) -> np.ndarray:
        return np.arange(len(self)) * self.dt

    @property
    def duration_s(self) -> float:
        return len(self) * self.dt

    def __repr__(self) -> str:
        """One line: the name, the number of samples, duration and step, the signals with their SI units."""
        from replay.base import signal_list

        name = self.name if len(self.name) <= 40 else "..." + self.name[-37:]
        return (f"Record({name!r}, {len(self)} samples, {self.duration_s:.6g} s at dt {self.dt * 1e3:.4g} ms: "
                f"{signal_list(tuple(self.signals))})")

    def require(self, names, what: str) -> None:
        missing = [n for n in names if n not in self.signals]
        if missing:
            raise DataError(f"{self.name}: {what} needs signal(s) {', '.join(missing)}; "
                            f"the record has {', '.join(self.signals) or 'none'}")

    def slice(self, start: int, stop: int) -> Record:
        fresh = None if self.fresh is None else {k: (v if v.size == 0 else v[start:stop].copy())
                                                  for k, v in self.fresh.items()}
        return Record(self.dt, {k: v[start:stop].copy() for k, v in self.signals.items()},
                      f"{self.name}[{start}:{stop}]", self.t0_ns + int(round(start * self.dt * 1e9)), fresh)

    def to_samples(self):
        from replay.base import Samples

        t_ns = self.t0_ns + np.round(np.arange(len(self)) * self.dt * 1e9).astype(np.int64)
        return Samples(t_ns, {k: v.copy() for k, v in self.signals.items()})


#: a held signal's runs of one value are this long most often, in this share of its runs at least
HELD_MIN_RUN = 2
HELD_MIN_SHARE = 0.5


def fresh_mask(values) -> np.ndarray | None:
    """The one rule for a signal at its own, slower rate held onto the grid: ``True`` where a sample is fresh
    (a measurement), ``False`` where it repeats the one before it bit for bit; ``None`` when the signal is
    refreshed on every sample.

    A signal is held when its value changes at a regular spacing of two samples or more: the most common
    distance between changes of value is at least :data:`HELD_MIN_RUN` samples, in at least
    :data:`HELD_MIN_SHARE` of them.  A signal measured on every sample changes at every sample, or (quantised,
    at rest) at geometrically distributed distances whose most common value is one: never held.  A held value
    is not a measurement; a fresh value that happens to equal the one before is lost with them (one sample).
    """
    v = np.asarray(values)
    if v.size < 8:
        return None
    change = v[1:] != v[:-1]
    idx = np.flatnonzero(change)
    if idx.size < 4:
        return None
    gaps = np.diff(idx)
    counts = np.bincount(gaps)
    mode = int(np.argmax(counts))
    if mode < HELD_MIN_RUN or counts[mode] < HELD_MIN_SHARE * gaps.size:
        return None
    return np.concatenate([[True], change])


def as_logged(record: Record, name: str, predicted: np.ndarray) -> np.ndarray:
    """A prediction of signal ``name`` as ``record`` logs it: at a held signal's held samples, the prediction
    at its last fresh sample (the sensor read then, the log repeated it); unchanged for a signal measured on
    every sample.  ``predicted [..., n]``: the first ``n`` samples of the record."""
    fresh = record.fresh_of(name)
    if fresh is None:
        return predicted
    n = predicted.shape[-1]
    k = np.arange(n)
    last = np.maximum.accumulate(np.where(fresh[:n], k, 0))
    return predicted[..., last]


def grid_steps(d_ns, dt_ns: float):
    """The one rule for time stamps: a step between samples counts as the nearest whole number of sample
    periods ``dt_ns``; what is left over (less than half a period) is time stamp jitter, not time.  Steps of
    one period are the uniform record, more are missing samples (a gap), none a repeated time."""
    return np.rint(np.asarray(d_ns, dtype=np.float64) / dt_ns).astype(np.int64)


def records_from_samples(samples, name: str = "record", min_samples: int = 50,
                         rel_tol: float = 0.05) -> list[Record]:
    """Cut ``samples`` into uniformly sampled records, splitting at gaps.

    The sample time is the median step.  Time stamps are read on the nominal grid
    (:func:`grid_steps`): a step within half a period of one period is one period
    (jitter, e.g. CAN arbitration, put back on the grid); any other step (a missing
    sample or more, a repeated time) starts a new record.  When the stamps jitter
    (a step off by more than ``rel_tol`` of the period), the period is the span of
    the record over its whole number of periods.  Pieces shorter than
    ``min_samples`` are dropped.
    """
    t = np.asarray(samples.t_ns, dtype=np.int64)
    if t.size < 2:
        raise DataError(f"{name}: {t.size} samples; a record needs at least 2")
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0])
        raise DataError(f"{name}: time does not increase at sample {i + 1} "
                        f"({t[i]} ns then {t[i + 1]} ns); read it through replay, which drops such samples")
    dt_ns = float(np.median(d))
    n = grid_steps(d, dt_ns)
    if np.any(np.abs(d - dt_ns) > rel_tol * dt_ns):  # jitter: the mean period over the whole periods
        dt_ns = float(t[-1] - t[0]) / float(n.sum())
        off = (t - t[0]) - np.concatenate([[0], np.cumsum(n)]) * dt_ns  # each stamp's distance from its grid point
        spread = float(np.max(off) - np.min(off))
        if spread > 0.5 * dt_ns:
            raise DataError(f"{name}: time stamps wander {spread * 1e-3:.4g} us about the {dt_ns * 1e-3:.4g} us grid "
                            "(more than half a period): not jitter of a fixed sample rate; the rate changes within "
                            "the log")
    cuts = np.flatnonzero(n != 1) + 1
    bounds = [0, *cuts.tolist(), t.size]
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < min_samples:
            continue
        sig = {k: np.asarray(v[a:b], dtype=np.float64) for k, v in samples.signals.items()}
        out.append(Record(dt_ns * 1e-9, sig, f"{name}[{a}:{b}]" if len(bounds) > 2 else name, int(t[a])))
    if not out:
        raise DataError(f"{name}: no piece of at least {min_samples} uniformly sampled samples")
    return out
