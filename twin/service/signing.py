"""Signed alarms: a per-rig Ed25519 key signs every alarm the twin puts or serves from its history.

Why: on a Zenoh bus without the router's access control (a plain peer bus, a
lab bench, a site without ``zenohd``) anyone on the network can put on
``fpdd/<rig>/alarm`` or answer ``fpdd/<rig>/alarm/history``. The signature lets
a subscriber tell the twin's alarms from anyone else's, whatever the bus.

What is signed: the alarm's JSON payload without its ``signature`` field, in a
canonical form (:func:`canonical`: keys sorted, no whitespace, UTF-8, numbers as
Python's ``json`` writes them), prefixed by the domain tag ``fpdd-alarm-v1\\n``.
Every field of the payload is covered (rig, epoch, seq, parameter, level, kind,
t_ns, t_s, estimate, std, baseline, band, statistic, message, unit), so a
changed field, a changed number or another rig's alarm under this rig's key
does not verify. Ed25519 signatures are deterministic: the live alarm and its
history reply carry the same signature.

Replays: a validly signed alarm recorded off the bus stays valid for ever, so the
signature also covers the alarm's ``epoch`` (the identity of the rig's numbering,
made with its journal, :mod:`twin.service.store`), and the rig's owner announces
that epoch in its status, signed too (domain ``fpdd-status-v1\\n``, :meth:`Signer.sign_status`).
A subscriber (:class:`twin.service.subscriber.AlarmSubscriber`) keeps per rig the
epoch and the numbers delivered, and refuses an alarm of an earlier epoch or a
number delivered before.

Keys (:func:`init_keys`, ``twin keys init``): ``<rig>.key`` (PKCS#8 PEM, mode
0600, read by the service) and ``<rig>.pub`` (SubjectPublicKeyInfo PEM, handed
to subscribers). A subscriber's trust store (:class:`TrustStore`) is a
directory of ``<rig>.pub`` files: the file name is the rig the key speaks for.

Verdicts of a payload (:meth:`TrustStore.check`):

* ``verified``: the rig has a key in the trust store and the signature verifies;
* ``unverified``: no key for the rig in the trust store (signed or not,
  nothing can be checked); delivered, and marked so, unless signatures are required;
* ``forged``: the rig has a key and the signature is missing, malformed or
  does not verify; never delivered.

Library: ``cryptography`` (pyca), the audited, maintained binding of OpenSSL's Ed25519.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import os
import stat
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fpdd.errors import ConfigError
from twin.online.events import RIG_PATTERN, AlarmEvent

__all__ = [
    "DOMAIN",
    "SIGNATURE_FIELD",
    "STATUS_DOMAIN",
    "Signer",
    "TrustStore",
    "Verdict",
    "canonical",
    "fingerprint",
    "init_keys",
    "key_file_info",
    "load_signer",
]

DOMAIN = b"fpdd-alarm-v1\n"
"""Prefix of every signed alarm: a signature over an alarm is good for nothing else."""
STATUS_DOMAIN = b"fpdd-status-v1\n"
"""Prefix of every signed status (it announces the rig's epoch): a status signature is no alarm's."""

SIGNATURE_FIELD = "signature"
"""The payload field that carries the base64 Ed25519 signature (64 bytes)."""

VERIFIED, UNVERIFIED, FORGED = "verified", "unverified", "forged"


def canonical(payload: Mapping[str, Any], domain: bytes = DOMAIN) -> bytes:
    """The bytes that are signed: ``payload`` without its signature, canonical JSON, after ``domain``."""
    body = {k: v for k, v in payload.items() if k != SIGNATURE_FIELD}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    return domain + text.encode("utf-8")


def fingerprint(public_key: Any) -> str:
    """``SHA256:`` and the first 16 hex digits of the SHA-256 of the raw 32-byte public key (shown, logged)."""
    from cryptography.hazmat.primitives import serialization

    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return "SHA256:" + hashlib.sha256(raw).hexdigest()[:16]


# --------------------------------------------------------------------------- the twin's side


class Signer:
    """One rig's private key: signs that rig's alarms."""

    def __init__(self, rig: str, private_key: Any, path: str = "") -> None:
        self.rig = rig
        self._key = private_key
        self.path = path
        self.fingerprint = fingerprint(private_key.public_key())

    def signature(self, event: AlarmEvent) -> str:
        """The base64 signature of ``event`` (over every field of its payload but ``signature``)."""
        from fpdd import jsonio

        if event.rig != self.rig:
            raise ConfigError(f"{self.path}: the signing key of rig {self.rig!r} cannot sign an alarm of rig "
                              f"{event.rig!r}")
        data = event.to_dict()
        data.pop(SIGNATURE_FIELD, None)
        # What is signed is what goes on the wire, read back as a subscriber reads it.
        payload = json.loads(jsonio.dumps(data, indent=None, sort_keys=True))
        return base64.b64encode(self._key.sign(canonical(payload))).decode("ascii")

    def payload(self, event: AlarmEvent) -> str:
        """The signed JSON payload of ``event`` (what is put and what a history reply carries)."""
        from fpdd import jsonio

        data = event.to_dict()
        data[SIGNATURE_FIELD] = self.signature(event)
        return jsonio.dumps(data, indent=None, sort_keys=True)

    def sign(self, event: AlarmEvent) -> AlarmEvent:
        """``event`` with its ``signature`` set."""
        from dataclasses import replace

        return replace(event, signature=self.signature(event))

    def sign_status(self, payload: str) -> str:
        """A status JSON payload (:class:`twin.online.events.StatusEvent`) with its ``signature`` (domain
        :data:`STATUS_DOMAIN`) over every other field; the payload as it was when it is another rig's."""
        from fpdd import jsonio

        data = json.loads(payload)
        if not isinstance(data, dict) or data.get("rig") != self.rig:
            return payload
        data.pop(SIGNATURE_FIELD, None)
        data[SIGNATURE_FIELD] = base64.b64encode(self._key.sign(canonical(data, STATUS_DOMAIN))).decode("ascii")
        return jsonio.dumps(data, indent=None, sort_keys=True)


def load_signer(path: str | Path, rig: str) -> Signer:
    """Read ``rig``'s private Ed25519 key (PKCS#8 PEM) from ``path``.

    :raises ConfigError: one line naming the file: missing, readable by others,
        not a PEM private key, or not Ed25519.
    """
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    path = str(path)
    try:
        st = os.stat(path)
        if stat.S_IMODE(st.st_mode) & 0o007:
            raise ConfigError(f"{path}: signing key of rig {rig!r} is readable by others "
                              f"(mode {stat.S_IMODE(st.st_mode):04o}); chmod 600 it (or 640 with the service's group)")
        with open(path, "rb") as f:
            data = f.read(64 * 1024)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the signing key of rig {rig!r} ({exc.strerror or exc})") from None
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{path}: not an unencrypted PEM private key ({exc}); make one with "
                          f"`twin keys init --rig {rig} --dir DIR`") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise ConfigError(f"{path}: the signing key of rig {rig!r} must be Ed25519, got {type(key).__name__}")
    return Signer(rig, key, path)


