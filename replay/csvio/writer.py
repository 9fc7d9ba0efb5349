"""Writing CSV files (:class:`CsvSink`): time in exact decimal seconds, values in SI."""

from __future__ import annotations

import gzip
import os
from typing import IO
from collections.abc import Mapping, Sequence

import numpy as np

from replay.base import Samples, Sink
from fpdd.errors import DataError, SourceError
from fpdd.units import SIGNALS
from replay.csvio.columns import TIME_COLUMN


def format_t_s(t_ns: np.ndarray) -> list[str]:
    """Exact decimal seconds ``"s.nnnnnnnnn"`` for integer nanoseconds (negative times too)."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    sign = np.where(t_ns < 0, "-", "")
    mag = np.abs(t_ns)
    sec = (mag // 1_000_000_000).tolist()
    frac = (mag % 1_000_000_000).tolist()
    return [f"{s}{a}.{b:09d}" for s, a, b in zip(sign.tolist(), sec, frac)]


class CsvSink(Sink):
    """Write samples as CSV: header ``t,<signals>``; ``t`` in exact decimal seconds, values
    in SI with the shortest repr that reads back to the same float64 (``nan``/``inf`` as is).

    ``signals``: column order; default: the signals of the first block written.  Every
    block must carry these signals.  ``units``: signal -> its SI unit, written in the header
    as the readers understand it (``t[s],x_ref[m],u[V],x[m],pA[Pa],pB[Pa]``,
    :func:`replay.csvio.columns.split_unit`); a signal it does not name takes its unit from
    :data:`fpdd.units.SIGNALS` (none for an unknown signal).  Default: no units in the
    header (every value is SI all the same).  The file is flushed after each :meth:`write`.
    A path ending in ``.gz`` is written through gzip.
    """

    def __init__(self, path: str | os.PathLike, signals: Sequence[str] | None = None,
                 units: Mapping[str, str] | None = None) -> None:
        self.path = str(path)
        self._signals: tuple[str, ...] | None = tuple(signals) if signals is not None else None
        self._units = dict(units) if units is not None else None
        try:
            self._file: IO[str] = (gzip.open(self.path, "wt", encoding="utf-8", newline="")
                                   if self.path.lower().endswith(".gz") else
                                   open(self.path, "w", encoding="utf-8", newline=""))
        except OSError as exc:
            raise SourceError(f"{self.path}: cannot create CSV file: {exc.strerror or exc}") from exc
        self._header_written = False

    def write(self, samples: Samples) -> None:
        if self._signals is None:
            self._signals = samples.names
        missing = [s for s in self._signals if s not in samples.signals]
        if missing:
            raise DataError(f"{self.path}: block to write lacks signal(s) {missing}; "
                            f"the file's columns are {list(self._signals)}")
        if TIME_COLUMN in self._signals:
            raise DataError(f"{self.path}: a signal may not be named {TIME_COLUMN!r} (the time column)")
        if not self._header_written:
            self._file.write(self._header() + "\n")
            self._header_written = True
        if not len(samples):
            return
        cols = [format_t_s(samples.t_ns)] + [list(map(repr, samples.signals[k].tolist()))
                                              for k in self._signals]
        self._file.write("\n".join(map(",".join, zip(*cols))) + "\n")
        self._file.flush()

    def _header(self) -> str:
        assert self._signals is not None
        if self._units is None:
            return ",".join((TIME_COLUMN, *self._signals))
        units = {TIME_COLUMN: "s", **{k: v.unit for k, v in SIGNALS.items()}, **self._units}
        return ",".join(f"{k}[{units[k]}]" if units.get(k) else k for k in (TIME_COLUMN, *self._signals))

    def close(self) -> None:
        if not self._file.closed:
            if not self._header_written and self._signals is not None:
                self._file.write(self._header() + "\n")
            self._file.close()

