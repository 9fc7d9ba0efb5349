"""Reading CSV files (:class:`CsvSource`): one header row naming the signals, one row per sample.

Layout::

    t,x_ref,u,x,pA,pB
    0.000000000,0.0,0.0,1.2e-05,2000000.0,1999000.0
    0.001000000,...

* ``t`` is the time in seconds (float); it becomes integer nanoseconds at ingest
  (``round(t * 1e9)``).  A float64 holds epoch seconds to about 0.2 us, record-relative
  seconds exactly enough for any rig rate.
* Every other column is a signal in the SI unit of :data:`fpdd.units.SIGNALS`
  (columns not in that table are kept as extra signals, unchecked; with a
  ``mapping``, such a column that is not mapped is not read, and the report's
  ``header`` problem names it).
* No time column: ``rate_hz`` (or ``dt_s``) gives the sample rate (row i at i/rate;
  a bad row keeps its slot).  Trailing empty columns (``"V1","V2",``), quoted names
  and values, units in the header (``x[mm]``, ``pA (bar)``) and ``.csv.gz`` are read.
* Bounds: at most :data:`MAX_COLUMNS` columns and :data:`MAX_LINE_CHARS` characters a
  line (a longer line is one bad row, never held whole); a last line without line end
  is dropped and counted (it may be cut); a header with no rows is refused.
* The oscillator contract is the same layout with the columns ``t, u, y``.
* A ``;``-separated export (a header without ``,`` but with ``;``) is read as such, its ``,`` in numbers as
  decimal commas (``0,001;2,5``); a column whose header unit is a flow (``Q[l/min]``) is kept as an extra signal
  and said to be no signal of a record.
* ``mapping`` renames foreign columns and converts units at ingest, e.g.
  ``{"pos_mm": ("x", "mm"), "p_a_bar": ("pA", "bar"), "time": ("t", "ms")}``; a plain
  string renames only.  Units: :data:`fpdd.units.UNITS`.  On the command line
  this is ``--map NAME=COLUMN[:UNIT]`` (``--map x=pos_mm:mm --map t=time:ms``),
  parsed by :func:`parse_map` for every command that reads a record.
* A time column whose median step gives a rate outside 10 Hz .. 200 kHz (a time in ms
  read as seconds looks like 1 Hz) is refused, the error naming the rate found and the
  unit that would make it plausible; an explicit time unit in the mapping (``t:s``,
  ``t:ms``, ...) is trusted.
* A file must have the time column and at least one known signal (after mapping);
  otherwise the error lists the columns found and those needed, with the ``--map``
  syntax.  UTF-8 (BOM or not) and ASCII are read; UTF-16/32, binary data and an
  undecodable header are refused with the byte offset; an undecodable byte further
  down spoils only its row (``bad_row``).
* Blank lines and lines starting with ``#`` are ignored; a row that does not parse
  (wrong field count, a field that is not a number, an empty field) is skipped,
  counted under ``bad_row`` and named by its line number (1 = the first line of the file).

Reading is chunked: each chunk of about 8 MB of lines goes through ``np.loadtxt`` (C
parser); only a chunk that fails is parsed line by line to find its bad rows.  A
one-hour 1 kHz file of six columns (410 MB) reads in about 4 s here (0.9 M samples/s,
3x a ``csv.reader`` loop).
"""

from __future__ import annotations

import dataclasses
import gzip
import os
import warnings
from zlib import error as zlib_error
from collections import Counter
from typing import IO
from collections.abc import Iterator, Sequence

import numpy as np

from fpdd.units import SIGNALS, UNITS, to_si
from replay.base import Problem, ReadReport, Samples, Source
from replay.quality import ACCEPTED_RATE_HZ, QualityGate, QualityOptions, add_skips, require_signals
from fpdd.errors import DataError, LogFormatError, SourceError
from replay.csvio.columns import (MAP_SYNTAX, MAX_COLUMNS, TIME_COLUMN, UNIT_IN_NAME, ColumnMap, expected_columns,
                                  is_flow, parse_mapping, show_columns, sniff_text, split_unit, suggest_map)

