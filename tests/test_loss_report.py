"""No silent loss: what a reader lost reaches every command that reads a record (twin track, fit, diagnose,
serve) as a warning line on stderr, ``input_lost`` in the JSON and exit status 3; a record without a usable
sample or without a signal the command needs is refused with one line.

The damaged files are made here from one short simulated record: an MCAP cut inside its third chunk, a CSV
with x NaN on every other row, a header-only CSV, a CSV whose x_ref and x columns carry a unit in their name.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from net_helpers import free_port
from replay.base import Samples
from replay.csvio import CsvSink
from replay.mcapio import McapSink
from twin import cli
from twin.models import msp25 as M
from twin.models.scenario import simulate_wear
from fpdd.units import NOMINAL_NOISE
from twin.models.simulate import excite

N = 2000  # samples of the record (2 s at 1 kHz)


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Samples:
    _, xr = excite(M.MODEL, N * 1e-3, 1e-3, seed=1031)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, (), noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=1031)
    return rec.to_samples()


def mcap_cut_in_third_chunk(s: Samples, d: Path) -> Path:
    p = d / "cut.mcap"
    with McapSink(p, flush_period_s=0.4) as sink:  # a chunk per 0.4 s of samples
        sink.write(s)
    with open(p, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 4, len(chunks)
    third = chunks[2]
    data = p.read_bytes()
    p.write_bytes(data[: third.chunk_start_offset + third.chunk_length // 2])
    return p


def csv_of(s: Samples, d: Path, name: str) -> Path:
    p = d / name
    with CsvSink(p) as sink:
        sink.write(s)
    return p


def csv_nan_every_other_x(s: Samples, d: Path) -> Path:
    x = s["x"].copy()
    x[1::2] = np.nan
    return csv_of(Samples(s.t_ns, {**s.signals, "x": x}), d, "nan.csv")


def csv_header_only(s: Samples, d: Path) -> Path:
    p = csv_of(s, d, "header.csv")
    p.write_text(p.read_text().splitlines()[0] + "\n")
    return p


def csv_unknown_columns(s: Samples, d: Path) -> Path:
    p = csv_of(s, d, "columns.csv")
    lines = p.read_text().splitlines()
    # x_ref[mm] is x_ref in mm (a unit in the header is read); x[zz] names no unit: a column not understood
    lines[0] = ",".join({"x_ref": "x_ref[mm]", "x": "x[zz]"}.get(c, c) for c in lines[0].split(","))
    p.write_text("\n".join(lines) + "\n")
    return p


@dataclasses.dataclass(frozen=True)
class Damage:
    name: str
    make: Callable[[Samples, Path], Path]
    code: int          # exit status of every command
    says: str          # substring of the warning (exit 3) or of the one-line refusal (exit 2)


DAMAGES = [
    Damage("mcap-cut-in-third-chunk", mcap_cut_in_third_chunk, 3, "input lost ("),
    Damage("csv-x-nan-every-other-row", csv_nan_every_other_x, 3, f"input lost (nan={N // 2}"),
    Damage("csv-header-only", csv_header_only, 2, "no data rows after the header (line 1): an empty record"),
    Damage("csv-unknown-columns", csv_unknown_columns, 2,
           "column(s) 'x[zz]' not understood (no signal of the msp25 model); missing signal(s) x; "),
]


def _track(path: Path, out: Path) -> list[str]:
    return ["track", str(path), "--out", str(out / "track"), "--json"]


def _fit(path: Path, out: Path) -> list[str]:
    return ["fit", str(path), "--free", "Ffric", "--starts", "1", "--json"]


def _diagnose(path: Path, out: Path) -> list[str]:
    return ["diagnose", str(path), "--candidates", "spool_deadband", "--max-effects", "1", "--no-timing-test", "--json"]


COMMANDS = {"track": _track, "fit": _fit, "diagnose": _diagnose}


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("damage", DAMAGES, ids=[d.name for d in DAMAGES])
def test_a_command_says_what_its_reader_lost_or_refuses(damage, command, good, tmp_path, capsys):
    path = damage.make(good, tmp_path)
    code = cli.main(["-q", *COMMANDS[command](path, tmp_path)])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    assert code == damage.code, err
    if code == 3:
        warnings = [line for line in err.splitlines() if line.startswith(f"twin {command}: warning: ")]
        assert len(warnings) == 1 and damage.says in warnings[0] and str(path) in warnings[0], err
        result = json.loads(out)
        assert result["input_lost"] == [warnings[0].split("warning: ", 1)[1]]
    else:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"twin {command}: error: {path}: "), err
        assert damage.says in lines[0]
        assert out == ""


def test_the_undamaged_record_reports_no_loss(good, tmp_path, capsys):
    path = csv_of(good, tmp_path, "good.csv")
    for command, args in COMMANDS.items():
        assert cli.main(["-q", *args(path, tmp_path)]) == 0, command
        out, err = capsys.readouterr()
        assert json.loads(out)["input_lost"] == [] and "warning" not in err
    code = cli.main(["-q", "serve", "--config", str(_serve_config(tmp_path, path)), "--json", "--log-level", "error"])
    out, err = capsys.readouterr()
    assert code == 0 and json.loads(out)["rig-a"]["input_lost"] == "" and "warning" not in err, err
    assert f"summary rig-a: finished, {N} samples" in err


def _serve_config(tmp_path: Path, log: Path) -> Path:
    p = tmp_path / "rigs.toml"
    p.write_text(f"""
[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{free_port()}"]

[service]
journal_dir = "{tmp_path / 'journal'}"

[[rig]]
name = "rig-a"
source = "{log}"
speed = 0
""")
    return p


@pytest.mark.parametrize("damage", DAMAGES, ids=[d.name for d in DAMAGES])
def test_serve_keeps_the_loss_in_its_summary_and_exits_3_or_refuses(damage, good, tmp_path, capsys):
    path = damage.make(good, tmp_path)
    code = cli.main(["-q", "serve", "--config", str(_serve_config(tmp_path, path)), "--json",
                     "--log-level", "error"])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    summary = next(line for line in err.splitlines() if line.startswith("twin serve: summary rig-a: "))
    if damage.code == 3:
        assert code == 3, err
        assert summary.startswith("twin serve: summary rig-a: finished") and damage.says in summary, summary
        warning = [line for line in err.splitlines() if line.startswith("twin serve: warning: rig rig-a: ")]
        assert len(warning) == 1 and damage.says in warning[0]
        assert damage.says in json.loads(out)["rig-a"]["input_lost"]
    else:
        assert code == 2, err
        assert "rig-a: failed" in summary and damage.says in summary, summary


def test_the_python_api_never_passes_a_loss_over_in_silence(good, tmp_path, caplog):
    import logging

    import twin

    path = csv_nan_every_other_x(good, tmp_path)
    caplog.set_level(logging.WARNING)
    records = twin.load_records(str(path))
    assert sum(len(r) for r in records) == N // 2
    assert [r.getMessage() for r in caplog.records if "input lost (nan=1000" in r.getMessage()]
    caplog.clear()
    reports: list = []
    twin.load_records(str(path), reports=reports)
    assert len(reports) == 1 and reports[0].lossy and reports[0].skipped["nan"] == N // 2
    assert not caplog.records  # the caller that asked for the report says it
    tracked = twin.track(str(path))
    assert tracked.read_report is not None and tracked.read_report.skipped["nan"] == N // 2
    assert [r.getMessage() for r in caplog.records if "input lost (nan=1000" in r.getMessage()]
