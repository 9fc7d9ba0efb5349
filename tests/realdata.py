"""Where the real measured records are kept: ``FPDD_REALDATA``, else a ``shared/realdata`` folder beside the project
(or beside any folder above it). Read there, never copied into the project."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def realdata(*parts: str) -> Path:
    """The file ``parts`` under the real-data folder.

    Where it is missing the test skips with one line naming the data set, except under ``CI=true``, where a missing
    data set is a failure (CI runs every test)."""
    roots = [Path(os.environ["FPDD_REALDATA"])] if os.environ.get("FPDD_REALDATA") else [
        p / "shared" / "realdata" for p in Path(__file__).resolve().parents]
    for root in roots:
        path = root.joinpath(*parts)
        if path.is_file():
            return path
    message = (f"the real-data record realdata/{'/'.join(parts)} is not beside the project (looked in "
               f"{', '.join(str(r) for r in roots)}; set FPDD_REALDATA to the realdata folder)")
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(message)
    pytest.skip(message)
