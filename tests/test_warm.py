"""``twin warm`` compiles a model's paths once, so that the next run loads them from the cache.

A copy of the packages in a temporary directory has no compiled code beside it (numba caches beside the modules
it compiles): the first ``twin warm`` there compiles, the second finds everything compiled."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _warm(tree: Path, *args: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    env.pop("NUMBA_CACHE_DIR", None)
    p = subprocess.run([sys.executable, "-m", "twin.cli", "warm", *args, "--json"], cwd=tree, env=env,
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


@pytest.mark.slow
def test_warm_compiles_once_and_the_next_run_loads(tmp_path) -> None:
    tree = tmp_path / "tree"
    for pkg in ("fpdd", "twin", "replay"):
        shutil.copytree(ROOT / pkg, tree / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    first = _warm(tree, "--model", "oscillator")
    (row,) = first["models"]
    assert row["model"] == "oscillator" and set(row["cpu_s"]) == {"simulate", "track", "fit"}
    assert any((tree / "twin" / "online" / "__pycache__" / "kernels").rglob("*.nbi")), \
        "the tracker's kernel was not cached beside the tree"
    second = _warm(tree, "--model", "oscillator")["models"][0]
    # the compiled code comes from the cache: the whole warm-up is a fraction of the first one's CPU, and so is
    # each step that compiled something (the tracker's kernel, the model's simulation)
    assert second["total_cpu_s"] < 0.5 * row["total_cpu_s"], (row, second)
    assert second["cpu_s"]["track"] < 0.5 * row["cpu_s"]["track"], (row, second)


def test_warm_refuses_an_unknown_model(capsys) -> None:
    from twin.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["warm", "--model", "nonesuch"])
    assert exc.value.code == 2
    assert "invalid choice: 'nonesuch'" in capsys.readouterr().err
