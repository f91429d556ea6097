"""The handshake of a :class:`~common.protocol.session.Session`: the connection's states and
the authentication steps (sans-I/O).

Client left, server right; every legal transition is in the session's ``_TRANSITIONS``::

    HELLO_SENT     --Hello-->       AWAIT_HELLO -> CHALLENGE_SENT
    AUTH_SENT      <--Challenge--   (server proved the client's credential)
                   --Auth-->        AUTHENTICATED: event PeerAuthenticated; the caller
                                    picks the peer's Link and calls attach() (or refuse())
    ESTABLISHED    <==Welcome==     ESTABLISHED

The credential is the one of the identity the client's Hello claims (``auth.py``); every
frame after Auth (``==``) is sealed with keys derived from it and the transcript
(``sealing.py``): a frame changed, injected, replayed or reordered on the way closes the
connection before anything in it is used.

:class:`Handshake` is a base of the session (which sets the attributes declared here) and
handles Hello, Challenge and Auth; the session's ``attach`` and Welcome handler resume the
link and establish the connection.
"""

from __future__ import annotations

import dataclasses
import enum
from collections import deque
from typing import TYPE_CHECKING

from common.protocol import auth, sealing
from common.protocol.config import MAX_NAME_LENGTH, SessionConfig
from common.protocol.errors import AuthenticationError, ProtocolError, RemoteProtocolError
from common.protocol.events import CloseCode, Event, PeerAuthenticated
from common.protocol.framing import PROTOCOL_VERSION, Frame
from common.protocol.messages import (
    SCHEMA_VERSION,
    Auth,
    Challenge,
    Hello,
    Message,
    encode_payload,
)


class State(enum.Enum):
    HELLO_SENT = "hello-sent"
    AUTH_SENT = "auth-sent"
    AWAIT_HELLO = "await-hello"
    CHALLENGE_SENT = "challenge-sent"
    AUTHENTICATED = "authenticated"
    ESTABLISHED = "established"
    CLOSED = "closed"


class Handshake:
    """Hello, Challenge and Auth of :class:`~common.protocol.session.Session`."""

    config: SessionConfig
    client: bool
    state: State
    peer_role: str | None
    peer_agent_id: str | None
    _events: deque[Event]
    _nonce: bytes
    _hello: Hello | None
    _hello_payload: bytes
    _challenge_payload: bytes
    _key: bytes
    _keys: sealing.ConnectionKeys

    if TYPE_CHECKING:  # the Session's

        def _emit(self, msg: Message) -> None: ...

        def _emit_payload(self, cls: type[Message], payload: bytes) -> None: ...

        def _fail(self, exc: ProtocolError, code: CloseCode) -> None: ...

    def _on_hello(self, msg: Hello, frame: Frame) -> None:
        self._check_versions(msg.protocol_version, msg.schema_version)
        _check_name("role", msg.role)
        _check_name("agent_id", msg.agent_id)
        if len(msg.nonce) != auth.NONCE_SIZE:
            raise RemoteProtocolError(f"Hello nonce must be {auth.NONCE_SIZE} bytes")
        self._hello, self._hello_payload = msg, frame.payload
        self.peer_role, self.peer_agent_id = msg.role, msg.agent_id
        key = self.config.keyring.credential(msg.role, msg.agent_id)
        if key is None:
            raise AuthenticationError(f"no credential for {msg.role} {msg.agent_id!r} here")
        self._key = key
        unsigned = Challenge(
            PROTOCOL_VERSION,
            SCHEMA_VERSION,
            self.config.role,
            self.config.agent_id,
            self._nonce,
            b"",
        )
        mac = auth.server_mac(key, frame.payload, encode_payload(unsigned))
        challenge = dataclasses.replace(unsigned, mac=mac)
        self._challenge_payload = encode_payload(challenge)
        self._emit_payload(Challenge, self._challenge_payload)
        self.state = State.CHALLENGE_SENT

    def _on_challenge(self, msg: Challenge, frame: Frame) -> None:
        self._check_versions(msg.protocol_version, msg.schema_version)
        _check_name("role", msg.role)
        _check_name("agent_id", msg.agent_id)
        unsigned = encode_payload(dataclasses.replace(msg, mac=b""))
        expected = auth.server_mac(self._key, self._hello_payload, unsigned)
        if not auth.macs_equal(expected, msg.mac):
            raise AuthenticationError(
                f"server failed authentication: it does not hold the credential of "
                f"{self.config.role} {self.config.agent_id!r} (wrong key or secret?)"
            )
        self.peer_role, self.peer_agent_id = msg.role, msg.agent_id
        self._challenge_payload = frame.payload
        self._emit(Auth(auth.client_mac(self._key, self._hello_payload, frame.payload)))
        self._start_sealing()
        self.state = State.AUTH_SENT

    def _on_auth(self, msg: Auth, frame: Frame) -> None:
        assert self._hello is not None
        expected = auth.client_mac(self._key, self._hello_payload, self._challenge_payload)
        if not auth.macs_equal(expected, msg.mac):
            raise AuthenticationError(
                f"client {self._hello.role} {self._hello.agent_id!r} failed authentication "
                "(wrong credential or secret?)"
            )
        self._start_sealing()
        self.state = State.AUTHENTICATED
        self._events.append(PeerAuthenticated(self._hello.role, self._hello.agent_id))

    def _start_sealing(self) -> None:
        """From the next frame on, both directions are sealed (if configured)."""
        if self.config.seal_frames:
            keys = (self._key, self._hello_payload, self._challenge_payload)
            self._keys.start(*keys, client=self.client)

    def _check_versions(self, protocol_version: int, schema_version: int) -> None:
        if protocol_version != PROTOCOL_VERSION or schema_version != SCHEMA_VERSION:
            self._fail(
                RemoteProtocolError(
                    f"peer speaks protocol {protocol_version}/schema {schema_version}, "
                    f"we speak {PROTOCOL_VERSION}/{SCHEMA_VERSION}"
                ),
                CloseCode.VERSION_MISMATCH,
            )


def _check_name(name: str, value: str) -> None:
    if not 0 < len(value) <= MAX_NAME_LENGTH:
        raise RemoteProtocolError(f"{name} must have 1..{MAX_NAME_LENGTH} characters")
