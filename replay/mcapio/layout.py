"""The MCAP layout of the product's files: topics, schemas, time fields (the reader is
:mod:`replay.mcapio.reader`, the writer :mod:`replay.mcapio.writer`).

Channel layout (written by :class:`McapSink`, plotted by Foxglove as is)
=========================================================================

Every channel has ``message_encoding = "json"`` and a ``jsonschema`` schema.  Message
``log_time`` and ``publish_time`` are the sample time in integer nanoseconds (the time
convention of :mod:`replay.base`).

``/rig/signals`` -- schema ``fpdd.RigSignals``, one message per sample::

    {"t": 12.345, "timestamp": {"sec": 12, "nsec": 345000000}, "rig": "hall1-a",
     "x_ref": 0.01, "u": 0.2, "x": 0.0099, "pA": 2.1e6, "pB": 1.9e6,
     "display": {"x_ref": 10.0, "u": 0.2, "x": 9.9, "pA": 2.1, "pB": 1.9}}

  ``t`` is the sample time in seconds (``log_time / 1e9``, for plotting only: readers
  take the exact time from ``log_time``), ``timestamp`` the same time exactly as the
  Foxglove ``time`` type (:data:`TIME_SCHEMA`), every other field a signal in its SI unit
  (:data:`fpdd.units.SIGNALS`; a non-finite value is written as ``null``).  Foxglove
  plots ``/rig/signals.x`` directly.  ``rig`` is the rig's name (the layout of the live view selects
  ``/rig/signals{rig==$rig}``) and ``display`` the same signals in display units (x in mm, pressures in MPa:
  :data:`fpdd.units.DISPLAY`), which the layout's plots read.  The channel metadata ``signals`` and ``units``
  list the fields in order (comma separated), ``rig`` and ``display_units`` the rest.

``/rig/signals_block`` -- schema ``fpdd.RigSignalsBlock``, one message per block of
samples (at most one flush period, 1 s by default), the same samples as
``/rig/signals`` in compact form for fast reading::

    {"t0": 12.345, "timestamp": {"sec": 12, "nsec": 345000000}, "n": 1000,
     "t_ns": "<base64 of n little-endian int64: sample times, ns>",
     "signals": {"x_ref": "<base64 of n little-endian float64, SI unit>", ...}}

  ``log_time`` is the time of the block's first sample, ``t0`` the same in seconds.
  The schema marks the arrays ``contentEncoding: base64`` and
  ``contentMediaType: application/octet-stream``; staying JSON keeps the file valid for
  every MCAP tool (Foxglove shows the block topic as raw messages).

Each flush writes the block message into its own chunk, then the per-sample messages of
the same samples into the next chunk, so that reading ``/rig/signals_block`` through
the chunk index touches only the small block chunks.

``/twin/estimate``, ``/twin/alarm``, ``/twin/status`` and any other topic:
:meth:`McapSink.write_message` -- a JSON object per message, with a schema registered
on first use (given, or derived from the first payload's fields).  Every message gets
``"timestamp": {"sec": .., "nsec": ..}`` (its ``log_time``; the Foxglove time type,
exact where a JSON reader holds numbers as doubles: ``t_ns`` above 2**53 is not), and
every schema declares it.

A metadata record ``fpdd.layout`` holds ``version``, ``signals_topic``,
``block_topic`` and ``block_max_span_ns`` (the longest block, which a time-range read
needs to know).  It is written with the first samples, so a file of other topics only
(a twin output) has none: it never names a topic the file does not contain.

Why the block topic (measured with ``python -m benchmarks.replay``, 2 cores, mcap 1.6): the
naive path -- ``mcap``'s reader plus one ``json.loads`` per message -- reads about
80 000 samples/s, i.e. 45 s for a one-hour 1 kHz record (3.6 M samples); batching the
``json.loads`` helps only 1.4x.  The block topic reads the same hour in 1.7 s
(2.1 M samples/s, 26x).  Writing both topics runs at about 137 000 samples/s (26 s for
the hour): formatting JSON floats with ``repr`` is half of it, ``mcap``'s
add_message and compression the rest (figures from before the per-sample rows carried ``rig`` and ``display``:
the display copy, formatted with ``%.7g``, costs about a quarter of the writing speed and a fifth more file).
"""

from __future__ import annotations

from typing import Any
from collections.abc import Mapping, Sequence

import numpy as np

from fpdd import jsonio
from fpdd.units import SIGNALS, display

SIGNALS_TOPIC = "/rig/signals"
SIGNALS_SCHEMA = "fpdd.RigSignals"
BLOCK_TOPIC = "/rig/signals_block"
BLOCK_SCHEMA = "fpdd.RigSignalsBlock"
LAYOUT_METADATA = "fpdd.layout"
LAYOUT_VERSION = "1"

