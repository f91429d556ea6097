"""Reliability state of one link (both directions); outlives connections.

A :class:`Link` holds what must survive a reconnect: the outbox of sent-but-unacknowledged
application messages (sequence numbers from 1, kept until the peer's application delivered
them) and the inbound position (peer stream id, last sequence accepted and delivered). One
:class:`~common.protocol.session.Session` per TCP connection drives it; a new session
resumes the same link after a cut. No I/O, no clock.
"""

from __future__ import annotations

import logging
import secrets
from collections import OrderedDict, deque
from dataclasses import dataclass

from common.protocol.accounting import TrafficCounters
from common.protocol.errors import LocalProtocolError, OutboxFullError, RemoteProtocolError
from common.protocol.framing import HEADER_SIZE, MAX_SEQ
from common.protocol.link_state import InboundPosition, OutboundState, OutboxEntry
from common.protocol.messages import Message, encode_payload

logger = logging.getLogger(__name__)

STREAM_ID_SIZE = 16


@dataclass(frozen=True)
class LinkLimits:
    """Bounds of one link's outbox (sender) and receive window (receiver).

    Attributes:
        max_outbox_messages: unacknowledged messages held before ``OutboxFullError``.
        max_outbox_bytes: payload bytes likewise (one message is always admitted).
        max_frame_size: largest frame in bytes, header included.
    """

    max_outbox_messages: int = 4096
    max_outbox_bytes: int = 256 * 1024 * 1024
    max_frame_size: int = 8 * 1024 * 1024


