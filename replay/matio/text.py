"""Tab- or whitespace-separated text records (``.txt``, ``.tsv``, and gzip'd ``.txt.gz``, ``.tsv.gz``).

* A first line that names the columns and is split by tabs: read by :class:`replay.csvio.CsvSource` with a
  tab delimiter (the CSV layout, units in names, ``--map``, bad rows counted; a column of text, such as a
  label, is read only when mapped, so map the signals).
* Otherwise the columns are split by any run of blanks; a first line that is not all numbers names them,
  and a file without such a line has its columns named by position, ``1``, ``2``, ... (``--map y=2``).
  Blank lines and lines starting with ``#`` or ``%`` are ignored; a row of another field count or with a
  field that is not a number is skipped and counted (``bad_row``, with its line number).

The time is the column ``t`` (or ``time``), one mapped with ``--map t=COLUMN[:UNIT]``, or ``--rate`` /
``--dt`` (:class:`replay.matio.ColumnSource`).
"""

from __future__ import annotations

import gzip
import os
import zlib
from collections.abc import Iterator, Sequence

import numpy as np

from fpdd.errors import LogFormatError, SourceError
from replay.base import Samples, Source
from replay.csvio.columns import ColumnMap, sniff_text
from replay.matio.columns import ColumnSource
from replay.quality import QualityOptions

_COMMENTS = ("#", "%")


def _open_text(path: str, encoding: str = "utf-8"):
    return (gzip.open(path, "rt", encoding=encoding, errors="replace", newline="") if path.lower().endswith(".gz")
            else open(path, encoding=encoding, errors="replace", newline=""))


def _numbers(fields: list[str]) -> bool:
    try:
        [float(f) for f in fields]
    except ValueError:
        return False
    return True


class TextSource(Source):
    """Samples from a tab- or whitespace-separated text file (see the module docstring).

    Options as :class:`~replay.csvio.CsvSource`: ``mapping``, ``required``, ``quality``, ``rate_hz`` / ``dt_s``.
    """

    def __init__(self, path: str | os.PathLike, *, mapping: ColumnMap | None = None, required: Sequence[str] = (),
                 quality: QualityOptions | None = None, rate_hz: float | None = None,
                 dt_s: float | None = None) -> None:
        self.path = os.fspath(path)
        try:
            with (gzip.open(self.path, "rb") if self.path.lower().endswith(".gz") else open(self.path, "rb")) as raw:
                head = raw.read(1 << 16)
        except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
            raise LogFormatError(f"{self.path}: not a readable gzip file ({exc}); expected gzip'd text") from None
        except OSError as exc:
            raise SourceError(f"{self.path}: cannot open text file: {exc.strerror or exc}") from None
        encoding = sniff_text(self.path, head, what="text")
        first = next((ln for ln in head.decode(encoding, errors="replace").splitlines()
                      if ln.strip() and not ln.lstrip().startswith(_COMMENTS)), "")
        if not first:
            raise LogFormatError(f"{self.path}: no data (only blank or comment lines); expected rows of numbers "
                                 "separated by tabs or blanks")
        self._inner: Source
        if "\t" in first and not _numbers(first.split()):
            from replay.csvio import CsvSource

            self._inner = CsvSource(self.path, mapping=mapping, required=required, quality=quality, delimiter="\t",
                                    rate_hz=rate_hz, dt_s=dt_s)
        else:
            columns = self._read_columns(encoding, header=not _numbers(first.split()))
            self._inner = ColumnSource(self.path, columns, what="column", mapping=mapping, required=required,
                                       quality=quality, rate_hz=rate_hz, dt_s=dt_s)
            self._inner.report.skipped.update(self._bad)
            self._inner.report.records_read += sum(self._bad.values())
            self._inner.report.problems[:0] = self._bad_rows
        self.report = self._inner.report

    def _read_columns(self, encoding: str, header: bool) -> dict[str, np.ndarray]:
        from collections import Counter

        from replay.base import Problem

        names: list[str] | None = None
        rows: list[list[float]] = []
        self._bad: Counter = Counter()
        self._bad_rows: list[Problem] = []
        with _open_text(self.path, encoding) as f:
            for line_no, line in enumerate(f, 1):
                text = line.strip()
                if not text or text.startswith(_COMMENTS):
                    continue
                fields = text.split()
                if names is None:
                    if header:
                        names = [c.strip('"') for c in fields]
                        if len(set(names)) != len(names):
                            raise LogFormatError(f"{self.path}: line {line_no}: a column name appears twice in "
                                                 f"{text[:80]!r}")
                        continue
                    names = [str(i + 1) for i in range(len(fields))]
                why = ""
                if len(fields) != len(names):
                    why = f"{len(fields)} fields, expected {len(names)}"
                else:
                    try:
                        rows.append([float(x) for x in fields])
                        continue
                    except ValueError:
                        why = "a field that is not a number"
                self._bad["bad_row"] += 1
                if len(self._bad_rows) < 5:
                    self._bad_rows.append(Problem(self.path, f"line {line_no}", f"{why}; row skipped"))
        if names is None or not rows:
            raise LogFormatError(f"{self.path}: no data rows" + (" after the header" if names else "")
                                 + "; expected rows of numbers separated by tabs or blanks")
        table = np.array(rows, dtype=np.float64)
        return {n: table[:, j] for j, n in enumerate(names)}

    @property
    def signals(self) -> tuple[str, ...]:
        return self._inner.signals

    def close(self) -> None:
        self._inner.close()

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        yield from self._inner.chunks(size)
