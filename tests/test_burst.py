"""A burst of malformed payloads on one rig's live key costs only those payloads: the rig's own good samples
that arrive during it are all processed (what is plainly not a payload is shed unparsed under the burst and
counted), and the neighbouring rig of the same service gets every sample. Real Zenoh sessions on loopback."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
import time

import pytest
import zenoh

from net_helpers import free_port
from replay.base import Samples
from replay.live import ZenohSampleSink
from fpdd.units import NOMINAL_NOISE
from fpdd.zenohconf import zenoh_config
from twin.models import msp25 as M
from twin.models.scenario import simulate_wear
from twin.models.simulate import excite
from twin.service.config import parse_config
from twin.service.serve import serve

RIGS = ("rig-a", "rig-b")
SECONDS = 12.0
BURST = 100_000


def _samples(seed: int) -> Samples:
    _, xr = excite(M.MODEL, SECONDS, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, (), noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=seed)
    s = rec.to_samples()
    return Samples(s.t_ns + (time.time_ns() // 10**6 - 60_000) * 10**6, s.signals)


def _keeper(latest: dict, rig: str):
    def keep(sample: zenoh.Sample) -> None:
        latest[rig] = json.loads(sample.payload.to_string())["counters"]
    return keep


def _until_all(latest: dict, rig: str, n: int, stall_s: float) -> bool:
    """Wait until ``rig`` reported ``n`` samples; False once its count has not moved for ``stall_s`` seconds."""
    seen, moved = -1, time.monotonic()
    while (count := latest.get(rig, {}).get("samples", 0)) < n:
        if count != seen:
            seen, moved = count, time.monotonic()
        elif time.monotonic() - moved > stall_s:
            return False
        time.sleep(0.05)
    return True


@pytest.mark.slow
def test_a_burst_of_malformed_payloads_costs_only_itself(tmp_path) -> None:
    port = free_port()
    cfg = parse_config({"zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
                        "service": {"journal_dir": str(tmp_path / "journal"), "stale_s": 0.3, "estimate_every": 100},
                        "rig": [{"name": r, "source": f"zenoh://fpdd/{r}/samples"} for r in RIGS]}, "<burst>")
    data = {r: _samples(1041 + i) for i, r in enumerate(RIGS)}
    n = len(data["rig-a"])
    stop = threading.Event()
    summaries: dict = {}
    service = threading.Thread(target=serve, args=(cfg, stop), kwargs={"summaries": summaries})
    service.start()
    try:
        with zenoh.open(zenoh_config("peer", connect=list(cfg.listen))) as session:
            latest: dict[str, dict] = {}  # rig -> the counters of its last status
            watch = [session.declare_subscriber(f"fpdd/{r}/status", _keeper(latest, r)) for r in RIGS]
            sinks = {r: ZenohSampleSink(f"fpdd/{r}/samples", session=session, end_marker=False, max_block=100)
                     for r in RIGS}
            try:
                for sink in sinks.values():
                    assert sink.wait_for_subscriber(20.0), "the service did not subscribe to its input"
                attacker = session.declare_publisher("fpdd/rig-a/samples")
                start = time.monotonic()
                for i in range(0, n, 100):
                    for r, sink in sinks.items():
                        sink.write(data[r].slice(i, i + 100))
                    if i == n // 3:  # a third in: malformed payloads as fast as they can be put
                        for k in range(BURST):
                            attacker.put(b"garbage" if k % 2 else b'{"t_ns": "bad", "x": 1}')
                    time.sleep(max(0.0, start + (i + 100) * 1e-3 - time.monotonic()))
                attacker.undeclare()
                # the neighbour catches up at the machine's pace: the wait ends when it has every sample, and
                # fails only when its count stops moving (a loaded machine is slow, not stuck)
                assert _until_all(latest, "rig-b", n, stall_s=120.0), latest
                # the target's last blocks, at the same pace (what was dropped never comes: its count stops short)
                _until_all(latest, "rig-a", n, stall_s=5.0)
            finally:
                for sink in sinks.values():
                    sink.close()
                for w in watch:
                    w.undeclare()
    finally:
        stop.set()
        service.join(timeout=60.0)
    assert not service.is_alive()
    assert latest["rig-b"]["samples"] == n, latest  # the neighbour: every sample
    assert latest["rig-a"]["samples"] == n, latest  # the target: every good sample, none dropped for the burst


_ATTACKER = """
import sys, time, zenoh
with zenoh.open(zenoh.Config.from_json5(sys.argv[1])) as s:
    p = s.declare_publisher(sys.argv[2])
    print("ready", flush=True)
    sys.stdin.readline()
    t = time.monotonic()
    for k in range(int(sys.argv[3])):
        p.put(b"garbage" if k % 2 else b'{"t_ns": "bad", "x": 1}')
    print(time.monotonic() - t, flush=True)
    sys.stdin.readline()
