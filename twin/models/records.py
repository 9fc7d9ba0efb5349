"""A model's records read from a file: any source ``replay`` knows (CSV, MCAP, MATLAB, text, CAN logs) read into uniform
:class:`twin.record.Record` pieces, its signals checked first against what the model needs (:func:`check_signals`:
a drive among the model's inputs, one of its outputs), in the signal vocabulary of the model's records
(:func:`signal_specs`).
"""

from __future__ import annotations

from fpdd.errors import DataError
from twin.models import DEFAULT_MODEL, get_model
from twin.record import Record, records_from_samples


def signal_specs(model: str):
    """The signal vocabulary of ``model``'s records: the signals the model declares (:attr:`Model.SIGNALS`: a
    force ``u`` in N for one, a valve voltage ``u`` in V for another), over the readers' common vocabulary
    (:data:`fpdd.units.SIGNALS`) for the names it does not declare; the common vocabulary alone for a name that
    is no registered model."""
    from fpdd.units import SIGNALS
    from twin.models import REGISTRY

    if model not in REGISTRY:
        return dict(SIGNALS)
    return {**SIGNALS, **get_model(model).signal_specs()}


def _fitting_models(have: set, model: str) -> list[str]:
    """The registered models other than ``model`` whose drive (or demand) and a measured output ``have`` holds."""
    from twin.models import MODELS

    out = []
    for name in MODELS:
        m = get_model(name)
        drives = set(m.signals("drive")) | set(m.signals("demand"))
        if name != model and have & drives and have & set(m.signals("output")):
            out.append(name)
    return out


def check_signals(path: str, names, model: str = DEFAULT_MODEL, needed=(), suggest: bool = False) -> None:
    """Refuse (:class:`DataError`, one line) a record without a signal its command needs.

    Needed: a drive of ``model`` (any of its inputs), at least one of its outputs, and
    ``needed``. A column that is no signal of ``model`` is "not understood"; one whose name
    starts with a missing signal's name and a unit (``x[mm]``, ``x_ref (mm)``) is that
    signal under a name the readers do not know: refused too, with the ``--map`` that reads it.
    ``suggest``: name the registered models whose signals the record has (``--model NAME``).
    """
    import re

    m = get_model(model)
    specs = signal_specs(model)
    names = tuple(names)
    have = set(names)
    foreign = [n for n in names if n not in specs]
    rig = (*m.INPUTS, *m.OUTPUTS, *[n for n in needed if n not in m.INPUTS + m.OUTPUTS])
    missing = [n for n in rig if n not in have]
    lacks = []
    if not have & set(m.INPUTS):
        sig = m.signals()
        drives = sorted(m.INPUTS, key=lambda n: sig[n].role != "drive" if n in sig else True)
        lacks.append(f"a drive ({' or '.join(f'the {sig[n].meaning} {n!r}' if n in sig else repr(n) for n in drives)})")
    if not have & set(m.OUTPUTS):
        lacks.append(f"a measured output (any of {', '.join(m.OUTPUTS)})")
    stems = {n: re.split(r"[\[\(\s]", n, maxsplit=1)[0] for n in foreign}
    mistaken = {n: stem for n, stem in stems.items() if stem in missing}
    absent = [n for n in missing if n in needed or n in mistaken.values()]
    if absent:
        lacks.append(f"signal(s) {', '.join(absent)}")
    if not lacks:
        return
    parts = []
    if foreign:
        parts.append(f"column(s) {', '.join(repr(n) for n in foreign)} not understood (no signal of the {model} "
                     "model)")
    parts.append(f"missing {' and '.join(lacks)}")
    hint = ""
    if mistaken:
        col, stem = next(iter(mistaken.items()))
        unit = re.search(r"[\[\(]\s*([^\]\)]+?)\s*[\]\)]", col)
        hint = f"; map a column with --map NAME=COLUMN[:UNIT], e.g. --map {stem}={col}" + (
            f":{unit.group(1)}" if unit else "")
    others = _fitting_models(have, model) if suggest else []
    if others:
        hint += f"; the record has the signals of the {' and the '.join(others)} model: --model {others[0]}"
    raise DataError(f"{path}: {'; '.join(parts)}; the record has {', '.join(names) or 'no signals'}{hint}")


def reader_options(path: str, model: str, options: dict) -> dict:
    """``options`` for reading ``path`` as ``model``'s record: a file of samples (CSV, MCAP, MATLAB, text) is
    checked against the model's own signal vocabulary (:func:`signal_specs`: the oscillator's ``u`` is a force)."""
    from replay import formats
    from replay.quality import QualityOptions

    if formats.suffix_of(path) in formats.SAMPLE_SUFFIXES and "quality" not in options:
        return {**options, "quality": QualityOptions(specs=signal_specs(model))}
    return options


def check_source(path: str, src, model: str = DEFAULT_MODEL, suggest: bool = False) -> None:
    """:func:`check_signals` of an open source; for a CAN log the refusal also says what was looked for and what
    its DBC has (``VectorCodec.describe_lookup``)."""
    try:
        check_signals(path, src.signals, model, suggest=suggest)
    except DataError as exc:
        codec = getattr(src, "codec", None)
        if codec is None:
            raise
        raise DataError(f"{exc}; {codec.describe_lookup()}") from None


def load_records(path: str, name: str | None = None, model: str = DEFAULT_MODEL, reports: list | None = None, *,
                 map=None, **options) -> list[Record]:  # noqa: A002
    """Read any source ``replay`` knows (CSV, MCAP, CAN logs) into uniform records of ``model``.

    ``map``: columns (of a CSV or text file; a MATLAB file's variables; a CAN log's DBC signals) under other
    names, units or scales, in the direction of ``--map``: ``{"x": "pos_mm:mm", "t": "time:ms", "u":
    "vir*35.15N/V"}``, or ``--map``'s strings (``"x=pos_mm:mm"`` or a list of them). ``dbc=`` (CAN logs) and
    other keyword options go to the reader.

    Refused (:class:`DataError`): a record without the signals a fit needs (:func:`check_signals`) or
    without a usable sample. ``reports``: receives the reader's :class:`replay.base.ReadReport` (what
    was lost on the way: ``report.lossy``, ``report.loss_line()``); without it a loss is logged as a
    warning (logger ``twin.models.records``), never passed over in silence.
    """
    from replay import formats
    from replay.factory import open_source

    if map:
        from replay.csvio import parse_map

        if not formats.takes_map(path):
            raise DataError(f"{path}: map names the columns of CSV, text and MATLAB files and the signals of CAN "
                            "logs; this file's signals are named by its format")
        items = [map] if isinstance(map, str) else ([f"{k}={v}" for k, v in map.items()] if isinstance(map, dict)
                                                     else list(map))
        options["mapping"] = parse_map(items, option="map")

    with open_source(path, **reader_options(path, model, options)) as src:
        check_source(str(path), src, model)
        samples = src.read_all()
        report = src.report
    if reports is not None:
        reports.append(report)
    elif report.lossy:
        import logging

        logging.getLogger(__name__).warning("%s", report.loss_line())
    if len(samples) == 0:
        raise DataError(f"{path}: no usable samples ({report.summary()})")
    return records_from_samples(samples, name or str(path))