def init_keys(rig: str, directory: str | Path, *, force: bool = False) -> tuple[Path, Path, str]:
    """Make a new key pair for ``rig``: ``DIR/<rig>.key`` (mode 0600) and ``DIR/<rig>.pub``.

    :returns: ``(private key path, public key path, fingerprint)``.
    :raises ConfigError: bad rig id, or a key exists already (without ``force``), or the files cannot be written.
    """
    import re

    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    if re.match(RIG_PATTERN, rig) is None:
        raise ConfigError(f"--rig: {rig!r} is not a valid rig id (must match {RIG_PATTERN})")
    directory = Path(directory)
    private, public = directory / f"{rig}.key", directory / f"{rig}.pub"
    if not force:
        for p in (private, public):
            if p.exists():
                raise ConfigError(f"{p}: exists already; a new key would orphan every subscriber's copy of "
                                  "the old one (use --force to replace it)")
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    pub = key.public_key().public_bytes(serialization.Encoding.PEM,
                                        serialization.PublicFormat.SubjectPublicKeyInfo)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        for path, data, mode in ((private, pem, 0o600), (public, pub, 0o644)):
            tmp = path.with_name(f".{path.name}.tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
            try:
                os.fchmod(fd, mode)  # the umask does not widen or narrow it
                os.write(fd, data)
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, path)
    except OSError as exc:
        raise ConfigError(f"{directory}: cannot write the keys of rig {rig!r} ({exc.strerror or exc})") from None
    return private, public, fingerprint(key.public_key())


