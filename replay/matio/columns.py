"""Named columns held in memory (a MATLAB file's vectors, a text file's columns) as a :class:`~replay.base.Source`.

What a column becomes follows the CSV reader (:mod:`replay.csvio.reader`): a column named as a signal of
:data:`fpdd.units.SIGNALS` is that signal in SI (a unit in its name, ``x[mm]``, is converted); ``mapping``
(``--map NAME=COLUMN[:UNIT][*GAIN][+OFFSET]``, :func:`replay.csvio.parse_map`) renames, converts and scales;
without a mapping a column of another name is kept as an extra signal, with one it is not read (the
report names it).  The time is the column ``t`` (s, or mapped with its unit), or the sample time
``sample_time_s`` the file states, or ``rate_hz`` / ``dt_s`` (sample i at i times the sample time).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, Sequence

import numpy as np

from fpdd.errors import DataError
from fpdd.units import SIGNALS, to_si
from replay.base import Problem, ReadReport, Samples, Source
from replay.csvio.columns import MAP_SYNTAX, TIME_COLUMN, ColumnMap, parse_mapping, split_unit
from replay.quality import ACCEPTED_RATE_HZ, QualityGate, QualityOptions, require_signals

#: Names a time column goes by when nothing maps one (case-insensitive).
TIME_NAMES = ("t", "time")


def show(names: Sequence[str], shapes: Mapping[str, str] | None = None, limit: int = 16) -> str:
    items = [f"{n} ({shapes[n]})" if shapes and n in shapes else n for n in names[:limit]]
    return ", ".join(items) + (f", ... ({len(names)} in all)" if len(names) > limit else "") if items else "none"


class ColumnSource(Source):
    """Samples from named columns (:mod:`module docstring <replay.matio.columns>`).

    ``columns``: name -> 1-D array (every vector of one length); ``others``: names of what the file holds
    besides vectors, with what they are (``"1x1 scalar"``, ``"struct"``), named when a mapping asks for one.
    ``what``: what a column is called in messages (``"variable"``, ``"column"``).
    """

    def __init__(self, path: str, columns: Mapping[str, np.ndarray], *, others: Mapping[str, str] | None = None,
                 what: str = "column", mapping: ColumnMap | None = None, required: Sequence[str] = (),
                 quality: QualityOptions | None = None, rate_hz: float | None = None, dt_s: float | None = None,
                 sample_time_s: float | None = None, scalars: Mapping[str, float] | None = None) -> None:
        self.path = str(path)
        self.report = ReadReport(self.path)
        options = quality or QualityOptions()
        if required:
            options = dataclasses.replace(options, required=tuple(required))
        self._options = options
        specs = options.specs if options.specs is not None else SIGNALS
        others = dict(others or {})
        scalars = dict(scalars or {})
        mapped = parse_mapping(self.path, mapping, specs)
        lengths = {n: len(v) for n, v in columns.items()}
        shapes = {n: f"{k} samples" for n, k in lengths.items()} | others
        everything = [*columns, *[n for n in others if n not in columns]]

        # the time: a mapped or named time column, a mapped sample-time scalar, the file's or the caller's
        t_col = next((c for c, m in mapped.items() if m[0] == TIME_COLUMN), None)
        if t_col is None and not any(m[0] == TIME_COLUMN for m in mapped.values()):
            t_col = next((c for c in columns if c.lower() in TIME_NAMES
                          or split_unit(c)[0].lower() in TIME_NAMES), None)
        step_s: float | None = None
        if t_col is not None and t_col not in columns and t_col in scalars:
            unit = mapped[t_col][1] if t_col in mapped else None
            step_s = float(to_si(np.array([scalars[t_col]]), unit, what=f"{self.path}: {what} {t_col!r}")[0]
                           if unit else scalars[t_col])
            t_col = None
        for col in mapped:
            if col not in columns and not (mapped[col][0] == TIME_COLUMN and col in scalars):
                if col in others:
                    raise DataError(f"{self.path}: {what} {col!r} (--map {mapped[col][0]}={col}) is {others[col]}, "
                                    f"expected a vector of samples; the file's vectors: {show(list(columns), shapes)}")
                raise DataError(f"{self.path}: {what} {col!r} (--map {mapped[col][0]}={col}) not in the file; "
                                f"expected a vector of samples; the file has {show(everything, shapes)}")
        given = [x for x in (rate_hz, dt_s, sample_time_s if step_s is None else step_s) if x is not None]
        if t_col is not None and (rate_hz is not None or dt_s is not None):
            raise DataError(f"{self.path}: the file has a time {what} {t_col!r}; a sample rate (--rate/--dt) is for "
                            "a file without one: drop the rate, or read the times")
        if t_col is None:
            if rate_hz is not None and dt_s is not None:
                raise DataError(f"{self.path}: both a sample rate and a sample time given; give one")
            if step_s is None:
                step_s = (1.0 / rate_hz if rate_hz else dt_s) if (rate_hz or dt_s) else sample_time_s
            lo, hi = ACCEPTED_RATE_HZ
            if step_s is None or not (np.isfinite(step_s) and step_s > 0 and lo <= 1.0 / step_s <= hi):
                raise DataError(
                    f"{self.path}: no time {what} ({' or '.join(repr(n) for n in TIME_NAMES)}, or one mapped with "
                    f"--map t=NAME[:UNIT]) and no sample time"
                    + (f" ({given[0]!r} is not one from {1 / hi:g} s to {1 / lo:g} s)" if given else "")
                    + f"; give --rate HZ or --dt S, or map a sample-time scalar with --map t=NAME[:UNIT]; the file "
                    f"has {show(everything, shapes)}")

        # the signals
        out: dict[str, np.ndarray] = {}
        units: dict[str, str | None] = {}
        scaled: dict[str, tuple[float, float]] = {}
        sources: dict[str, str] = {}
        skipped = []
        for col in columns:
            if col == t_col:
                continue
            if col in mapped:
                name, unit = mapped[col][:2]
                if len(mapped[col]) == 4:
                    scaled[name] = (float(mapped[col][2]), float(mapped[col][3]))
            else:
                name, unit = split_unit(col)
                if unit is not None and name in specs:
                    parse_mapping(self.path, {col: (name, unit)}, specs)  # the unit fits the signal
                else:
                    name, unit = col, None
                if mapped and name not in specs:
                    skipped.append(col)
                    continue
            if name in sources:
                raise DataError(f"{self.path}: {what}s {sources[name]!r} and {col!r} are both signal {name!r}")
            sources[name] = col
            out[name] = np.asarray(columns[col])
            units[name] = unit
        if not out:
            raise DataError(f"{self.path}: no {what} that is a signal; the file has {show(everything, shapes)}; map "
                            f"them with {MAP_SYNTAX}, e.g. --map y={next(iter(columns), 'NAME')}")
        if skipped:
            self.report.problems.append(Problem(self.path, "columns", f"{what}(s) {show(skipped)} not read: neither "
                                                f"a known signal nor mapped (map them with {MAP_SYNTAX})"))
        n = lengths[sources[next(iter(out))]] if t_col is None else lengths[t_col]
        odd = [sources[s] for s in out if len(out[s]) != n]
        if odd:
            name = next(s for s in out if len(out[s]) != n)
            like = t_col if t_col is not None else sources[next(iter(out))]
            raise DataError(f"{self.path}: {what} {odd[0]!r} has {len(out[name])} samples, expected {n} (as {like!r})")
        if t_col is not None:
            t_unit = mapped[t_col][1] if t_col in mapped else split_unit(t_col)[1]
            t_s = np.asarray(columns[t_col], dtype=np.float64)
            if t_unit:
                t_s = to_si(t_s, t_unit, what=f"{self.path}: {what} {t_col!r}")
            good = np.isfinite(t_s)
            t_ns = np.where(good, np.rint(np.where(good, t_s, 0.0) * 1e9), 0).astype(np.int64)
            if not good.all():
                self.report.skip("bad_time", f"sample {int(np.flatnonzero(~good)[0]) + 1}",
                                 f"time {t_col!r} is not a finite number")
                self.report.skipped["bad_time"] += int((~good).sum()) - 1
                t_ns, keep = t_ns[good], good
                out = {k: v[keep] for k, v in out.items()}
            self._check_rate(t_ns, t_col)
        else:
            assert step_s is not None
            t_ns = np.rint(np.arange(n) * step_s * 1e9).astype(np.int64)
        values: dict[str, np.ndarray] = {}
        for name, v in out.items():
            data = np.asarray(v, dtype=np.float64)
            if units[name]:
                data = to_si(data, str(units[name]), what=f"{self.path}: {what} {sources[name]!r}")
            if name in scaled:
                factor, offset = scaled[name]
                data = data * factor + offset
            values[name] = np.ascontiguousarray(data)
        self._signals = tuple(values)
        require_signals(self.path, self._signals, self._options.required)
        self.report.records_read = len(t_ns)
        self._samples = Samples(t_ns, values)
        self._done = False

    def _check_rate(self, t_ns: np.ndarray, col: str) -> None:
        steps = np.diff(t_ns[:2000])
        steps = steps[steps > 0]
        if steps.size < 3:
            return
        rate = 1e9 / float(np.median(steps))
        lo, hi = ACCEPTED_RATE_HZ
        if not lo <= rate <= hi:
            raise DataError(f"{self.path}: time {col!r}: median step {1 / rate:.6g} s ({rate:.6g} Hz) is not a "
                            f"record's rate (expected {lo:g} Hz to {hi:g} Hz in seconds); give its unit with "
                            f"--map t={col}:ms (or us, ns)")

    @property
    def signals(self) -> tuple[str, ...]:
        return self._signals

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Blocks of at most ``size`` samples through the quality gate; the samples are delivered once."""
        if self._done:
            return
        self._done = True
        gate = QualityGate(self.report, self._options)
        block = gate.apply(self._samples, np.arange(1, len(self._samples) + 1), "sample")
        for start in range(0, len(block), size):
            yield block.slice(start, start + size) if len(block) > size else block
