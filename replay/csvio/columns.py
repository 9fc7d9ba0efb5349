"""The columns of a CSV record: the ``--map NAME=COLUMN[:UNIT]`` mapping, units in a header
(``x[mm]``, ``pA (bar)``), sniffing a file's text and suggesting the mapping a foreign header needs."""

from __future__ import annotations

import re
import shlex
from collections.abc import Mapping, Sequence


from fpdd.units import SIGNALS, UNITS, SignalSpec, si_unit
from fpdd.errors import DataError, LogFormatError

#: Name of the time column (seconds).
TIME_COLUMN = "t"

ColumnMap = Mapping[str, "str | tuple[str, str]"]

MAP_SYNTAX = "--map NAME=COLUMN[:UNIT][*GAIN][+OFFSET]"
#: A header of more columns is refused (a rig record has tens of columns)
MAX_COLUMNS = 4096
UNIT_IN_NAME = re.compile(r"^(?P<name>.*?)\s*[\[(](?P<unit>[^\[\]()]*)[\])]\s*$")


#: One number (a gain or an offset of a ``--map`` item), then its optional unit.
_UNSIGNED = r"(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUMBER = r"[-+]?" + _UNSIGNED
_TARGET = re.compile(
    r"^(?P<column>.+?)(?::(?P<unit>[^:*]+?))?"
    rf"(?:\s*\*\s*(?P<gain>{_NUMBER})\s*(?P<gain_unit>[^+\-\s][^+]*?)?)?"
    rf"(?:\s*(?P<sign>[+-])\s*(?P<offset>{_UNSIGNED})\s*(?P<offset_unit>[^\d\s.+\-][^+]*?)?)?\s*$")


def split_target(target: str) -> tuple[str, str, str, str]:
    """``COLUMN[:UNIT][*GAIN[UNIT]][+OFFSET[UNIT]]`` -> (column, unit, gain, offset), each "" when absent
    (``"vir*35.15N/V"`` -> ``("vir", "", "35.15N/V", "")``, ``"pos*0.001+0.2"`` -> ``("pos", "", "0.001",
    "+0.2")``, ``"pos:mm"`` -> ``("pos", "mm", "", "")``)."""
    m = _TARGET.match(target.strip())
    if m is None:
        return target.strip(), "", "", ""
    gain = (m.group("gain") or "") + (m.group("gain_unit") or "").strip()
    offset = ((m.group("sign") or "") + (m.group("offset") or "") + (m.group("offset_unit") or "").strip()
              if m.group("offset") else "")
    return m.group("column").strip(), (m.group("unit") or "").strip(), gain, offset


def parse_map(items: Sequence[str] | None, *, option: str = "--map") -> dict[str, str | tuple]:
    """Parse command-line column mappings ``NAME=COLUMN[:UNIT][*GAIN][+OFFSET]`` into a ``mapping``.

    ``["x=pos_mm:mm", "pA=p_a", "t=time:ms"]`` -> ``{"pos_mm": ("x", "mm"), "p_a": "pA",
    "time": ("t", "ms")}`` (foreign column -> signal name or (signal, unit), the form the sources
    take); with a gain or an offset the entry is ``(signal, unit, gain, offset)``:
    ``"u=vir*35.15N/V"`` -> ``{"vir": ("u", "", "35.15N/V", "")}``.  ``NAME`` is a signal of
    :data:`fpdd.units.SIGNALS`, ``t`` for the time column, or an extra signal's name; ``COLUMN``
    a column of a CSV or text file, a variable of a MATLAB file or a signal of a CAN log's DBC;
    ``UNIT`` the unit the column is in (:data:`fpdd.units.UNITS`); ``GAIN`` and ``OFFSET`` numbers,
    each with an optional unit (the signal is ``column * GAIN + OFFSET``; their units are checked
    against the signal's, through pint, by :func:`parse_mapping` when the record is read).  Every
    command that reads a record calls this for its ``--map`` option.  Raises
    :class:`~fpdd.errors.DataError` naming the item and the expected syntax (a swapped
    ``COLUMN=NAME`` is recognised and the right order suggested).
    """

    out: dict[str, str | tuple] = {}
    names: dict[str, str] = {}
    for item in items or ():
        name, sep, target = str(item).partition("=")
        name, target = name.strip(), target.strip()
        column, unit, gain, offset = split_target(target)
        bare_colon = target.endswith(":")
        if "*" in target and not gain:
            raise DataError(f"{option} {item!r}: expected a number after '*' (the gain, optionally with a unit: "
                            f"{option} u=vir*35.15N/V)")
        if not sep or not name or not column or bare_colon:
            raise DataError(f"{option} {item!r}: expected {option} {MAP_SYNTAX.split(' ', 1)[1]}, e.g. "
                            f"{option} x=pos_mm:mm (signal x is the column pos_mm, in mm) or "
                            f"{option} u=vir*35.15N/V (u is the column vir, in V, times 35.15 N/V)")
        known_name = name == TIME_COLUMN or name in SIGNALS
        if not known_name and (column == TIME_COLUMN or column in SIGNALS):
            swapped = f"{column}={name}" + (f":{unit}" if unit else "")
            raise DataError(f"{option} {item!r}: {name!r} is not a signal name but {column!r} is; the syntax is "
                            f"NAME=COLUMN[:UNIT]: did you mean {option} {swapped}?")
        if unit and unit not in UNITS and is_flow(unit):
            raise DataError(f"{option} {item!r}: {unit!r} is a flow (a volume per time), and no signal of a record is "
                            f"a flow (the signals: {expected_columns()}); leave the column unmapped (it is kept as an "
                            "extra signal, unchecked) or drop it")
        if unit and unit not in UNITS:
            raise DataError(f"{option} {item!r}: unknown unit {unit!r}; known units: {', '.join(UNITS)}")
        if (gain or offset) and name == TIME_COLUMN:
            raise DataError(f"{option} {item!r}: the time takes a unit (e.g. {option} t={column}:ms), not a gain "
                            "or an offset")
        for what, text in (("gain", gain), ("offset", offset)):
            if text:
                _quantity(text, f"{option} {item!r}: {what}")
        if name in names:
            raise DataError(f"{option} {item!r}: signal {name!r} is already mapped to column {names[name]!r}")
        if column in out:
            raise DataError(f"{option} {item!r}: column {column!r} is already mapped")
        names[name] = column
        out[column] = (name, unit, gain, offset) if (gain or offset) else (name, unit) if unit else name
    return out


