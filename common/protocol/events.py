"""Events a :class:`~common.protocol.session.Session` emits, and ``Close`` reason codes."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from common.protocol.messages import Message


class CloseCode(enum.IntEnum):
    """Reason codes carried by ``Close``."""

    NORMAL = 0
    PROTOCOL_ERROR = 1
    AUTH_FAILED = 2
    VERSION_MISMATCH = 3
    REFUSED = 4
    TIMEOUT = 5
    REPLACED = 6
    HANDLER_FAILED = 7
    REJECTED = 8
    """Codes 7 and 8 are no longer sent (protocol 1 closed the connection on a handler
    failure or refusal): a failing handler is retried in place, a refusal is a ``Reject``."""


@dataclass(frozen=True)
class PeerAuthenticated:
    """Server only: the client proved the secret; call ``attach(link)`` or ``refuse()``."""

    role: str
    agent_id: str


@dataclass(frozen=True)
class HandshakeComplete:
    """The session is established; ``replay`` messages will be (re)sent from the outbox."""

    role: str
    agent_id: str
    replay: int


@dataclass(frozen=True)
class MessageReceived:
    """A new application message, in order; call ``mark_delivered(seq)`` once handled."""

    message: Message
    seq: int
    stream_id: bytes
    size: int


@dataclass(frozen=True)
class Acknowledged:
    """The peer delivered everything up to ``upto``; outbox space was freed."""

    upto: int


@dataclass(frozen=True)
class PeerClosed:
    code: int
    reason: str


@dataclass(frozen=True)
class PeerRejected:
    """The peer's application refused our message ``seq`` for good (it will not be resent)."""

    seq: int
    reason: str


Event = (
    PeerAuthenticated
    | HandshakeComplete
    | MessageReceived
    | Acknowledged
    | PeerClosed
    | PeerRejected
)
