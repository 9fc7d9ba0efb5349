"""Open a source or sink by path or URI; the format comes from the suffix or the scheme.

==========================  ==============================================================
path or URI                 source / sink
==========================  ==============================================================
``*.csv``                   :class:`replay.csvio.CsvSource` / :class:`~replay.csvio.CsvSink`
``*.mcap``                  :class:`replay.mcapio.McapSource` / :class:`~replay.mcapio.McapSink`
``*.asc .blf .log .trc``    ``replay.canio.CanLogSource(path, dbc=..., **options)`` /
                            ``replay.canio.CanLogSink(path, **options)``
``can://INTERFACE/CHANNEL`` ``replay.live.CanBusSource(uri, **options)``
``zenoh://KEYEXPR``         ``replay.live.ZenohSource(uri, **options)``
==========================  ==============================================================

The CAN and live modules are imported only when asked for.  Options are passed on as
keyword arguments to the class.  An unknown format raises
:class:`~twin.errors.LogFormatError` naming the path and the formats known; a file that
cannot be read raises :class:`~twin.errors.SourceError`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from replay.base import Sink, Source
from twin.errors import LogFormatError, SourceError

#: Log-file suffixes of python-can formats, read through ``replay.canio``.
CAN_LOG_SUFFIXES: tuple[str, ...] = (".asc", ".blf", ".log", ".trc")
FILE_SUFFIXES: tuple[str, ...] = (".csv", ".mcap", *CAN_LOG_SUFFIXES)
URI_SCHEMES: tuple[str, ...] = ("can", "zenoh")


def _known() -> str:
    return f"files {', '.join(FILE_SUFFIXES)} and URIs can://INTERFACE/CHANNEL, zenoh://KEYEXPR"


def _scheme(path_or_uri: str) -> str | None:
    """The URI scheme, or None for a plain path (a Windows drive letter is not a scheme)."""
    if "://" not in path_or_uri:
        return None
    scheme = path_or_uri.split("://", 1)[0].lower()
    return scheme if len(scheme) > 1 else None


def open_source(path_or_uri: str | os.PathLike, **options: Any) -> Source:
    """Open a sample source; the format comes from the suffix or URI scheme (table above).

    ``options`` go to the source's constructor (e.g. ``mapping=`` for CSV, ``topic=``,
    ``start_ns=``, ``end_ns=`` for MCAP, ``dbc=`` for CAN logs, ``required=`` for all
    file sources).
    """
    text = os.fspath(path_or_uri)
    scheme = _scheme(text)
    if scheme == "can":
        from replay.live import CanBusSource

        return CanBusSource(text, **options)
    if scheme == "zenoh":
        from replay.live import ZenohSource

        return ZenohSource(text, **options)
    if scheme is not None:
        raise LogFormatError(f"{text}: unknown URI scheme {scheme!r}; known: {_known()}")
    path = Path(text)
    suffix = path.suffix.lower()
    if suffix not in FILE_SUFFIXES:
        raise LogFormatError(f"{text}: unknown format (suffix {suffix or 'none'!r}); known: {_known()}")
    if not path.is_file():
        what = "is a directory" if path.is_dir() else "does not exist"
        raise SourceError(f"{text}: cannot read log file: {what}")
    if not os.access(path, os.R_OK):
        raise SourceError(f"{text}: cannot read log file: permission denied")
    if suffix == ".csv":
        from replay.csvio import CsvSource

        return CsvSource(path, **options)
    if suffix == ".mcap":
        from replay.mcapio import McapSource

        return McapSource(path, **options)
    from replay.canio import CanLogSource

    dbc = options.pop("dbc", None)
    return CanLogSource(path, dbc=dbc, **options)


def open_sink(path: str | os.PathLike, **options: Any) -> Sink:
    """Open a sink for ``.csv``, ``.mcap`` or a CAN log suffix; ``options`` go to its constructor."""
    text = os.fspath(path)
    p = Path(text)
    suffix = p.suffix.lower()
    if suffix not in FILE_SUFFIXES:
        raise LogFormatError(f"{text}: unknown output format (suffix {suffix or 'none'!r}); "
                             f"known: {', '.join(FILE_SUFFIXES)}")
    if p.parent and not p.parent.is_dir():
        raise SourceError(f"{text}: cannot create output file: directory {str(p.parent)!r} does not exist")
    if suffix == ".csv":
        from replay.csvio import CsvSink

        return CsvSink(p, **options)
    if suffix == ".mcap":
        from replay.mcapio import McapSink

        return McapSink(p, **options)
    from replay.canio import CanLogSink

    return CanLogSink(p, **options)


__all__ = ["open_source", "open_sink", "CAN_LOG_SUFFIXES", "FILE_SUFFIXES", "URI_SCHEMES"]
