"""The one sample stream every source produces, and the interfaces of sources and sinks.

Time convention: integer nanoseconds (``t_ns``, int64, UNIX epoch or record start)
at the ingest boundary, float seconds (``t_s``) only inside models.  Signal values
are float64 in SI units (m, V, Pa, N, K; the signals and their units: :data:`fpdd.units.SIGNALS`).

A :class:`Samples` block is columnar: ``t_ns`` has shape ``(n,)`` and every signal
in ``signals`` has shape ``(n,)`` too (time first).  Sources yield blocks for
offline work (``source.chunks()``) or single :class:`Sample` for live work
(``iter(source)``), and keep a :class:`ReadReport` of everything they skipped.
"""

from __future__ import annotations

import abc
import dataclasses
from collections import Counter
from collections.abc import Iterator, Mapping
from typing import Self

import numpy as np

# --- samples ---------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Sample:
    """One time instant of the stream (live path)."""

    t_ns: int
    values: Mapping[str, float]


@dataclasses.dataclass
class Samples:
    """A block of samples, columnar and time first."""

    t_ns: np.ndarray
    signals: dict[str, np.ndarray]

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64)
        n = self.t_ns.shape[0]
        for k, v in list(self.signals.items()):
            v = np.asarray(v, dtype=np.float64)
            if v.shape != (n,):
                raise ValueError(f"signal {k!r} has shape {v.shape}, expected ({n},) like t_ns")
            self.signals[k] = v

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.signals[name]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.signals)

    @property
    def t_s(self) -> np.ndarray:
        """Seconds from the first sample of this block."""
        if len(self) == 0:
            return np.zeros(0)
        return (self.t_ns - self.t_ns[0]).astype(np.float64) * 1e-9

    def rows(self) -> Iterator[Sample]:
        names = self.names
        cols = [self.signals[k] for k in names]
        for i in range(len(self)):
            yield Sample(int(self.t_ns[i]), {k: float(c[i]) for k, c in zip(names, cols)})

    def slice(self, start: int, stop: int) -> Samples:
        return Samples(self.t_ns[start:stop].copy(), {k: v[start:stop].copy() for k, v in self.signals.items()})

    def __repr__(self) -> str:
        """One line: the number of samples, their span and step, the signals with their SI units."""
        n = len(self)
        if n < 2:
            return f"Samples({n} sample{'' if n == 1 else 's'}: {signal_list(self.names)})"
        span_s = float(self.t_ns[-1] - self.t_ns[0]) * 1e-9
        steps = np.diff(self.t_ns)
        step = float(np.median(steps)) * 1e-9
        uniform = bool(steps.max() - steps.min() <= 1)  # a step of 1/3 ms rounds to whole ns
        return (f"Samples({n} samples over {span_s:.6g} s, dt {'' if uniform else '~'}{step * 1e3:.4g} ms: "
                f"{signal_list(self.names)})")

    @staticmethod
    def empty(names: tuple[str, ...] | list[str] = ()) -> Samples:
        """A block of no samples carrying the given signal names."""
        return Samples(np.zeros(0, np.int64), {k: np.zeros(0) for k in names})

    @staticmethod
    def concat(blocks: list[Samples]) -> Samples:
        blocks = [b for b in blocks if len(b)]
        if not blocks:
            return Samples(np.zeros(0, np.int64), {})
        names = blocks[0].names
        return Samples(
            np.concatenate([b.t_ns for b in blocks]),
            {k: np.concatenate([b.signals[k] for b in blocks]) for k in names},
        )


def signal_list(names: tuple[str, ...] | list[str], width: int = 100) -> str:
    """``x [m], pA [Pa], ... 3 more``: signal names with their SI units where known
    (:data:`fpdd.units.SIGNAL_UNITS`), as many as fit in about ``width`` characters, for a one-line repr."""
    from fpdd.units import SIGNAL_UNITS

    shown: list[str] = []
    for n in names:
        item = f"{n} [{SIGNAL_UNITS[n]}]" if n in SIGNAL_UNITS else n
        if shown and len(", ".join([*shown, item])) > width:
            break
        shown.append(item)
    more = len(names) - len(shown)
    return ", ".join(shown) + (f", ... {more} more" if more > 0 else "") if shown else "no signals"


# --- what a read skipped -----------------------------------------------------------------

@dataclasses.dataclass
class Problem:
    """One thing a read could not use, said so that an operator can find it."""

    file: str
    where: str  # record, line, frame or channel
    what: str   # what was wrong and what was expected

    def __str__(self) -> str:
        return f"{self.file}: {self.where}: {self.what}"


#: Skip reasons that are informational, not a loss (see :meth:`ReadReport.losses`).
INFO_REASONS = frozenset({"warmup", "asc_date", "ignored_line", "counter_gap"})
INFO_PREFIXES = ("unknown_id", "stale ")
_NOT_LOSS_WHERE = ("footer and summary", "header")