"""



def _ready(args: list[str], ready: str) -> subprocess.Popen:
    """A helper process, once it printed its first line (``ready`` begins it)."""
    p = subprocess.Popen([sys.executable, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None and p.stdout.readline().startswith(ready)
    return p


@pytest.mark.slow
def test_a_burst_through_the_router_leaves_the_neighbours_link_free(tmp_path) -> None:
    """A site's service is a client of its router, so everything reached it on one link: a burst on one rig's key
    held the neighbour's samples behind it for the burst's whole time on that link (lag max 0.26 s, as the
    target's own). Each ``zenoh://`` rig's input now has its own session to the router: the neighbour's lag stays
    a fraction of the target's. As on a site: the router, the service (``twin serve``), each rig's gateway (its
    own session) and the attacker are apart, the router, the service and the attacker each in a process."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    config = tmp_path / "rigs.toml"
    config.write_text(f'[zenoh]\nmode = "client"\nconnect = ["{endpoint}"]\n[service]\njournal_dir = '
                      f'"{tmp_path / "journal"}"\nstale_s = 0.3\nestimate_every = 100\n'
                      + "".join(f'[[rig]]\nname = "{r}"\nsource = "zenoh://fpdd/{r}/samples"\n' for r in RIGS))
    data = {r: _samples(1051 + i) for i, r in enumerate(RIGS)}
    n = len(data["rig-a"])
    router_conf = tmp_path / "router.json5"
    router_conf.write_text(str(zenoh_config("router", listen=[endpoint])))
    procs = [_ready(["-m", "twin.service.router", str(router_conf)], "router: listening")]
    try:
        attacker = _ready(["-c", _ATTACKER, str(zenoh_config("client", connect=[endpoint])), "fpdd/rig-a/samples",
                           str(BURST)], "ready")
        procs.append(attacker)
        with open(tmp_path / "serve.err", "w") as err:
            service = subprocess.Popen([sys.executable, "-m", "twin.cli", "serve", "--config", str(config)],
                                       stdout=subprocess.DEVNULL, stderr=err)
        procs.append(service)
        gateways = {r: zenoh.open(zenoh_config("client", connect=[endpoint])) for r in RIGS}
        try:
            latest: dict[str, dict] = {}
            watch = [gateways[r].declare_subscriber(f"fpdd/{r}/status", _keeper(latest, r)) for r in RIGS]
            sinks = {r: ZenohSampleSink(f"fpdd/{r}/samples", session=gateways[r], end_marker=False, max_block=100)
                     for r in RIGS}
            for sink in sinks.values():
                assert sink.wait_for_subscriber(60.0), "the service did not subscribe to its input"
            start = time.monotonic()
            for i in range(0, n, 100):
                for r, sink in sinks.items():
                    sink.write(data[r].slice(i, i + 100))
                if i == n // 3:
                    assert attacker.stdin is not None
                    attacker.stdin.write("go\n")
                    attacker.stdin.flush()
                time.sleep(max(0.0, start + (i + 100) * 1e-3 - time.monotonic()))
            assert attacker.stdout is not None
            put_s = float(attacker.stdout.readline())
            assert _until_all(latest, "rig-b", n, stall_s=120.0), latest
            _until_all(latest, "rig-a", n, stall_s=5.0)
            for sink in sinks.values():
                sink.close()
            for w in watch:
                w.undeclare()
        finally:
            for s in gateways.values():
                s.close()
        service.send_signal(signal.SIGTERM)
        assert service.wait(timeout=60.0) == 0
    finally:
        for p in procs:
            p.kill()
            p.communicate(timeout=30.0)  # and its pipes closed
    assert latest["rig-b"]["samples"] == n and latest["rig-a"]["samples"] == n, latest
    summary = (tmp_path / "serve.err").read_text()
    lag = {r: float(v) for r, v in re.findall(r"summary (rig-\w): .*lag max ([0-9.]+) s", summary)}
    # the target waits for its own burst (about the time it took on the wire); the neighbour does not
    assert lag["rig-a"] > 0.3 * put_s, (lag, put_s)
    assert lag["rig-b"] < 0.5 * lag["rig-a"], (lag, put_s)
