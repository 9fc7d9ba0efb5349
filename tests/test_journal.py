"""The alarm journal on a real SQLite file: numbering, identity, durability, corruption, write failures,
checkpoints, and the import of the old JSON-lines journal."""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from event_helpers import T0_NS
from event_helpers import alarm
from fpdd.errors import DataError, LogFormatError, SourceError
from twin.online.events import event_to_json
from twin.service.journal import AlarmJournal
from twin.service.checkpoint_file import Checkpoint
from twin.service.store import Store


@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / "journal" / "rig.db"


def read_only_disk(journal: AlarmJournal, on: bool) -> None:
    """Make every write of this journal fail as on a file system remounted read-only (SQLITE_READONLY)."""
    journal.store._db.execute(f"PRAGMA query_only = {'ON' if on else 'OFF'}")


def test_append_assigns_per_rig_sequence_numbers(path: Path) -> None:
    with AlarmJournal(path) as journal:
        seqs = [journal.append(alarm("a", i)).seq for i in range(3)]
        seqs_b = [journal.append(alarm("b", i)).seq for i in range(2)]
        assert seqs == [1, 2, 3] and seqs_b == [1, 2]
        assert journal.last_seq("a") == 3 and journal.last_seq("b") == 2
        assert journal.last_seq("c") == 0
        assert journal.rigs() == ["a", "b"]
        assert len(journal) == 5


def test_a_committed_alarm_is_in_the_file_in_wal_mode(path: Path) -> None:
    with AlarmJournal(path) as journal:
        event = journal.append(alarm())
        # another connection (another process would do the same) reads it while the writer is open
        with sqlite3.connect(path) as other:
            assert other.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
            (payload,) = other.execute("SELECT payload FROM alarms WHERE seq = 1").fetchone()
        assert json.loads(payload) == event.to_dict()
        assert journal.store._db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL


def test_the_same_alarm_is_journaled_once(path: Path) -> None:
    with AlarmJournal(path) as journal:
        first = journal.record(alarm(i=1))
        again = journal.record(alarm(i=1))  # raised again by re-processed data
        other = journal.record(alarm(i=2))
        assert (first.new, again.new, other.new) == (True, False, True)
        assert again.event == first.event and other.event.seq == 2
    with AlarmJournal(path) as journal:
        assert not journal.record(alarm(i=1)).new
        assert [e.seq for e in journal.read()] == [1, 2]


def test_explicit_seq_must_be_the_next_one(path: Path) -> None:
    with AlarmJournal(path) as journal:
        assert journal.append(alarm(i=1, seq=1)).seq == 1
        with pytest.raises(DataError, match=r"AlarmEvent\.seq: 3 for rig 'msp25' where 2"):
            journal.append(alarm(i=3, seq=3))
        assert journal.append(alarm(i=2, seq=2)).seq == 2


def test_reopen_resumes_at_last_seq_plus_one(path: Path) -> None:
    with AlarmJournal(path) as journal:
        first = [journal.append(alarm("a", i)) for i in range(3)]
        journal.append(alarm("b", 9))
    with AlarmJournal(path) as journal:
        assert journal.read(rig="a") == first
        assert journal.append(alarm("a", 4)).seq == 4
        assert journal.append(alarm("b", 10)).seq == 2
    with AlarmJournal(path) as journal:
        assert [e.seq for e in journal.read(rig="a")] == [1, 2, 3, 4]


def test_a_flipped_bit_in_a_committed_alarm_is_reported_not_repaired(path: Path) -> None:
    with AlarmJournal(path) as journal:
        for i in range(1, 4):
            journal.append(alarm(i=i))  # the last one is the alarm a torn-write heuristic would have cut
    data = bytearray(path.read_bytes())
    at = data.index(b'"message":"alarm 3"') + len('"message":"alarm ')
    data[at] ^= 0x01  # "alarm 3" -> "alarm 2": a single flipped bit
    path.write_bytes(bytes(data))
    with pytest.raises(LogFormatError, match=r"rig\.db: alarm 'msp25' seq 3: stored CRC does not match") as info:
        AlarmJournal(path)
    assert "restore the journal from a backup" in str(info.value)
    assert path.read_bytes() == bytes(data)  # untouched: nothing deleted, nothing renumbered


