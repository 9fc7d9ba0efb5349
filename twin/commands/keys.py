"""``twin keys``: a rig's alarm-signing key pair (library: :mod:`twin.service.signing`).

``twin keys init --rig R --dir DIR`` writes ``DIR/R.key`` (the private key,
PKCS#8 PEM, mode 0600: the service reads it, ``signing_key`` in
``rigs.toml``) and ``DIR/R.pub`` (the public key: copy it into every
subscriber's trust store, ``twin alarms --keys DIR``). ``twin keys show FILE``
prints a key's rig and fingerprint, to compare the two ends.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the sub-commands of ``twin keys`` to ``parser``."""
    sub = parser.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    init = sub.add_parser("init", help="make a new Ed25519 key pair per rig: DIR/<rig>.key (0600) and DIR/<rig>.pub",
                          description="Make a new Ed25519 key pair for each --rig: DIR/<rig>.key (private, mode "
                          "0600, for the service: rigs.toml signing_key) and DIR/<rig>.pub (public, for the "
                          "subscribers' trust store: twin alarms --keys DIR). An existing key is kept unless "
                          "--force.")
    init.add_argument("--rig", action="append", required=True, metavar="RIG", help="rig id (repeatable)")
    init.add_argument("--dir", type=Path, required=True, metavar="DIR",
                      help="directory for the key files, e.g. /etc/fpdd/keys beside /etc/fpdd/tls")
    init.add_argument("--force", action="store_true", help="replace existing keys (subscribers need the new .pub)")
    init.add_argument("--json", action="store_true", help="print the files and fingerprints as JSON")
    show = sub.add_parser("show", help="print the rig and fingerprint of key files (.key or .pub)",
                          description="Print the rig and SHA-256 fingerprint of key files, to check that a "
                          "subscriber's .pub belongs to the service's .key.")
    show.add_argument("files", nargs="+", type=Path, metavar="FILE", help="<rig>.key or <rig>.pub")
    show.add_argument("--json", action="store_true", help="print JSON")
    return parser


def run(args: argparse.Namespace) -> int:
    """``twin keys``: returns 0; errors are one-line :class:`~fpdd.errors.ConfigError`."""
    from twin.commands.common import dump
    from twin.service.signing import init_keys, key_file_info

    rows = []
    if args.keys_command == "init":
        for rig in args.rig:
            private, public, fp = init_keys(rig, args.dir, force=args.force)
            rows.append({"rig": rig, "private_key": str(private), "public_key": str(public), "fingerprint": fp})
        if args.json:
            dump({"keys": rows})
        else:
            for r in rows:
                print(f"{r['rig']}: {r['private_key']} (private, mode 0600), {r['public_key']} (public), "
                      f"{r['fingerprint']}")
        return 0
    for path in args.files:
        rows.append(key_file_info(path))
    if args.json:
        dump({"keys": rows})
    else:
        for r in rows:
            print(f"{r['file']}: rig {r['rig']}, {r['kind']} key, {r['fingerprint']}")
    return 0
