"""Who runs each rig when several ``twin serve`` share it: the ``[failover]`` configuration, the liveliness
tokens and the rule.

Key space (liveliness tokens; ``<prio>`` the service's ``priority``, ``<id>`` its ``service_id``)::

    fpdd/<rig>/owner/<prio>/<id>      the service that runs the rig now
    fpdd/<rig>/standby/<prio>/<id>    a service ready to take the rig over (keeps its replica)
    fpdd/<rig>/prefer/<prio>/<id>     a standby that asks for the rig back (``prefer = true``)

The rule (:func:`rank`): the lower ``priority`` first, then the lower ``service_id`` (string order). A standby
claims a rig only when no owner token of it is alive and it is the first, by the rule, of the live standbys;
it declares its owner token, waits ``claim_s`` and runs the rig unless an owner that ranks before it
appeared meanwhile (then it withdraws). An owner that sees another owner ranked before it (two sides of a
split network that joined again) stands down; so does one that sees a ``prefer`` token ranked before it. A
service never takes a rig from a live owner otherwise: a returning service stands by.

Terms (fencing): every run of a rig by a service is an ownership *term*, numbered by :func:`new_term` (the
wall-clock time it began, in ms: a later owner has a larger term without any message between them). The
term is in every alarm, estimate and status the owner publishes; two terms publishing at once are two
owners (a split network): the owners' statuses, ``twin alarms`` and ``twin top`` say so in one line.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import threading
from collections.abc import Callable
from typing import Any

from fpdd.errors import ConfigError
from twin.service.config_values import _check_keys, _get, _number
from twin.online.events import RIG_PATTERN

log = logging.getLogger("twin.serve")

FAILOVER_KEYS = ("service_id", "priority", "prefer", "lease_s", "claim_s")
#: The liveliness timeout bounds: shorter than half a second and a busy host looks dead; longer than a
#: minute and a dead host's rigs go unwatched that long [s].
LEASE_RANGE = (0.5, 60.0)
ROLES = ("owner", "standby", "prefer")


@dataclasses.dataclass(frozen=True)
class FailoverConfig:
    """``[failover]`` of ``rigs.toml``: this service shares its rigs with others (see the module docstring)."""

    service_id: str
    """This service's name on the bus (one key chunk, unique among the services sharing a rig; default: the
    host name and a digest of ``journal_dir``)."""
    priority: int = 100
    """Preference order: the lowest runs a rig first (ties: the lower ``service_id``)."""
    prefer: bool = False
    """Take a rig back from a running owner that ranks after this service (default: stand by)."""
    lease_s: float = 2.0
    """The Zenoh link lease: a host silent this long is dead, its tokens go [s]."""
    claim_s: float = 0.5
    """How long a claim waits for a competing owner's token before the rig runs [s]."""


def default_service_id(journal_dir: str) -> str:
    """``<host name>-<6 hex digits of the journal directory's absolute path>``: one id per host and journal, the
    same at every start (so two services on one host differ, and a restarted service is the one it was)."""
    import hashlib
    import os
    import socket

    host = re.sub(r"[^A-Za-z0-9_.\-]", "-", socket.gethostname()).strip("-.")[:40] or "host"
    return f"{host}-{hashlib.sha1(os.path.abspath(journal_dir).encode()).hexdigest()[:6]}"


def parse_failover(doc: dict, path: str, journal_dir: str) -> FailoverConfig | None:
    """The ``[failover]`` table (``None`` without one); errors name the file and the key. Without
    ``service_id``: :func:`default_service_id`."""
    if "failover" not in doc:
        return None
    f = doc["failover"]
    where = f"{path}: failover"
    if not isinstance(f, dict):
        raise ConfigError(f"{where}: expected a table")
    _check_keys(f, FAILOVER_KEYS, where)
    sid = _get(f, "service_id", str, where, "") or default_service_id(journal_dir)
    if not re.match(RIG_PATTERN, sid) or len(sid) > 64:
        raise ConfigError(f"{where}.service_id: {sid!r} must be 1-64 letters, digits, _ . - (one key chunk)")
    prio = _get(f, "priority", int, where, 100)
    if not 0 <= prio <= 1_000_000:
        raise ConfigError(f"{where}.priority: {prio}; expected 0..1000000 (the lowest runs a rig first)")
    lease = _number(f, "lease_s", where, 2.0)
    if not LEASE_RANGE[0] <= lease <= LEASE_RANGE[1]:
        raise ConfigError(f"{where}.lease_s: {lease:g} seconds; expected {LEASE_RANGE[0]:g} to {LEASE_RANGE[1]:g}")
    claim = _number(f, "claim_s", where, 0.5)
    if not 0.05 <= claim <= 10.0:
        raise ConfigError(f"{where}.claim_s: {claim:g} seconds; expected 0.05 to 10")
    return FailoverConfig(sid, prio, _get(f, "prefer", bool, where, False), lease, claim)


