"""deploy/: the Zenoh configurations load, their access control holds, the recipes are coherent.

The JSON5 files are loaded with ``zenoh.Config.from_file`` (Zenoh 1.10 rejects
unknown keys and unknown ACL message names, so this catches typos without a
router). One test then runs the router configuration for real on loopback,
with certificates made by the README's own openssl commands.
"""

from __future__ import annotations

import json
import re
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh

from twin.bus import AlarmSubscriber, TwinPublisher, live_twins
from twin.events import AlarmEvent, event_to_json
from twin.journal import AlarmJournal
from twin.demo import free_port

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
ROUTER = DEPLOY / "zenoh-router.json5"
PEER = DEPLOY / "twin-peer.json5"
README = DEPLOY / "README.md"
WAIT_S = 10.0


def get(config: zenoh.Config, key: str) -> object:
    return json.loads(config.get_json(key))


def test_configs_load_with_this_zenoh() -> None:
    router = zenoh.Config.from_file(str(ROUTER))
    peer = zenoh.Config.from_file(str(PEER))
    assert get(router, "mode") == "router"
    assert get(peer, "mode") == "client"
    for config in (router, peer):
        assert get(config, "scouting/multicast/enabled") is False
        assert get(config, "transport/link/protocols") == ["tls"]
        assert get(config, "transport/link/tls/enable_mtls") is True
        assert get(config, "transport/link/tls/verify_name_on_connect") is True
    assert all(e.startswith("tls/") for e in get(router, "listen/endpoints"))
    assert all(e.startswith("tls/") for e in get(peer, "connect/endpoints"))


