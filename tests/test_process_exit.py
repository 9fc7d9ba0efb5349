"""A program that loaded Zenoh leaves the process with its code while Zenoh's threads still deliver samples.

The interpreter's own finalization cannot be trusted then: a Zenoh thread calling a Python callback while the
interpreter shuts down either hangs the exit or aborts the process (SIGABRT, "FATAL: exception not rethrown",
seen once in CI on ``twin serve`` after its summary). ``fpdd.process.exit_process`` skips that finalization.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
import time

import zenoh

from fpdd.zenohconf import zenoh_config

WAIT_S = 60.0  # a process that exits within about a second; the bound only stops a hung one

SUBSCRIBER = textwrap.dedent("""
    import sys, time, zenoh
    from fpdd.process import exit_process
    from fpdd.zenohconf import zenoh_config
    seen = [0]
    def on_sample(sample):
        seen[0] += 1
        time.sleep(0.0005)  # the callback is still running on Zenoh's thread when the main thread leaves
    session = zenoh.open(zenoh_config("peer", connect=[sys.argv[1]]))
    session.declare_subscriber("fpdd/exit-test", on_sample)
    t0 = time.monotonic()
    while seen[0] < 200 and time.monotonic() - t0 < 30:
        time.sleep(0.01)
    print(f"seen {seen[0]}", flush=True)
    exit_process(3 if seen[0] >= 200 else 1)  # the session left open on purpose: a sample in flight at the exit
""")


def test_exit_process_leaves_with_its_code_while_zenoh_delivers_samples(endpoint: str, tmp_path) -> None:
    script = tmp_path / "subscriber.py"
    script.write_text(SUBSCRIBER)
    stop = threading.Event()
    with zenoh.open(zenoh_config("peer", listen=[endpoint])) as session:
        publisher = session.declare_publisher("fpdd/exit-test")

        def flood() -> None:
            while not stop.is_set():
                publisher.put(b"0" * 64)
                time.sleep(0.0001)

        th = threading.Thread(target=flood, name="flood", daemon=True)
        th.start()
        try:
            done = subprocess.run([sys.executable, str(script), endpoint], capture_output=True, text=True,
                                  timeout=WAIT_S)
        finally:
            stop.set()
            th.join(WAIT_S)
    assert done.stdout.startswith("seen "), done.stderr
    assert int(done.stdout.split()[1]) >= 200, done.stdout
    assert done.returncode == 3, (done.returncode, done.stderr[-2000:])
