"""deploy/: the Zenoh configurations load, their access control holds, the recipes are coherent.

The JSON5 files are loaded with ``zenoh.Config.from_file`` (Zenoh 1.10 rejects
unknown keys and unknown ACL message names, so this catches typos without a
router). One test then runs the router configuration for real on loopback,
with certificates made by the README's own openssl commands.
"""

from __future__ import annotations

import json
import os
import queue
import re
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh

from twin.service.bus import TwinPublisher
from twin.service.queries import live_twins
from twin.service.subscriber import AlarmSubscriber
from twin.service.config import load_config
from twin.online.events import AlarmEvent, event_to_json
from twin.service.journal import AlarmJournal
from net_helpers import free_port

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


def test_access_control_is_consistent_and_each_twin_publishes_only_its_rigs() -> None:
    acl = get(zenoh.Config.from_file(str(ROUTER)), "access_control")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert len(rules) == len(acl["rules"]) and len(subjects) == len(acl["subjects"])
    put_keys: dict[str, set[str]] = {}
    denied_put: set[str] = set()
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= set(rules), f"policy {policy['id']}: unknown rule"
        assert set(policy["subjects"]) <= set(subjects), f"policy {policy['id']}: unknown subject"
        for rule in (rules[r] for r in policy["rules"]):
            if "put" in rule["messages"] and "ingress" in rule["flows"]:
                for subject in policy["subjects"]:
                    if rule["permission"] == "allow":
                        put_keys.setdefault(subject, set()).update(rule["key_exprs"])
                    else:
                        denied_put.add(subject)
    assert put_keys == {
        "twin-hall1": {"fpdd/msp25-hall1-a/**", "fpdd/msp25-hall1-b/**"},
        "twin-hall2": {"fpdd/msp25-hall2-a/**"},
        "router": {"fpdd/**"},
    }
    assert denied_put == {"observer"}
    assert subjects["twin-hall1"]["cert_common_names"] == ["fpdd-twin-hall1"]
    # the example rigs.toml is hall 1's: every one of its rigs is in hall 1's rules, and only those
    example = [r.name for r in load_config(str(DEPLOY / "rigs.example.toml")).rigs]
    assert put_keys["twin-hall1"] == {f"fpdd/{r}/**" for r in example}


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
    # the kernels compiled once at install, into the cache directory the service is given
    cache = next(v for k, v in settings if k == "Environment" and v.startswith("NUMBA_CACHE_DIR="))
    assert re.search(r"^RUN twin warm\b", recipe, re.MULTILINE)
    assert re.search(r"NUMBA_CACHE_DIR=(\S+) \S*twin warm", unit), "the unit's install notes warm its cache"
    assert cache.split("=", 1)[1] in (DEPLOY / "README.md").read_text(encoding="utf-8").split("twin warm")[0]


# --------------------------------------------------------------------------- live mTLS + ACL


