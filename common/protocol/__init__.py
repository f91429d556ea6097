"""Wire protocol: sans-I/O framing, messages, session/reliability, handshake, auth, accounting.

No sockets, clocks or asyncio in here; ``common.transport`` drives it over TCP.
"""

import logging

from common.protocol.accounting import TrafficCounters
from common.protocol.auth import Identity, Keyring
from common.protocol.config import SessionConfig
from common.protocol.errors import (
    AuthenticationError,
    LocalProtocolError,
    OutboxFullError,
    PeerRejectedError,
    PeerTimeoutError,
    PeerUnreachableError,
    ProtocolError,
    RejectedMessageError,
    RemoteProtocolError,
)
from common.protocol.events import (
    Acknowledged,
    CloseCode,
    HandshakeComplete,
    MessageReceived,
    PeerAuthenticated,
    PeerClosed,
    PeerRejected,
)
from common.protocol.framing import HEADER_SIZE, PROTOCOL_VERSION, FrameDecoder, encode_frame
from common.protocol.handshake import State
from common.protocol.link import Link, LinkLimits
from common.protocol.link_state import InboundPosition, OutboundState
from common.protocol.messages import SCHEMA_VERSION, Blob, Message, message
from common.protocol.session import Session
from common.protocol.store import (
    DeliveryStore,
    FileDeliveryStore,
    FileOutboxStore,
    MemoryDeliveryStore,
)

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "HEADER_SIZE",
    "PROTOCOL_VERSION",
    "SCHEMA_VERSION",
    "Acknowledged",
    "AuthenticationError",
    "Blob",
    "CloseCode",
    "DeliveryStore",
    "FileDeliveryStore",
    "FileOutboxStore",
    "FrameDecoder",
    "HandshakeComplete",
    "Identity",
    "InboundPosition",
    "Keyring",
    "Link",
    "LinkLimits",
    "LocalProtocolError",
    "MemoryDeliveryStore",
    "Message",
    "MessageReceived",
    "OutboundState",
    "OutboxFullError",
    "PeerAuthenticated",
    "PeerClosed",
    "PeerRejected",
    "PeerRejectedError",
    "PeerTimeoutError",
    "PeerUnreachableError",
    "ProtocolError",
    "RejectedMessageError",
    "RemoteProtocolError",
    "Session",
    "SessionConfig",
    "State",
    "TrafficCounters",
    "encode_frame",
    "message",
]
