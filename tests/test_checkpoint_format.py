"""Checkpoints are data, never code: a versioned JSON document of numbers, strings, lists and arrays (bit for
bit), refused with one line when it is anything else (a pickle of an earlier version, another version, damage);
a twin restored from it continues exactly as one that was never interrupted."""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from event_helpers import alarm
from net_helpers import free_port
from replay.mcapio import McapSink
from fpdd.errors import LogFormatError
from twin.models import msp25 as M
from twin.models.scenario import Drift, simulate_wear
from fpdd.units import NOMINAL_NOISE
from twin.models.simulate import excite
from twin.service.config import parse_config
from twin.service.journal import AlarmJournal, Binding
from twin.service.rig import make_twin
from twin.service.checkpoint_file import (CHECKPOINT_VERSION, Checkpoint, decode_state, encode_state,
                                          read_checkpoints, write_checkpoints)

ROOT = Path(__file__).resolve().parent.parent


class Planted:
    """Unpickling this creates ``path``: the proof that code ran."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (open, (str(self.path), "w"))


def test_plain_state_round_trips_bit_for_bit() -> None:
    rng = np.random.default_rng(1000)
    state = {"x": rng.standard_normal((3, 4)), "nan": np.array([np.nan, np.inf, -np.inf, -0.0, 5e-324]),
             "ints": np.array([-(2**63), 2**63 - 1, 0], dtype=np.int64), "mask": np.array([[True, False]]),
             "empty": np.zeros((0, 3)), "scalars": [None, True, 3, -0.0, float("nan"), float("-inf"), "text"],
             "nested": {"a": {"b": (1, 2.5)}}, "np_scalar": np.float64(0.1), "np_int": np.int64(7)}
    doc = json.loads(json.dumps(encode_state(state), allow_nan=False))
    back = decode_state(doc)
    for key in ("x", "nan", "ints", "mask", "empty"):
        assert back[key].dtype == state[key].dtype and back[key].shape == state[key].shape
        assert back[key].tobytes() == state[key].tobytes(), key
    assert back["scalars"][:4] == [None, True, 3, -0.0] and str(back["scalars"][3]) == "-0.0"
    assert np.isnan(back["scalars"][4]) and back["scalars"][5] == -np.inf and back["scalars"][6] == "text"
    assert back["nested"] == {"a": {"b": [1, 2.5]}} and back["np_scalar"] == 0.1 and back["np_int"] == 7


@pytest.mark.parametrize("value, where", [
    ({"tracker": Planted(Path("/nonexistent"))}, r"state\.tracker: a Planted cannot be saved"),
    ({"blob": b"\x80\x04"}, r"state\.blob: a bytes cannot be saved"),
    ({"arr": np.array([object()])}, r"state\.arr: an array of object cannot be saved"),
    ({"l": [1, {2: 3}]}, r"state\.l\[1\]: key 2"),
    ({"$array": 1}, r"key '\$array'"),
])
def test_only_data_can_be_saved(value, where) -> None:
    with pytest.raises(TypeError, match=where):
        encode_state(value)


@pytest.mark.parametrize("doc, message", [
    ({"$array": {"dtype": "object", "shape": [1], "data": ""}}, r"array dtype 'object'"),
    ({"$array": {"dtype": "float64", "shape": [2], "data": "AAAAAAAAAAA="}}, r"8 bytes for shape \[2\]"),
    ({"$array": {"dtype": "float64", "shape": [-1], "data": ""}}, r"array shape"),
    ({"$float": "1e999"}, r"special float"),
    ({"$code": "print()"}, r"unknown tag '\$code'"),
])
def test_a_document_that_is_not_plain_state_is_refused(doc, message) -> None:
    with pytest.raises(ValueError, match=message):
        decode_state({"k": doc})


def _saved(tmp_path: Path) -> Path:
    """A journal with two alarms and a checkpoint of rig ``msp25``; returns the checkpoint file."""
    with AlarmJournal(tmp_path / "rig.db") as journal:
        journal.append(alarm(i=1))
        journal.append(alarm(i=2))
        journal.save_checkpoint(Checkpoint("msp25", 5, 10, "fp", {"x": np.arange(3.0)}, 1.0))
    return tmp_path / "rig.checkpoint.json"


def test_a_checkpoint_records_its_journal_and_last_alarm(tmp_path: Path) -> None:
    path = _saved(tmp_path)
    doc = json.loads(path.read_text())
    assert doc["format"] == "fpdd-twin checkpoint" and doc["version"] == CHECKPOINT_VERSION
    jid, cps = read_checkpoints(path)
    with AlarmJournal(tmp_path / "rig.db") as journal:
        assert jid == journal.store.journal_id and len(jid) == 32
        cp = journal.load_checkpoint("msp25")
    assert cp is not None and cps["msp25"].alarm_seq == cp.alarm_seq
    assert cp.alarm_seq == 2 and cp.journal_id == jid and cp.t_ns == 5 and cp.samples == 10
    assert cp.state["x"].tolist() == [0.0, 1.0, 2.0]


@pytest.mark.parametrize("damage, message", [
    (lambda d: d.replace('"version":2', '"version":99'), r"checkpoint version 99, this program reads version 2"),
    (lambda d: d.replace('"format":"fpdd-twin checkpoint"', '"format":"other"'), r"not a checkpoint of this "
                                                                                   r"program \(format 'other'"),
    (lambda d: d.replace('"alarm_seq":2', '"alarm_seq":1'), r"HMAC does not match its content under the journal's "
                                                            r"key"),
    (lambda d: d[: len(d) // 2], r"not a JSON checkpoint document"),
    (lambda d: d.replace('"hmac"', '"hmac":NaN,"x"'), r"not a JSON checkpoint document"),
])
def test_a_checkpoint_of_another_version_or_damaged_is_refused_with_one_line(tmp_path: Path, damage,
                                                                             message) -> None:
    path = _saved(tmp_path)
    path.write_text(damage(path.read_text()))
    with pytest.raises(LogFormatError, match=message) as info:
        AlarmJournal(tmp_path / "rig.db")
    text = str(info.value)
    assert "\n" not in text and text.startswith(str(path)) and "move it aside" in text


def test_a_pickled_checkpoint_never_runs(tmp_path: Path) -> None:
    """A crafted pickle in the checkpoint's place (file beside the journal, or the table of an earlier
    version) is refused with one line; the file its code would create is never created."""
    marker = tmp_path / "planted"
    path = _saved(tmp_path)
    path.write_bytes(pickle.dumps({"tracker": Planted(marker)}))
    with pytest.raises(LogFormatError, match=r"rig\.checkpoint\.json: not a checkpoint of this program"):
        AlarmJournal(tmp_path / "rig.db")
    assert not marker.exists()
    # a journal of schema 1 that still holds a pickled checkpoint in its table
    old = tmp_path / "old.db"
    with sqlite3.connect(old) as db:
        db.executescript("""
            CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
            INSERT INTO meta VALUES ('schema_version', '1');
            CREATE TABLE checkpoints (rig TEXT PRIMARY KEY, t_ns INTEGER NOT NULL, samples INTEGER NOT NULL,
                fingerprint TEXT NOT NULL, state BLOB NOT NULL, crc INTEGER NOT NULL, saved_at REAL NOT NULL);""")
        db.execute("INSERT INTO checkpoints VALUES ('r', 1, 1, 'fp', ?, 0, 0.0)",
                   (pickle.dumps({"tracker": Planted(marker)}),))
    before = old.read_bytes()
    with pytest.raises(LogFormatError, match=r"old\.db: holds checkpoints of an earlier version \(pickled"):
        AlarmJournal(old)
    assert not marker.exists() and old.read_bytes() == before
    with sqlite3.connect(old) as db:  # what the refusal says to do
        db.execute("DELETE FROM checkpoints")
    db.close()
    with AlarmJournal(old) as journal:  # the journal of schema 1 opens, its rigs start afresh
        assert journal.store.meta("schema_version") == "2" and journal.append(alarm(i=1)).seq == 1
    assert not marker.exists()


def _wear_log(path: Path, seed: int, seconds: float = 12.0) -> None:
    _, xr = excite(M.MODEL, seconds, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [Drift("Ffric", 3.0, 3.0, shape="step")],
                           noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}, seed=seed)
    with McapSink(str(path)) as sink:
        sink.write(rec.to_samples())


@pytest.mark.slow
def test_twin_serve_refuses_a_pickled_checkpoint_or_a_lost_journal_with_one_line(tmp_path: Path) -> None:
    log = tmp_path / "rig.mcap"
    _wear_log(log, 1001)
    journal = tmp_path / "journal"
    config = tmp_path / "rigs.toml"
    config.write_text(f"""
