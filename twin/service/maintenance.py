"""Recorded maintenance events: a rig's maintenance log, the bus's ``fpdd/<rig>/maintenance`` and what a runner
does with them.

A maintenance event (a seal replaced, a valve serviced) says that the recent trend of some parameters no longer
predicts their future: the rig's degradation forecasts of those parameters (:mod:`twin.online.forecast`) forget
their history (a standing ``early`` alarm returns) and start afresh.  The drift test's healthy band is *not*
changed: the band is the rig's healthy specification, which a maintenance restores the part to, not a new one;
the drift test judges each estimate against it as before (its ``warning``/``alarm`` return by their own
hysteresis once the estimate is back inside).  A re-commissioning is the way to a new band.

* ``twin maintenance --rig R --parameter P [--note TEXT]`` sends a ``get`` on ``fpdd/<rig>/maintenance`` whose
  payload is ``{"parameters": [...], "note": "..."}``; the service's process (:func:`maintenance_queryables`)
  checks the names against the rig's tracked parameters, appends the event to the rig's maintenance log
  (``<journal_dir>/<rig>.maintenance.jsonl``, one JSON line per event, ``fsync``-ed before the reply) and replies
  with the event as recorded (``seq``: 1, 2, ... per rig; ``wall_ns``: when it was recorded).  A refused event
  is an error reply naming the field.
* Each runner (in whatever process) looks at the log after each block (a ``stat`` when nothing is new) and
  applies the events it has not applied yet (:meth:`twin.service.rig.RigTwin.maintenance`); the last applied
  ``seq`` is part of the forecast monitor's state, hence of the rig's checkpoint: a restart (a kill -9
  included) applies exactly the events its checkpoint had not, once.
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from fpdd.errors import DataError

log = logging.getLogger("twin.serve")

#: ``fpdd/<rig>/maintenance``: where a maintenance event is sent (a ``get`` with a JSON payload).
SUFFIX = "maintenance"
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
NOTE_MAX = 500


def maintenance_key(rig: str) -> str:
    from twin.service.bus import KEY_PREFIX

    return f"{KEY_PREFIX}/{rig}/{SUFFIX}"


def maintenance_path(journal_dir: str | os.PathLike, rig: str) -> Path:
    """The rig's maintenance log, beside its journal."""
    return Path(journal_dir) / f"{rig}.maintenance.jsonl"


def check_request(doc: Any, tracked: Sequence[str]) -> tuple[list[str], str]:
    """``(parameters, note)`` of a maintenance request, or :class:`DataError` naming the field."""
    if not isinstance(doc, dict):
        raise DataError("maintenance: the payload must be a JSON object {\"parameters\": [...], \"note\": \"...\"}")
    params = doc.get("parameters")
    if isinstance(params, str):
        params = [params]
    if not isinstance(params, list) or not params or not all(isinstance(p, str) for p in params):
        raise DataError("maintenance.parameters: expected a non-empty list of parameter names")
    unknown = [p for p in params if p not in tracked]
    if unknown:
        raise DataError(f"maintenance.parameters: {', '.join(map(repr, unknown))} not tracked on this rig "
                        f"(tracked: {', '.join(tracked)})")
    note = doc.get("note", "")
    if not isinstance(note, str) or len(note) > NOTE_MAX or "\n" in note:
        raise DataError(f"maintenance.note: expected one line of text of at most {NOTE_MAX} characters")
    return list(dict.fromkeys(params)), note


