"""The alarm journal on a real SQLite file: numbering, identity, durability, corruption, write failures,
checkpoints, and the import of the old JSON-lines journal."""

from __future__ import annotations

import json
import logging
import sqlite3
from pathlib import Path

import pytest

from event_helpers import T0_NS
from event_helpers import alarm
from twin.errors import DataError, LogFormatError, SourceError
from twin.online.events import event_to_json
from twin.service.journal import AlarmJournal
from twin.service.store import Checkpoint, Store


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


def test_a_failed_write_keeps_the_alarm_publishes_it_and_retries(path: Path, caplog) -> None:
    with AlarmJournal(path) as journal:
        journal.append(alarm(i=1))
        read_only_disk(journal, True)
        with caplog.at_level(logging.ERROR, logger="twin.service.journal"):
            kept = journal.record(alarm(i=2))
        assert kept.new and not kept.durable and kept.event.seq == 2
        assert str(path) in journal.write_error and "readonly" in journal.write_error
        assert str(path) not in caplog.text or "seq 2 kept in memory" in caplog.text
        assert journal.pending == 1 and journal.last_seq("msp25") == 2
        assert [e.seq for e in journal.read()] == [1, 2]  # the history serves it meanwhile
        assert not journal.record(alarm(i=2)).new  # still recognised
        third = journal.record(alarm(i=3))
        assert third.event.seq == 3 and not third.durable
        assert not journal.retry()
        read_only_disk(journal, False)
        assert journal.retry() and journal.pending == 0 and journal.write_error is None
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


def test_checkpoints_replace_each_other_and_a_damaged_one_is_ignored(path: Path) -> None:
    with AlarmJournal(path) as journal:
        assert journal.load_checkpoint("r") is None
        journal.save_checkpoint(Checkpoint("r", 10, 100, "fp", b"state-1", 1.0))
        journal.save_checkpoint(Checkpoint("r", 20, 200, "fp", b"state-2", 2.0))
        assert journal.load_checkpoint("r") == Checkpoint("r", 20, 200, "fp", b"state-2", 2.0)
        journal.store._db.execute("UPDATE checkpoints SET state = ? WHERE rig = 'r'", (b"state-3",))
        assert journal.load_checkpoint("r") is None  # CRC mismatch: start afresh rather than from garbage


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
