"""The edge's per-robot journal: append, read back, torn tail, delivery-store positions."""

from pathlib import Path

import pytest

from common.protocol.link_state import InboundPosition
from services.edge.journal import JournalError, JournalRecord, JournalStore, RobotJournal


def test_records_round_trip_and_position_is_the_last_record(tmp_path: Path) -> None:
    store = JournalStore(tmp_path, fsync_interval_s=0.0)
    assert store.load("robot/1") is None
    store.register("robot/1")
    j = store.journal("robot/1")
    for seq in range(1, 4):
        j.append(JournalRecord(b"s1", seq, 0x0201, bytes([seq]) * seq))
    store.save("robot/1", InboundPosition(b"s1", 3))
    store.close()
    again = JournalStore(tmp_path)
    assert again.agents() == ["robot/1"]  # exact agent id despite the sanitised file name
    assert again.load("robot/1") == InboundPosition(b"s1", 3)
    recs = again.journal("robot/1").read()
    assert [r.seq for r in recs] == [1, 2, 3] and recs[2].payload == b"\x03\x03\x03"
    again.close()


def test_torn_last_record_is_cut_and_appends_continue(tmp_path: Path) -> None:
    path = tmp_path / "r.journal"
    j = RobotJournal(path)
    j.append(JournalRecord(b"s", 1, 0x0201, b"abc"))
    j.append(JournalRecord(b"s", 2, 0x0201, b"defgh"))
    j.close()
    size = path.stat().st_size
    with path.open("r+b") as f:
        f.truncate(size - 3)  # a crash in the middle of the second record
    j = RobotJournal(path)
    assert j.records == 1 and j.last == InboundPosition(b"s", 1)
    j.append(JournalRecord(b"s", 2, 0x0201, b"again"))
    j.close()
    assert [r.payload for r in RobotJournal(path).read()] == [b"abc", b"again"]


def test_runs_are_counted_per_robot_across_restarts(tmp_path):
    """Each edge start that serves a robot gets the next run number, kept on disk."""
    store = JournalStore(tmp_path)
    assert [store.next_run("robot-a"), store.next_run("robot-a")] == [0, 1]
    assert store.next_run("robot/b") == 0  # another robot (a sanitised file name)
    store.close()
    assert JournalStore(tmp_path).next_run("robot-a") == 2
    (tmp_path / "robot-a.runs").write_text("two")
    with pytest.raises(JournalError, match=r"robot-a\.runs"):
        JournalStore(tmp_path).next_run("robot-a")