class MaintenanceLog:
    """A rig's append-only maintenance log (JSON lines; written by the service's process, read by runners)."""

    def __init__(self, path: str | os.PathLike, rig: str) -> None:
        self.path = Path(path)
        self.rig = rig
        self._lock = threading.Lock()
        self._size = -1  # the file's size when last read
        self._events: list[dict] = []

    def append(self, parameters: Sequence[str], note: str = "") -> dict:
        """Record an event (``fsync``-ed before it returns) and return it."""
        with self._lock:
            events = self.read()
            ev = {"rig": self.rig, "seq": (events[-1]["seq"] + 1) if events else 1, "parameters": list(parameters),
                  "note": note, "wall_ns": time.time_ns()}
            line = (json.dumps(ev, allow_nan=False) + "\n").encode()
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
            try:
                os.write(fd, line)
                os.fsync(fd)
            finally:
                os.close(fd)
            return ev

    def read(self) -> list[dict]:
        """Every complete event of the log (a cheap ``stat`` when it has not grown since the last read)."""
        try:
            size = self.path.stat().st_size
        except FileNotFoundError:
            return []
        if size == self._size:
            return self._events
        with open(self.path, "rb") as f:
            data = f.read(size)
        events = []
        for k, line in enumerate(data.split(b"\n")[:-1]):  # a line being written has no newline yet
            try:
                ev = json.loads(line)
                if not isinstance(ev, dict) or not isinstance(ev.get("seq"), int):
                    raise ValueError("not an event")
            except ValueError:
                log.warning("%s: line %d is not a maintenance event; skipped", self.path, k + 1)
                continue
            events.append(ev)
        self._size = len(data) - len(data.split(b"\n")[-1])
        self._events = events
        return events

    def since(self, seq: int) -> list[dict]:
        """The events after ``seq``."""
        return [ev for ev in self.read() if ev["seq"] > seq]


def maintenance_queryables(session, rigs: Sequence, journal_dir: str | os.PathLike) -> list:
    """The service's ``fpdd/<rig>/maintenance`` queryables (one per rig); undeclare them when done."""
    import zenoh

    out = []
    for rig in rigs:
        mlog = MaintenanceLog(maintenance_path(journal_dir, rig.name), rig.name)
        tracked = tuple(rig.track)
        key = maintenance_key(rig.name)

        def handler(query, mlog=mlog, tracked=tracked, key=key):
            with query:
                try:
                    payload = query.payload.to_bytes() if query.payload is not None else b""
                    try:
                        doc = json.loads(payload or b"null")
                    except ValueError:
                        raise DataError("maintenance: the payload is not JSON") from None
                    params, note = check_request(doc, tracked)
                    ev = mlog.append(params, note)
                except DataError as exc:
                    query.reply_err(json.dumps({"error": str(exc)}), encoding=zenoh.Encoding.APPLICATION_JSON)
                    return
                except OSError as exc:
                    log.error("rig %s: maintenance event not recorded: %s", mlog.rig, exc)
                    query.reply_err(json.dumps({"error": f"not recorded: {exc}"}),
                                    encoding=zenoh.Encoding.APPLICATION_JSON)
                    return
                log.info("rig %s: maintenance #%d recorded: %s%s", mlog.rig, ev["seq"], ", ".join(params),
                         f" ({note})" if note else "")
                query.reply(key, json.dumps(ev), encoding=zenoh.Encoding.APPLICATION_JSON)

        out.append(session.declare_queryable(maintenance_key(rig.name), handler))
    return out


def send_maintenance(session, rig: str, parameters: Sequence[str], note: str = "", timeout: float = 10.0) -> dict:
    """Send a maintenance event to the running twin of ``rig``; the event as recorded, or :class:`DataError`
    (refused: its reason) / :class:`fpdd.errors.SourceError` (no twin answered)."""
    import zenoh

    from fpdd.errors import SourceError

    for p in parameters:
        if not _NAME_RE.match(p):
            raise DataError(f"--parameter: {p!r} is not a parameter name")
    body = json.dumps({"parameters": list(parameters), "note": note})
    replies = session.get(maintenance_key(rig), payload=body, encoding=zenoh.Encoding.APPLICATION_JSON,
                          target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)
    for reply in replies:
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_string())
        try:
            why = json.loads(reply.err.payload.to_string()).get("error", "refused")
        except ValueError:
            why = reply.err.payload.to_string()
        raise DataError(f"rig {rig!r}: {why}")
    raise SourceError(f"rig {rig!r}: no running twin answered on {maintenance_key(rig)} within {timeout:g} s "
                      "(is the service running and reachable?)")