def _quantity(text: str, what: str):
    """``text`` (``35.15N/V``, ``0.001``, ``-3.2N``) as a pint quantity; DataError naming ``what``."""
    import pint

    from fpdd.units import _registry

    m = re.fullmatch(rf"\s*({_NUMBER})\s*(.*?)\s*", text.replace("µ", "u").replace("²", "^2"))
    try:
        if m is None:
            raise ValueError(text)
        unit = m.group(2) or "dimensionless"
        return _registry().Quantity(float(m.group(1)), "degC" if unit in ("°C", "C") else unit)
    except (pint.errors.PintError, ValueError, TypeError, AttributeError, AssertionError):
        raise DataError(f"{what} {text!r}: expected a number, optionally with a unit (e.g. 35.15N/V, 0.001, "
                        "-3.2N)") from None


#: The SI units a mapped column may end in (what :data:`fpdd.units.SIGNALS` are kept in).
_SI_UNITS = ("m", "m/s", "Pa", "V", "N", "K", "s", "A", "kg", "m^3/s")


def scaling(file: str, column: str, name: str, unit: str | None, gain: str, offset: str,
            spec: SignalSpec | None) -> tuple[float, float, str]:
    """(factor, offset, SI unit) of a mapped column with a gain or an offset: the signal in SI is
    ``to_si(column, unit) * factor + offset`` (:func:`parse_mapping`).

    The gain's unit says what the column is in when ``unit`` does not: ``u=vir*35.15N/V`` reads
    ``vir`` in V (the gain's denominator) and gives newtons.  The result's dimension must be the
    signal's (``spec``: its SI unit and the units it accepts), the offset's too (a bare offset is in
    the signal's SI unit); else :class:`DataError` naming the file, the column and both units.
    """
    import pint

    from fpdd.units import _registry

    ureg = _registry()
    item = f"{file}: --map {name}={column}" + (f":{unit}" if unit else "") + (f"*{gain}" if gain else "") + offset
    g = _quantity(gain, f"{item}: gain") if gain else ureg.Quantity(1.0, "dimensionless")
    if unit:
        column_unit = ureg.Unit(si_unit(unit, what=item))
    else:  # the gain's denominator: the unit the gain expects the column in
        below = {u: -e for u, e in g.unit_items() if e < 0}
        column_unit = ureg.Unit("dimensionless")
        for u, e in below.items():
            column_unit = column_unit * ureg.Unit(u) ** e
    result = ureg.Quantity(float(g.magnitude), g.units * column_unit)
    if result.dimensionless and not unit and str(g.units) == "dimensionless":  # plain numbers: the signal's SI
        result = ureg.Quantity(float(g.magnitude), ureg.Unit(spec.unit if spec is not None else "dimensionless"))
    if spec is not None:
        candidates = [spec.unit, *(a for a in spec.accepts if a != "*")]
        if "*" in spec.accepts:
            candidates += [u for u in _SI_UNITS if u not in candidates]
    else:
        candidates = list(_SI_UNITS)
    target = None
    for cand in candidates:
        try:
            factor = float(result.to(ureg.Unit(cand)).magnitude)
        except pint.errors.DimensionalityError:
            continue
        target = cand
        break
    if target is None:
        if spec is None or "*" in spec.accepts:
            factor, target = float(result.to_base_units().magnitude), f"{result.to_base_units().units:~}"
        else:
            expected = " or ".join(candidates)
            given = f"{result.units:~}" if str(result.units) != "dimensionless" else "a plain number"
            raise DataError(f"{item}: gives {given}, but {name!r} is in {expected} (a gain's unit A/B reads "
                            f"the column in B and gives A)")
    off = 0.0
    if offset:
        q = _quantity(offset, f"{item}: offset")
        if str(q.units) == "dimensionless":
            off = float(q.magnitude)
        else:
            try:
                off = float(q.to(ureg.Unit(target)).magnitude)
            except pint.errors.DimensionalityError:
                raise DataError(f"{item}: the offset {offset} is not in a unit of {target} (the signal's unit)"
                                ) from None
    return factor, off, target