def test_a_file_that_is_not_a_journal_is_reported(path: Path) -> None:
    path.parent.mkdir(parents=True)
    path.write_bytes(b"SQLite format 3\x00" + bytes(range(256)) * 64)
    with pytest.raises(LogFormatError, match=r"rig\.db: the journal is corrupt .*left untouched"):
        AlarmJournal(path)


def test_a_failed_write_holds_the_alarm_unpublished_and_retries(path: Path) -> None:
    with AlarmJournal(path) as journal:
        journal.append(alarm(i=1))
        read_only_disk(journal, True)
        kept = journal.record(alarm(i=2))
        assert kept.new and not kept.durable and kept.event.seq == 2  # numbered, not to be published yet
        assert str(path) in journal.write_error and "readonly" in journal.write_error
        assert journal.pending == 1 and journal.last_seq("msp25") == 2
        assert [e.seq for e in journal.read()] == [1]  # the history serves journaled alarms only
        assert not journal.record(alarm(i=2)).new  # still recognised
        third = journal.record(alarm(i=3))
        assert third.event.seq == 3 and not third.durable
        assert not journal.retry() and journal.take_written() == []
        with pytest.raises(SourceError, match=r"checkpoint held while 2 alarm\(s\) of rig msp25 are not journaled"):
            journal.save_checkpoint(Checkpoint("msp25", 1, 1, "fp", {}, 0.0))
        read_only_disk(journal, False)
        assert journal.retry() and journal.pending == 0 and journal.write_error is None
        assert [e.seq for e in journal.take_written()] == [2, 3] and journal.take_written() == []
    with AlarmJournal(path) as journal:
        assert [(e.seq, e.message) for e in journal.read()] == [(1, "alarm 1"), (2, "alarm 2"), (3, "alarm 3")]


def test_read_filters(path: Path) -> None:
    with AlarmJournal(path) as journal:
        for i in range(5):
            journal.append(alarm("a", i))
        journal.append(alarm("b", 2))
        assert [e.seq for e in journal.read(since_seq=3, rig="a")] == [3, 4, 5]
        since = T0_NS + 3 * 1_000_000_000
        assert [(e.rig, e.seq) for e in journal.read(since_t_ns=since)] == [("a", 4), ("a", 5)]
        assert [(e.rig, e.seq) for e in journal.read(since_t_ns=T0_NS + 2_000_000_000, rig="*")] == [
            ("a", 3), ("a", 4), ("a", 5), ("b", 1)]
        assert list(journal) == journal.read()


def test_checkpoints_replace_each_other_beside_the_journal(path: Path) -> None:
    with AlarmJournal(path) as journal:
        assert journal.load_checkpoint("r") is None
        journal.save_checkpoint(Checkpoint("r", 10, 100, "fp", {"v": 1}, 1.0))
        journal.append(alarm("r", 1))
        journal.save_checkpoint(Checkpoint("r", 20, 200, "fp", {"v": 2}, 2.0))
        journal.save_checkpoint(Checkpoint("q", 30, 300, "fp", {"v": 3}, 3.0))
    assert sorted(p.name for p in path.parent.iterdir() if "checkpoint" in p.name) == ["rig.checkpoint.json"]
    with AlarmJournal(path) as journal:
        r, q = journal.load_checkpoint("r"), journal.load_checkpoint("q")
        assert (r.t_ns, r.samples, r.state, r.alarm_seq) == (20, 200, {"v": 2}, 1)
        assert (q.t_ns, q.state, q.alarm_seq, q.journal_id) == (30, {"v": 3}, 0, journal.store.journal_id)


def test_one_writer_per_journal_and_readers_beside_it(path: Path) -> None:
    with AlarmJournal(path) as journal:
        with pytest.raises(SourceError, match="locked by another process"):
            AlarmJournal(path, lock_wait_s=0.1)
        journal.append(alarm())
        with Store(path, writer=False) as reader:
            assert [e.seq for e in reader.alarms()] == [1]
    with AlarmJournal(path) as journal:  # released on close
        assert not journal.closed


def test_closed_journal_refuses_appends(path: Path) -> None:
    journal = AlarmJournal(path)
    journal.close()
    journal.close()
    with pytest.raises(SourceError, match="closed"):
        journal.append(alarm())


def test_a_journal_under_a_regular_file_is_a_source_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(SourceError, match=r"file/sub: cannot create the journal directory"):
        AlarmJournal(blocker / "sub" / "rig.db")


# --------------------------------------------------------------------------- migration


