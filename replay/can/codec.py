"""The MSP25 rig's CAN database and a vectorised decoder/encoder driven by it.

The MSP25 DBC (``replay/data/msp25.dbc``)
=========================================

Classic CAN at 1 Mbit/s, 11-bit identifiers, four messages (about 2 600 frames/s,
roughly 25 % bus load)::

    id     name            rate    DLC  byte order  signals (bit start|length, scale, DBC unit -> SI)
    0x100  MSP25_Position  1 kHz   8    Intel       x      0|32 signed   0.1 um/bit -> m
                                                    x_ref 32|32 signed   0.1 um/bit -> m
    0x101  MSP25_Valve     1 kHz   4    Intel       u      0|16 signed   0.5 mV/bit -> V
                                                    RollCnt 16|8 rolling counter (mod 256)
                                                    CtrlMode 24|8 (Idle/Position/Force/Fault)
    0x120  MSP25_Pressure  500 Hz  5    Intel       pA     0|16 unsigned 1 kPa/bit  -> Pa
                                                    pB    16|16 unsigned 1 kPa/bit  -> Pa
                                                    RollCnt 32|8 rolling counter (mod 256)
    0x3A0  HPU_Status      10 Hz   8    Motorola    pP     7|16 unsigned 1 kPa/bit  -> Pa
                                                    T_oil 23|16 signed   0.1 degC/bit -> K
                                                    HPU_State 39|8
                                                    RollCnt 51|4 rolling counter (mod 16)

The controller sends ``MSP25_Position`` and then ``MSP25_Valve`` in every 1 ms
control cycle, ``MSP25_Pressure`` every second cycle; the hydraulic power unit's PLC
sends ``HPU_Status`` (big-endian, as PLCs do) every 100 ms.  The signal attribute
``RigSignal`` maps a CAN signal onto an fpdd-twin signal name of
:data:`fpdd.units.SIGNALS` (``"counter"`` marks a rolling counter); without the
attribute a CAN signal whose name is a rig signal name maps onto it.  A DBC of other
names needs neither: a column map (``--map x=MyPosSignal:mm``, :func:`replay.csvio.parse_map`,
the ``mapping`` of :class:`VectorCodec`) maps its signals onto the rig's as a CSV's columns, with
the unit the signal is in (where the DBC gives none, or to override it), a gain and an offset
(``--map u=ValveCmd*0.001``); a mapped rig signal is taken from the mapped CAN signal only.  The message
attribute ``GenMsgCycleTime`` (ms) gives the nominal period used for alignment.
Values in the DBC are in the units the rig reports; :data:`UNIT_TO_SI` converts them.

The vectorised codec
====================

:class:`VectorCodec` reads every signal's start bit, length, byte order,
signedness, scale and offset from the DBC and decodes a whole block of frames of one
message id in a handful of numpy operations: the 8 data bytes are viewed as one
little-endian (Intel signals) or big-endian (Motorola signals) 64-bit word, shifted
and masked, sign-extended, then scaled.  The physical values are bit-identical to
``cantools``' ``Message.decode(data, decode_choices=False)`` (the same IEEE
operations ``raw * scale + offset``).  Multiplexed messages fall back to a per-frame
``cantools`` decode.  Classic CAN only (messages of at most 8 bytes).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from collections.abc import Mapping
from typing import cast

import cantools
import cantools.database
import numpy as np

from fpdd.units import SIGNALS, UNITS
from fpdd.errors import LogFormatError, SourceError

#: The DBC shipped for the MSP25 rig.
DEFAULT_DBC: Path = Path(__file__).parent.parent / "data" / "msp25.dbc"

#: DBC unit -> (factor, offset) so that ``si = value * factor + offset``, and the SI unit.
#: DBC units and their conversion to SI: the one unit table of :mod:`replay.quality`.
UNIT_TO_SI = UNITS

#: SocketCAN's flag for 29-bit identifiers; frame keys are ``id | EFF_FLAG`` when extended.
EFF_FLAG = 0x8000_0000

#: RigSignal attribute value that marks a rolling counter.
COUNTER = "counter"


def frame_key(arbitration_id: int, is_extended: bool) -> int:
    """The key under which a frame id is looked up (29-bit ids carry :data:`EFF_FLAG`)."""
    return int(arbitration_id) | (EFF_FLAG if is_extended else 0)


def key_str(key: int) -> str:
    """A frame key as written in logs: ``0x100`` or ``0x18FF0001x`` for extended ids."""
    if key & EFF_FLAG:
        return f"0x{key & 0x1FFF_FFFF:08X}x"
    return f"0x{key:03X}"


def load_dbc(path: str | Path | None = None) -> cantools.database.can.Database:
    """Load a DBC (default: the MSP25 one) with cantools, with errors that name the file."""
    p = Path(path) if path is not None else DEFAULT_DBC
    try:
        db = cantools.database.load_file(str(p), database_format="dbc", strict=True)
    except FileNotFoundError as e:
        raise SourceError(f"{p}: DBC file not found") from e
    except OSError as e:
        raise SourceError(f"{p}: cannot read DBC file: {e}") from e
    except Exception as e:  # cantools raises its own ParseError/UnsupportedDatabaseFormatError
        raise LogFormatError(f"{p}: not a valid DBC file: {e}") from e
    if not isinstance(db, cantools.database.can.Database):
        raise LogFormatError(f"{p}: expected a CAN database (DBC)")
    return db


# --- frames ---------------------------------------------------------------------------------

@dataclasses.dataclass
class Frames:
    """A block of CAN frames, columnar.

    ``t_ns`` int64 (n,) timestamps in ns; ``key`` uint32 (n,) arbitration id, with
    :data:`EFF_FLAG` set for 29-bit ids; ``dlc`` uint8 (n,) data length in bytes;
    ``data`` uint8 (n, 8) payload, zero padded; ``kind`` uint8 (n,): 0 data frame,
    1 remote frame, 2 error frame, 3 CAN FD frame longer than 8 bytes (payload cut).
    """

    t_ns: np.ndarray
    key: np.ndarray
    dlc: np.ndarray
    data: np.ndarray
    kind: np.ndarray

    DATA = 0
    REMOTE = 1
    ERROR = 2
    LONG_FD = 3

    def __post_init__(self) -> None:
        self.t_ns = np.asarray(self.t_ns, dtype=np.int64)
        n = self.t_ns.shape[0]
        self.key = np.asarray(self.key, dtype=np.uint32).reshape(n)
        self.dlc = np.asarray(self.dlc, dtype=np.uint8).reshape(n)
        self.data = np.ascontiguousarray(self.data, dtype=np.uint8).reshape(n, 8)
        self.kind = np.asarray(self.kind, dtype=np.uint8).reshape(n)

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @staticmethod
    def empty() -> Frames:
        return Frames(np.zeros(0, np.int64), np.zeros(0, np.uint32), np.zeros(0, np.uint8),
                      np.zeros((0, 8), np.uint8), np.zeros(0, np.uint8))

    def take(self, idx: np.ndarray | slice) -> Frames:
        return Frames(self.t_ns[idx], self.key[idx], self.dlc[idx], self.data[idx], self.kind[idx])

    @staticmethod
    def concat(blocks: list[Frames]) -> Frames:
        blocks = [b for b in blocks if len(b)]
        if not blocks:
            return Frames.empty()
        if len(blocks) == 1:
            return blocks[0]
        return Frames(*(np.concatenate([getattr(b, f) for b in blocks])
                        for f in ("t_ns", "key", "dlc", "data", "kind")))


class FrameCollector:
    """Collects python-can :class:`can.Message` objects into :class:`Frames` blocks.

    The per-frame work is the minimum (a few attribute reads and list appends); the
    conversion to arrays happens once per block.
    """

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self._t: list[float] = []
        self._key: list[int] = []
        self._dlc: list[int] = []
        self._data: list[bytes] = []
        self._kind: list[int] = []

    def __len__(self) -> int:
        return len(self._t)

    def add(self, msg) -> None:  # msg: can.Message
        """Append one python-can message (timestamp in s)."""
        data = bytes(msg.data) if msg.data is not None else b""
        kind = Frames.DATA
        if msg.is_error_frame:
            kind = Frames.ERROR
        elif msg.is_remote_frame:
            kind = Frames.REMOTE
        elif len(data) > 8:
            kind = Frames.LONG_FD
        self._t.append(msg.timestamp)
        self._key.append(msg.arbitration_id | (EFF_FLAG if msg.is_extended_id else 0))
        # the DLC that counts is the number of data bytes actually present
        self._dlc.append(min(len(data), 255) if kind != Frames.REMOTE else msg.dlc)
        self._data.append(data[:8].ljust(8, b"\0"))
        self._kind.append(kind)

    def take(self) -> Frames:
        """The collected frames as a block (timestamps rounded to whole microseconds)."""
        n = len(self._t)
        if n == 0:
            return Frames.empty()
        t_s = np.asarray(self._t, dtype=np.float64)
        # every CAN log format here stores microseconds at best: round there, in ns
        t_ns = np.round(t_s * 1e6).astype(np.int64) * 1000
        out = Frames(t_ns, np.asarray(self._key, np.uint32), np.asarray(self._dlc, np.uint8),
                     np.frombuffer(b"".join(self._data), np.uint8).reshape(n, 8),
                     np.asarray(self._kind, np.uint8))
        self.clear()
        return out


# --- signal and message layouts ----------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class SignalLayout:
    """Where a signal sits in the frame and how it scales (from the DBC).

    ``shift`` is the position of the signal's least significant bit in the 64-bit
    word the frame is read as (little-endian word for Intel signals, big-endian word
    for Motorola signals).  ``rig`` is the fpdd-twin signal name (or ``"counter"``,
    or ``None`` when the signal is not used); ``si_factor``/``si_offset`` convert the
    DBC unit to SI.
    """

    name: str
    rig: str | None
    shift: int
    length: int
    big_endian: bool
    signed: bool
    is_float: bool
    scale: float
    offset: float
    minimum: float | None
    maximum: float | None
    unit: str
    si_factor: float
    si_offset: float

    @property
    def mask(self) -> int:
        return (1 << self.length) - 1


@dataclasses.dataclass(frozen=True)
class MessageLayout:
    """A DBC message as the codec uses it. ``period_s`` from GenMsgCycleTime (None if absent)."""

    key: int
    name: str
    length: int
    period_s: float | None
    signals: tuple[SignalLayout, ...]
    multiplexed: bool

    @property
    def rig_signals(self) -> dict[str, SignalLayout]:
        """Signals mapped onto rig signal names, by rig name."""
        return {s.rig: s for s in self.signals if s.rig is not None and s.rig != COUNTER}

    @property
    def counter(self) -> SignalLayout | None:
        for s in self.signals:
            if s.rig == COUNTER:
                return s
        return None

    @property
    def label(self) -> str:
        return f"{key_str(self.key)} {self.name}"


def _rig_name(sig, source: str, mapping: Mapping[str, tuple] | None = None) -> str | None:
    if mapping:
        if sig.name in mapping:
            return mapping[sig.name][0]
        taken = {m[0] for m in mapping.values()}
        name = _rig_name(sig, source)
        return None if name in taken else name  # a mapped rig signal comes from its mapped CAN signal only
    attr = None
    if sig.dbc is not None and "RigSignal" in sig.dbc.attributes:
        attr = sig.dbc.attributes["RigSignal"].value
    if attr:
        if attr != COUNTER and attr not in SIGNALS:
            raise LogFormatError(
                f"{source}: signal {sig.name!r}: RigSignal {attr!r} is not a known signal "
                f"(expected one of {sorted(SIGNALS)} or {COUNTER!r})")
        return attr
    return sig.name if sig.name in SIGNALS else None


def _signal_layout(sig, rig: str | None, source: str, msg_name: str, mapped: tuple | None = None) -> SignalLayout:
    if sig.byte_order == "little_endian":
        shift, big = sig.start, False
    else:
        byte, bit = divmod(sig.start, 8)
        msb = (7 - byte) * 8 + bit  # bit index of the MSB in the big-endian 64-bit word
        shift, big = msb - sig.length + 1, True
    if shift < 0 or shift + sig.length > 64:
        raise LogFormatError(f"{source}: message {msg_name}: signal {sig.name!r} does not fit in 8 bytes")
    unit = (mapped[1] if mapped is not None and mapped[1] else None) or sig.unit or ""
    si_factor, si_offset = 1.0, 0.0
    if mapped is not None and len(mapped) == 4:  # a gain and an offset (checked against the signal's unit)
        factor, offset = mapped[2], mapped[3]
        if mapped[1]:
            f_u, o_u, _ = UNIT_TO_SI[mapped[1]]
            si_factor, si_offset = f_u * factor, o_u * factor + offset
        else:  # the DBC's value as the gain reads it
            si_factor, si_offset = factor, offset
    elif rig is not None and rig != COUNTER:
        want = SIGNALS[rig].unit
        hint = f"; give its unit with --map {rig}={sig.name}:UNIT" if not unit or unit not in UNIT_TO_SI else ""
        if unit not in UNIT_TO_SI:
            raise LogFormatError(
                f"{source}: message {msg_name}: signal {sig.name!r} (-> {rig}) has unit {unit!r}; "
                f"expected one convertible to {want!r} (known: {', '.join(UNIT_TO_SI)}){hint}")
        si_factor, si_offset, si_unit = UNIT_TO_SI[unit]
        if si_unit != want:
            raise LogFormatError(
                f"{source}: message {msg_name}: signal {sig.name!r} (-> {rig}) has unit {unit!r} "
                f"= {si_unit}, but {rig} is in {want}")
    return SignalLayout(sig.name, rig, shift, sig.length, big, bool(sig.is_signed), bool(sig.is_float),
                        float(sig.scale), float(sig.offset), sig.minimum, sig.maximum, unit,
                        si_factor, si_offset)


def check_mapping(db: cantools.database.can.Database, source: str, mapping) -> dict[str, tuple]:
    """A column map of CAN signals (:func:`replay.csvio.parse_map`'s form) normalised and checked against
    ``db``: every mapped name a signal of the DBC, every target a rig signal, the units fitting it."""
    from fpdd.errors import DataError
    from replay.csvio.columns import parse_mapping

    mapped = parse_mapping(source, mapping, SIGNALS)
    have = sorted({sg.name for m in db.messages for sg in m.signals})
    for name, target in mapped.items():
        if name not in have:
            raise DataError(f"{source}: --map {target[0]}={name}: no signal {name!r} in the DBC; its signals: "
                            f"{', '.join(have) or 'none'}")
        if target[0] not in SIGNALS:
            raise DataError(f"{source}: --map {target[0]}={name}: {target[0]!r} is not a rig signal; CAN signals map "
                            f"onto {', '.join(SIGNALS)}")
    return mapped


def message_layouts(db: cantools.database.can.Database, source: str = "DBC",
                    mapping=None) -> dict[int, MessageLayout]:
    """Layouts of every message of ``db``, by frame key; ``mapping``: CAN signal -> rig signal
    (:func:`check_mapping`), before the ``RigSignal`` attribute and the names."""
    mapped = check_mapping(db, source, mapping) if mapping else {}
    out: dict[int, MessageLayout] = {}
    for m in db.messages:
        if m.length > 8:
            raise LogFormatError(
                f"{source}: message {m.name} has length {m.length}; the codec supports classic CAN (<= 8 bytes)")
        sigs = []
        seen: dict[str, str] = {}
        for s in m.signals:
            rig = _rig_name(s, source, mapped)
            if rig is not None and rig != COUNTER:
                if rig in seen:
                    raise LogFormatError(f"{source}: message {m.name}: signals {seen[rig]!r} and {s.name!r} "
                                         f"both map to {rig!r}")
                seen[rig] = s.name
            sigs.append(_signal_layout(s, rig, source, m.name, mapped.get(s.name)))
        period = m.cycle_time / 1000.0 if m.cycle_time else None
        key = frame_key(m.frame_id, m.is_extended_frame)
        out[key] = MessageLayout(key, m.name, m.length, period, tuple(sigs), m.is_multiplexed())
    rigs: dict[str, str] = {}
    for lay in out.values():
        for r in lay.rig_signals:
            if r in rigs:
                raise LogFormatError(f"{source}: rig signal {r!r} is carried by both {rigs[r]} and {lay.name}")
            rigs[r] = lay.name
    return out


# --- the codec -------------------------------------------------------------------------------

_SIGN_TYPES = {32: (np.uint32, np.float32), 64: (np.uint64, np.float64)}


class VectorCodec:
    """Decode and encode blocks of frames of one message id at a time, from a DBC.

    ``decode_raw(key, data)`` returns, for every signal of the message, the physical
    value in the DBC unit (float64, what ``cantools`` returns with
    ``decode_choices=False``; the rig signals in SI come from each signal's ``si_factor`` and
    ``si_offset``).  ``encode(key, values)`` is the inverse (DBC units in, (n, 8) bytes out).
    """

    def __init__(self, db: cantools.database.can.Database | str | Path | None = None, *, mapping=None) -> None:
        source = "DBC"
        if db is None or isinstance(db, (str, Path)):
            source = str(db if db is not None else DEFAULT_DBC)
            db = load_dbc(db)
        self.db = db
        self.source = source
        self.mapping = mapping
        self.messages: dict[int, MessageLayout] = message_layouts(db, source, mapping)
        self.keys = np.array(sorted(self.messages), dtype=np.uint32)
        self._cantools = {frame_key(m.frame_id, m.is_extended_frame): m for m in db.messages}

    # -- lookup
    def message_of(self, rig: str) -> MessageLayout | None:
        """The message carrying rig signal ``rig`` (None if no message does)."""
        for lay in self.messages.values():
            if rig in lay.rig_signals:
                return lay
        return None

    @property
    def rig_signals(self) -> tuple[str, ...]:
        """Every rig signal the DBC carries, in SIGNALS order."""
        have = {r for lay in self.messages.values() for r in lay.rig_signals}
        return tuple(s for s in SIGNALS if s in have)

    def describe_lookup(self) -> str:
        """What a rig signal is looked for as, and what the DBC has: for an error that finds none."""
        sigs = [f"{sg.name} ({sg.unit or 'no unit'}, in {m.name})" for m in self.db.messages for sg in m.signals]
        shown = ", ".join(sigs[:24]) + (f", ... ({len(sigs)} in all)" if len(sigs) > 24 else "")
        return (f"looked for CAN signals named as a rig signal ({', '.join(SIGNALS)}), with a RigSignal attribute"
                + (", or mapped with --map" if self.mapping else "")
                + f"; the DBC {self.source} has {shown or 'no signals'}; map them with --map NAME=SIGNAL[:UNIT], "
                "e.g. --map x=" + (self.db.messages[0].signals[0].name if self.db.messages and
                                   self.db.messages[0].signals else "MyPosSignal") + ":mm")

    # -- decode
    @staticmethod
    def _words(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        data = np.ascontiguousarray(data, dtype=np.uint8)
        return data.view("<u8").reshape(-1), data.view(">u8").reshape(-1)

    @staticmethod
    def _raw(sig: SignalLayout, le: np.ndarray, be: np.ndarray) -> np.ndarray:
        word = be if sig.big_endian else le
        raw = word >> np.uint64(sig.shift)
        if sig.length < 64:
            raw = raw & np.uint64(sig.mask)
        if sig.is_float:
            utype, ftype = _SIGN_TYPES[sig.length]
            with np.errstate(invalid="ignore"):  # signalling NaN bit patterns are data too
                return raw.astype(utype).view(ftype).astype(np.float64)
        if sig.signed:
            if sig.length == 64:
                return raw.view(np.int64).astype(np.float64)
            sign = np.int64(1 << (sig.length - 1))
            r = raw.astype(np.int64)
            return ((r ^ sign) - sign).astype(np.float64)
        return raw.astype(np.float64)

    def decode_raw(self, key: int, data: np.ndarray) -> dict[str, np.ndarray]:
        """Physical values in DBC units of every signal of message ``key`` for ``data`` (n, 8)."""
        lay = self.messages[int(key)]
        if lay.multiplexed:
            return self._decode_cantools(lay, data)
        le, be = self._words(data)
        out = {}
        for s in lay.signals:
            raw = self._raw(s, le, be)
            out[s.name] = raw if (s.is_float or (s.scale == 1.0 and s.offset == 0.0)) else raw * s.scale + s.offset
        return out

    def _decode_cantools(self, lay: MessageLayout, data: np.ndarray) -> dict[str, np.ndarray]:
        msg = self._cantools[lay.key]
        out = {s.name: np.full(len(data), np.nan) for s in lay.signals}
        for i, row in enumerate(np.asarray(data, np.uint8)):
            # decode_choices=False: a plain mapping of numbers
            decoded = cast(dict[str, float], msg.decode(bytes(row[: lay.length]), decode_choices=False))
            for k, v in decoded.items():
                out[k][i] = float(v)
        return out

    def out_of_range(self, key: int, phys: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Boolean masks of values outside the DBC's [minimum, maximum] (DBC units), per signal."""
        lay = self.messages[int(key)]
        out = {}
        for s in lay.signals:
            v = phys[s.name]
            bad = ~np.isfinite(v)
            if s.minimum is not None:
                bad |= v < s.minimum
            if s.maximum is not None:
                bad |= v > s.maximum
            if bad.any():
                out[s.name] = bad
        return out

    # -- encode
    def encode(self, key: int, values: Mapping[str, np.ndarray], n: int | None = None) -> np.ndarray:
        """Frames (n, 8) uint8 of message ``key`` from physical values in DBC units.

        Signals missing from ``values`` are encoded as raw 0.  Raises
        :class:`~fpdd.errors.DataError` (naming signal and row) for a value that is not
        finite, outside the DBC's [minimum, maximum] or does not fit the bit field.
        """
        from fpdd.errors import DataError

        lay = self.messages[int(key)]
        if lay.multiplexed:
            raise DataError(f"{self.source}: message {lay.name} is multiplexed; encoding it is not supported")
        if n is None:
            n = len(next(iter(values.values())))
        le = np.zeros(n, np.uint64)
        be = np.zeros(n, np.uint64)
        for s in lay.signals:
            if s.name not in values:
                continue
            v = np.asarray(values[s.name], dtype=np.float64).reshape(n)
            bad = ~np.isfinite(v)
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise DataError(f"{self.source}: message {lay.name}: signal {s.name!r} row {i}: "
                                f"value {v[i]} is not finite")
            out_lo = (v < s.minimum) if s.minimum is not None else np.zeros(n, bool)
            out_hi = (v > s.maximum) if s.maximum is not None else np.zeros(n, bool)
            if (out_lo | out_hi).any():
                i = int(np.flatnonzero(out_lo | out_hi)[0])
                raise DataError(f"{self.source}: message {lay.name}: signal {s.name!r} row {i}: value {v[i]:g} "
                                f"{s.unit} outside the DBC range [{s.minimum:g}, {s.maximum:g}]")
            if s.is_float:
                utype, ftype = _SIGN_TYPES[s.length]
                raw_u = v.astype(ftype).view(utype).astype(np.uint64)
            else:
                raw = np.round((v - s.offset) / s.scale)
                lo, hi = ((-(1 << (s.length - 1)), (1 << (s.length - 1)) - 1) if s.signed
                          else (0, (1 << s.length) - 1))
                bad = (raw < lo) | (raw > hi)
                if bad.any():
                    i = int(np.flatnonzero(bad)[0])
                    raise DataError(
                        f"{self.source}: message {lay.name}: signal {s.name!r} row {i}: value {v[i]} {s.unit} "
                        f"does not fit {s.length} bits (raw {lo}..{hi} at scale {s.scale}, offset {s.offset})")
                raw_u = raw.astype(np.int64).view(np.uint64)
                if s.length < 64:
                    raw_u = raw_u & np.uint64(s.mask)
            if s.big_endian:
                be |= raw_u << np.uint64(s.shift)
            else:
                le |= raw_u << np.uint64(s.shift)
        out = le.astype("<u8").view(np.uint8).reshape(n, 8).copy()
        out |= be.astype(">u8").view(np.uint8).reshape(n, 8)
        return out

    def encode_rig(self, key: int, rig_values: Mapping[str, np.ndarray], n: int,
                   extra: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Frames of message ``key`` from rig signals in SI units (+ raw DBC-unit ``extra`` by CAN name)."""
        lay = self.messages[int(key)]
        vals: dict[str, np.ndarray] = dict(extra or {})
        for s in lay.signals:
            if s.rig is not None and s.rig != COUNTER and s.rig in rig_values:
                vals[s.name] = (np.asarray(rig_values[s.rig], np.float64) - s.si_offset) / s.si_factor
        return self.encode(key, vals, n)