@dataclasses.dataclass
class ReadReport:
    """Summary of a read: counts of what was kept and skipped, gaps, and the first problems."""

    file: str
    records_read: int = 0
    samples_out: int = 0
    skipped: Counter = dataclasses.field(default_factory=Counter)
    gaps: list[tuple[int, int]] = dataclasses.field(default_factory=list)  # (t_ns start, t_ns end)
    problems: list[Problem] = dataclasses.field(default_factory=list)
    truncated: bool = False
    samples_lost: int = 0  # samples known (or estimated) to be lost to damage, beside those skipped
    max_problems: int = 50

    def skip(self, reason: str, where: str, what: str) -> None:
        """Count a skipped record under ``reason`` and keep its message (the first few)."""
        self.skipped[reason] += 1
        if len(self.problems) < self.max_problems:
            self.problems.append(Problem(self.file, where, what))

    def losses(self) -> dict[str, int]:
        """The skip counts that mean input was damaged or dropped (not merely informational).

        Informational, not a loss: ``warmup`` (grid instants before every signal had a
        value), ``asc_date``, ``ignored_line`` (a log line that is no CAN frame, e.g. an
        event), ``unknown_id ...`` (traffic of other ECUs), ``stale ...`` (a held value
        too old: kept as NaN), ``counter_gap`` (frames lost before the log was written).
        """
        return {k: v for k, v in self.skipped.items()
                if v and k not in INFO_REASONS and not k.startswith(INFO_PREFIXES)}

    @property
    def lossy(self) -> bool:
        """True when the read lost anything: damaged or dropped records, or a truncated file."""
        return bool(self.truncated or self.samples_lost or self.losses())

    def loss_line(self) -> str:
        """One line saying what was lost, for a command's stderr ("" when nothing was)."""
        if not self.lossy:
            return ""
        parts = [f"{k}={v}" for k, v in sorted(self.losses().items())]
        if self.samples_lost:
            parts.append(f"about {self.samples_lost} sample(s) lost to damage")
        if self.truncated:
            parts.append("truncated or corrupt")
        first = next((str(p) for p in self.problems if p.where not in _NOT_LOSS_WHERE), "")
        return (f"{self.file}: input lost ({', '.join(parts)}); {self.samples_out} samples kept"
                + (f"; first: {first.split(': ', 1)[-1]}" if first else ""))

    def summary(self) -> str:
        parts = [f"{self.file}: {self.records_read} records read, {self.samples_out} samples out"]
        if self.skipped:
            parts.append("skipped: " + ", ".join(f"{k}={v}" for k, v in sorted(self.skipped.items())))
        if self.samples_lost:
            parts.append(f"about {self.samples_lost} sample(s) lost to damage")
        if self.gaps:
            parts.append(f"{len(self.gaps)} gap(s)")
        if self.truncated:
            parts.append("file truncated or corrupt: readable part kept")
        return "; ".join(parts)

    def __repr__(self) -> str:
        """One line: the counts of :meth:`summary` and how many problems are kept (:attr:`problems` lists them)."""
        problems = f"; {len(self.problems)} problem(s) kept" if self.problems else ""
        return f"ReadReport({self.summary()}{problems})"

    def to_dict(self) -> dict:
        return {
            "file": self.file,
            "records_read": self.records_read,
            "samples_out": self.samples_out,
            "skipped": dict(self.skipped),
            "gaps_ns": [list(g) for g in self.gaps],
            "truncated": self.truncated,
            "samples_lost": self.samples_lost,
            "lossy": self.lossy,
            "losses": self.losses(),
            "loss_line": self.loss_line(),
            "problems": [str(p) for p in self.problems],
        }


# --- sources and sinks -------------------------------------------------------------------

class Source(abc.ABC):
    """A stream of rig samples. Use as a context manager.

    ``chunks(n)`` yields :class:`Samples` blocks of at most ``n`` samples (offline);
    iterating the source yields :class:`Sample` one by one (live).  ``report`` tells
    what was skipped so far.
    """

    path: str
    report: ReadReport

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release files, buses and sessions."""

    @property
    @abc.abstractmethod
    def signals(self) -> tuple[str, ...]:
        """Names of the signals this source delivers."""

    @abc.abstractmethod
    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Blocks of samples in time order."""

    def __iter__(self) -> Iterator[Sample]:
        for block in self.chunks():
            yield from block.rows()

    def read_all(self) -> Samples:
        return Samples.concat(list(self.chunks()))


class Sink(abc.ABC):
    """Where samples are written. Use as a context manager."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @abc.abstractmethod
    def write(self, samples: Samples) -> None:
        """Append a block of samples."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Flush and release."""