class Link:
    """Outbox and delivery positions for the link to one peer.

    Args:
        limits: outbox bounds.
        inbound: durable position to resume from (see ``store.py``); None for a fresh link.
        outbound: persisted sending side to resume; None starts a new stream.
        peer: agent id of the peer if known (servers learn it in the handshake).
    """

    def __init__(
        self,
        limits: LinkLimits | None = None,
        *,
        inbound: InboundPosition | None = None,
        outbound: OutboundState | None = None,
        peer: str | None = None,
    ) -> None:
        self.limits = limits or LinkLimits()
        self.peer = peer
        self.counters = TrafficCounters()
        # sending side
        self.outbox: OrderedDict[int, OutboxEntry] = OrderedDict()
        self.outbox_bytes = 0
        self.acked_bytes = 0  # payload bytes acknowledged so far (rate estimates)
        if outbound is None:
            self.out_stream_id = secrets.token_bytes(STREAM_ID_SIZE)
            self.next_seq = 1
        else:
            self.out_stream_id = outbound.stream_id
            self.next_seq = outbound.next_seq
            for seq, entry in outbound.pending:
                self.outbox[seq] = entry
                self.outbox_bytes += len(entry.payload)
        self.highest_sent = self.next_seq - 1 if outbound else 0
        # receiving side
        self.in_stream_id = inbound.stream_id if inbound else b""
        self.last_delivered = inbound.last_delivered if inbound else 0
        self.last_accepted = self.last_delivered
        self._pending_sizes: deque[int] = deque()  # payload sizes of accepted, undelivered
        self.pending_bytes = 0

    # ------------------------------------------------------------------ sending side
    @property
    def first_unacked(self) -> int:
        """Lowest sequence still in the outbox (``next_seq`` if the outbox is empty)."""
        return next(iter(self.outbox)) if self.outbox else self.next_seq

    def has_room(self, payload_size: int) -> bool:
        """Whether a payload of this size fits in the outbox now."""
        if not self.outbox:
            return True
        return (
            len(self.outbox) < self.limits.max_outbox_messages
            and self.outbox_bytes + payload_size <= self.limits.max_outbox_bytes
        )

    def encode(self, message: Message) -> OutboxEntry:
        """Encode ``message`` (LocalProtocolError if invalid or larger than a frame)."""
        if message.CONTROL:
            raise LocalProtocolError(f"{type(message).__name__} is a control message")
        payload = encode_payload(message)
        if HEADER_SIZE + len(payload) > self.limits.max_frame_size:
            raise LocalProtocolError(
                f"{type(message).__name__} of {HEADER_SIZE + len(payload)} bytes exceeds "
                f"max_frame_size {self.limits.max_frame_size}"
            )
        return OutboxEntry(message.TYPE_ID, type(message).__name__, payload)

    def enqueue(self, message: Message | OutboxEntry) -> int:
        """Append to the outbox and return its sequence; ``OutboxFullError`` if no room."""
        entry = message if isinstance(message, OutboxEntry) else self.encode(message)
        if not self.has_room(len(entry.payload)):
            raise OutboxFullError(
                f"outbox holds {len(self.outbox)} messages / {self.outbox_bytes} bytes"
            )
        if self.next_seq > MAX_SEQ:
            raise LocalProtocolError("sequence space exhausted; start a new stream")
        seq = self.next_seq
        self.next_seq += 1
        self.outbox[seq] = entry
        self.outbox_bytes += len(entry.payload)
        return seq

    def acknowledge(self, upto: int) -> list[tuple[int, int]]:
        """Drop entries with seq <= ``upto``; return their ``(seq, payload size)``."""
        removed = []
        while self.outbox:
            seq = next(iter(self.outbox))
            if seq > upto:
                break
            entry = self.outbox.pop(seq)
            self.outbox_bytes -= len(entry.payload)
            self.acked_bytes += len(entry.payload)
            removed.append((seq, len(entry.payload)))
        return removed

    def outbound_state(self) -> OutboundState:
        """Snapshot of the sending side for persistence."""
        return OutboundState(self.out_stream_id, self.next_seq, tuple(self.outbox.items()))

    # ---------------------------------------------------------------- receiving side
    @property
    def pending_messages(self) -> int:
        """Accepted messages whose handler has not returned yet."""
        return len(self._pending_sizes)

    def accept(self, seq: int, payload_size: int) -> None:
        """Record that message ``seq`` was handed to the application."""
        if seq != self.last_accepted + 1:
            raise LocalProtocolError(f"accept({seq}) out of order after {self.last_accepted}")
        self.last_accepted = seq
        self._pending_sizes.append(payload_size)
        self.pending_bytes += payload_size

    def mark_delivered(self, seq: int) -> None:
        """The application's handler for ``seq`` returned (deliveries are in order)."""
        if seq != self.last_delivered + 1 or seq > self.last_accepted:
            raise LocalProtocolError(
                f"mark_delivered({seq}) but last delivered is {self.last_delivered} "
                f"and last accepted {self.last_accepted}"
            )
        self.last_delivered = seq
        self.pending_bytes -= self._pending_sizes.popleft()

    def rewind_inbound(self) -> None:
        """Forget accepted-but-undelivered messages (the peer will replay them)."""
        self.last_accepted = self.last_delivered
        self._pending_sizes.clear()
        self.pending_bytes = 0

    def switch_inbound_stream(self, stream_id: bytes, first_seq: int) -> None:
        """Follow a new peer stream starting at ``first_seq`` (peer restarted without state)."""
        if self.in_stream_id:
            logger.warning(
                "peer %s started a new stream (was %s, delivered up to %d): it restarted "
                "without its outbox; anything it had not sent is lost on its side",
                self.peer,
                self.in_stream_id.hex()[:8],
                self.last_delivered,
            )
        self.in_stream_id = stream_id
        self.last_delivered = first_seq - 1
        self.rewind_inbound()

    def resume(
        self,
        peer_out_stream: bytes,
        peer_first_unacked: int,
        peer_in_stream: bytes,
        peer_last_delivered: int,
    ) -> None:
        """Apply the peer's resume position from the handshake (RemoteProtocolError if it is
        impossible): drop what its application delivered from our outbox, and follow its
        outgoing stream (a new one, or the same one from ``peer_first_unacked``)."""
        if peer_first_unacked < 1 or peer_last_delivered < 0:
            raise RemoteProtocolError("invalid resume position in handshake")
        if peer_in_stream == self.out_stream_id:
            if peer_last_delivered >= self.next_seq:
                raise RemoteProtocolError(
                    f"peer claims delivery of {peer_last_delivered}, never sent past "
                    f"{self.next_seq - 1}"
                )
            self.acknowledge(peer_last_delivered)
        if peer_out_stream != self.in_stream_id:
            self.switch_inbound_stream(peer_out_stream, peer_first_unacked)
        elif peer_first_unacked > self.last_accepted + 1:
            if self.pending_messages:
                raise RemoteProtocolError("peer skipped messages we have not delivered")
            logger.warning(
                "peer %s no longer holds messages %d..%d that we never recorded as "
                "delivered (our saved position is stale); continuing from %d",
                self.peer,
                self.last_delivered + 1,
                peer_first_unacked - 1,
                peer_first_unacked,
            )
            self.last_delivered = self.last_accepted = peer_first_unacked - 1

    def inbound_position(self) -> InboundPosition:
        """Current delivered position (what a receiver persists)."""
        return InboundPosition(self.in_stream_id, self.last_delivered)
