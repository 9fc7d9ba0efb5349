"""A rig's checkpoint as a file: data only (:func:`encode_state`, :func:`read_checkpoints`), a versioned JSON
document of numbers, strings, lists and numeric arrays (raw little-endian bytes in base64, bit for bit); nothing
in it is ever executed. A checkpoint of an unknown format or version, or a damaged one, is refused with one line
naming the file. The runner's side (when to take one, how to resume) is :mod:`twin.service.checkpoints`.

Integrity (version 2): the body carries, per rig, what the checkpoint resumes from (the journal's epoch of the
rig's alarm numbering, the source's URI and, for a file, its length) and is sealed by an HMAC-SHA256 under the
journal's own random key (:attr:`twin.service.store.Store.secret`, made with the journal, kept inside it). A
bare digest can be recomputed by anyone who edits the file; the HMAC cannot without the journal, and the
journal it names must be the one beside it. Version 1 (a bare SHA-256) is read only beside a journal of an
earlier version (one that had no key yet), once: the next checkpoint is written as version 2."""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from fpdd.errors import LogFormatError, SourceError

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "Checkpoint", "checkpoint_path", "decode_state",
           "encode_state", "read_checkpoints", "source_identity", "write_checkpoints"]


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """A rig's saved state (plain data, see :func:`encode_state`) and where in its input it was taken."""

    rig: str
    t_ns: int
    """Time of the last sample processed (resume after it)."""
    samples: int
    fingerprint: str
    """What the state was computed under (rig configuration); a mismatch invalidates it."""
    state: dict[str, Any]
    saved_at: float
    """Wall-clock time of the save [s since the epoch]."""
    alarm_seq: int = 0
    """The rig's last alarm number in the journal when the checkpoint was taken."""
    journal_id: str = ""
    """The id of the journal those alarms are in."""
    epoch: str = ""
    """The journal's epoch of the rig's alarm numbering when it was taken (:mod:`twin.service.store`)."""
    source: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    """What it resumes from: ``{"uri"}`` and, for a file, ``"bytes"`` (its length then)."""



CHECKPOINT_FORMAT = "fpdd-twin checkpoint"
#: The checkpoint documents this program reads and writes.
CHECKPOINT_VERSION = 2
#: The earlier version, read beside a journal of an earlier version only (see the module docstring).
LEGACY_VERSION = 1
_ARRAY_DTYPES = {"float64": "<f8", "int64": "<i8", "bool": "|b1"}
_SPECIAL_FLOATS = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


def checkpoint_path(journal: str | os.PathLike[str]) -> Path:
    """Where the checkpoints of a journal's rigs are kept: ``<journal stem>.checkpoint.json`` beside it."""
    p = Path(journal)
    return p.with_name(p.stem + ".checkpoint.json")


