"""Records by spec, through a disk cache keyed by a hash of the full spec and of this package's source.

Directory: ``$FPDD_REFCACHE``, default ``tests/.refcache/``.  :func:`batch` fills the
misses in parallel processes.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import multiprocessing
import os
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from .record import Record

_HERE = Path(__file__).resolve().parent


def cache_dir() -> Path:
    return Path(os.environ.get("FPDD_REFCACHE") or _HERE.parent / ".refcache")


def _canon(o):
    if isinstance(o, np.ndarray):
        a = np.ascontiguousarray(o)
        return {"__array__": hashlib.sha256(a.tobytes()).hexdigest(), "dtype": str(a.dtype), "shape": a.shape}
    if isinstance(o, dict):
        return {str(k): _canon(v) for k, v in sorted(o.items())}
    if isinstance(o, (list, tuple)):
        return [_canon(v) for v in o]
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, float):
        return repr(o)
    return o


_SOURCE_DIGEST: str | None = None


def source_digest() -> str:
    """Digest of this package's source files (a change of the simulator invalidates the cache)."""
    global _SOURCE_DIGEST
    if _SOURCE_DIGEST is None:
        h = hashlib.sha256()
        for f in sorted(_HERE.glob("*.py")):
            if f.name in ("cli.py", "__main__.py"):
                continue
            h.update(f.name.encode())
            h.update(f.read_bytes())
        _SOURCE_DIGEST = h.hexdigest()[:16]
    return _SOURCE_DIGEST


def spec_key(spec: dict) -> str:
    text = json.dumps(_canon(spec), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256((source_digest() + text).encode()).hexdigest()[:32]


def simulate(spec: dict) -> Record:
    """One record from a complete spec (no cache)."""
    if spec["model"] == "msp25":
        from .msp25 import simulate_msp25

        return simulate_msp25(spec)
    if spec["model"] == "oscillator":
        from .oscillator import simulate_oscillator

        return simulate_oscillator(spec)
    raise ValueError(f"unknown model {spec['model']!r}")


def _path(spec: dict) -> Path:
    return cache_dir() / f"{spec['model']}-{spec_key(spec)}.npz"


def _simulate_and_store(spec: dict) -> str:
    path = _path(spec)
    simulate(spec).save(path)
    return str(path)


def _warm_up() -> None:
    """Compile (or load from numba's cache) the right-hand sides before starting workers."""
    from .msp25 import msp25_spec
    from .oscillator import oscillator_spec

    simulate(msp25_spec(0, duration=0.01, preroll=0.0, noise=None))
    simulate(msp25_spec(0, duration=0.01, preroll=0.0, controller="analog", noise=None))
    simulate(oscillator_spec(0, duration=0.01, noise=None))


def batch(specs: Sequence[dict], workers: int = 2, cache: bool = True) -> list[Record]:
    """Records of ``specs`` in order: hits read from the cache, misses simulated in ``workers``
    processes (spawned: a calling script needs the ``if __name__ == "__main__":`` guard) and stored."""
    specs = list(specs)
    if not cache:
        return [simulate(s) for s in specs]
    cache_dir().mkdir(parents=True, exist_ok=True)
    paths = [_path(s) for s in specs]
    todo: dict[Path, dict] = {}
    for p, s in zip(paths, specs):
        if not p.exists():
            todo.setdefault(p, s)
    if todo:
        if workers <= 1 or len(todo) == 1:
            for s in todo.values():
                _simulate_and_store(s)
        else:
            _warm_up()
            ctx = multiprocessing.get_context("spawn")
            with cf.ProcessPoolExecutor(max_workers=min(workers, len(todo)), mp_context=ctx) as ex:
                list(ex.map(_simulate_and_store, todo.values()))
    return [Record.load(p) for p in paths]


def get_record(spec: dict, cache: bool = True) -> Record:
    return batch([spec], workers=1, cache=cache)[0]
