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

The sending side may persist its unacknowledged outbox (``Link.outbound_state()``, e.g. into
a :class:`FileOutboxStore`) and restore it with ``SessionConfig.new_link(outbound=...)``
passed to ``Client(link=...)``; otherwise a restarted sender starts a new stream and the
receiver resets its position for that peer (logged).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Protocol

import msgpack

from common.protocol.errors import LocalProtocolError
from common.protocol.link_state import InboundPosition, OutboundState, OutboxEntry


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
        data = json.dumps(
            {"stream_id": position.stream_id.hex(), "last_delivered": position.last_delivered}
        ).encode()
        _atomic_write(self._path(peer), data, self.fsync)
        if self.fsync:
            dfd = os.open(self.directory, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)


def _atomic_write(path: Path, data: bytes, fsync: bool) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.write(fd, data)
        if fsync:
            os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)


class FileOutboxStore:
    """The sending side of one link in one file (msgpack), for a sender that must survive
    its own restart without losing unacknowledged messages.

    Save whenever the application needs a durability point (e.g. after queuing a batch, at
    shutdown): messages queued after the last save are lost if the process dies, and the
    restored link replays everything in the file that the peer has not delivered.
    """

    def __init__(self, path: str | Path, *, fsync: bool = True) -> None:
        self.path = Path(path)
        self.fsync = fsync

    def save(self, state: OutboundState) -> None:
        rows = [[seq, e.type_id, e.type_name, e.payload] for seq, e in state.pending]
        data = msgpack.packb([1, state.stream_id, state.next_seq, rows], use_bin_type=True)
        _atomic_write(self.path, data, self.fsync)

    def load(self) -> OutboundState | None:
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        try:
            version, stream_id, next_seq, rows = msgpack.unpackb(raw, raw=False)
            if version != 1:
                raise ValueError(f"unknown outbox file version {version}")
            pending = tuple(
                (int(seq), OutboxEntry(int(t), str(name), bytes(payload)))
                for seq, t, name, payload in rows
            )
            return OutboundState(bytes(stream_id), int(next_seq), pending)
        except (ValueError, TypeError, msgpack.UnpackException) as exc:
            raise LocalProtocolError(f"{self.path}: corrupt outbox file ({exc})") from exc