[zenoh]
listen = ["tcp/127.0.0.1:{free_port()}"]
[service]
journal_dir = "{journal}"
[[rig]]
name = "rig-p"
source = "{log}"
speed = 0
""")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-m", "twin.cli", "serve", "--config", str(config)]
    first = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert first.returncode == 0, first.stderr
    slot = journal / "rig-p.checkpoint.json"
    assert read_checkpoints(slot)[1]["rig-p"].alarm_seq >= 1  # the rig ran and raised its alarm
    good = slot.read_bytes()
    # another (shorter) log under the same name: the checkpoint would resume past its end; refused in one line
    kept = log.read_bytes()
    _wear_log(log, 1003, seconds=6.0)
    other = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    errors = [line for line in other.stderr.splitlines() if "error" in line]
    assert other.returncode != 0 and len(errors) == 1 and "Traceback" not in other.stderr, other.stderr
    assert f"resumes {log} of {len(kept)} bytes, the file has {log.stat().st_size} bytes now" in errors[0]
    log.write_bytes(kept)
    marker = tmp_path / "planted"
    slot.write_bytes(pickle.dumps({"tracker": Planted(marker)}))
    second = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    errors = [line for line in second.stderr.splitlines() if "error" in line]
    assert second.returncode != 0 and len(errors) == 1, second.stderr
    assert errors[0].startswith("twin serve: error: ") and "rig-p.checkpoint.json: not a checkpoint" in errors[0]
    assert "Traceback" not in second.stderr and not marker.exists()
    # the checkpoint back, the journal gone: refused too, and no new journal is started
    slot.write_bytes(good)
    (journal / "rig-p.db").unlink()
    third = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    errors = [line for line in third.stderr.splitlines() if "error" in line]
    assert third.returncode != 0 and len(errors) == 1 and "Traceback" not in third.stderr, third.stderr
    assert "rig-p.db: the journal is missing, but its checkpoint rig-p.checkpoint.json" in errors[0]
    assert not (journal / "rig-p.db").exists()


def _blocks(seed: int):
    _, xr = excite(M.MODEL, 10.0, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [Drift("Ffric", 3.0, 3.0, shape="step"),
                                                       Drift("CdAleak", 30.0, 5.0, 8.0, "ramp")],
                           noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}, seed=seed)
    s = rec.to_samples()
    return [s.slice(i, min(i + 500, len(s))) for i in range(0, len(s), 500)]


def test_a_twin_restored_from_its_plain_state_continues_exactly(tmp_path: Path) -> None:
    """Half a record, the state through the checkpoint file, a fresh twin, the other half: the same alarms and
    the same filter state, bit for bit, as one uninterrupted twin."""
    rig = parse_config({"service": {"journal_dir": str(tmp_path)},
                        "rig": [{"name": "rig-s", "source": str(tmp_path / "none.mcap")}]}, "<test>").rigs[0]
    blocks = _blocks(1002)
    whole = make_twin(rig)
    for b in blocks:
        whole.write(b)
    first = make_twin(rig)
    half = len(blocks) // 2
    for b in blocks[:half]:
        first.write(b)
    path = tmp_path / "r.checkpoint.json"
    write_checkpoints(path, "id", {"rig-s": Checkpoint("rig-s", 0, 0, "fp", first.state(), 0.0)}, b"key")
    second = make_twin(rig)
    second.restore(read_checkpoints(path, b"key")[1]["rig-s"].state)
    for b in blocks[half:]:
        second.write(b)
    got = [(a.identity, a.estimate, a.statistic) for a in list(first.alarms) + list(second.alarms)]
    assert got == [(a.identity, a.estimate, a.statistic) for a in whole.alarms] and len(got) >= 2
    for name in ("x", "P", "fs", "ch"):
        assert getattr(second.tracker, name).tobytes() == getattr(whole.tracker, name).tobytes(), name
    assert second.drift.state() == whole.drift.state()


def test_a_state_of_another_configuration_is_refused(tmp_path: Path) -> None:
    cfg = {"service": {"journal_dir": str(tmp_path)},
           "rig": [{"name": "rig-s", "source": str(tmp_path / "none.mcap")}]}
    twin = make_twin(parse_config(cfg, "<test>").rigs[0])
    state = twin.state()
    other = make_twin(parse_config({**cfg, "rig": [{**cfg["rig"][0], "track": ["Ffric", "CdAleak"]}]},
                                   "<test>").rigs[0])
    with pytest.raises(Exception, match=r"tracker state: tracks .* this rig \['Ffric', 'CdAleak'\]"):
        other.restore(state)
    state["tracker"]["version"] = 7
    with pytest.raises(Exception, match=r"tracker state: version 7, this program reads 1"):
        twin.restore(state)


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.shape == b.shape
                and a.tobytes() == b.tobytes())
    try:
        return bool(a == b)
    except ValueError:
        return False


def test_everything_of_the_tracker_and_detector_that_changes_is_in_their_state(tmp_path: Path) -> None:
    """What processing changes in the tracker or the detector (caches of the detector aside) is named in their
    plain state, so a checkpoint cannot silently miss a part added later."""
    import copy

    rig = parse_config({"service": {"journal_dir": str(tmp_path)},
                        "rig": [{"name": "rig-s", "source": str(tmp_path / "none.mcap")}]}, "<test>").rigs[0]
    twin = make_twin(rig)
    plain = (np.ndarray, dict, list, tuple, int, float, str, type(None))
    same_object = {(o, k): v for o in ("tracker", "drift") for k, v in vars(getattr(twin, o)).items()}
    before = {key: copy.deepcopy(v) for key, v in same_object.items() if isinstance(v, plain)}
    for b in _blocks(1003)[:8]:
        twin.write(b)
    changed = {(o, k) for o in ("tracker", "drift") for k, v in vars(getattr(twin, o)).items()
               if (o, k) not in same_object or v is not same_object[(o, k)]
               or ((o, k) in before and not _same(before[(o, k)], v))}
    caches = {("drift", "_const"), ("drift", "_buf")}  # rebuilt from the configuration when missing
    named = {("tracker", k) for k in twin.tracker.state()} | {("drift", k) for k in twin.drift.state()} | \
        {("drift", "_next_t"), ("drift", "params")}
    assert changed and {(o, k.lstrip("_")) if o == "tracker" else (o, k) for o, k in changed} - caches <= named


# --------------------------------------------------------------------------- bound to the rig


def _campaign(directory: Path, rig: str, key: str = "") -> None:
    """A rig's journal of five alarms and its checkpoint, as the service leaves them."""
    with AlarmJournal(directory / f"{rig}.db", bind=Binding(rig, key, f"/data/{rig}.mcap")) as journal:
        for i in range(1, 6):
            journal.append(alarm(rig, i))
        journal.save_checkpoint(Checkpoint(rig, 5_000_000_000, 5000, "fp", {"x": np.arange(3.0)}, 1.0,
                                           source={"uri": f"/data/{rig}.mcap", "bytes": 1000}))