def legacy_lines(n: int) -> bytes:
    """What the old journal wrote: one compact JSON object per line."""
    return b"".join(event_to_json(alarm(i=i, seq=i)).encode() + b"\n" for i in range(1, n + 1))


def test_an_old_json_lines_journal_is_imported_once(tmp_path: Path) -> None:
    old = tmp_path / "rig.alarms.jsonl"
    old.write_bytes(legacy_lines(3) + b'{"rig":"msp25","se')  # and a line torn by a crash
    with AlarmJournal(tmp_path / "rig.db", legacy=old) as journal:
        assert journal.imported == 3
        assert [e.seq for e in journal.read()] == [1, 2, 3]
        assert journal.append(alarm(i=4)).seq == 4
    assert not old.exists() and (tmp_path / "rig.alarms.jsonl.imported").exists()
    with AlarmJournal(tmp_path / "rig.db", legacy=old) as journal:
        assert journal.imported == 0 and [e.seq for e in journal.read()] == [1, 2, 3, 4]


@pytest.mark.parametrize("damage, message", [
    (lambda b: b.replace(b'"message":"alarm 2"', b'"message":"alarm 2\x00'), r"rig\.alarms\.jsonl:2: corrupt"),
    (lambda b: b.replace(b'"message":"alarm 3"', b'"message":"alarm 3\x00'), r"rig\.alarms\.jsonl:3: corrupt"),
    (lambda b: b"".join(line + b"\n" for line in b.split(b"\n")[0:3:2]), r"rig\.alarms\.jsonl:2: rig 'msp25' seq 3 where 2"),
])
def test_a_damaged_old_journal_is_not_imported(tmp_path: Path, damage, message) -> None:
    """A bad *complete* line, even the last one, is damage (not a torn write): nothing is imported."""
    old = tmp_path / "rig.alarms.jsonl"
    old.write_bytes(damage(legacy_lines(3)))
    with pytest.raises(LogFormatError, match=message):
        AlarmJournal(tmp_path / "rig.db", legacy=old)
    assert old.exists()
    with Store(tmp_path / "rig.db", writer=False) as store:
        assert store.alarms() == []


# --------------------------------------------------------------------------- a journal that survives its own files

WRITER = """
import sys, time
from event_helpers import alarm
from twin.service.journal import AlarmJournal
journal = AlarmJournal(sys.argv[1])
for i in range(1, 6):
    journal.append(alarm(i=i))
print("durable 5", flush=True)
if sys.argv[2] == "unfolded":  # killed after committing alarm 6, before it is folded (and so before it is published)
    journal.store._fold = lambda: None
    journal.append(alarm(i=6))
print("ready", flush=True)
time.sleep(600)
"""


def _killed_writer(tmp_path: Path, moment: str) -> Path:
    """A writer process that journals alarms and is killed with SIGKILL; returns its directory (db, WAL, shm)."""
    root = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root.parent), str(root), os.environ.get("PYTHONPATH", "")])}
    d = tmp_path / "killed"
    d.mkdir()
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(d / "rig.db"), moment], stdout=subprocess.PIPE,
                            text=True, env=env)
    try:
        assert proc.stdout.readline().strip() == "durable 5"
        assert proc.stdout.readline().strip() == "ready"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    return d