def readme_certificate_script() -> str:
    text = README.read_text(encoding="utf-8")
    section = text.split("## Certificates", 1)[1]
    return re.search(r"```sh\n(.*?)```", section, re.DOTALL).group(1)  # type: ignore[union-attr]


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The README's openssl commands, plus a router certificate for 127.0.0.1, hall 2's twin and an intruder."""
    directory = tmp_path_factory.mktemp("tls")
    script = readme_certificate_script() + (
        'issue router-local fpdd-router-hall-a "IP:127.0.0.1"\n'
        'issue twin-hall2 fpdd-twin-hall2 "DNS:fpdd-twin-hall2"\n'
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


RIG = "msp25-hall1-a"


def alarm(i: int, message: str, rig: str = RIG) -> AlarmEvent:
    return AlarmEvent(
        rig, "Kleak", "alarm", "raised", 1_740_000_000_000_000_000 + i, float(i),
        3e-12, 2e-13, 1e-12, 5e-13, 2e-12, 12.0, message,
    )


def test_router_config_lets_only_the_rigs_own_twin_publish(certs: Path, tmp_path: Path) -> None:
    endpoint = f"tls/127.0.0.1:{free_port()}"
    arrived: queue.Queue[str] = queue.Queue()  # every payload that reaches an observer on the alarm key
    with node(ROUTER, certs, "router-local", endpoint), node(
        PEER, certs, "twin", endpoint
    ) as twin_session, AlarmJournal(tmp_path / "alarms.db") as journal, TwinPublisher(
        twin_session, RIG, journal
    ) as twin:
        first = twin.publish_alarm(alarm(1, "real"))
        with node(PEER, certs, "observer", endpoint) as observer, AlarmSubscriber(observer, RIG) as sub:
            raw = observer.declare_subscriber(f"fpdd/{RIG}/alarm",
                                              lambda s: arrived.put(json.loads(s.payload.to_string())["message"]))
            assert sub.recv(timeout=WAIT_S) == first  # history through the router
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            second = twin.publish_alarm(alarm(2, "real"))
            assert sub.recv(timeout=WAIT_S) == second  # live through the router
            assert arrived.get(timeout=WAIT_S) == "real"
            # Forgers, each from its own session (a session's own subscribers would get it locally):
            # an observer, and the twin of hall 2 whose certificate may publish only hall 2's rigs.
            for who in ("observer", "twin-hall2"):
                with node(PEER, certs, who, endpoint) as forger:
                    forger.put(f"fpdd/{RIG}/alarm", event_to_json(alarm(3, f"forged by {who}").with_seq(3)))
                    forger.put(f"fpdd/{RIG}/alarm", event_to_json(alarm(100, f"forged by {who}").with_seq(100)))
                    # A round trip on the same link: the router has handled the puts when it answers.
                    list(forger.get(f"fpdd/{RIG}/status", timeout=WAIT_S))
            with node(PEER, certs, "twin-hall2", endpoint) as hall2, \
                    AlarmJournal(tmp_path / "hall2.db") as other, TwinPublisher(hall2, "msp25-hall2-a", other) as own:
                own.publish_alarm(alarm(1, "hall 2's own", rig="msp25-hall2-a"))  # its own rig: allowed
                with AlarmSubscriber(observer, "msp25-hall2-a") as sub2:
                    assert sub2.recv(timeout=WAIT_S).message == "hall 2's own"
            third = twin.publish_alarm(alarm(3, "real"))
            assert sub.recv(timeout=WAIT_S) == third
            # Nothing else, whatever the machine's speed: the twin's next alarm, through the same router, is the
            # next one delivered, and on the raw key the next payloads are the real third and fourth alone.
            fourth = twin.publish_alarm(alarm(4, "real"))
            assert sub.recv(timeout=WAIT_S) == fourth
            assert [arrived.get(timeout=WAIT_S) for _ in range(2)] == ["real", "real"]  # no forged payload came
            assert arrived.empty()
            raw.undeclare()
            assert sub.rejected == 0 and sub.missed == []
        with node(PEER, certs, "intruder", endpoint) as intruder:
            assert live_twins(intruder, timeout=1.0) == []
            assert list(intruder.get(f"fpdd/{RIG}/alarm/history", timeout=1.0)) == []


# --------------------------------------------------------------------------- README, word for word


def readme_section_script(title: str) -> str:
    text = README.read_text(encoding="utf-8")
    section = text.split(f"## {title}", 1)[1].split("\n## ", 1)[0]
    return "\n".join(re.findall(r"```sh\n(.*?)```", section, re.DOTALL))


@pytest.mark.slow
def test_the_readme_try_it_commands_run_as_written(tmp_path: Path) -> None:
    """Certificates, router, ZENOH_CONFIG=... twin serve, twin alarms --zenoh-config: exactly as documented."""
    script = readme_certificate_script() + readme_section_script("Try it on one machine")
    bin_dir = str(Path(sys.executable).parent)
    env = {**os.environ, "FPDD": str(DEPLOY.parent), "PATH": bin_dir + os.pathsep + os.environ["PATH"],
           "PYTHONPATH": os.pathsep.join([str(DEPLOY.parent), os.environ.get("PYTHONPATH", "")])}
    env.pop("ZENOH_CONFIG", None)
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stdout + done.stderr
    got = AlarmEvent.from_dict(json.loads((tmp_path / "alarm.json").read_text()))
    assert (got.rig, got.parameter, got.seq) == (RIG, "Ffric", 1) and got.level in ("warning", "alarm")
    assert json.loads((tmp_path / "alarm.json").read_text())["verification"] == "verified"  # signed by the service
    assert "Ffric" in done.stdout  # the second twin alarms printed the history
    serve_log = (tmp_path / "serve.log").read_text()
    assert "twin serve: 1 rig(s)" in serve_log and "zenoh client" in serve_log and "Traceback" not in serve_log
