"""Per-robot append-only journal of the raw robot messages: the edge's restart memory.

The robot's feature and IMU streams are differential and the VIO's state is the sum of every
frame, so a restarted edge must see every frame again. The robot replays only what the edge
has not acknowledged; the journal holds the rest. Each record is
``[u32 little-endian length][msgpack [stream_id, seq, type_id, payload]]``, appended with
``os.write`` before the message handler returns (hence before the transport acks it), so a
killed process (SIGKILL) never loses an acknowledged frame; ``fsync`` runs in batches (every
``fsync_interval_s``, and at close) for power-loss durability of all but the newest batch.

The journal *is* the transport's :class:`~common.protocol.store.DeliveryStore`: ``load``
returns the (stream id, seq) of the last record, ``save`` only triggers the batched fsync, so
the saved position and the journaled effect can never disagree. A torn last record (crash
mid-write) is cut off on open.
"""

from __future__ import annotations

import logging
import os
import re
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import msgpack

from common.errors import RecslamError
from common.protocol.link_state import InboundPosition

logger = logging.getLogger(__name__)

_LEN = struct.Struct("<I")
_SAFE = re.compile(r"[^A-Za-z0-9_.-]")


class JournalError(RecslamError):
    """A journal file is unreadable (names the file and byte offset)."""


@dataclass(frozen=True)
class JournalRecord:
    """One journaled message: the link position and the raw payload of type ``type_id``."""

    stream_id: bytes
    seq: int
    type_id: int
    payload: bytes


class RobotJournal:
    """The append-only journal file of one robot (see the module docstring)."""

    def __init__(self, path: Path, fsync_interval_s: float = 0.2) -> None:
        self.path = path
        self.fsync_interval_s = fsync_interval_s
        self.records = 0
        self.last: InboundPosition | None = None
        self._dirty = False
        self._last_sync = time.monotonic()
        good = 0
        for rec, end in self._scan():
            self.records += 1
            self.last = InboundPosition(rec.stream_id, rec.seq)
            good = end
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        if os.fstat(self._fd).st_size > good:
            logger.warning("%s: cutting a torn record after byte %d", path, good)
            os.ftruncate(self._fd, good)

    def _scan(self) -> Iterator[tuple[JournalRecord, int]]:
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return
        pos = 0
        while pos + _LEN.size <= len(data):
            (n,) = _LEN.unpack_from(data, pos)
            end = pos + _LEN.size + n
            if end > len(data):
                return  # torn tail
            try:
                sid, seq, tid, payload = msgpack.unpackb(data[pos + _LEN.size : end], raw=False)
                rec = JournalRecord(bytes(sid), int(seq), int(tid), bytes(payload))
            except (ValueError, TypeError, msgpack.UnpackException) as exc:
                raise JournalError(f"{self.path}: corrupt record at byte {pos} ({exc})") from exc
            yield rec, end
            pos = end

    def read(self) -> list[JournalRecord]:
        """Every record, oldest first."""
        return [rec for rec, _ in self._scan()]

    def append(self, record: JournalRecord) -> None:
        """Write one record (one ``write`` syscall: survives a killed process)."""
        body = msgpack.packb(
            [record.stream_id, record.seq, record.type_id, record.payload], use_bin_type=True
        )
        os.write(self._fd, _LEN.pack(len(body)) + body)
        self.records += 1
        self.last = InboundPosition(record.stream_id, record.seq)
        self._dirty = True

    def sync(self, force: bool = False) -> None:
        """fsync if records were written and the batch interval passed (or ``force``)."""
        now = time.monotonic()
        if self._dirty and (force or now - self._last_sync >= self.fsync_interval_s):
            os.fsync(self._fd)
            self._dirty = False
            self._last_sync = now

    def close(self) -> None:
        self.sync(force=True)
        os.close(self._fd)


class JournalStore:
    """``DeliveryStore`` over the robots' journals in ``directory`` (one file per robot)."""

    def __init__(self, directory: str | Path, fsync_interval_s: float = 0.2) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.fsync_interval_s = fsync_interval_s
        self._open: dict[str, RobotJournal] = {}

    def path(self, agent_id: str) -> Path:
        return self.directory / f"{_SAFE.sub('_', agent_id)}.journal"

    def journal(self, agent_id: str) -> RobotJournal:
        j = self._open.get(agent_id)
        if j is None:
            j = self._open[agent_id] = RobotJournal(self.path(agent_id), self.fsync_interval_s)
        return j

    def agents(self) -> list[str]:
        """Robots with a journal; names are read back from ``<agent>.agent`` side files."""
        out = []
        for p in sorted(self.directory.glob("*.journal")):
            name_file = p.with_suffix(".agent")
            out.append(name_file.read_text() if name_file.exists() else p.stem)
        return out

    def next_run(self, agent_id: str) -> int:
        """How many edge runs served this robot before this one (0 the first time), counted
        durably in ``<agent>.runs``: a restarted edge re-runs the robot's VIO from the journal,
        and that re-run is a new map, not the first run's (which the cloud already holds)."""
        path = self.path(agent_id).with_suffix(".runs")
        try:
            run = int(path.read_text()) if path.exists() else 0
        except ValueError as exc:
            raise JournalError(f"{path}: not a run count ({exc})") from exc
        tmp = path.with_suffix(".runs.tmp")
        with open(tmp, "w") as f:
            f.write(str(run + 1))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        return run

    def register(self, agent_id: str) -> None:
        """Remember the exact agent id of a journal (file names are sanitised)."""
        name_file = self.path(agent_id).with_suffix(".agent")
        if not name_file.exists():
            name_file.write_text(agent_id)

    # DeliveryStore
    def load(self, peer: str) -> InboundPosition | None:
        if not self.path(peer).exists():
            return None
        return self.journal(peer).last

    def save(self, peer: str, position: InboundPosition) -> None:
        j = self._open.get(peer)
        if j is not None:
            j.sync()

    def close(self) -> None:
        for j in self._open.values():
            j.close()
        self._open.clear()
