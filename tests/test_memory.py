"""Memory per rig: bounded buffers whatever the record length, and the marginal memory of a rig in one worker.

The worker test runs ``twin serve`` in its own process (real Zenoh on
loopback, replayed MCAP logs, ``workers = 1``) with 1 and with 6 rigs, and
compares the worker's resident memory of the two runs made by this test: the
marginal memory per rig must stay under the target. No timing is asserted.
"""

from __future__ import annotations

import collections
from pathlib import Path

import numpy as np
import pytest

from benchmarks.memory import TARGET_MB_PER_RIG, run_count
from benchmarks.service import _log
from twin.service.rig import ALARMS_KEPT, FORECASTS_KEPT, SERVICE_HISTORY, Ring, make_twin


def test_ring_holds_its_capacity_whatever_the_stream_length():
    rng = np.random.default_rng(1000)
    ring = Ring(3, 64)
    sizes = set()
    for k in range(1000):
        ring.add(float(k), rng.normal(size=3), rng.normal(size=3))
        sizes.add(sum(a.nbytes for a in (ring._t, ring._v, ring._s)))
    assert len(sizes) == 1 and len(ring) == 64
    t, v, _ = ring.arrays()
    assert t[0] == 1000 - 64 and t[-1] == 999  # the newest rows, in time order


def test_a_service_twin_bounds_its_histories():
    from twin.service.config import parse_config

    cfg = parse_config({"service": {"journal_dir": "j", "workers": 0},
                        "rig": [{"name": "r", "source": "x.mcap", "speed": 0}]})
    twin = make_twin(cfg.rigs[0])
    assert isinstance(twin.alarms, collections.deque) and twin.alarms.maxlen == ALARMS_KEPT
    assert isinstance(twin.forecasts, collections.deque) and twin.forecasts.maxlen == FORECASTS_KEPT
    assert twin._ring.capacity == SERVICE_HISTORY
    assert twin.forecast.max_points > 0


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_marginal_memory_per_rig_in_one_worker_is_under_the_target(tmp_path: Path):
    seconds = 20.0
    logs = [tmp_path / f"rig{i}.mcap" for i in range(2)]
    for i, p in enumerate(logs):
        _log(p, seconds, seed=1000 + i)
    one = run_count(tmp_path, logs, 1, seconds, 4.0, soak=False, say=lambda m: None)
    many = run_count(tmp_path, logs, 6, seconds, 4.0, soak=False, say=lambda m: None)
    assert one["samples"] >= 2 and many["samples"] >= 2  # the worker was read while every rig ran
    per_rig = (many["rss_mb_max"] - one["rss_mb_max"]) / 5
    assert per_rig < TARGET_MB_PER_RIG, (one, many)


def _held(open_it) -> int:
    import gc
    import tracemalloc

    gc.collect()
    tracemalloc.start()
    try:
        a = tracemalloc.get_traced_memory()[0]
        obj = open_it()
        b = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    if hasattr(obj, "close"):
        obj.close()
    return b - a


def test_a_replayed_mcap_keeps_a_small_index_per_chunk(tmp_path: Path):
    from mcap.reader import SeekingReader

    from replay.mcapio import McapSource

    files = {s: tmp_path / f"r{s:g}.mcap" for s in (10.0, 40.0)}
    for s, p in files.items():
        _log(p, s, seed=1001)
    chunks, ours, theirs = [], [], []
    for p in files.values():
        src = McapSource(str(p))
        chunks.append(len(src._summary.chunk_indexes))
        src.close()
        ours.append(_held(lambda p=p: McapSource(str(p))))
        with open(p, "rb") as f:
            theirs.append(_held(lambda f=f: SeekingReader(f).get_summary()))
    assert chunks[1] >= 3 * chunks[0] > 0  # the longer log has proportionally more chunks
    per_chunk = (ours[1] - ours[0]) / (chunks[1] - chunks[0])
    per_chunk_lib = (theirs[1] - theirs[0]) / (chunks[1] - chunks[0])
    assert per_chunk < per_chunk_lib / 3, (per_chunk, per_chunk_lib)
    assert per_chunk < 160  # a handful of 64-bit numbers per chunk (seven arrays of them)


def test_the_heap_freed_by_a_long_run_goes_back_to_the_system() -> None:
    """What the rigs free stays in the C heap (glibc keeps it in its arenas) until it is trimmed: the worker trims
    every ``TRIM_EVERY_S`` (``fpdd.process.trim_heap``). Here 125 MiB of 64-KiB blocks, freed below one still held
    (so the heap's top cannot shrink), are still resident until the trim."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        from fpdd.process import trim_heap
        def rss():
            with open("/proc/self/status") as f:
                return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024
        blocks = [bytearray(b"\\1" * 65536) for _ in range(2000)]
        held = blocks[-1]
        del blocks
        freed = rss()
        print(trim_heap(), freed, rss())
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True,
                         cwd=Path(__file__).parent.parent).stdout.split()
    trimmed, before, after = out[0] == "True", float(out[1]), float(out[2])
    assert trimmed, "no malloc_trim on this system"
    assert before - after > 100.0, (before, after)