def _damage_wal(wal: Path, how: str) -> None:
    if how == "none" or not wal.exists():
        return
    if how == "deleted":
        wal.unlink()
        return
    data = bytearray(wal.read_bytes())
    page = int.from_bytes(data[8:12], "big") if len(data) >= 32 else 4096
    frame = 24 + page
    frames = (len(data) - 32) // frame
    if frames < 1:
        return
    if how == "bit_in_last_frame":
        data[32 + (frames - 1) * frame + 24 + page // 2] ^= 0x10
    elif how == "cut_by_a_frame":
        data = data[:32 + (frames - 1) * frame]
    wal.write_bytes(bytes(data))


@pytest.mark.parametrize("moment", ["folded", "unfolded"])
def test_a_killed_writer_and_a_damaged_wal_lose_no_committed_alarm(tmp_path: Path, moment: str) -> None:
    """SIGKILL after 5 alarms were journaled (``folded``), or while a 6th was between its commit and its fold
    into the main file (``unfolded``, not yet returned, so not yet published); then the WAL deleted, a bit
    flipped in its last frame, or cut by a frame: every journaled alarm is still there, numbered 1, 2, ..."""
    d = _killed_writer(tmp_path, moment)
    wal = d / "rig.db-wal"
    if moment == "folded":  # the main file alone holds every journaled alarm: nothing is left in the WAL
        assert not wal.exists() or wal.stat().st_size == 0
    else:
        assert wal.stat().st_size > 32  # alarm 6 is in the WAL only
    for how in ("none", "deleted", "bit_in_last_frame", "cut_by_a_frame"):
        case = tmp_path / how
        case.mkdir()
        for f in d.iterdir():
            if f.name.startswith("rig.db") and not f.name.endswith(".lock"):
                shutil.copy2(f, case / f.name)
        _damage_wal(case / "rig.db-wal", how)
        with AlarmJournal(case / "rig.db") as journal:
            seqs = [e.seq for e in journal.read()]
            assert seqs[:5] == [1, 2, 3, 4, 5] and seqs == list(range(1, len(seqs) + 1)), (how, seqs)
            assert [e.message for e in journal.read()][:5] == [f"alarm {i}" for i in range(1, 6)]
            if how == "none":
                assert len(seqs) == (5 if moment == "folded" else 6)  # an intact WAL keeps alarm 6 too
            assert journal.append(alarm(i=7)).seq == len(seqs) + 1  # numbering goes on
        assert (case / "rig.db-wal").stat().st_size == 0 if (case / "rig.db-wal").exists() else True


def _ran_before(path: Path) -> None:
    with AlarmJournal(path) as journal:
        for i in range(1, 6):
            journal.append(alarm(i=i))
        journal.save_checkpoint(Checkpoint("msp25", 1, 1, "fp", {}, 0.0))


def _replace_with_another_journal(path: Path) -> None:
    other = path.with_name("other.db")
    with AlarmJournal(other) as journal:
        for i in range(1, 6):
            journal.append(alarm(i=i))
    os.replace(other, path)


def _set(sql: str):
    def run(path: Path) -> None:
        with sqlite3.connect(path) as db:
            db.execute(sql)
        db.close()
    return run


def _empty_database(path: Path) -> None:
    path.unlink()
    db = sqlite3.connect(path)
    db.execute("PRAGMA user_version = 1")
    db.close()


@pytest.mark.parametrize("damage, message", [
    (lambda p: p.unlink(), r"rig\.db: the journal is missing, but its checkpoint rig\.checkpoint\.json of .* says "
                           r"the rig ran before; refused \(alarm numbers never restart\)"),
    (lambda p: p.write_bytes(b""), r"rig\.db: the journal is empty \(0 bytes\), but its checkpoint"),
    (_empty_database, r"rig\.db: the journal holds no alarm journal \(an empty or replaced database\), but its "
                      r"checkpoint"),
    (_replace_with_another_journal, r"rig\.db: the journal was replaced: its id is [0-9a-f]{32}, its checkpoint "
                                    r"rig\.checkpoint\.json of .* was written with journal [0-9a-f]{32}"),
    (_set("DELETE FROM alarms WHERE seq > 3"), r"rig\.db: the alarms of rig 'msp25' end at seq 3, but its "
                                               r"checkpoint .* says 5 were journaled"),
    (_set("UPDATE meta SET value = '99' WHERE key = 'schema_version'"),
     r"rig\.db: schema_version '99' is not one this program reads \(1, 2\)"),
])
def test_a_journal_that_disagrees_with_its_checkpoint_is_refused_with_one_line(path: Path, damage, message) -> None:
    _ran_before(path)
    damage(path)
    before = path.read_bytes() if path.exists() else None
    with pytest.raises(LogFormatError, match=message) as info:
        AlarmJournal(path)
    assert "\n" not in str(info.value)
    assert (path.read_bytes() if path.exists() else None) == before  # left as it was: nothing created or renumbered


def test_a_commissioning_beside_a_missing_journal_is_refused(path: Path) -> None:
    witness = path.with_name("rig.commission.json")
    path.parent.mkdir(parents=True)
    witness.write_text("{}")
    with pytest.raises(LogFormatError, match=r"rig\.db: the journal is missing, but .*rig\.commission\.json says "
                                             r"the rig ran before"):
        AlarmJournal(path, witnesses=[witness])
    with AlarmJournal(path) as journal:  # a rig never run before starts a journal
        assert journal.append(alarm()).seq == 1
    with AlarmJournal(path, witnesses=[witness]) as journal:  # and the commissioning beside it is consistent
        assert journal.last_seq("msp25") == 1


def _small_pages(path: Path) -> None:
    """A new journal file of 512-byte pages: an alarm needs pages of its own, so a page limit fills at once."""
    path.parent.mkdir(parents=True, exist_ok=True)
    db = sqlite3.connect(path)
    db.execute("PRAGMA page_size = 512")
    db.execute("PRAGMA journal_mode = WAL")
    db.close()


def full_disk(journal: AlarmJournal) -> None:
    """Every page the file may have is used: the next write fails with SQLITE_FULL (a full disk)."""
    db = journal.store._db
    db.execute(f"PRAGMA max_page_count = {db.execute('PRAGMA page_count').fetchone()[0]}")


def test_a_full_disk_holds_the_alarm_until_it_is_written(path: Path) -> None:
    _small_pages(path)
    with AlarmJournal(path) as journal:
        journal.append(alarm(i=1))
        full_disk(journal)
        held = journal.record(alarm(i=2))
        assert held.new and not held.durable and "full" in journal.write_error and str(path) in journal.write_error
        assert journal.read() == [journal.read()[0]] and journal.pending == 1
        journal.store._db.execute("PRAGMA max_page_count = 1000000")
        assert journal.retry() and [e.seq for e in journal.take_written()] == [2]


@pytest.mark.slow
def test_a_full_disk_until_shutdown_never_publishes_an_alarm_twice(tmp_path: Path) -> None:
    """The disk fills after the first alarm and stays full until the rig stops; a restart on a good disk:
    every alarm of an uninterrupted run reaches the bus exactly once, with its number."""
    import queue
    import threading

    from replay.mcapio import McapSink
    from twin.models import msp25 as M
    from twin.models.scenario import Drift, simulate_wear
    from fpdd.units import NOMINAL_NOISE
    from twin.models.simulate import excite
    from twin.service.config import parse_config
    from twin.service.checkpoints import journal_path
    from twin.service.runner import RigRunner

    _, xr = excite(M.MODEL, 16.0, 1e-3, seed=1011)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3,
                           [Drift("Ffric", 3.0, 3.0, shape="step"), Drift("wn", 0.6, 6.0, 12.0, "ramp")],
                           noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}, seed=1011)
    log = tmp_path / "rig.mcap"
    with McapSink(str(log)) as sink:
        sink.write(rec.to_samples())

    def config(d: str):
        return parse_config({"service": {"journal_dir": str(tmp_path / d), "checkpoint_s": 0.05},
                             "rig": [{"name": "rig-f", "source": str(log), "speed": 0}]}, "<full disk>")

    class Bus(queue.Queue):
        """What the runner sends to the bus; ``fill`` fills the disk once the first alarm went out."""

        def __init__(self, journal: AlarmJournal | None = None, wal: Path | None = None) -> None:
            super().__init__()
            self.journal, self.alarms, self.messages, self.wal, self.wal_sizes = journal, [], [], wal, []

        def put(self, item, block=True, timeout=None) -> None:
            for m in item[2] if item[0] == "batch" else ():
                if m[0] == "alarm":
                    # only journaled alarms go out (numbered; the WAL is checked empty at this moment below)
                    assert len(m) == 2 and m[1].seq > 0, m
                    self.alarms.append(m[1])
                    if self.wal is not None:
                        self.wal_sizes.append(self.wal.stat().st_size if self.wal.exists() else 0)
                    if self.journal is not None and not fill:
                        full_disk(self.journal)
                        fill.append(True)
                elif m[0] == "status":
                    self.messages.append(m[3])

    def run(cfg, bus_of) -> Bus:
        with AlarmJournal(journal_path(cfg, "rig-f")) as journal:
            bus = bus_of(journal)
            RigRunner(cfg.rigs[0], cfg, journal, bus, threading.Event()).run()
        return bus

    ref = run(config("ref"), lambda j: Bus(wal=j.path.with_name(j.path.name + "-wal")))
    reference = ref.alarms
    assert len(reference) >= 3
    assert ref.wal_sizes == [0] * len(reference)  # when an alarm goes out, the main file holds it: the WAL is empty
    fill: list[bool] = []
    cfg = config("journal")
    _small_pages(journal_path(cfg, "rig-f"))
    first = run(cfg, lambda j: Bus(j))
    assert [a.seq for a in first.alarms] == [1] and fill == [True]
    assert any("alarm(s) held, published once journaled (#2 " in m and "full" in m for m in first.messages)
    second = run(cfg, lambda j: Bus())  # the disk has room again
    got = first.alarms + second.alarms
    assert [(a.seq, a.identity, a.estimate) for a in got] == [(a.seq, a.identity, a.estimate) for a in reference]


