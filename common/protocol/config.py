"""Settings of one protocol endpoint (:class:`SessionConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from common.protocol import auth
from common.protocol.errors import LocalProtocolError
from common.protocol.framing import DEFAULT_MAX_FRAME_SIZE
from common.protocol.link import Link, LinkLimits
from common.protocol.link_state import InboundPosition, OutboundState

MAX_NAME_LENGTH = 64


@dataclass(frozen=True)
class SessionConfig:
    """Protocol settings of one endpoint (built once, handed down).

    Attributes:
        role: this endpoint's role ("robot", "edge", "cloud", ...), sent to the peer.
        agent_id: this endpoint's id; a server keys links by the client's agent id.
        secret: the operator secret, at least 16 bytes (never sent): shorthand for
            ``keys=Keyring.from_secret(secret)``, which derives every credential.
        keys: the key material of this endpoint (:class:`~common.protocol.auth.Keyring`);
            give ``secret`` or ``keys``. A client's keys must hold its own credential.
        seal_frames: authenticated encryption of every frame after the handshake (see
            ``sealing.py``). Off only to measure its cost: without it a man in the middle
            can change, inject or replay frames.
        max_frame_size: largest frame accepted or sent, header included (bytes).
        heartbeat_interval: send a Heartbeat after this many idle seconds.
        idle_timeout: peer silent this long (s) = dead; must exceed heartbeat_interval.
        handshake_timeout: handshake must complete within this many seconds.
        retransmit_timeout: least timeout (s) before the oldest in-flight message is resent;
            it adapts upwards to the measured time to an ack, and a peer heard from meanwhile
            gets no resend (``recovery.py``).
        max_retransmit_timeout: cap of the adaptive and doubling retransmit timeout (s).
        ack_delay: an explicit Ack goes out at most this many seconds after a delivery.
        ack_every: ... or immediately after this many unacknowledged deliveries.
        window_messages: receive window, messages accepted but not yet delivered.
        window_bytes: receive window in payload bytes (one message always fits).
        max_outbox_messages: bound of the send outbox (``send`` waits when full).
        max_outbox_bytes: bound of the send outbox in payload bytes.
    """

    role: str
    agent_id: str
    secret: bytes | None = field(default=None, repr=False)
    keys: auth.Keyring | None = field(default=None, repr=False)
    seal_frames: bool = True
    max_frame_size: int = DEFAULT_MAX_FRAME_SIZE
    heartbeat_interval: float = 2.0
    idle_timeout: float = 10.0
    handshake_timeout: float = 5.0
    retransmit_timeout: float = 5.0
    max_retransmit_timeout: float = 60.0
    ack_delay: float = 0.005
    ack_every: int = 64
    window_messages: int = 1024
    window_bytes: int = 32 * 1024 * 1024
    max_outbox_messages: int = 4096
    max_outbox_bytes: int = 256 * 1024 * 1024

    def __post_init__(self) -> None:
        if (self.secret is None) == (self.keys is None):
            raise LocalProtocolError("give exactly one of secret= and keys=")
        if self.keys is None:
            object.__setattr__(self, "keys", auth.Keyring.from_secret(self.secret or b""))
        for name in ("role", "agent_id"):
            value = getattr(self, name)
            if not isinstance(value, str) or not 0 < len(value) <= MAX_NAME_LENGTH:
                raise LocalProtocolError(f"{name} must be a non-empty str of <= 64 chars")
        if self.idle_timeout <= self.heartbeat_interval:
            raise LocalProtocolError("idle_timeout must exceed heartbeat_interval")
        if not 0 < self.retransmit_timeout <= self.max_retransmit_timeout:
            raise LocalProtocolError(
                "need 0 < retransmit_timeout <= max_retransmit_timeout, got "
                f"{self.retransmit_timeout}, {self.max_retransmit_timeout}"
            )
        if min(self.window_messages, self.window_bytes, self.ack_every) < 1:
            raise LocalProtocolError("windows and ack_every must be positive")

    @property
    def keyring(self) -> auth.Keyring:
        assert self.keys is not None  # set by __post_init__
        return self.keys

    def own_credential(self) -> bytes:
        """This endpoint's credential as a client (LocalProtocolError if its keys lack it)."""
        credential = self.keyring.credential(self.role, self.agent_id)
        if credential is None:
            raise LocalProtocolError(
                f"the keys hold no credential for {self.role} {self.agent_id!r}"
            )
        return credential

    def link_limits(self) -> LinkLimits:
        return LinkLimits(self.max_outbox_messages, self.max_outbox_bytes, self.max_frame_size)

    def new_link(
        self,
        *,
        inbound: InboundPosition | None = None,
        outbound: OutboundState | None = None,
        peer: str | None = None,
    ) -> Link:
        """A fresh :class:`Link` with this config's limits (the keywords go to ``Link``)."""
        return Link(self.link_limits(), inbound=inbound, outbound=outbound, peer=peer)
