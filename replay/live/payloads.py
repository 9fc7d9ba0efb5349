"""The two payloads of a live Zenoh stream, encoded and validated.

Zenoh payloads
==============

Two payloads travel on a key expression; a :class:`ZenohSource` accepts either
(it tells them apart by their first bytes) and keeps to the kind it saw first.

``fpdd.samples/1`` — JSON, one object per block of samples, encoding
``application/json``::

    {"format": "fpdd.samples/1", "t_ns": [1700000000000000000, ...],
     "signals": {"x": [0.0012, ...], "u": [...], ...}}

SI units (``fpdd.units.SIGNALS``), every list as long as ``t_ns``, ``t_ns`` integers
in the int64 range, ``null`` for a missing value (delivered as NaN: the tracker takes
it as a missing measurement).  A single sample is a block of one (scalars instead of
lists).  The end of a stream is ``{"format": "fpdd.samples/1", "end": true}``.

``fpdd.can/1`` — raw CAN frames, binary, encoding ``application/octet-stream``:
an 8-byte header ``b"FCAN"``, uint16 version (1), uint16 record size (24), then
little-endian records ``int64 t_ns, uint32 id (bit 31 set for 29-bit ids),
uint8 dlc, uint8 kind (0 data, 1 remote, 2 error), 2 pad bytes, 8 data bytes``.  A
header with no records ends the stream.  By convention the key is
``fpdd/<rig>/can``.  This is how CAN frames cross processes here (the ``virtual``
bus of python-can is in-process only); the receiving side decodes them with the DBC
exactly as a CAN log (:mod:`replay.can.logs`).

Zenoh sessions are opened from :func:`zenoh_config` (explicit endpoints, multicast
scouting optional) and closed on ``close()``; sources and sinks are context managers.
"""

from __future__ import annotations

import json
import math

import numpy as np

from replay.base import Samples
from replay.can.codec import Frames
from fpdd.errors import LogFormatError

SAMPLES_FORMAT = "fpdd.samples/1"
CAN_MAGIC = b"FCAN"
CAN_VERSION = 1
#: One raw CAN frame on Zenoh (``fpdd.can/1``).
CAN_RECORD = np.dtype([("t_ns", "<i8"), ("key", "<u4"), ("dlc", "u1"), ("kind", "u1"),
                       ("pad", "u1", (2,)), ("data", "u1", (8,))])
assert CAN_RECORD.itemsize == 24

#: Defaults of the validation limits (:mod:`replay.live.watch`).
MAX_PAYLOAD_BYTES = 8 << 20
MAX_BLOCK = 100_000
MAX_QUEUE = 256
MAX_FRAMES_PER_S = 20_000  # a classic CAN bus at 1 Mbit/s carries at most about 9 000 frames/s
INT64 = (-(1 << 63), (1 << 63) - 1)


# --- payloads ------------------------------------------------------------------------------------

class PayloadError(LogFormatError):
    """A live payload that cannot be used; ``cause`` is the drop cause it is counted under."""

    def __init__(self, cause: str, message: str) -> None:
        super().__init__(message)
        self.cause = cause


def samples_to_json(samples: Samples) -> bytes:
    """``fpdd.samples/1`` payload of a block (NaN -> null)."""
    sig = {}
    for k, v in samples.signals.items():
        lst = v.tolist()
        if not np.isfinite(v).all():
            lst = [x if np.isfinite(x) else None for x in lst]
        sig[k] = lst
    return json.dumps({"format": SAMPLES_FORMAT, "t_ns": samples.t_ns.tolist(), "signals": sig},
                      separators=(",", ":")).encode()


_EXPECTED = (f'expected {{"format": "{SAMPLES_FORMAT}", "t_ns": [int ns, ...], '
             '"signals": {"name": [number or null, ...], ...}}')


def _times(where: str, t) -> np.ndarray:
    arr = np.array(t)
    if arr.dtype == np.int64 and arr.ndim == 1:
        return arr
    for i, x in enumerate(t):
        if type(x) is not int:
            raise PayloadError("bad_time", f"{where}: t_ns[{i}] = {x!r} is a {type(x).__name__}, "
                                           "expected an integer number of ns")
        if not INT64[0] <= x <= INT64[1]:
            raise PayloadError("bad_time", f"{where}: t_ns[{i}] = {x} is beyond the int64 range of ns "
                                           f"[{INT64[0]}, {INT64[1]}]")
    raise PayloadError("bad_time", f"{where}: t_ns is not a list of integers")