def parse_mapping(file: str, mapping: ColumnMap | None,
                  specs: Mapping[str, SignalSpec] | None = None) -> dict[str, tuple]:
    """Normalise ``mapping`` to ``{foreign column: (signal, unit or None[, factor, offset])}`` and check units.

    A unit must be dimensionally compatible with the signal (``specs``, default
    :data:`~fpdd.units.SIGNALS`): ``x`` takes mm, not bar; a generic signal (the
    oscillator's ``y``) takes any unit.  An entry with a gain or an offset (``(signal, unit, gain,
    offset)``, from :func:`parse_map`) becomes ``(signal, unit or None, factor, offset)``: the signal
    in SI is ``to_si(column, unit) * factor + offset`` (:func:`scaling`).
    """
    specs = SIGNALS if specs is None else specs
    out: dict[str, tuple] = {}
    for column, target in (mapping or {}).items():
        if isinstance(target, str):
            out[column] = (target, None)
            continue
        if isinstance(target, tuple) and len(target) == 4:
            name, unit, gain, offset = target
            spec = specs.get(name) or SIGNALS.get(name)
            factor, off, _ = scaling(file, column, name, unit or None, gain or "", offset or "", spec)
            out[column] = (name, unit or None, factor, off)
            continue
        try:
            name, unit = target
        except (TypeError, ValueError):
            raise DataError(f"{file}: mapping for column {column!r} is {target!r}, "
                            "expected a signal name or a (signal, unit) pair") from None
        si = si_unit(unit, what=f"{file}: mapping for column {column!r}")
        spec = specs.get(name) or SIGNALS.get(name)
        if name == TIME_COLUMN:
            ok, expected = si == "s", "s"
        elif spec is not None:
            ok = spec.takes(si)
            expected = " or ".join((spec.unit, *(a for a in spec.accepts if a != "*")))
        else:
            ok, expected = True, si
        if not ok:
            raise DataError(f"{file}: mapping {column!r} -> ({name!r}, {unit!r}): {unit} converts to {si}, "
                            f"but {name!r} is in {expected}")
        out[column] = (name, unit)
    return out


#: units a logged flow is written in (a flow is no signal of a record; pint is asked about any other unit)
FLOW_UNITS = ("l/min", "L/min", "lpm", "LPM", "l/s", "L/s", "m^3/s", "m3/s", "gpm", "cc/s", "ml/s", "ml/min", "cm^3/s")


def is_flow(unit: str) -> bool:
    """Whether ``unit`` is a unit of flow (volume per time): ``l/min``, ``lpm``, ``m^3/s``, ``gpm``, ..."""
    unit = unit.strip()
    if unit in FLOW_UNITS:
        return True
    try:
        from fpdd.units import _registry

        ureg = _registry()
        return bool(ureg.Unit(unit).dimensionality == ureg.Unit("m^3/s").dimensionality)
    except Exception:  # not a unit pint knows
        return False


def expected_columns() -> str:
    return ", ".join(f"{k} ({v.unit})" for k, v in SIGNALS.items())


