"""Where the real measured records are kept: ``FPDD_REALDATA``, else a ``shared/realdata`` folder beside the project
(or beside any folder above it). Read there, never copied into the project."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def realdata(*parts: str) -> Path:
    """The file ``parts`` under the real-data folder; the test fails with one line saying where it looked."""
    roots = [Path(os.environ["FPDD_REALDATA"])] if os.environ.get("FPDD_REALDATA") else [
        p / "shared" / "realdata" for p in Path(__file__).resolve().parents]
    for root in roots:
        path = root.joinpath(*parts)
        if path.is_file():
            return path
    pytest.fail(f"the real-data record realdata/{'/'.join(parts)} is not beside the project (looked in "
                f"{', '.join(str(r) for r in roots)}; set FPDD_REALDATA to the realdata folder)")