def test_another_rigs_journal_and_checkpoint_copied_in_together_are_refused_with_one_line(tmp_path: Path) -> None:
    _campaign(tmp_path, "rig-z")
    _campaign(tmp_path, "rig-y")
    before = (tmp_path / "rig-y.db").read_bytes()
    for suffix in (".db", ".checkpoint.json"):  # rig-z's files put in rig-y's place
        (tmp_path / f"rig-y{suffix}").write_bytes((tmp_path / f"rig-z{suffix}").read_bytes())
    with pytest.raises(LogFormatError) as info:
        AlarmJournal(tmp_path / "rig-y.db", bind=Binding("rig-y", "", "/data/rig-y.mcap"))
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"{tmp_path / 'rig-y.db'}: the journal of rig 'rig-z', not of rig "
                                                "'rig-y' (copied from another rig?); refused")
    # a journal of an earlier version, without a recorded rig but with another rig's alarms: refused too
    legacy = tmp_path / "old"
    legacy.mkdir()
    with AlarmJournal(legacy / "rig-y.db") as journal:
        journal.append(alarm("rig-z", 1))
    with pytest.raises(LogFormatError, match=r"the journal of rig 'rig-z', not of rig 'rig-y'"):
        AlarmJournal(legacy / "rig-y.db", bind=Binding("rig-y"))
    # under another signing key: another rig's journal (or a new key, which starts a new journal)
    (tmp_path / "rig-y.db").write_bytes(before)
    (tmp_path / "rig-y.checkpoint.json").unlink()
    keyed = tmp_path / "keyed"
    keyed.mkdir()
    _campaign(keyed, "rig-k", key="SHA256:00112233aabbccdd")
    with pytest.raises(LogFormatError, match=r"under signing key SHA256:00112233aabbccdd, the rig's key is "
                                             r"SHA256:ffffffffffffffff now"):
        AlarmJournal(keyed / "rig-k.db", bind=Binding("rig-k", "SHA256:ffffffffffffffff"))
    with AlarmJournal(keyed / "rig-k.db", bind=Binding("rig-k", "SHA256:00112233aabbccdd")) as journal:
        cp = journal.load_checkpoint("rig-k")
        assert cp is not None and cp.epoch == journal.epoch("rig-k") and cp.source["bytes"] == 1000


def test_a_checkpoint_whose_digest_is_recomputed_is_refused(tmp_path: Path) -> None:
    """An edited checkpoint (resuming past the end of its log) with a digest anyone can recompute: refused."""
    _campaign(tmp_path, "rig-y")
    path = tmp_path / "rig-y.checkpoint.json"
    doc = json.loads(path.read_text())
    body = doc["body"]
    body["rigs"]["rig-y"]["t_ns"] = 10**18  # past the end of the log
    data = json.dumps(body, sort_keys=True, separators=(",", ":")).encode()
    for forged in ({"format": doc["format"], "version": 1, "sha256": hashlib.sha256(data).hexdigest(), "body": body},
                   {**doc, "body": body, "hmac": hashlib.sha256(data).hexdigest()}):
        path.write_text(json.dumps(forged))
        with pytest.raises(LogFormatError) as info:
            AlarmJournal(tmp_path / "rig-y.db", bind=Binding("rig-y"))
        text = str(info.value)
        assert "\n" not in text and text.startswith(str(path)) and "refused" in text
        assert ("checkpoint version 1 (a bare SHA-256 anyone can recompute)" in text
                or "HMAC does not match its content under the journal's key" in text)
