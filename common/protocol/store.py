"""Durable positions: what a receiver must remember to get exactly-once across restarts.

The receiving side of a link is described by an :class:`InboundPosition`: the id of the
peer's outgoing stream and the last sequence of it that the application has *delivered*
(its handler returned). A process that wants no loss and no duplicates across its own
restart hands the position it saved back to the transport at start (``DeliveryStore.load``);
the handshake tells the peer, which replays everything after it.

Exactly-once across a crash needs the application's effect and the saved position to be
atomic. Two ways to get that:

- record ``(stream_id, seq)`` together with the effect (same file write, same database
  transaction) and implement :class:`DeliveryStore` so that ``load`` reads it back and
  ``save`` does nothing (the fault test's receiver process does this with an append log);
- or make the handler idempotent per ``(stream_id, seq)`` and use :class:`FileDeliveryStore`,
  which saves after each handler return (a crash between the two re-delivers one message).

The sending side may persist its unacknowledged outbox with ``Link.outbound_state()`` and
restore it with ``Link(..., outbound=...)``; otherwise a restarted sender starts a new stream
and the receiver resets its position for that peer (logged).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from common.protocol.errors import LocalProtocolError


@dataclass(frozen=True)
class InboundPosition:
    """Receiver's durable position on one link: peer stream id and last delivered sequence."""

    stream_id: bytes
    last_delivered: int


class DeliveryStore(Protocol):
    """Where a receiver keeps its :class:`InboundPosition` per peer (agent id)."""

    def load(self, peer: str) -> InboundPosition | None: ...

    def save(self, peer: str, position: InboundPosition) -> None: ...


class MemoryDeliveryStore:
    """Positions kept in memory: survives reconnects, not process restarts (the default)."""

    def __init__(self) -> None:
        self._positions: dict[str, InboundPosition] = {}

    def load(self, peer: str) -> InboundPosition | None:
        return self._positions.get(peer)

    def save(self, peer: str, position: InboundPosition) -> None:
        self._positions[peer] = position


_SAFE = re.compile(r"[^A-Za-z0-9_.-]")


class FileDeliveryStore:
    """One small JSON file per peer under ``directory``, replaced atomically on each save.

    Args:
        directory: created if missing.
        fsync: fsync file and directory on every save (durable across power loss; slower).
    """

    def __init__(self, directory: str | Path, *, fsync: bool = True) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.fsync = fsync

    def _path(self, peer: str) -> Path:
        return self.directory / f"{_SAFE.sub('_', peer)}.position.json"

    def load(self, peer: str) -> InboundPosition | None:
        path = self._path(peer)
        try:
            raw = json.loads(path.read_text())
            return InboundPosition(bytes.fromhex(raw["stream_id"]), int(raw["last_delivered"]))
        except FileNotFoundError:
            return None
        except (ValueError, KeyError, TypeError) as exc:
            raise LocalProtocolError(f"{path}: corrupt delivery position ({exc})") from exc

    def save(self, peer: str, position: InboundPosition) -> None:
        path = self._path(peer)
        tmp = path.with_suffix(".tmp")
        data = json.dumps(
            {"stream_id": position.stream_id.hex(), "last_delivered": position.last_delivered}
        ).encode()
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            os.write(fd, data)
            if self.fsync:
                os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        if self.fsync:
            dfd = os.open(self.directory, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
