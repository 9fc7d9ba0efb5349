"""The one registry of log formats by file suffix (like python-can's ``MESSAGE_WRITERS``).

Every place in :mod:`replay` that needs to know which suffixes exist, which class reads
or writes them, or whether a CAN log is text, asks this module; adding a format is one
entry in :data:`FORMATS`.

==========  ==========  ===================================  ============================
suffix      kind        source / sink                        python-can reader / writer
==========  ==========  ===================================  ============================
``.csv``    samples     ``replay.csvio.CsvSource/CsvSink``   -
``.mcap``   samples     ``replay.mcapio.McapSource/McapSink``  -
``.mat``    samples     ``replay.matio.MatSource`` (read only)  -
``.txt``    samples     ``replay.matio.TextSource`` (read only) -
``.tsv``    samples     ``replay.matio.TextSource`` (read only) -
``.asc``    can (text)  ``replay.can.logs.CanLogSource/Sink``   ``ASCReader`` / ``ASCWriter``
``.blf``    can         ``replay.can.logs.CanLogSource/Sink``   ``BLFReader`` / ``BLFWriter``
``.log``    can (text)  ``replay.can.logs.CanLogSource/Sink``   ``CanutilsLogReader`` / ``...Writer``
``.trc``    can (text)  ``replay.can.logs.CanLogSource/Sink``   ``TRCReader`` / ``TRCWriter``
==========  ==========  ===================================  ============================

Classes are named as ``"module:Class"`` strings and imported only when asked for
(:func:`load`), so importing this module costs nothing (no python-can, no mcap).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
from pathlib import Path
from typing import Any

from fpdd.errors import LogFormatError

#: URI schemes of live inputs (``can://INTERFACE/CHANNEL``, ``zenoh://KEYEXPR``).
URI_SCHEMES: dict[str, str] = {
    "can": "replay.can.bus:CanBusSource",
    "zenoh": "replay.live:ZenohSource",
}


@dataclasses.dataclass(frozen=True)
class Format:
    """One log format: its suffix, what it holds and the classes that read and write it."""

    suffix: str
    kind: str                      # "samples" (signals in SI) or "can" (raw CAN frames + DBC)
    source: str                    # "module:Class" of the replay source
    sink: str | None               # "module:Class" of the replay sink (None: read only)
    description: str
    text: bool = False             # a line-oriented text file
    can_reader: str | None = None  # python-can reader class name (CAN logs)
    can_writer: str | None = None  # python-can writer class name (CAN logs)

    @property
    def name(self) -> str:
        return self.suffix[1:].upper()


FORMATS: dict[str, Format] = {f.suffix: f for f in (
    Format(".csv", "samples", "replay.csvio:CsvSource", "replay.csvio:CsvSink",
           "CSV file (header row t,<signals>, one row per sample)", text=True),
    Format(".mcap", "samples", "replay.mcapio:McapSource", "replay.mcapio:McapSink",
           "MCAP file"),
    Format(".asc", "can", "replay.can.logs:CanLogSource", "replay.can.logs:CanLogSink",
           "Vector ASC CAN log", text=True, can_reader="ASCReader", can_writer="ASCWriter"),
    Format(".blf", "can", "replay.can.logs:CanLogSource", "replay.can.logs:CanLogSink",
           "Vector BLF binary CAN log", can_reader="BLFReader", can_writer="BLFWriter"),
    Format(".log", "can", "replay.can.logs:CanLogSource", "replay.can.logs:CanLogSink",
           "candump -l CAN log", text=True, can_reader="CanutilsLogReader", can_writer="CanutilsLogWriter"),
    Format(".trc", "can", "replay.can.logs:CanLogSource", "replay.can.logs:CanLogSink",
           "PEAK TRC CAN log", text=True, can_reader="TRCReader", can_writer="TRCWriter"),
    Format(".mat", "samples", "replay.matio:MatSource", None,
           "MATLAB file (v4-v7; named vectors, a time vector t or a sample time)"),
    Format(".txt", "samples", "replay.matio:TextSource", None,
           "text file (columns separated by tabs or blanks, a header row naming them or none)", text=True),
    Format(".tsv", "samples", "replay.matio:TextSource", None,
           "tab-separated text file (a header row naming the columns)", text=True),
)}

#: Every file suffix, and those of CAN logs (python-can formats).
FILE_SUFFIXES: tuple[str, ...] = tuple(FORMATS)
CAN_LOG_SUFFIXES: tuple[str, ...] = tuple(s for s, f in FORMATS.items() if f.kind == "can")
SAMPLE_SUFFIXES: tuple[str, ...] = tuple(s for s, f in FORMATS.items() if f.kind == "samples")


def known() -> str:
    """What can be opened, for error messages."""
    return (f"files {', '.join(FILE_SUFFIXES)} and URIs "
            + ", ".join(f"{s}://{'INTERFACE/CHANNEL' if s == 'can' else 'KEYEXPR'}" for s in URI_SCHEMES))


#: Formats also read gzip'd (``.csv.gz``, ``.mat.gz``, ...).
GZIP_SUFFIXES: tuple[str, ...] = (".csv", ".mat", ".txt", ".tsv")


def suffix_of(path: str | os.PathLike) -> str:
    """The format suffix of ``path``, lower case; a gzip'd file (``.csv.gz``, ``.mat.gz``) is its format's."""
    p = Path(os.fspath(path))
    suffix = p.suffix.lower()
    if suffix == ".gz" and Path(p.stem).suffix.lower() in GZIP_SUFFIXES:
        return Path(p.stem).suffix.lower()
    return suffix


def takes_map(path: str | os.PathLike) -> bool:
    """Whether a record of ``path``'s format takes a column map (``--map``): CSV, text, MATLAB files and CAN
    logs (the DBC's signals), not MCAP (its signals are named)."""
    suf = suffix_of(path)
    return suf in FORMATS and suf != ".mcap"


def takes_rate(path: str | os.PathLike) -> bool:
    """Whether a record of ``path``'s format may be given its sample rate (``--rate``/``--dt``): one that may
    lack a time column (CSV, text, MATLAB files)."""
    return suffix_of(path) in (".csv", ".mat", ".txt", ".tsv")


def lookup(path: str | os.PathLike, *, kind: str | None = None, what: str = "log") -> Format:
    """The format of ``path`` by its suffix; :class:`LogFormatError` naming the known ones if none."""
    suf = suffix_of(path)
    fmt = FORMATS.get(suf)
    if fmt is not None and what == "output" and fmt.sink is None:
        raise LogFormatError(f"{os.fspath(path)}: {fmt.name} files are read, not written; write one of "
                             f"{', '.join(s for s, f in FORMATS.items() if f.sink)}")
    if fmt is None or (kind is not None and fmt.kind != kind):
        pool = FILE_SUFFIXES if kind is None else tuple(s for s, f in FORMATS.items() if f.kind == kind)
        if kind is None and what == "log":
            raise LogFormatError(f"{os.fspath(path)}: unknown format (suffix {suf or 'none'!r}); known: {known()}")
        raise LogFormatError(f"{os.fspath(path)}: unknown {what} format (suffix {suf or 'none'!r}); "
                             f"known: {', '.join(pool)}")
    return fmt


def is_can_log(path: str | os.PathLike) -> bool:
    return suffix_of(path) in CAN_LOG_SUFFIXES


def load(dotted: str) -> Any:
    """Import ``"module:Name"`` and return the object."""
    module, _, name = dotted.partition(":")
    return getattr(importlib.import_module(module), name)


def python_can_classes(suffix: str) -> tuple[type, type]:
    """python-can's (reader, writer) classes of a CAN log suffix."""
    import can

    fmt = FORMATS[suffix]
    if fmt.can_reader is None or fmt.can_writer is None:  # as getattr(can, None) would
        raise TypeError(f"{suffix} is not a CAN log format")
    return getattr(can, fmt.can_reader), getattr(can, fmt.can_writer)


__all__ = ["Format", "FORMATS", "FILE_SUFFIXES", "CAN_LOG_SUFFIXES", "SAMPLE_SUFFIXES", "URI_SCHEMES", "GZIP_SUFFIXES",
           "known", "lookup", "suffix_of", "is_can_log", "load", "python_can_classes", "takes_map", "takes_rate"]