#: Sample rates a rig record plausibly has (Hz); a time column outside is taken as a wrong unit.
PLAUSIBLE_RATE_HZ = (10.0, 200.0e3)
_TIME_UNITS = ("ms", "us", "ns")
_SNIFF_BYTES = 1 << 16
#: Bounds of what is parsed at all: a line longer than this is refused (a row of tens of columns is well
#: under a kilobyte); :data:`~replay.csvio.columns.MAX_COLUMNS` bounds the header.
MAX_LINE_CHARS = 1 << 20
_MAX_T_S = 9.2e9  # what int64 nanoseconds hold, in seconds
_CUT = "\x01"  # marks the last line of a file that ends without a line end


class CsvSource(Source):
    """Read rig samples from a CSV file (see the module docstring for the layout).

    ``mapping``: foreign column -> signal name or (signal name, unit).  ``required``:
    signals that must be present (:class:`~fpdd.errors.DataError` otherwise).
    ``quality``: gate options (gaps, range check).  ``delimiter``: field separator.
    ``rate_hz`` (or ``dt_s``): the sample rate of a file without a time column (sample i
    is at ``i / rate_hz`` s, counting every data row, so a bad row leaves its gap).
    A path ending in ``.gz`` is read through gzip.
    """

    def __init__(self, path: str | os.PathLike, *, mapping: ColumnMap | None = None,
                 required: Sequence[str] = (), quality: QualityOptions | None = None,
                 delimiter: str = ",", chunk_bytes: int = 8 << 20, rate_hz: float | None = None,
                 dt_s: float | None = None) -> None:
        self.path = str(path)
        self.report = ReadReport(self.path)
        self._delimiter = delimiter
        self._chunk_chars = max(int(chunk_bytes), 1024)
        options = quality or QualityOptions()
        if required:
            options = dataclasses.replace(options, required=tuple(required))
        self._options = options
        self._dt_ns = self._sample_period(rate_hz, dt_s)
        mapped = parse_mapping(self.path, mapping, options.specs)
        gz = self.path.lower().endswith(".gz")
        try:
            with (gzip.open(self.path, "rb") if gz else open(self.path, "rb")) as raw:
                head = raw.read(_SNIFF_BYTES)
        except IsADirectoryError:
            raise SourceError(f"{self.path}: cannot open CSV file: is a directory, expected a file") from None
        except (gzip.BadGzipFile, EOFError, zlib_error) as exc:
            raise LogFormatError(f"{self.path}: not a readable gzip file ({exc}); expected a gzip'd CSV file") from None
        except OSError as exc:
            raise SourceError(f"{self.path}: cannot open CSV file: {exc.strerror or exc}") from exc
        if not head:
            raise LogFormatError(f"{self.path}: empty file (0 bytes), expected a header row naming the columns "
                                 "(e.g. 't,x_ref,u,x,pA,pB') and one row per sample")
        encoding = sniff_text(self.path, head)
        try:
            self._file: IO[str] = (gzip.open(self.path, "rt", encoding=encoding, errors="replace", newline="")
                                   if gz else open(self.path, encoding=encoding, errors="replace", newline=""))
        except OSError as exc:
            raise SourceError(f"{self.path}: cannot open CSV file: {exc.strerror or exc}") from exc
        self._carry = ""
        self._eof = False
        self._line = 0  # lines consumed
        self._row = 0  # data rows (not blank, not comment) after the header
        try:
            self._setup(mapped)
        except Exception:
            self._file.close()
            raise
        self._gate = QualityGate(self.report, options)
        self._done = False
        self._time_checked = self._t_col is None or self._units[self._t_col] is not None

    def _sample_period(self, rate_hz: float | None, dt_s: float | None) -> int | None:
        """The sample period in ns that ``rate_hz`` / ``dt_s`` state (None when neither is given)."""
        if rate_hz is None and dt_s is None:
            return None
        if rate_hz is not None and dt_s is not None:
            raise DataError(f"{self.path}: both a sample rate ({rate_hz} Hz) and a sample time ({dt_s} s) given; "
                            "give one (--rate HZ or --dt S)")
        try:
            rate = float(rate_hz) if rate_hz is not None else 1.0 / float(dt_s)  # type: ignore[arg-type]
        except (TypeError, ValueError, ZeroDivisionError):
            rate = float("nan")
        what = f"--rate {rate_hz} Hz" if rate_hz is not None else f"--dt {dt_s} s"
        lo, hi = ACCEPTED_RATE_HZ
        if not (np.isfinite(rate) and lo <= rate <= hi):
            raise DataError(f"{self.path}: {what}: expected a sample rate from {lo:g} Hz to {hi:g} Hz "
                            f"(a sample time from {1 / hi:g} s to {1 / lo:g} s)")
        return int(round(1e9 / rate))

    def _setup(self, mapped: dict[str, tuple]) -> None:
        columns, self._header_line = self._read_header()
        self._columns = columns
        names: list[str] = []
        units: list[str | None] = []
        self._scaled: dict[int, tuple[float, float]] = {}  # column -> (factor, offset) of a gain/offset map
        for col in columns:
            if col in mapped:
                name, unit = mapped[col][:2]
                if len(mapped[col]) == 4:
                    self._scaled[len(names)] = (float(mapped[col][2]), float(mapped[col][3]))
            else:
                name, unit = split_unit(col)
                if unit is not None and (name == TIME_COLUMN or name in SIGNALS):
                    parse_mapping(self.path, {col: (name, unit)}, self._options.specs)  # the unit fits
                else:
                    name, unit = col, None
            names.append(name)
            units.append(unit)
        have = set(columns)
        unused = [c for c in mapped if c not in have]
        if unused:
            raise DataError(f"{self.path}: line {self._header_line}: mapped column(s) "
                            f"{', '.join(repr(c) for c in unused)} not in the header; the file has "
                            f"{show_columns(columns)}")
        counts = Counter(names)
        dup = sorted(n for n, k in counts.items() if k > 1)
        if dup:
            raise LogFormatError(f"{self.path}: line {self._header_line}: column(s) {', '.join(dup[:8])} "
                                 f"appear more than once (after mapping) in the header ({show_columns(columns)})")
        specs = self._options.specs if self._options.specs is not None else SIGNALS
        has_time = TIME_COLUMN in counts
        has_signal = any(n in specs or n in SIGNALS for n in counts if n != TIME_COLUMN)
        if has_time and self._dt_ns is not None:
            raise DataError(f"{self.path}: line {self._header_line}: the file has a time column "
                            f"{columns[names.index(TIME_COLUMN)]!r}; a sample rate (--rate/--dt) is for a file "
                            "without one: drop the rate, or read the times")
        if not has_signal or (not has_time and self._dt_ns is None):
            found = show_columns(columns)
            lacks = " and ".join(w for w, ok in ((f"no time column {TIME_COLUMN!r} (s)", has_time),
                                                 ("no column that is a known signal", has_signal)) if not ok)
            foreign = [c for c, n in zip(columns, names) if n == c and c not in (TIME_COLUMN, *SIGNALS)]
            needed = ([] if has_time else [TIME_COLUMN]) + ([] if has_signal else list(SIGNALS))
            example = suggest_map(foreign, needed)
            advice = [f"map foreign columns with {MAP_SYNTAX}" + (f", e.g. {example}" if example else "")]
            if not has_time:
                advice.append("a file without a time column needs its sample rate: --rate HZ (or --dt S)")
            raise DataError(f"{self.path}: line {self._header_line}: {lacks}; found columns {found}; needed: the "
                            f"time {TIME_COLUMN!r} (s) or a sample rate, and any of {expected_columns()}; "
                            + "; ".join(advice))
        self._names = names
        self._units = units
        self._t_col: int | None = names.index(TIME_COLUMN) if has_time else None
        # with a mapping, a column that is neither mapped nor a known signal is not read (an empty overload
        # flag column, say, would spoil every row); it is named in the report
        known = set(specs) | set(SIGNALS) | {TIME_COLUMN}
        self._use = [j for j, (c, n) in enumerate(zip(columns, names)) if not mapped or c in mapped or n in known]
        used = set(self._use)
        skipped = [c for j, c in enumerate(columns) if j not in used]
        if skipped:
            self.report.problems.append(Problem(
                self.path, "header", f"column(s) {show_columns(skipped, 8)} not read: neither a known signal nor "
                f"mapped (map them with {MAP_SYNTAX} to read them)"))
        extra = [columns[j] for j in self._use if names[j] not in known and columns[j] not in mapped]
        flows = [c for c in extra if (m := UNIT_IN_NAME.match(c)) and is_flow(m.group("unit"))]
        if flows:  # a flow is no signal of a record: said plainly, no --map offered for it
            extra = [c for c in extra if c not in flows]
            self.report.problems.append(Problem(
                self.path, "header", f"column(s) {show_columns(flows, 8)}: a flow (volume per time) is no signal of "
                "a record; kept as extra signals, unchecked"))
        if extra:
            hint = suggest_map(extra, [n for n in (TIME_COLUMN, *SIGNALS) if n not in counts])
            self.report.problems.append(Problem(
                self.path, "header", f"column(s) {show_columns(extra, 8)} not understood: no known signal "
                f"(kept as extra signals, unchecked; map them with {MAP_SYNTAX}"
                + (f", e.g. {hint})" if hint else ")")))
        self._t_pos = self._use.index(self._t_col) if self._t_col is not None else None
        self._signals = tuple(names[j] for j in self._use if names[j] != TIME_COLUMN)
        require_signals(self.path, self._signals, self._options.required)

    # -- lines, bounded ------------------------------------------------------------------------

    def _next_lines(self, budget: int) -> list[str]:
        """The next whole lines (about ``budget`` characters; [] at the end), each without its ending.

        A line longer than :data:`MAX_LINE_CHARS` is never held whole: it becomes the empty
        marker ``"\\0"`` (counted as a bad row by the parser) and is skipped to its end.
        """
        lines: list[str] = []
        size = 0
        while size < budget and not (self._eof and not self._carry):
            block = "" if self._eof else self._read(min(budget, MAX_LINE_CHARS))
            if not block:
                self._eof = True
            text = self._carry + block
            cut = text.rfind("\n")
            if cut < 0 and not self._eof:
                if len(text) > MAX_LINE_CHARS:  # one line longer than the limit: skip to its end
                    lines.append("\0")
                    self._carry = ""
                    self._skip_long_line()
                    size += MAX_LINE_CHARS
                else:
                    self._carry = text
                continue
            if self._eof:
                body, self._carry = text, ""
            else:
                body, self._carry = text[:cut], text[cut + 1:]
            if body or not self._eof:
                got = body.split("\n")
                if len(body) > MAX_LINE_CHARS:
                    got = [ln if len(ln) <= MAX_LINE_CHARS else "\0" for ln in got]
                if self._eof and got[-1].strip():  # the file ends inside this line: it may be cut
                    got[-1] = _CUT + got[-1]
                lines.extend(got)
                size += len(body)
            if len(self._carry) > MAX_LINE_CHARS:
                lines.append("\0")
                self._carry = ""
                self._skip_long_line()
        return lines

    def _read(self, n: int) -> str:
        """Up to ``n`` characters; a gzip stream that is cut or corrupt ends here, said in the report."""
        try:
            return self._file.read(n)
        except (EOFError, gzip.BadGzipFile, zlib_error) as exc:
            self.report.truncated = True
            self.report.skip("damaged_record", f"line {self._line + 1}",
                             f"the gzip stream is cut or corrupt ({exc}); the rows before are kept")
            return ""

    def _skip_long_line(self) -> None:
        """Read on to the end of the current (over-long) line, holding at most one block."""
        while True:
            block = self._read(1 << 16)
            if not block:
                self._eof = True
                return
            cut = block.find("\n")
            if cut >= 0:
                self._carry = block[cut + 1:]
                return

    # -- header ------------------------------------------------------------------------------

    def _read_header(self) -> tuple[list[str], int]:
        while True:
            lines = self._next_lines(1 << 16)
            if not lines:
                break
            for i, line in enumerate(lines):
                self._line += 1
                line_no = self._line
                text = line.removeprefix(_CUT).strip()
                if not text or text.startswith("#"):
                    continue
                if text == "\0":
                    raise LogFormatError(f"{self.path}: line {line_no}: header longer than {MAX_LINE_CHARS} "
                                         "characters; expected a header row naming the columns (e.g. "
                                         "'t,x_ref,u,x,pA,pB')")
                self._carry = "\n".join(lines[i + 1:]) + ("\n" if i + 1 < len(lines) else "") + self._carry
                return self._header_columns(text, line_no), line_no
        raise LogFormatError(f"{self.path}: empty file (only blank or comment lines), expected a header row "
                             "naming the columns (e.g. 't,x_ref,u,x,pA,pB')")

    def _header_columns(self, text: str, line_no: int) -> list[str]:
        """The column names of header ``text`` (quotes and spaces stripped, trailing empty columns dropped)."""
        if "\ufffd" in text:
            raise LogFormatError(f"{self.path}: line {line_no}: header is not UTF-8 text ({text[:60]!r}); "
                                 "expected a header row naming the columns (e.g. 't,x_ref,u,x,pA,pB')")
        if self._delimiter == "," and "," not in text and text.count(";") >= 1:
            self._delimiter = ";"  # a ';'-separated export (a locale with decimal commas), found from its header
        self._decimal_comma = self._delimiter == ";"  # ';' separates the fields: a ',' in a number is its decimal
        n = text.count(self._delimiter) + 1
        if n > MAX_COLUMNS:
            raise LogFormatError(f"{self.path}: line {line_no}: header has {n} columns, more than {MAX_COLUMNS}; "
                                 "expected a rig record's header row naming its columns (e.g. 't,x_ref,u,x,pA,pB')")
        cols = [c.strip().strip('"').strip() for c in text.split(self._delimiter)]
        self._n_fields = len(cols)
        while cols and not cols[-1]:  # a trailing delimiter, e.g. '"V1","V2",'
            cols.pop()
        if not cols or any(not c for c in cols):
            raise LogFormatError(f"{self.path}: line {line_no}: header {text[:80]!r} has an empty column name; "
                                 "expected a header row naming the columns (e.g. 't,x_ref,u,x,pA,pB')")
        try:
            [float(c) for c in cols]
        except ValueError:
            return cols
        raise LogFormatError(f"{self.path}: line {line_no}: expected a header row naming the "
                             f"columns (e.g. 't,x_ref,u,x,pA,pB'), found numbers {text[:80]!r}")

    def _check_rate(self, step_ns: float, col: str) -> None:
        """Refuse an explicitly given time axis whose rate no rig record has."""
        lo, hi = ACCEPTED_RATE_HZ
        rate = 1e9 / step_ns
        if not lo <= rate <= hi:
            assert self._t_col is not None
            given = self._units[self._t_col] or "s"
            raw_step = step_ns * 1e-9 / UNITS[given][0]  # the step as written in the file
            fits = [f"{u} ({1.0 / (raw_step * UNITS[u][0]):.6g} Hz)" for u in ("s", *_TIME_UNITS)
                    if PLAUSIBLE_RATE_HZ[0] <= 1.0 / (raw_step * UNITS[u][0]) <= PLAUSIBLE_RATE_HZ[1]]
            raise DataError(f"{self.path}: column {col!r} read in {given}: median time step {step_ns * 1e-9:.6g} s "
                            f"({rate:.6g} Hz) is not a rig record's rate (expected {lo:g} Hz to {hi:g} Hz)"
                            + (f"; the times look like {' or '.join(fits)}: --map t={col}:{fits[0].split()[0]}"
                               if fits else "; check the time unit in the mapping"))

    def _check_time_unit(self, t_raw: np.ndarray) -> None:
        """Refuse a time column whose steps give an implausible rig sample rate (a wrong unit)."""
        t = t_raw[np.isfinite(t_raw)][:2000]
        if t.size < 4:
            return
        self._time_checked = True
        steps = np.diff(t)
        steps = steps[steps > 0]
        if steps.size < 3:
            return
        step = float(np.median(steps))
        lo, hi = PLAUSIBLE_RATE_HZ
        rate = 1.0 / step
        typical = float(np.median(np.abs(t)))
        big = typical >= _MAX_T_S  # most times beyond what int64 ns holds as seconds (a single one: bad_time)
        if lo <= rate <= hi and not big:
            return
        assert self._t_col is not None
        col = self._columns[self._t_col]
        fits = []
        for unit in _TIME_UNITS:
            f = UNITS[unit][0]
            if lo <= 1.0 / (step * f) <= hi and typical * f < _MAX_T_S:
                fits.append(f"{unit} ({1.0 / (step * f):.6g} Hz)")
        hint = (f"; the times look like {' or '.join(fits)}: give the unit with --map t={col}:{fits[0].split()[0]}"
                if fits else "")
        high_ok = hi < rate <= ACCEPTED_RATE_HZ[1] and not big
        raise DataError(f"{self.path}: column {col!r}: median time step {step:.6g} s ({rate:.6g} Hz"
                        + (f", times about {typical:.6g} s" if big else "")
                        + f") is implausible for a rig record (expected {lo:g} Hz to {hi:g} Hz in seconds)"
                        + hint + (f"; if seconds are right, say so with --map t={col}:s" if high_ok else ""))

    # -- Source --------------------------------------------------------------------------------

    @property
    def signals(self) -> tuple[str, ...]:
        return self._signals

    def close(self) -> None:
        self._file.close()

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Blocks of at most ``size`` samples; the file is read once (a second call yields none)."""
        if self._done:
            return
        while True:
            lines = self._next_lines(self._chunk_chars)
            if not lines:
                break
            first = self._line + 1
            self._line += len(lines)
            block = self._parse(lines, first)
            if block is None:
                continue
            samples, labels = block
            samples = self._gate.apply(samples, labels, "line")
            for start in range(0, len(samples), size):
                yield samples.slice(start, start + size) if len(samples) > size else samples
        self._done = True
        if self._row == 0:
            raise LogFormatError(f"{self.path}: no data rows after the header (line {self._header_line}): an empty "
                                 "record (file cut after its header?); expected one row per sample")

    # -- parsing -------------------------------------------------------------------------------

    def _parse(self, lines: list[str], first: int) -> tuple[Samples, np.ndarray] | None:
        ncol = len(self._columns)
        some = len(self._use) < ncol
        row0 = self._row
        if self._decimal_comma:
            lines = [ln.replace(",", ".") for ln in lines]
        try:
            if "\0" in lines or lines[-1].startswith(_CUT):
                raise ValueError("over-long or unterminated line")
            if self._n_fields > ncol or some:
                # usecols alone would take a row of any field count: every row has the header's (the unnamed
                # trailing columns empty); a row this quick test doubts is parsed line by line
                d = self._delimiter
                if any(self._strip(ln, right=True).rstrip(d).count(d) != ncol - 1 for ln in lines
                       if ln.strip() and not ln.lstrip().startswith("#")):
                    raise ValueError("a value in an unnamed column")
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*input contained no data", category=UserWarning)
                table = np.loadtxt(lines, delimiter=self._delimiter, dtype=np.float64, ndmin=2, comments="#",
                                   quotechar='"', usecols=self._use if (self._n_fields > ncol or some) else None)
            if table.shape[0] and table.shape[1] != len(self._use):
                raise ValueError("column count")
        except ValueError:
            table, labels, rows = self._parse_slowly(lines, first)
        else:
            if table.shape[0] == len(lines):
                labels = np.arange(first, first + len(lines))
                rows = np.arange(row0, row0 + len(lines))
                self._row += len(lines)
            else:  # blank or comment lines were skipped by loadtxt
                labels = np.array([first + i for i, ln in enumerate(lines)
                                   if ln.strip() and not ln.lstrip().startswith("#")], dtype=np.int64)
                rows = np.arange(row0, row0 + labels.size)
                self._row += labels.size
            self.report.records_read += table.shape[0]
        if table.shape[0] == 0:
            return None
        if self._t_col is None:
            assert self._dt_ns is not None
            if float(rows[-1]) * self._dt_ns >= _MAX_T_S * 1e9:
                raise DataError(f"{self.path}: line {labels[-1]}: row {rows[-1]} at {self._dt_ns} ns per sample "
                                "is beyond what a time in int64 nanoseconds holds (292 years)")
            t_ns = rows.astype(np.int64) * np.int64(self._dt_ns)
        else:
            t_ns, table, labels = self._times(table, labels)
        signals: dict[str, np.ndarray] = {}
        for pos, j in enumerate(self._use):
            name, unit = self._names[j], self._units[j]
            if j == self._t_col:
                continue
            col = table[:, pos]
            if unit is not None:
                col = to_si(col, unit, what=f"{self.path}: column {self._columns[j]!r}")
            if j in self._scaled:
                factor, offset = self._scaled[j]
                col = col * factor + offset
            signals[name] = np.ascontiguousarray(col)
        return Samples(t_ns, signals), labels

    def _times(self, table: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The time column in int64 ns (rows whose time is not a finite time in range dropped and counted)."""
        assert self._t_col is not None and self._t_pos is not None
        t_s = table[:, self._t_pos]
        if not self._time_checked:
            self._check_time_unit(t_s)
        t_unit = self._units[self._t_col]
        if t_unit is not None:
            t_s = to_si(t_s, t_unit, what=f"{self.path}: column {self._columns[self._t_col]!r}")
        good_t = np.isfinite(t_s) & (np.abs(t_s) < _MAX_T_S)
        if not good_t.all():
            bad = np.flatnonzero(~good_t)
            add_skips(self.report, "bad_time", int(bad.size), (
                (f"line {labels[i]}", f"time {self._columns[self._t_col]!r} = {t_s[i]} is not a finite "
                 f"time in seconds within +-{_MAX_T_S:g} s") for i in bad[:5]))
            table, labels, t_s = table[good_t], labels[good_t], t_s[good_t]
        t_ns = np.rint(t_s * 1e9).astype(np.int64)
        if t_unit is not None and not self._rate_checked and t_ns.size >= 4:
            steps = np.diff(t_ns[:2000])
            steps = steps[steps > 0]
            if steps.size >= 3:
                self._rate_checked = True
                self._check_rate(float(np.median(steps)), self._columns[self._t_col])
        return t_ns, table, labels

    _rate_checked = False
    _decimal_comma = False

    def _strip(self, line: str, right: bool = False) -> str:
        """``line`` without its surrounding blanks; with a tab delimiter only spaces and line ends go (a trailing
        tab is an empty last field, as in a tab-separated export whose last column is empty on some rows)."""
        if self._delimiter == "\t":
            return line.rstrip(" \r\n") if right else line.strip(" \r\n")
        return line.rstrip() if right else line.strip()

    def _parse_slowly(self, lines: list[str], first: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Line by line, to find and count the rows np.loadtxt refused."""
        ncol = len(self._columns)
        rows: list[list[float]] = []
        labels: list[int] = []
        index: list[int] = []
        for i, line in enumerate(lines):
            cut = line.startswith(_CUT)
            text = self._strip(line.removeprefix(_CUT))
            if not text or text.startswith("#"):
                continue
            self.report.records_read += 1
            row = self._row
            self._row += 1
            where = f"line {first + i}"
            if cut:
                self.report.truncated = True
                self.report.skip("bad_row", where, "the file ends inside this line (no line end): the row may be "
                                 "cut (file cut or writer killed), dropped")
                continue
            if text == "\0":
                self.report.skip("bad_row", where, f"line longer than {MAX_LINE_CHARS} characters, expected "
                                 f"{ncol} fields ({show_columns(self._columns, 6)})")
                continue
            fields = text.split(self._delimiter, ncol + 1)
            if len(fields) > ncol and not "".join(fields[ncol:]).strip():
                fields = fields[:ncol]  # a trailing delimiter
            if len(fields) != ncol:
                count = text.count(self._delimiter) + 1
                self.report.skip("bad_row", where, f"{count} fields, expected {ncol} "
                                 f"({','.join(self._columns) if ncol <= 12 else show_columns(self._columns, 6)})")
                continue
            fields = [fields[j].strip().strip('"') for j in self._use]
            try:
                rows.append([float(f) for f in fields])
            except ValueError:
                for col, f in zip((self._columns[j] for j in self._use), fields):
                    try:
                        float(f)
                    except ValueError:
                        what = "is empty" if not f.strip() else f"= {f.strip()[:40]!r} is not a number"
                        self.report.skip("bad_row", where, f"field {col!r} {what}, expected a float")
                        break
                continue
            labels.append(first + i)
            index.append(row)
        table = np.array(rows, dtype=np.float64).reshape(len(rows), len(self._use))
        return table, np.array(labels, dtype=np.int64), np.array(index, dtype=np.int64)