def sniff_text(path: str, head: bytes, what: str = "CSV") -> str:
    """The encoding to read ``path`` with, from its first bytes; LogFormatError for what is not text.

    UTF-8 (with or without BOM) and ASCII are read; UTF-16/32, binary data (NUL bytes)
    and bytes that are not UTF-8 in the header line are refused with the byte offset.
    """
    for bom, name in ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"),
                      (b"\xff\xfe", "UTF-16"), (b"\xfe\xff", "UTF-16")):
        if head.startswith(bom):
            raise LogFormatError(f"{path}: {name} encoded text (byte order mark {bom.hex(' ')}); expected a UTF-8 "
                                 f"or ASCII {what} file: convert it, e.g. iconv -f {name} -t UTF-8 IN > OUT")
    nul = head.find(b"\x00")
    if nul >= 0:
        even = head[0:64:2].count(0) + head[1:64:2].count(0)
        kind = ("UTF-16 encoded text without byte order mark" if even >= 8 and len(set(head[1:64:2])) <= 2
                else "binary data")
        raise LogFormatError(f"{path}: {kind} (NUL byte at offset {nul}); expected a UTF-8 or ASCII {what} file")
    if head.startswith(b"\xef\xbb\xbf"):
        return "utf-8-sig"
    first_line = head.split(b"\n", 1)[0]
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        # a cut multi-byte character at the end of the sniffed bytes is fine
        bad_at = exc.start
        cut = bad_at >= len(head) - 4 and exc.reason == "unexpected end of data"
        n_bad = sum(1 for b in head if b >= 0x80) if not cut else 0
        if not cut and (bad_at <= len(first_line) or n_bad > max(16, len(head) // 100)):
            line = head[:bad_at].count(b"\n") + 1
            raise LogFormatError(f"{path}: not UTF-8 text: byte 0x{head[bad_at]:02x} at offset {bad_at} (line {line}) "
                                 f"cannot be decoded; expected a UTF-8 or ASCII {what} file") from None
    return "utf-8"


#: Words in a foreign column's name that say which signal it is (lower case; matched per word).
SYNONYMS: dict[str, tuple[str, ...]] = {
    TIME_COLUMN: ("t", "time", "timestamp", "zeit", "sec", "secs", "seconds", "elapsed", "timems", "time_ms"),
    "x_ref": ("ref", "xref", "demand", "dem", "setpoint", "sp", "cmd", "command", "target", "soll", "desired"),
    "x": ("x", "pos", "position", "disp", "displacement", "lvdt", "stroke", "ist", "actual"),
    "u": ("u", "valve", "servo", "sv", "drive", "volt", "voltage", "spool"),
    "pA": ("pa", "pressa", "p1"),
    "pB": ("pb", "pressb", "p2"),
    "F": ("f", "force", "load", "loadcell"),
    "T_oil": ("temp", "temperature", "toil", "oil"),
    "pP": ("ps", "pp", "supply", "psupply"),
    "y": ("y", "out", "output"),
}
UNIT_WORDS: dict[str, str] = {u.lower(): u for u in UNITS} | {"c": "degC", "degc": "degC", "sec": "s"}


def split_unit(column: str) -> tuple[str, str | None]:
    """``"x[mm]"``, ``"x (mm)"`` -> ``("x", "mm")``: a column name and the unit written in it, if any.

    Only a unit of :data:`fpdd.units.UNITS` counts; ``"pos[furlong]"`` -> ``("pos[furlong]", None)``.
    """
    m = UNIT_IN_NAME.match(column)
    if m:
        unit = UNIT_WORDS.get(m.group("unit").strip().lower())
        if unit is not None and m.group("name").strip():
            return m.group("name").strip(), unit
    return column, None


def guess(column: str) -> tuple[str | None, str | None]:
    """(signal, unit) a foreign column name suggests, e.g. ``"pos_mm"`` -> ``("x", "mm")``."""
    stem, unit = split_unit(column)
    words = [w for w in re.split(r"[^0-9a-zA-Z]+", stem.lower()) if w]
    if unit is None and len(words) > 1 and words[-1] in UNIT_WORDS:
        unit = UNIT_WORDS[words[-1]]
        words = words[:-1]
    si = UNITS[unit][2] if unit else None
    joined = "".join(words)
    for name, syn in SYNONYMS.items():
        if joined in syn or any(w in syn for w in words):
            want = "s" if name == TIME_COLUMN else SIGNALS[name].unit
            if si is None or si == want or (name != TIME_COLUMN and SIGNALS[name].takes(si)):
                return name, unit
    if si == "s":
        return TIME_COLUMN, unit
    return None, unit


def suggest_map(columns: Sequence[str], needed: Sequence[str]) -> str:
    """``--map`` items that map foreign ``columns`` onto the ``needed`` names, from the words and units
    in the column names (``time_ms`` -> ``t=time_ms:ms``, ``dem_mm`` -> ``x_ref=dem_mm:mm``);
    "" when no column name says what it is.  A column is suggested for one name only."""
    out: list[str] = []
    taken: set[str] = set()
    for column in columns[:MAX_COLUMNS]:
        name, unit = guess(column)
        if name is None or name in taken or name not in needed:
            continue
        taken.add(name)
        out.append("--map " + shlex.quote(f"{name}={column}" + (f":{unit}" if unit else "")))
    return " ".join(out)


def show_columns(columns: Sequence[str], limit: int = 12) -> str:
    shown = ", ".join(repr(c[:40] + ("..." if len(c) > 40 else "")) for c in columns[:limit])
    return shown + (f", ... ({len(columns)} columns)" if len(columns) > limit else "")