# --------------------------------------------------------------------------- epochs


def test_each_journal_numbers_in_its_own_epoch_and_a_standby_adopts_the_owners(tmp_path: Path) -> None:
    with AlarmJournal(tmp_path / "a.db") as a:
        first = a.append(alarm("r1", 1))
        epoch_a = a.epoch("r1")
        assert first.epoch == epoch_a and len(epoch_a) == 32 and a.read()[0].epoch == epoch_a
    with AlarmJournal(tmp_path / "a.db") as a:  # reopened: the same numbering, the same epoch
        assert a.append(alarm("r1", 2)).epoch == epoch_a and a.epoch("r1") == epoch_a
    with AlarmJournal(tmp_path / "b.db") as b:  # a new journal numbers from 1 again: in a new, later epoch
        again = b.append(alarm("r1", 3))
        assert again.seq == 1 and again.epoch != epoch_a and again.epoch > epoch_a
    with AlarmJournal(tmp_path / "standby.db") as s:
        s.epoch("r1")  # made before any alarm (its service started first)
        kept = s.record(first)  # the owner's alarm under the owner's number: the owner's epoch is adopted
        assert kept.new and kept.event.epoch == epoch_a and s.epoch("r1") == epoch_a
        with pytest.raises(DataError, match=r"AlarmEvent\.epoch: .* where this journal numbers the rig's alarms in "
                                            f"epoch {epoch_a}"):
            s.record(replace(again, seq=2))  # another numbering's alarm under this one's next number
        assert [e.seq for e in s.read()] == [1]
    with Store(tmp_path / "a.db", writer=False) as reader:
        assert reader.epoch("r1") == epoch_a and reader.epoch("r9") == ""  # a reader makes none


