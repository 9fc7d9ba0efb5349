"""``twin track`` says what a damaged CAN log lost as ``twin serve`` does: ``input_lost`` in ``--json``, a warning
line on stderr, exit 3; an undamaged log: nothing lost, exit 0.  The logs are the repository's MSP25 CAN logs
(``tests/data/msp25_short.*``), damaged by the helpers of the damaged-input tests."""

from __future__ import annotations

import json

import pytest

import test_damaged_inputs as D
from twin import cli

DAMAGED = {
    "blf-container": D.blf_flip_container(1),
    "blf-signature": D.blf_break_signature(2),
    "asc-wild-time": D.text_edit(".asc", D.wild_time(".asc"), "asc-wild-time"),
    "asc-truncated": D.text_edit(".asc", D.truncate_mid_line, "asc-truncated"),
}


def _track(path, tmp_path, capsys):
    capsys.readouterr()
    rc = cli.main(["-q", "track", str(path), "--out", str(tmp_path / "track"), "--json"])
    out, err = capsys.readouterr()
    return rc, json.loads(out), err


@pytest.mark.parametrize("damage", sorted(DAMAGED))
def test_a_damaged_can_log_is_tracked_with_its_loss_said(damage, tmp_path, capsys):
    path = DAMAGED[damage](tmp_path)
    rc, out, err = _track(path, tmp_path, capsys)
    assert rc == 3, (damage, err)
    assert len(out["input_lost"]) == 1 and str(path) in out["input_lost"][0] and "input lost" in out["input_lost"][0]
    assert 0 < out["samples"] <= D.N_CAN
    warnings = [ln for ln in err.splitlines() if ln.startswith("twin track: warning:")]
    assert warnings == [f"twin track: warning: {out['input_lost'][0]}"]


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_an_undamaged_can_log_loses_nothing(suffix, tmp_path, capsys):
    path = D.DATA / f"msp25_short{suffix}"
    rc, out, err = _track(path, tmp_path, capsys)
    assert rc == 0 and out["input_lost"] == [] and "warning" not in err
    assert out["samples"] == D.N_CAN