#: Fields of a JSON message that carry its time, not a signal.
TIME_FIELDS = frozenset({"t", "t_ns", "timestamp"})


# --- schemas -------------------------------------------------------------------------------

def signals_schema(signals: Sequence[str]) -> dict:
    """JSON Schema of ``/rig/signals`` for these signals: the time, the rig's name, each signal in SI and under
    ``display`` in its display unit (x in mm, pressures in MPa, as the live view's ``/rig/signals``)."""
    props: dict[str, Any] = {"t": {"type": "number", "description": "sample time, s (log_time / 1e9)"},
                             "timestamp": TIME_SCHEMA,
                             "rig": {"type": "string", "description": "the rig's name (Foxglove's layout selects "
                                                                      "/rig/signals{rig==$rig})"}}
    shown: dict[str, Any] = {}
    for name in signals:
        spec = SIGNALS.get(name)
        desc = f"{spec.meaning}, {spec.unit}" if spec else "extra signal, SI unit"
        props[name] = {"type": ["number", "null"], "description": desc}
        shown[name] = {"type": ["number", "null"],
                       "description": f"{spec.meaning}, {display(spec.unit)[0]}" if spec else "extra signal"}
    props["display"] = {"type": "object", "properties": shown, "required": list(signals),
                        "description": "the signals in display units (SI times the factor of "
                                       "fpdd.units.DISPLAY: x in mm, pressures in MPa)"}
    return {"title": SIGNALS_SCHEMA, "type": "object", "properties": props,
            "required": ["t", "timestamp", "rig", *signals, "display"]}


def block_schema(signals: Sequence[str]) -> dict:
    """JSON Schema of ``/rig/signals_block`` for these signals."""
    arr = {"type": "string", "contentEncoding": "base64", "contentMediaType": "application/octet-stream"}
    return {
        "title": BLOCK_SCHEMA,
        "type": "object",
        "description": "a block of samples: little-endian int64 times (ns) and float64 signals (SI)",
        "properties": {
            "t0": {"type": "number", "description": "time of the first sample, s"},
            "timestamp": TIME_SCHEMA,
            "n": {"type": "integer", "description": "number of samples"},
            "t_ns": {**arr, "description": "n little-endian int64 sample times, ns"},
            "signals": {"type": "object", "properties": {
                name: {**arr, "description": f"n little-endian float64, "
                                             f"{SIGNALS[name].unit if name in SIGNALS else 'SI unit'}"}
                for name in signals}},
        },
        "required": ["t0", "timestamp", "n", "t_ns", "signals"],
    }


#: The Foxglove ``time`` type: a message's time as whole seconds and nanoseconds (exact in
#: every JSON reader; an int64 ``t_ns`` above 2**53 is not exact in JavaScript).
TIME_SCHEMA: dict[str, Any] = {
    "title": "time", "type": "object", "description": "message time (log_time), Foxglove time type",
    "properties": {"sec": {"type": "integer", "description": "whole seconds (UNIX epoch or record start)"},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999,
                            "description": "nanoseconds within the second"}},
    "required": ["sec", "nsec"],
}
TIME_FIELD = "timestamp"


def foxglove_time(t_ns: int) -> dict[str, int]:
    """``{"sec": ..., "nsec": ...}`` of integer nanoseconds (``nsec`` in [0, 1e9))."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def with_time_schema(schema: Mapping[str, Any]) -> dict:
    """``schema`` with the :data:`TIME_FIELD` property (Foxglove time) added and required."""
    out = dict(schema)
    props = dict(out.get("properties", {}))
    props.setdefault(TIME_FIELD, TIME_SCHEMA)
    out["properties"] = props
    req = list(out.get("required", []))
    if TIME_FIELD not in req:
        req.append(TIME_FIELD)
    out["required"] = req
    return out


def generic_schema(title: str, payload: Mapping[str, Any]) -> dict:
    def kind(v: Any) -> str:
        if isinstance(v, bool):
            return "boolean"
        if isinstance(v, (int, float, np.number)):
            return "number"
        if isinstance(v, str):
            return "string"
        if isinstance(v, Mapping):
            return "object"
        return "array"
    return {"title": title, "type": "object",
            "properties": {k: {"type": [kind(v), "null"]} for k, v in payload.items() if k != TIME_FIELD}}


def encode_json(payload: Mapping[str, Any]) -> bytes:
    """Compact JSON bytes; non-finite numbers become ``null`` (:func:`fpdd.jsonio.compact`)."""
    return jsonio.compact(payload)