# --------------------------------------------------------------------------- a journal alone


def _vacuumed(sql: str):
    def run(path: Path) -> None:
        db = sqlite3.connect(path)
        db.executescript(sql)
        db.commit()
        db.execute("VACUUM")  # the file shrinks as if the rows had never been there
        db.close()
    return run


@pytest.mark.parametrize("damage, message", [
    (_set("DELETE FROM alarms WHERE seq > 3"), r"the alarms of rig 'msp25' end at seq 3, but the journal's own "
                                               r"high-water mark says rig 'msp25' journaled 5: seq 4\.\.5 of rig "
                                               r"'msp25' missing"),
    (_vacuumed("DELETE FROM alarms WHERE seq = 5"), r"end at seq 4, .* journaled 5: seq 5 of rig 'msp25' missing"),
    (_set("DELETE FROM alarms"), r"end at seq 0, .* journaled 5: seq 1\.\.5 of rig 'msp25' missing"),
    (_vacuumed("DROP TABLE alarms"), r"its alarms table is missing, .* seq 1\.\.5 of rig 'msp25' missing"),
    (_vacuumed("DELETE FROM meta WHERE key LIKE 'last_seq:%'; DELETE FROM alarms WHERE seq > 2"),
     r"the journal's header counts 5 alarms, 2 are there: 3 missing"),
])
def test_a_journal_alone_tells_deleted_or_dropped_alarms(path: Path, damage, message) -> None:
    with AlarmJournal(path) as journal:  # no checkpoint, no witness: the journal alone
        for i in range(1, 6):
            journal.append(alarm(i=i))
    damage(path)
    with pytest.raises(LogFormatError, match=message) as info:
        AlarmJournal(path)
    assert "\n" not in str(info.value) and str(info.value).startswith(str(path))


def test_a_journal_alone_cut_anywhere_is_refused(path: Path) -> None:
    with AlarmJournal(path) as journal:
        for i in range(1, 201):
            journal.append(alarm(i=i))
    data = path.read_bytes()
    cuts = list(range(512, len(data), 4096 + 512))  # inside pages and at their ends
    for cut in cuts:
        path.write_bytes(data[:cut])
        with pytest.raises(LogFormatError) as info:
            AlarmJournal(path)
        assert "\n" not in str(info.value), cut
    assert len(cuts) >= 20
