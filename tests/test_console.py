"""The service's console: a reader that stops reading never stalls the service (twin.service.console)."""

from __future__ import annotations

import io
import logging
import os
import threading

from twin.service.console import Console, install


def test_lines_to_a_console_nobody_reads_never_block_and_the_loss_is_said_when_it_moves():
    r, w = os.pipe()
    stream = os.fdopen(w, "w", buffering=1)
    console = Console(stream, capacity=100)
    done = threading.Event()

    def flood():
        for i in range(5000):  # far more than the pipe (64 KiB) and the queue hold
            console.line(f"line {i:05d} " + "x" * 60)
        done.set()

    th = threading.Thread(target=flood, daemon=True)
    th.start()
    assert done.wait(60.0), "a console nobody reads blocked the writer"
    assert console.dropped > 0
    # the reader comes back: what was kept is written, and the loss is said
    reader = os.fdopen(r, "r")
    chunks = []
    t = threading.Thread(target=lambda: chunks.append(reader.read()), daemon=True)
    t.start()
    # the queue empties as the reader reads: a line written before it has room is dropped (and counted) too
    dropped, tries = console.dropped, 0
    while True:
        console.line("after the stall")
        if console.dropped == dropped:
            break
        dropped, tries = console.dropped, tries + 1
        assert tries < 100_000, "the console never moved again"
        threading.Event().wait(0.001)
    assert console.close(timeout=30.0)
    stream.close()
    t.join(30.0)
    reader.close()
    text = chunks[0]
    assert text.startswith("line 00000 ")
    assert "console line(s) dropped: the console was not read" in text
    assert text.rstrip().endswith("after the stall")
    written = [ln for ln in text.splitlines() if ln.startswith("line ")]
    assert len(written) + console.dropped - tries == 5000


def test_log_records_go_through_the_console_in_order():
    buf = io.StringIO()
    root = logging.getLogger()
    saved = list(root.handlers), root.level
    try:
        console = install(logging.INFO, stream=buf)
        log = logging.getLogger("twin.serve")
        log.info("rig a: started")
        log.debug("not shown")
        log.warning("rig a: stale input")
        assert console.close()
    finally:
        for h in list(root.handlers):
            root.removeHandler(h)
        for h in saved[0]:
            root.addHandler(h)
        root.setLevel(saved[1])
    assert buf.getvalue().splitlines() == ["twin serve: rig a: started", "twin serve: rig a: stale input"]
