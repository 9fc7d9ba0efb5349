"""The alarm journal: durable appends, sequence numbers, restart, torn last line."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import pytest

from twin.errors import DataError, LogFormatError, SourceError
from event_helpers import T0_NS
from event_helpers import alarm
from twin.events import AlarmEvent
from twin.journal import AlarmJournal





@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / "journal" / "alarms.jsonl"


def test_append_assigns_per_rig_sequence_numbers(path: Path) -> None:
    with AlarmJournal(path) as journal:
        seqs = [journal.append(alarm("a", i)).seq for i in range(3)]
        seqs_b = [journal.append(alarm("b", i)).seq for i in range(2)]
        assert seqs == [1, 2, 3] and seqs_b == [1, 2]
        assert journal.last_seq("a") == 3 and journal.last_seq("b") == 2
        assert journal.last_seq("c") == 0
        assert journal.rigs() == ["a", "b"]
        assert len(journal) == 5


def test_append_is_on_disk_when_it_returns(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    synced: list[int] = []
    real_fsync = os.fsync

    def spy(fd: int) -> None:
        synced.append(fd)
        real_fsync(fd)

    with AlarmJournal(path) as journal:
        monkeypatch.setattr(os, "fsync", spy)
        event = journal.append(alarm())
        assert synced, "append must fsync"
        lines = path.read_text(encoding="utf-8").splitlines()
        assert AlarmEvent.from_dict(json.loads(lines[-1])) == event


def test_explicit_seq_must_be_the_next_one(path: Path) -> None:
    with AlarmJournal(path) as journal:
        assert journal.append(alarm(seq=1)).seq == 1
        with pytest.raises(DataError, match=r"AlarmEvent\.seq: 3 for rig 'msp25' where 2"):
            journal.append(alarm(seq=3))
        with pytest.raises(DataError):
            journal.append(alarm(seq=1))
        assert journal.append(alarm(seq=2)).seq == 2


def test_reopen_resumes_at_last_seq_plus_one(path: Path) -> None:
    with AlarmJournal(path) as journal:
        first = [journal.append(alarm("a", i)) for i in range(3)]
        journal.append(alarm("b", 9))
    with AlarmJournal(path) as journal:
        assert journal.read(rig="a") == first
        assert journal.torn_bytes == 0
        assert journal.append(alarm("a", 4)).seq == 4
        assert journal.append(alarm("b", 10)).seq == 2
    with AlarmJournal(path) as journal:
        assert [e.seq for e in journal.read(rig="a")] == [1, 2, 3, 4]


def test_torn_last_line_is_reported_and_truncated(
    path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with AlarmJournal(path) as journal:
        for i in range(3):
            journal.append(alarm(i=i))
    good_size = path.stat().st_size
    torn = b'{"band_hi":2e-12,"band_lo":5e-13,"baseline":1e-12,"est'
    with path.open("ab") as f:  # a crash in the middle of writing the 4th line
        f.write(torn)
    with caplog.at_level(logging.WARNING, logger="twin.journal"):
        journal = AlarmJournal(path)
    with journal:
        assert journal.torn_bytes == len(torn)
        assert "torn last line" in caplog.text
        assert path.stat().st_size == good_size
        assert journal.append(alarm(i=4)).seq == 4
    with AlarmJournal(path) as journal:
        assert [e.seq for e in journal.read()] == [1, 2, 3, 4]
        assert journal.torn_bytes == 0


def test_unreadable_complete_last_line_is_treated_as_torn(path: Path) -> None:
    with AlarmJournal(path) as journal:
        journal.append(alarm())
    with path.open("ab") as f:
        f.write(b'{"rig": "msp25", "seq": 2}\n')  # complete line, not a valid alarm
    with AlarmJournal(path) as journal:
        assert journal.torn_bytes == len(b'{"rig": "msp25", "seq": 2}\n')
        assert journal.append(alarm(i=2)).seq == 2


def test_corruption_before_the_last_line_is_an_error(path: Path) -> None:
    with AlarmJournal(path) as journal:
        for i in range(3):
            journal.append(alarm(i=i))
    lines = path.read_bytes().split(b"\n")
    lines[1] = b"garbage"
    path.write_bytes(b"\n".join(lines))
    with pytest.raises(LogFormatError, match=r"alarms\.jsonl:2: corrupt journal line"):
        AlarmJournal(path)


def test_sequence_hole_in_the_file_is_an_error(path: Path) -> None:
    with AlarmJournal(path) as journal:
        for i in range(3):
            journal.append(alarm(i=i))
    lines = path.read_bytes().split(b"\n")
    del lines[1]
    path.write_bytes(b"\n".join(lines))
    with pytest.raises(LogFormatError, match=r":2: rig 'msp25' seq 3 where 2 was expected"):
        AlarmJournal(path)


def test_read_filters(path: Path) -> None:
    with AlarmJournal(path) as journal:
        for i in range(5):
            journal.append(alarm("a", i))
        journal.append(alarm("b", 2))
        assert [e.seq for e in journal.read(since_seq=3, rig="a")] == [3, 4, 5]
        since = T0_NS + 3 * 1_000_000_000
        assert [(e.rig, e.seq) for e in journal.read(since_t_ns=since)] == [
            ("a", 4),
            ("a", 5),
        ]
        assert [(e.rig, e.seq) for e in journal.read(since_t_ns=T0_NS + 2_000_000_000, rig="*")] == [
            ("a", 3),
            ("a", 4),
            ("a", 5),
            ("b", 1),
        ]
        assert list(journal) == journal.read()


def test_one_writer_per_journal(path: Path) -> None:
    with AlarmJournal(path):
        with pytest.raises(SourceError, match="locked by another process"):
            AlarmJournal(path)
    with AlarmJournal(path) as journal:  # released on close
        assert not journal.closed


def test_closed_journal_refuses_appends(path: Path) -> None:
    journal = AlarmJournal(path)
    journal.close()
    journal.close()
    with pytest.raises(SourceError, match="closed"):
        journal.append(alarm())


def test_unopenable_path_is_a_source_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(SourceError, match="cannot open alarm journal"):
        AlarmJournal(blocker / "alarms.jsonl")
