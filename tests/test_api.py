"""The README's Python API example runs as written, and the curated API is what it says."""

from __future__ import annotations

import pathlib
import re

import replay
import twin

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def test_readme_api_example_runs(capsys):
    text = README.read_text()
    m = re.search(r"<!-- api-example -->\n```python\n(.*?)```", text, re.S)
    assert m, "README: the API example block is missing"
    exec(compile(m.group(1), "README.md:api-example", "exec"), {})
    out = capsys.readouterr().out
    assert "Ffric" in out and "zeta tracked:" in out


def test_every_public_name_resolves():
    for name in twin.__all__:
        assert getattr(twin, name) is not None, name
    for name in replay.__all__:
        assert getattr(replay, name) is not None, name
    assert twin.TwinError is replay.TwinError  # one error tree, at the bottom layer


def test_api_functions_survive_their_modules_being_imported():
    import importlib

    for mod in ("twin.estimation.fit", "twin.service.track", "twin.estimation.diagnose"):
        importlib.import_module(mod)
    assert callable(twin.fit) and callable(twin.track) and callable(twin.diagnose)
    assert twin.fit.__module__ == "twin.estimation.fit" and twin.diagnose.__name__ == "diagnose"