def test_access_control_is_consistent_and_only_the_twin_publishes() -> None:
    acl = get(zenoh.Config.from_file(str(ROUTER)), "access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert len(rules) == len(acl["rules"]) and len(subjects) == len(acl["subjects"])
    allowed_put: set[str] = set()
    denied_put: set[str] = set()
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= set(rules), f"policy {policy['id']}: unknown rule"
        assert set(policy["subjects"]) <= set(subjects), f"policy {policy['id']}: unknown subject"
        for rule in (rules[r] for r in policy["rules"]):
            if "put" in rule["messages"] and "ingress" in rule["flows"]:
                target = allowed_put if rule["permission"] == "allow" else denied_put
                target.update(policy["subjects"])
    assert allowed_put == {"twin", "router"}
    assert denied_put == {"observer"}
    assert subjects["twin"]["cert_common_names"] == ["fpdd-twin"]


def test_every_certificate_path_is_explained_in_the_readme() -> None:
    readme = README.read_text(encoding="utf-8")
    for config in (ROUTER, PEER):
        tls = get(zenoh.Config.from_file(str(config)), "transport/link/tls")
        for key, value in tls.items():
            if key.endswith(("certificate", "private_key")) and value:
                path = Path(value)
                assert str(path.parent) in readme and path.name in readme, (config.name, value)


def test_systemd_unit_and_containerfile() -> None:
    unit = (DEPLOY / "fpdd-twin.service").read_text(encoding="utf-8")
    settings = re.findall(r"^(\w+)=(.*)$", unit, flags=re.MULTILINE)
    keys = {k for k, _ in settings}
    values = dict(settings)
    assert values["ExecStart"].endswith("twin serve --config /etc/fpdd/rigs.toml")
    assert values["Restart"] == "on-failure" and values["KillSignal"] == "SIGINT"
    assert values["User"] == "fpdd" and values["ProtectSystem"] == "strict"
    assert "fpdd/journal" in values["StateDirectory"].split()
    assert {"NoNewPrivileges", "CapabilityBoundingSet", "SystemCallFilter"} <= keys
    assert "MemoryDenyWriteExecute" not in keys  # numba's JIT needs W+X memory
    assert {"[Unit]", "[Service]", "[Install]"} <= set(re.findall(r"^\[\w+\]$", unit, re.MULTILINE))
    recipe = (DEPLOY / "Containerfile").read_text(encoding="utf-8")
    assert re.search(r"^FROM python:3\.11-slim$", recipe, re.MULTILINE)
    assert re.search(r"^USER fpdd", recipe, re.MULTILINE)
    assert 'VOLUME ["/var/lib/fpdd"]' in recipe
    assert "twin-peer.json5" in recipe


# --------------------------------------------------------------------------- live mTLS + ACL


def readme_certificate_script() -> str:
    text = README.read_text(encoding="utf-8")
    section = text.split("## Certificates", 1)[1]
    return re.search(r"```sh\n(.*?)```", section, re.DOTALL).group(1)  # type: ignore[union-attr]


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The README's openssl commands, plus a router certificate for 127.0.0.1 and an intruder."""
    directory = tmp_path_factory.mktemp("tls")
    script = readme_certificate_script() + (
        'issue router-local fpdd-router-hall-a "IP:127.0.0.1"\n'
        'issue intruder someone-else "DNS:someone-else"\n'
    )
    subprocess.run(
        ["bash", "-euo", "pipefail", "-c", script],
        cwd=directory, check=True, capture_output=True, timeout=60,
    )
    return directory


@contextmanager
def node(path: Path, certs: Path, name: str, endpoint: str) -> Iterator[zenoh.Session]:
    config = zenoh.Config.from_file(str(path))
    tls = {"root_ca_certificate": "ca.pem"}
    if path == ROUTER:
        config.insert_json5("listen/endpoints", json.dumps([endpoint]))
        tls |= {"listen_certificate": f"{name}.pem", "listen_private_key": f"{name}.key"}
    else:
        config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    tls |= {"connect_certificate": f"{name}.pem", "connect_private_key": f"{name}.key"}
    for key, file in tls.items():
        config.insert_json5(f"transport/link/tls/{key}", json.dumps(str(certs / file)))
    with zenoh.open(config) as session:
        yield session


def alarm(i: int, message: str) -> AlarmEvent:
    return AlarmEvent(
        "r1", "Kleak", "alarm", "raised", 1_740_000_000_000_000_000 + i, float(i),
        3e-12, 2e-13, 1e-12, 5e-13, 2e-12, 12.0, message,
    )


def test_router_config_lets_only_the_twin_publish(certs: Path, tmp_path: Path) -> None:
    endpoint = f"tls/127.0.0.1:{free_port()}"
    with node(ROUTER, certs, "router-local", endpoint), node(
        PEER, certs, "twin", endpoint
    ) as twin_session, AlarmJournal(tmp_path / "alarms.jsonl") as journal, TwinPublisher(
        twin_session, "r1", journal
    ) as twin:
        first = twin.publish_alarm(alarm(1, "real"))
        with node(PEER, certs, "observer", endpoint) as observer, AlarmSubscriber(observer, "r1") as sub:
            assert sub.recv(timeout=WAIT_S) == first  # history through the router
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            second = twin.publish_alarm(alarm(2, "real"))
            assert sub.recv(timeout=WAIT_S) == second  # live through the router
            # Another observer forges alarm 3 (from its own session: a session's
            # own subscribers would get it locally, without the router).
            with node(PEER, certs, "observer", endpoint) as forger:
                forger.put("fpdd/r1/alarm", event_to_json(alarm(3, "forged").with_seq(3)))
                # A round trip on the same link: the router has handled the put when it answers.
                list(forger.get("fpdd/r1/status", timeout=WAIT_S))
            third = twin.publish_alarm(alarm(3, "real"))
            assert sub.recv(timeout=WAIT_S) == third
            with pytest.raises(TimeoutError):
                sub.recv(timeout=0.3)
            assert [e.message for e in journal.read()] == ["real"] * 3
        with node(PEER, certs, "intruder", endpoint) as intruder:
            assert live_twins(intruder, timeout=1.0) == []
            assert list(intruder.get("fpdd/r1/alarm/history", timeout=1.0)) == []
