"""Open a source or sink by path or URI; the format comes from the suffix or the scheme.

==========================  ==============================================================
path or URI                 source / sink
==========================  ==============================================================
``*.csv``                   :class:`replay.csvio.CsvSource` / :class:`~replay.csvio.CsvSink`
``*.mcap``                  :class:`replay.mcapio.McapSource` / :class:`~replay.mcapio.McapSink`
``*.mat`` (``.mat.gz``)     :class:`replay.matio.MatSource` (read only)
``*.txt .tsv`` (``.gz``)    :class:`replay.matio.TextSource` (read only)
``*.asc .blf .log .trc``    ``replay.can.logs.CanLogSource(path, dbc=..., **options)`` /
                            ``replay.can.logs.CanLogSink(path, **options)``
``can://INTERFACE/CHANNEL`` ``replay.can.bus.CanBusSource(uri, **options)``
``zenoh://KEYEXPR``         ``replay.live.ZenohSource(uri, **options)``
==========================  ==============================================================

The suffixes and classes come from the one registry :mod:`replay.formats`; modules
are imported only when asked for.  Options are passed on as keyword arguments to the
class.  An unknown format raises :class:`~fpdd.errors.LogFormatError` naming the path
and the formats known; a file that cannot be read (missing, a directory, no
permission, empty) raises :class:`~fpdd.errors.SourceError` /
:class:`~fpdd.errors.LogFormatError` naming it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from replay import formats
from replay.base import Sink, Source
from replay.formats import CAN_LOG_SUFFIXES, FILE_SUFFIXES, URI_SCHEMES
from fpdd.errors import LogFormatError, SourceError


def _scheme(path_or_uri: str) -> str | None:
    """The URI scheme, or None for a plain path (a Windows drive letter is not a scheme)."""
    if "://" not in path_or_uri:
        return None
    scheme = path_or_uri.split("://", 1)[0].lower()
    return scheme if len(scheme) > 1 else None


def check_readable(text: str) -> Path:
    """``text`` as a Path that is a readable, non-empty regular file; SourceError/LogFormatError otherwise."""
    path = Path(text)
    if not path.exists():
        raise SourceError(f"{text}: cannot read log file: does not exist")
    if path.is_dir():
        raise SourceError(f"{text}: cannot read log file: is a directory, expected a file")
    if not path.is_file():
        raise SourceError(f"{text}: cannot read log file: not a regular file")
    if not os.access(path, os.R_OK):
        raise SourceError(f"{text}: cannot read log file: permission denied")
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise SourceError(f"{text}: cannot read log file: {exc.strerror or exc}") from exc
    if size == 0:
        raise LogFormatError(f"{text}: empty file (0 bytes), expected a {formats.lookup(text).description}")
    return path


def open_source(path_or_uri: str | os.PathLike, **options: Any) -> Source:
    """Open a sample source; the format comes from the suffix or URI scheme (table above).

    ``options`` go to the source's constructor (e.g. ``mapping=`` for CSV, text and MATLAB files,
    ``topic=``, ``start_ns=``, ``end_ns=`` for MCAP, ``dbc=`` for CAN logs, ``required=`` for all
    file sources).  A CAN log's ``mapping`` (``{"MyPosSignal": ("x", "mm")}``, :func:`replay.csvio.parse_map`)
    maps the DBC's signals onto the rig's, as a CSV's columns.
    """
    text = os.fspath(path_or_uri)
    scheme = _scheme(text)
    if scheme == "can" and options.get("mapping"):  # a live bus decoded with your own DBC's names mapped
        from replay.can.codec import VectorCodec

        options["dbc"] = VectorCodec(options.get("dbc"), mapping=options.pop("mapping"))
    if scheme in URI_SCHEMES:
        return formats.load(URI_SCHEMES[scheme])(text, **options)
    if scheme is not None:
        raise LogFormatError(f"{text}: unknown URI scheme {scheme!r}; known: {formats.known()}")
    if Path(text).is_dir():
        raise SourceError(f"{text}: cannot read log file: is a directory, expected a log file "
                          f"({', '.join(FILE_SUFFIXES)})")
    fmt = formats.lookup(text)
    path = check_readable(text)
    cls = formats.load(fmt.source)
    if fmt.kind == "can":
        dbc = options.pop("dbc", None)
        mapping = options.pop("mapping", None)
        if mapping:  # the DBC's own signal names mapped onto the rig's (--map x=MyPosSignal:mm)
            from replay.can.codec import VectorCodec

            dbc = VectorCodec(dbc, mapping=mapping)
        return cls(path, dbc=dbc, **options)
    return cls(path, **options)


def open_sink(path: str | os.PathLike, **options: Any) -> Sink:
    """Open a sink for ``.csv``, ``.mcap`` or a CAN log suffix; ``options`` go to its constructor."""
    text = os.fspath(path)
    fmt = formats.lookup(text, what="output")
    p = Path(text)
    if p.is_dir():
        raise SourceError(f"{text}: cannot create output file: is a directory")
    if p.parent and not p.parent.is_dir():
        raise SourceError(f"{text}: cannot create output file: directory {str(p.parent)!r} does not exist")
    assert fmt.sink is not None  # lookup(what="output") refuses a read-only format
    return formats.load(fmt.sink)(p, **options)


__all__ = ["open_source", "open_sink", "check_readable", "CAN_LOG_SUFFIXES", "FILE_SUFFIXES", "URI_SCHEMES"]
