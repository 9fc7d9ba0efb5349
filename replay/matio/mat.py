"""MATLAB ``.mat`` files (v4 to v7, through :func:`scipy.io.loadmat`; ``.mat.gz`` through gzip) as records.

A file holds named variables; the vectors (``n x 1``, ``1 x n``) of one length are the columns, read as
:class:`replay.matio.ColumnSource` reads columns: ``t`` (or ``time``) is the time in s, a variable named as
a signal is that signal, ``--map NAME=VARIABLE[:UNIT][*GAIN][+OFFSET]`` maps the others.  The time may
instead be a scalar sample time (``--map t=Ts``, or a scalar named ``Ts``, ``dt`` or ``Ts_s``) or
``--rate`` / ``--dt``.  A mapped variable that is missing, or is not a vector (a scalar, a matrix, a
struct, text), is refused in one line naming the file, the variable and what was expected.  A MATLAB 7.3
file (HDF5) is refused with how to save it readable (``save -v7``).
"""

from __future__ import annotations

import gzip
import os
import zlib
from collections.abc import Sequence

import numpy as np

from fpdd.errors import LogFormatError, SourceError
from replay.csvio.columns import ColumnMap
from replay.matio.columns import ColumnSource
from replay.quality import QualityOptions

#: Scalars taken for the sample time (s) when nothing else gives one.
SAMPLE_TIME_NAMES = ("Ts", "dt", "Ts_s", "dt_s")


def load_mat(path: str) -> dict[str, object]:
    """The variables of a MATLAB file (``__header__`` and the like dropped); LogFormatError naming the file."""
    import scipy.io

    try:
        with (gzip.open(path, "rb") if path.lower().endswith(".gz") else open(path, "rb")) as f:
            data = scipy.io.loadmat(f, squeeze_me=False, struct_as_record=True)
    except NotImplementedError:
        raise LogFormatError(f"{path}: a MATLAB 7.3 (HDF5) file; expected a MATLAB v4-v7 file: save it with "
                             "save(FILE, '-v7')") from None
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise LogFormatError(f"{path}: not a readable gzip file ({exc}); expected a gzip'd MATLAB file") from None
    except OSError as exc:
        raise SourceError(f"{path}: cannot read MATLAB file: {exc.strerror or exc}") from None
    except Exception as exc:  # scipy raises ValueError, TypeError, MatReadError for what is not a .mat file
        raise LogFormatError(f"{path}: not a MATLAB .mat file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); "
                             "expected a MATLAB v4-v7 file of named vectors") from None
    return {k: v for k, v in data.items() if not k.startswith("__")}


def describe(value: object) -> str:
    """What a variable is, for messages: ``"1x1 scalar"``, ``"3x4 matrix"``, ``"struct"``, ``"text"``."""
    a = np.asarray(value)
    if a.dtype.names:
        return "a struct"
    if a.dtype.kind in "US":
        return "text"
    if a.dtype == object:
        return "a cell array"
    shape = "x".join(str(n) for n in a.shape) or "1x1"
    if a.size == 1:
        return f"a {shape} scalar"
    if a.dtype.kind not in "biuf":
        return f"a {shape} array of {a.dtype.kind!r} values"
    return f"a {shape} matrix"


class MatSource(ColumnSource):
    """Samples from a MATLAB ``.mat`` (or ``.mat.gz``) file (see the module docstring).

    Options as :class:`~replay.csvio.CsvSource`: ``mapping`` (variable -> signal, ``--map``), ``required``,
    ``quality``, ``rate_hz`` / ``dt_s`` for a file without a time vector.
    """

    def __init__(self, path: str | os.PathLike, *, mapping: ColumnMap | None = None, required: Sequence[str] = (),
                 quality: QualityOptions | None = None, rate_hz: float | None = None,
                 dt_s: float | None = None) -> None:
        path = os.fspath(path)
        data = load_mat(path)
        columns: dict[str, np.ndarray] = {}
        others: dict[str, str] = {}
        scalars: dict[str, float] = {}
        for name, value in data.items():
            a = np.asarray(value)
            numeric = a.dtype.kind in "biuf" and not a.dtype.names
            if numeric and a.ndim <= 2 and a.size > 1 and min(a.shape) == 1:
                columns[name] = a.reshape(-1).astype(np.float64)
                continue
            if numeric and a.size == 1:
                scalars[name] = float(a.reshape(-1)[0])
            others[name] = describe(value)
        lengths = {len(v) for v in columns.values()}
        if len(lengths) > 1:  # keep the vectors of the most common length (parameter tables beside the log)
            common = max(lengths, key=lambda k: (sum(len(v) == k for v in columns.values()), k))
            for name in [n for n, v in columns.items() if len(v) != common]:
                others[name] = f"a vector of {len(columns[name])} samples (the log's vectors have {common})"
                del columns[name]
        if not columns:
            from fpdd.errors import DataError

            raise DataError(f"{path}: no vector variable; expected named vectors of samples (the file has "
                            f"{', '.join(f'{n} ({d})' for n, d in others.items()) or 'no variables'})")
        step = next((scalars[n] for n in SAMPLE_TIME_NAMES if n in scalars), None)
        super().__init__(path, columns, others=others, what="variable", mapping=mapping, required=required,
                         quality=quality, rate_hz=rate_hz, dt_s=dt_s, sample_time_s=step, scalars=scalars)