def new_term() -> int:
    """A new ownership term: the wall-clock time now in ms (later owners have larger terms)."""
    import time

    return time.time_ns() // 1_000_000


def token_key(rig: str, role: str, priority: int, service_id: str) -> str:
    return f"fpdd/{rig}/{role}/{priority}/{service_id}"


def parse_token(key: str) -> tuple[str, str, int, str] | None:
    """``(rig, role, priority, service_id)`` of a token key, ``None`` for another key."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != "fpdd" or parts[2] not in ROLES or not parts[3].isdigit():
        return None
    return parts[1], parts[2], int(parts[3]), parts[4]


def rank(priority: int, service_id: str) -> tuple[int, str]:
    """The rule's order: the smaller runs a rig first."""
    return (priority, service_id)


@dataclasses.dataclass
class RigView:
    """The live tokens of one rig: role -> {service_id: priority}."""

    roles: dict[str, dict[str, int]] = dataclasses.field(default_factory=lambda: {r: {} for r in ROLES})

    def ranked(self, role: str) -> list[tuple[int, str]]:
        return sorted(rank(p, s) for s, p in self.roles[role].items())

    def as_dict(self) -> dict[str, Any]:
        return {role: [s for _, s in self.ranked(role)] for role in ROLES}


class Ownership:
    """This service's tokens and its view of every service's, for its rigs (thread-safe).

    :param on_change: called (from a Zenoh thread) whenever a token of one of the rigs came or went.
    """

    def __init__(self, session, rigs: list[str], me: FailoverConfig, on_change: Callable[[], None]) -> None:
        self._session = session
        self.me = me
        self._rigs = set(rigs)
        self._lock = threading.Lock()
        self._views = {r: RigView() for r in rigs}
        self._tokens: dict[tuple[str, str], Any] = {}
        self._on_change = on_change
        # one subscription per rig: a site's access control grants a service its rigs' keys only
        self._subs = [session.liveliness().declare_subscriber(f"fpdd/{r}/*/*/*", self._on_sample, history=True)
                      for r in rigs]
        for r in rigs:  # what is there already, answered before any decision (the subscriber's history may come later)
            try:
                for reply in session.liveliness().get(f"fpdd/{r}/*/*/*", timeout=2.0):
                    if reply.ok is not None:
                        self._seen(str(reply.ok.key_expr), True)
            except Exception as exc:  # noqa: BLE001 - zenoh.ZError: the subscriber still reports them
                log.debug("liveliness get: %s", exc)

    @property
    def my_rank(self) -> tuple[int, str]:
        return rank(self.me.priority, self.me.service_id)

    def _on_sample(self, sample) -> None:
        import zenoh

        self._seen(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    def _seen(self, key: str, alive: bool) -> None:
        parsed = parse_token(key)
        if parsed is None or parsed[0] not in self._rigs:
            return
        rig, role, prio, sid = parsed
        if sid == self.me.service_id:
            return  # our own tokens are kept by declare/undeclare
        with self._lock:
            held = self._views[rig].roles[role]
            if alive:
                held[sid] = prio
            else:
                held.pop(sid, None)
        self._on_change()

    def view(self, rig: str) -> RigView:
        """A copy of the rig's live tokens, this service's own included."""
        with self._lock:
            v = RigView({role: dict(m) for role, m in self._views[rig].roles.items()})
        for (r, role) in list(self._tokens):
            if r == rig:
                v.roles[role][self.me.service_id] = self.me.priority
        return v

    def hold(self, rig: str, role: str, on: bool) -> None:
        """Declare (``on``) or undeclare this service's ``role`` token of ``rig`` (idempotent)."""
        k = (rig, role)
        if on and k not in self._tokens:
            self._tokens[k] = self._session.liveliness().declare_token(
                token_key(rig, role, self.me.priority, self.me.service_id))
        elif not on and k in self._tokens:
            tok = self._tokens.pop(k)
            try:
                tok.undeclare()
            except Exception as exc:  # noqa: BLE001 - zenoh.ZError on a closed session: gone anyway
                log.debug("undeclare %s: %s", k, exc)

    def holds(self, rig: str, role: str) -> bool:
        return (rig, role) in self._tokens

    def close(self) -> None:
        for k in list(self._tokens):
            self.hold(*k, on=False)
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception as exc:  # noqa: BLE001
                log.debug("undeclare the token subscriber: %s", exc)