def key_file_info(path: str | Path) -> dict[str, str]:
    """``{"file", "rig", "kind" (private/public), "fingerprint"}`` of a ``<rig>.key`` or ``<rig>.pub`` file.

    :raises ConfigError: unreadable, or not an Ed25519 PEM key.
    """
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

    path = Path(path)
    try:
        data = path.read_bytes()[:64 * 1024]
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the key ({exc.strerror or exc})") from None
    key: Any
    try:
        if b"PRIVATE KEY" in data:
            key, kind = serialization.load_pem_private_key(data, password=None), "private"
        else:
            key, kind = serialization.load_pem_public_key(data), "public"
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{path}: not a PEM key ({exc})") from None
    if isinstance(key, Ed25519PrivateKey):
        key = key.public_key()
    if not isinstance(key, Ed25519PublicKey):
        raise ConfigError(f"{path}: not an Ed25519 key ({type(key).__name__})")
    return {"file": str(path), "rig": path.stem, "kind": kind, "fingerprint": fingerprint(key)}


# --------------------------------------------------------------------------- the subscriber's side


@dataclass(frozen=True)
class Verdict:
    """What the trust store says of one payload: ``status`` (verified/unverified/forged) and why."""

    status: str
    reason: str = ""


class TrustStore:
    """Public keys a subscriber trusts: ``{rig: key}``, read from a directory of ``<rig>.pub`` files.

    :param directory: ``None`` for an empty store (every alarm is ``unverified``).
    :raises ConfigError: the directory cannot be read, or a ``.pub`` file is not an Ed25519 public key
        (one line naming the file).
    """

    def __init__(self, directory: str | Path | None = None) -> None:
        self.directory = None if directory is None else str(directory)
        self._keys: dict[str, Any] = {}
        if directory is None:
            return
        import re

        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

        try:
            files = sorted(p for p in Path(directory).iterdir() if p.suffix == ".pub")
        except OSError as exc:
            raise ConfigError(f"{directory}: cannot read the trust store ({exc.strerror or exc})") from None
        for path in files:
            rig = path.stem
            if re.match(RIG_PATTERN, rig) is None:
                raise ConfigError(f"{path}: the file name must be <rig>.pub with a valid rig id")
            try:
                key = serialization.load_pem_public_key(path.read_bytes()[:64 * 1024])
            except (OSError, ValueError) as exc:
                raise ConfigError(f"{path}: not a PEM public key ({exc})") from None
            if not isinstance(key, Ed25519PublicKey):
                raise ConfigError(f"{path}: must be an Ed25519 public key, got {type(key).__name__}")
            self._keys[rig] = key
        if not self._keys:
            raise ConfigError(f"{directory}: no <rig>.pub public key in the trust store")

    @property
    def rigs(self) -> list[str]:
        return sorted(self._keys)

    def has_key(self, rig: str) -> bool:
        return rig in self._keys

    def check(self, payload: Mapping[str, Any], domain: bytes = DOMAIN) -> Verdict:
        """The verdict on a decoded alarm payload (a status's with ``domain`` :data:`STATUS_DOMAIN`), before or
        after schema validation."""
        from cryptography.exceptions import InvalidSignature

        rig = payload.get("rig")
        key = self._keys.get(rig) if isinstance(rig, str) else None
        if key is None:
            return Verdict(UNVERIFIED, f"no public key of rig {rig!r} in the trust store")
        text = payload.get(SIGNATURE_FIELD)
        if not isinstance(text, str) or not text:
            return Verdict(FORGED, f"unsigned, but rig {rig!r} signs its alarms")
        try:
            signature = base64.b64decode(text, validate=True)
        except (binascii.Error, ValueError):
            return Verdict(FORGED, "the signature is not base64")
        try:
            key.verify(signature, canonical(payload, domain))
        except InvalidSignature:
            return Verdict(FORGED, f"the signature does not verify with the key of rig {rig!r}")
        except (TypeError, ValueError) as exc:
            return Verdict(FORGED, f"cannot check the payload ({exc})")
        return Verdict(VERIFIED)
