"""The persistable state of a link: plain data shared by the link and the stores.

:class:`~common.protocol.link.Link` produces and restores these; the stores of
:mod:`common.protocol.store` save and load them. Both import this module and not each other.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class InboundPosition:
    """Receiver's durable position on one link: peer stream id and last delivered sequence."""

    stream_id: bytes
    last_delivered: int


@dataclass(frozen=True, slots=True)
class OutboxEntry:
    """One queued application message, already encoded."""

    type_id: int
    type_name: str
    payload: bytes


@dataclass(frozen=True)
class OutboundState:
    """Persistable sending side: stream id, next sequence and the unacknowledged entries."""

    stream_id: bytes
    next_seq: int
    pending: tuple[tuple[int, OutboxEntry], ...]