def json_to_samples(payload: bytes, where: str, max_block: int = MAX_BLOCK) -> tuple[Samples, np.ndarray] | None:
    """Samples of an ``fpdd.samples/1`` payload and the mask of non-finite (not null) values.

    None for the end marker; :class:`PayloadError` (with its drop ``cause``) if malformed.
    """
    try:
        obj = json.loads(payload)
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise PayloadError("bad_json", f"{where}: payload is not JSON ({str(e)[:80]}); {_EXPECTED}") from None
    if not isinstance(obj, dict):
        raise PayloadError("bad_schema", f"{where}: JSON {type(obj).__name__}, not an object; {_EXPECTED}")
    if obj.get("format") != SAMPLES_FORMAT:
        raise PayloadError("bad_schema", f"{where}: \"format\" is {obj.get('format')!r}, expected "
                                         f"\"{SAMPLES_FORMAT}\"; {_EXPECTED}")
    if obj.get("end") is True:
        return None
    t = obj.get("t_ns")
    sig = obj.get("signals")
    if not isinstance(sig, dict) or not sig or not all(isinstance(k, str) for k in sig):
        raise PayloadError("bad_schema", f"{where}: \"signals\" is {type(sig).__name__}"
                                         f"{' (empty)' if isinstance(sig, dict) else ''}, expected an object of "
                                         f"signal name -> list of values; {_EXPECTED}")
    if isinstance(t, int) and not isinstance(t, bool):  # a single sample: scalars
        t = [t]
        if any(isinstance(v, list) for v in sig.values()):
            raise PayloadError("bad_schema", f"{where}: scalar \"t_ns\" with list signals; {_EXPECTED}")
        sig = {k: [v] for k, v in sig.items()}
    if not isinstance(t, list):
        raise PayloadError("bad_time" if isinstance(t, (float, bool, str)) else "bad_schema",
                           f"{where}: \"t_ns\" is {t!r:.40}, expected an integer or a list of integers (ns)")
    if len(t) > max_block:
        raise PayloadError("oversized", f"{where}: {len(t)} samples in one payload, at most {max_block} accepted")
    t_ns = _times(where, t) if t else np.zeros(0, np.int64)
    cols: dict[str, np.ndarray] = {}
    bad = np.zeros(len(t_ns), dtype=bool)
    for k, v in sig.items():
        if not isinstance(v, list) or len(v) != len(t_ns):
            raise PayloadError("bad_schema", f"{where}: signal {k!r} is "
                                             + (f"a list of {len(v)}" if isinstance(v, list) else type(v).__name__)
                                             + f", expected a list as long as t_ns ({len(t_ns)})")
        none = [x is None for x in v]
        arr = np.array([math.nan if n else x for n, x in zip(none, v)])
        if arr.size and arr.dtype.kind not in "fi":
            i = next(j for j, x in enumerate(v) if x is not None and (type(x) not in (int, float)))
            raise PayloadError("bad_schema", f"{where}: signal {k!r}[{i}] = {v[i]!r:.40} is not a number; "
                                             "expected numbers or null")
        arr = arr.astype(np.float64)
        bad |= ~np.isfinite(arr) & ~np.array(none, dtype=bool)
        cols[k] = arr
    return Samples(t_ns, cols), bad


def frames_to_payload(frames: Frames) -> bytes:
    """``fpdd.can/1`` payload of a frame block (an empty block is the end marker)."""
    rec = np.zeros(len(frames), CAN_RECORD)
    rec["t_ns"] = frames.t_ns
    rec["key"] = frames.key
    rec["dlc"] = frames.dlc
    rec["kind"] = frames.kind
    rec["data"] = frames.data
    head = CAN_MAGIC + np.array([CAN_VERSION, CAN_RECORD.itemsize], "<u2").tobytes()
    return head + rec.tobytes()


def payload_to_frames(payload: bytes, where: str) -> Frames:
    """Frames of an ``fpdd.can/1`` payload; :class:`PayloadError` (``bad_payload``) if malformed."""
    if len(payload) < 8 or payload[:4] != CAN_MAGIC:
        raise PayloadError("bad_payload", f"{where}: not an fpdd.can payload (expected header {CAN_MAGIC!r})")
    ver, size = np.frombuffer(payload[4:8], "<u2")
    if ver != CAN_VERSION or size != CAN_RECORD.itemsize or (len(payload) - 8) % size:
        raise PayloadError("bad_payload", f"{where}: fpdd.can version {ver}, record size {size}, "
                                          f"{len(payload) - 8} bytes of records; expected version {CAN_VERSION}, "
                                          f"records of {CAN_RECORD.itemsize} bytes")
    rec = np.frombuffer(payload[8:], CAN_RECORD)
    if (rec["dlc"] > 8).any() or (rec["kind"] > 3).any():
        raise PayloadError("bad_payload", f"{where}: fpdd.can record with DLC > 8 or unknown kind")
    return Frames(rec["t_ns"], rec["key"], rec["dlc"], rec["data"], rec["kind"])


# --- what live sources share: drop counting, rate-limited logging, staleness ---------------------
