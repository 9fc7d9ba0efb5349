"""The ``replay`` command: info, convert, help, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from replay import cli
from replay.options import EXIT_LOSS
from replay.factory import open_source
from roundtrip_base import DATA


def run(capsys: pytest.CaptureFixture, *argv: str) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("name", ["reference.mcap", "reference.csv"])
def test_info_json(capsys: pytest.CaptureFixture, name: str) -> None:
    code, out, _ = run(capsys, "info", str(DATA / name), "--json")
    assert code == 0
    d = json.loads(out)
    assert d["signals"] == ["x_ref", "u", "x", "pA", "pB"]
    assert d["samples"] == 200
    assert d["duration_s"] == pytest.approx(0.199, abs=1e-6)
    assert d["rate_hz"] == pytest.approx(1000.0, rel=1e-4)
    assert d["median_step_s"] == pytest.approx(1e-3, rel=1e-4)
    assert d["report"]["skipped"] == {} and d["report"]["gaps_ns"] == []
    if name.endswith(".mcap"):
        topics = {t["topic"]: t["messages"] for t in d["format"]["topics"]}
        assert topics == {"/rig/signals_block": 1, "/rig/signals": 200}


def test_info_ranges_carry_units(capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    """Text: each range in its display unit (x in mm, pressures in MPa, u in V, T_oil in K: the one display table
    of fpdd.units, a factor only, as in the reports); JSON: SI with the unit beside."""
    code, out, _ = run(capsys, "info", str(DATA / "reference.csv"), "--json")
    assert code == 0
    ranges = json.loads(out)["ranges"]
    assert {k: r["unit"] for k, r in ranges.items()} == {"x_ref": "m", "u": "V", "x": "m", "pA": "Pa", "pB": "Pa"}
    code, text, _ = run(capsys, "info", str(DATA / "reference.csv"))
    assert code == 0
    shown = {line.split(":")[0].strip(): line.split(":", 1)[1].strip() for line in text.splitlines()
             if line.startswith("  ") and line.rstrip().endswith(("mm", "MPa", "V"))}
    for k, (unit, scale) in {"x_ref": ("mm", 1e3), "x": ("mm", 1e3), "u": ("V", 1.0), "pA": ("MPa", 1e-6),
                             "pB": ("MPa", 1e-6)}.items():
        lo, hi = (float(v) for v in shown[k].removesuffix(unit).strip().strip("[]").split(","))
        assert lo == pytest.approx(ranges[k]["min"] * scale, rel=1e-5)
        assert hi == pytest.approx(ranges[k]["max"] * scale, rel=1e-5)
    path = tmp_path / "oil.csv"
    path.write_text("t,T_oil\n" + "".join(f"{i * 1e-3!r},{313.15 + i}\n" for i in range(11)))
    code, out, _ = run(capsys, "info", str(path), "--json")
    assert json.loads(out)["ranges"]["T_oil"] == {"min": pytest.approx(313.15), "max": pytest.approx(323.15),
                                                  "unit": "K"}
    code, text, _ = run(capsys, "info", str(path))
    assert "T_oil: [313.15, 323.15] K" in text


def test_info_text_reports_gaps_and_bad_rows(capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    path = tmp_path / "gappy.csv"
    rows = [f"{i * 1e-3!r},{0.001 * i!r}" for i in range(40)] + ["0.041,oops"]
    rows += [f"{0.5 + i * 1e-3!r},0.0" for i in range(40)]
    path.write_text("t,x\n" + "\n".join(rows) + "\n")
    code, out, err = run(capsys, "info", str(path))
    assert code == EXIT_LOSS  # it completed, but a row was lost: the exit status says so
    assert "samples: 80" in out and "gaps: 1" in out and "bad_row=1" in out
    assert "line 42: field 'x' = 'oops' is not a number" in out
    assert err == (f"replay: warning: {path}: input lost (bad_row=1); 80 samples kept; first: line 42: "
                   "field 'x' = 'oops' is not a number, expected a float\n")


def test_convert_csv_to_mcap_and_back(capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    mcap = tmp_path / "ref.mcap"
    csv = tmp_path / "back.csv"
    assert run(capsys, "convert", str(DATA / "reference.csv"), str(mcap))[0] == 0
    code, out, _ = run(capsys, "convert", str(mcap), str(csv), "--json")
    assert code == 0 and json.loads(out)["input"]["samples_out"] == 200
    with open_source(DATA / "reference.csv") as a, open_source(csv) as b:
        x, y = a.read_all(), b.read_all()
    assert np.array_equal(x.t_ns, y.t_ns) and all(np.array_equal(x[k], y[k]) for k in x.names)


def test_convert_with_mapping(capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    src = tmp_path / "foreign.csv"
    src.write_text("t,pos_mm,p_a_bar\n0.0,1.0,100\n0.001,2.0,110\n")
    out = tmp_path / "si.csv"
    code, _, err = run(capsys, "convert", str(src), str(out), "--map", "x=pos_mm:mm", "--map", "pA=p_a_bar:bar")
    assert code == 0, err
    with open_source(out) as s:
        got = s.read_all()
    assert got.names == ("x", "pA")
    np.testing.assert_allclose(got["pA"], [1e7, 1.1e7])


def test_errors_name_the_file_and_exit_1(capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    code, _, err = run(capsys, "info", str(tmp_path / "log.xyz"))
    assert code == 1 and "log.xyz: unknown format" in err
    code, _, err = run(capsys, "info", str(tmp_path / "absent.mcap"))
    assert code == 1 and "absent.mcap: cannot read log file" in err


@pytest.mark.parametrize("argv, message", [
    (["info", str(DATA / "reference.csv"), "--map", "nonsense"], "expected --map NAME=COLUMN[:UNIT]"),
    (["info", str(DATA / "reference.csv"), "--map", "pos_mm=x:mm"], "did you mean --map x=pos_mm:mm?"),
    (["info", str(DATA / "reference.mcap"), "--map", "a=x"], "--map applies to CSV input"),
    (["info", str(DATA / "reference.csv"), "--topic", "/rig/signals"], "--topic applies to MCAP input"),
    (["convert", str(DATA / "reference.mcap"), "out.csv", "--dbc", "rig.dbc"], "--dbc applies to CAN logs"),
])
def test_misplaced_options_are_usage_errors(capsys: pytest.CaptureFixture, argv: list[str], message: str) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv", [[], ["info"], ["convert"], ["play"], ["record"]])
def test_every_command_has_help(capsys: pytest.CaptureFixture, argv: list[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main([*argv, "--help"])
    assert exc.value.code == 0
    assert "usage: replay" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [["-q", "play"], ["play", "-q"], ["--quiet", "play"]])
def test_quiet_anywhere_and_speed_0_is_as_fast_as_possible(capsys: pytest.CaptureFixture, argv: list[str],
                                                           tmp_path) -> None:
    """``replay -q`` (or ``play -q``) prints no progress; ``--speed 0`` plays as fast as possible, as in
    ``twin demo --speed 0`` (a 1 s log takes no wall-clock second)."""
    import can

    slow = tmp_path / "short_1s.blf"  # the short log's frames stretched to 1 s (50 Hz): far from real time on a busy machine
    with can.BLFReader(str(DATA / "msp25_short.blf")) as reader, can.BLFWriter(str(slow)) as writer:
        t0 = None
        for msg in reader:
            t0 = msg.timestamp if t0 is None else t0
            msg.timestamp = t0 + 20.0 * (msg.timestamp - t0)
            writer.on_message_received(msg)
    channel = f"q{len(argv[0])}{argv[-1]}"
    with can.Bus(interface="virtual", channel=channel) as rx:
        code, out, err = run(capsys, *argv, str(slow), "--to", "can", "--channel",
                             f"can://virtual/{channel}", "--speed", "0", "--json")
        frames = 0
        while rx.recv(timeout=0.0) is not None:
            frames += 1
    assert code == 0 and err == "", err
    stats = json.loads(out)["stats"]
    assert stats["speed"] is None and stats["samples"] > 0 and frames > stats["samples"]
    assert stats["wall_s"] < stats["log_span_s"]
    with pytest.raises(SystemExit) as info:
        cli.main(["play", str(DATA / "msp25_short.blf"), "--to", "can", "--channel", f"can://virtual/{channel}",
                  "--speed", "-1"])
    assert info.value.code == 2
    assert "expected a factor > 0, or 0 (or inf) for as fast as possible" in capsys.readouterr().err