def encode_state(value: Any, where: str = "state") -> Any:
    """Plain data as JSON values: ``None``, bools, ints, strings, floats (non-finite ones as ``{"$float": "nan"}``),
    lists and tuples (as lists), dicts with string keys, numpy arrays of float64, int64 or bool (``{"$array":
    {"dtype", "shape", "data"}}``, raw little-endian bytes in base64: bit for bit).

    :raises TypeError: anything else (naming where in the state), so that only data is ever saved.
    """
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)) and not isinstance(value, np.bool_):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else {"$float": "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")}
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        name = value.dtype.name
        if name not in _ARRAY_DTYPES:
            raise TypeError(f"{where}: an array of {value.dtype} cannot be saved in a checkpoint "
                            f"(only {', '.join(_ARRAY_DTYPES)})")
        raw = np.ascontiguousarray(value, dtype=np.dtype(_ARRAY_DTYPES[name])).tobytes()
        return {"$array": {"dtype": name, "shape": list(value.shape), "data": base64.b64encode(raw).decode("ascii")}}
    if isinstance(value, (list, tuple)):
        return [encode_state(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str) or k.startswith("$"):
                raise TypeError(f"{where}: key {k!r} (keys are strings not starting with '$')")
            out[k] = encode_state(v, f"{where}.{k}")
        return out
    raise TypeError(f"{where}: a {type(value).__name__} cannot be saved in a checkpoint (data only)")


def decode_state(value: Any, where: str = "state") -> Any:
    """The inverse of :func:`encode_state`; raises ValueError naming where the document is not plain state."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, list):
        return [decode_state(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if not isinstance(value, dict):
        raise ValueError(f"{where}: unexpected {type(value).__name__}")
    if "$float" in value:
        if len(value) != 1 or value["$float"] not in _SPECIAL_FLOATS:
            raise ValueError(f"{where}: a special float must be one of {', '.join(_SPECIAL_FLOATS)}")
        return _SPECIAL_FLOATS[value["$float"]]
    if "$array" in value:
        a = value["$array"]
        if len(value) != 1 or not isinstance(a, dict) or set(a) != {"dtype", "shape", "data"}:
            raise ValueError(f"{where}: an array needs exactly dtype, shape and data")
        if a["dtype"] not in _ARRAY_DTYPES:
            raise ValueError(f"{where}: array dtype {a['dtype']!r} (one of {', '.join(_ARRAY_DTYPES)})")
        shape = a["shape"]
        if not (isinstance(shape, list) and len(shape) <= 8
                and all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d < 2**31 for d in shape)):
            raise ValueError(f"{where}: array shape {shape!r} (a list of sizes)")
        dt = np.dtype(_ARRAY_DTYPES[a["dtype"]])
        try:
            raw = base64.b64decode(str(a["data"]), validate=True)
        except ValueError as exc:
            raise ValueError(f"{where}: array data is not base64 ({exc})") from None
        if len(raw) != math.prod(shape) * dt.itemsize:
            raise ValueError(f"{where}: array data of {len(raw)} bytes for shape {shape} of {a['dtype']}")
        if a["dtype"] == "bool":
            return np.frombuffer(raw, dtype=np.uint8).reshape(shape) != 0
        return np.frombuffer(raw, dtype=dt).reshape(shape).astype(np.dtype(a["dtype"]), copy=True)
    out = {}
    for k, v in value.items():
        if k.startswith("$"):
            raise ValueError(f"{where}: unknown tag {k!r}")
        out[k] = decode_state(v, f"{where}.{k}")
    return out


def _canonical(body: Any) -> bytes:
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode("utf-8")


def _mac(secret: bytes, data: bytes) -> str:
    import hmac

    return hmac.new(secret, b"fpdd-checkpoint-v2\n" + data, hashlib.sha256).hexdigest()


def source_identity(uri: str) -> dict[str, Any]:
    """What a checkpoint resumes from: ``{"uri"}``, with ``"bytes"`` (the file's length) for a file."""
    out: dict[str, Any] = {"uri": uri}
    try:
        st = os.stat(uri)
    except (OSError, ValueError):
        return out
    if os.path.isfile(uri):
        out["bytes"] = int(st.st_size)
    return out


def write_checkpoints(path: Path, journal_id: str, checkpoints: Mapping[str, Checkpoint], secret: bytes) -> None:
    """Write the checkpoints of a journal's rigs atomically (a temporary file, fsync, rename over the old one),
    sealed with an HMAC under the journal's ``secret`` (see the module docstring).

    The folder is not synced after the rename: a power cut that loses the rename leaves the previous
    checkpoint, which is consistent with the journal too (its alarm number is not larger), so one fsync a
    checkpoint is enough (the cost of the SQLite commit it replaces).

    :raises SourceError: the file cannot be written (naming it).
    :raises TypeError: a state holds something that is not plain data.
    """
    if not secret:
        raise SourceError(f"{path}: the journal has no checkpoint key; no checkpoint is written without one")
    rigs = {rig: {"t_ns": cp.t_ns, "samples": cp.samples, "fingerprint": cp.fingerprint, "saved_at": cp.saved_at,
                  "alarm_seq": cp.alarm_seq, "epoch": cp.epoch, "source": dict(cp.source),
                  "state": encode_state(cp.state, f"{rig}.state")}
            for rig, cp in sorted(checkpoints.items())}
    body = {"journal_id": journal_id, "rigs": rigs}
    data = _canonical(body)
    head = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "hmac": _mac(secret, data)}
    doc = b'{"body":' + data + b"," + _canonical(head)[1:]  # the body serialised once
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(doc + b"\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise SourceError(f"{path}: cannot write the checkpoint ({exc.strerror or exc})") from None


def read_checkpoints(path: Path, secret: bytes | None = None,
                     legacy: bool = False) -> tuple[str, dict[str, Checkpoint]] | None:
    """The journal id and the checkpoints of a checkpoint file (``None`` when there is none).

    Only data is read (JSON; arrays from raw bytes): nothing in the file can run code.

    :param secret: the journal's checkpoint key: the HMAC is checked (``None``: not checked, a first look
        before the journal is open; the journal checks it once open).
    :param legacy: a version 1 document (a bare SHA-256) is read (beside a journal of an earlier version).
    :raises LogFormatError: one line naming the file and what is wrong: not a checkpoint document (e.g. a
        pickle of an earlier version), another format or an unknown version, an HMAC (or SHA-256) that does
        not match.
    """
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise SourceError(f"{path}: cannot read the checkpoint ({exc.strerror or exc})") from None
    fix = "move it aside to start the rig afresh from its journal (its alarms are kept)"
    try:
        doc = json.loads(raw.decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, ValueError):
        raise LogFormatError(f"{path}: not a checkpoint of this program (not a JSON checkpoint document; a "
                             f"checkpoint is never unpickled or executed); refused: {fix}") from None
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise LogFormatError(f"{path}: not a checkpoint of this program (format "
                             f"{doc.get('format') if isinstance(doc, dict) else None!r}, expected "
                             f"{CHECKPOINT_FORMAT!r}); refused: {fix}")
    version = doc.get("version")
    if version not in (CHECKPOINT_VERSION, LEGACY_VERSION):
        raise LogFormatError(f"{path}: checkpoint version {version!r}, this program reads version "
                             f"{CHECKPOINT_VERSION}; refused: {fix}")
    body = doc.get("body")
    if not isinstance(body, dict):
        raise LogFormatError(f"{path}: not a valid checkpoint (no body); refused: {fix}")
    if version == LEGACY_VERSION:
        if secret is not None and not legacy:
            raise LogFormatError(f"{path}: checkpoint version 1 (a bare SHA-256 anyone can recompute) beside a "
                                 f"journal that seals its checkpoints (version {CHECKPOINT_VERSION}); refused: {fix}")
        if hashlib.sha256(_canonical(body)).hexdigest() != doc.get("sha256"):
            raise LogFormatError(f"{path}: the checkpoint's SHA-256 does not match its content (the file is "
                                 f"damaged); refused: {fix}")
    elif secret is not None:
        import hmac

        mac = doc.get("hmac")
        if not isinstance(mac, str) or not secret or not hmac.compare_digest(mac, _mac(secret, _canonical(body))):
            raise LogFormatError(f"{path}: the checkpoint's HMAC does not match its content under the journal's key "
                                 f"(changed, damaged, or another journal's checkpoint); refused: {fix}")
    try:
        jid = body["journal_id"]
        if not isinstance(jid, str):
            raise ValueError("journal_id is not a string")
        out = {}
        for rig, e in body["rigs"].items():
            source = e.get("source", {})
            if not isinstance(source, dict):
                raise ValueError(f"{rig}.source is not a mapping")
            cp = Checkpoint(rig, _int(e["t_ns"]), _int(e["samples"]), str(e["fingerprint"]),
                            decode_state(e["state"], f"{rig}.state"), float(e["saved_at"]), _int(e["alarm_seq"]),
                            jid, str(e.get("epoch", "")), source)
            if not isinstance(cp.state, dict):
                raise ValueError(f"{rig}.state is not a mapping")
            out[rig] = cp
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise LogFormatError(f"{path}: not a valid checkpoint ({type(exc).__name__}: {exc}); refused: {fix}") \
            from None
    return jid, out


def _int(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{v!r} is not an integer")
    return v


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")
