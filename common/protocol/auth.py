"""Challenge-response authentication with a shared secret (HMAC-SHA256, both directions).

Transcript (no secret ever crosses the wire):

1. client -> server ``Hello`` with a fresh 32-byte client nonce;
2. server -> client ``Challenge`` with a fresh server nonce and
   ``mac_s = HMAC(K, "recslam/server" | len|hello | len|challenge-with-empty-mac)``;
3. client checks ``mac_s`` (the server knows K), answers ``Auth`` with
   ``mac_c = HMAC(K, "recslam/client" | len|hello | len|challenge)``;
4. server checks ``mac_c`` (the client knows K) and only then reveals its resume position.

Distinct labels stop reflection; both nonces stop replay; comparisons are constant-time.

One identity per peer: K is not one secret shared by everybody but the *credential* of the
client's (role, agent id), derived from the operator's secret (:func:`agent_credential`).
The server looks the credential up from the identity the Hello claims (:class:`Keyring`), so
a client can only be the identity whose credential it holds. Who holds what:

- the operator secret derives every credential (the cloud; a single-host demo);
- a role key (``role_key(operator, "robot")``) derives the credentials of every agent of
  that role: an edge holds the robots' role key to verify robots, and its own credential;
- a robot holds only its own credential.

After the handshake both sides derive per-direction frame keys from K and the transcript
(:mod:`common.protocol.sealing`).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import struct
from dataclasses import dataclass, field

from common.protocol.errors import LocalProtocolError

NONCE_SIZE = 32
MAC_SIZE = 32
MIN_SECRET_SIZE = 16
_SERVER_LABEL = b"recslam/server"
_CLIENT_LABEL = b"recslam/client"
_ROLE_LABEL = b"recslam/role-key"
_AGENT_LABEL = b"recslam/credential"


def check_secret(secret: bytes) -> bytes:
    """Return ``secret`` if usable (bytes, >= 16 bytes), else LocalProtocolError."""
    if not isinstance(secret, bytes) or len(secret) < MIN_SECRET_SIZE:
        raise LocalProtocolError(f"shared secret must be at least {MIN_SECRET_SIZE} bytes")
    return secret


def new_nonce() -> bytes:
    """A fresh random nonce of ``NONCE_SIZE`` bytes."""
    return secrets.token_bytes(NONCE_SIZE)


def _mac(secret: bytes, label: bytes, *parts: bytes) -> bytes:
    h = hmac.new(secret, label, hashlib.sha256)
    for part in parts:
        h.update(struct.pack("!I", len(part)))
        h.update(part)
    return h.digest()


def server_mac(secret: bytes, hello_payload: bytes, challenge_unsigned: bytes) -> bytes:
    """Server's proof over the Hello payload and the Challenge payload with ``mac=b""``."""
    return _mac(secret, _SERVER_LABEL, hello_payload, challenge_unsigned)


def client_mac(secret: bytes, hello_payload: bytes, challenge_payload: bytes) -> bytes:
    """Client's proof over the Hello payload and the full Challenge payload."""
    return _mac(secret, _CLIENT_LABEL, hello_payload, challenge_payload)


def macs_equal(expected: bytes, received: bytes) -> bool:
    """Constant-time comparison."""
    return hmac.compare_digest(expected, received)


def role_key(operator_secret: bytes, role: str) -> bytes:
    """The key that derives the credential of every agent of ``role`` (32 bytes)."""
    return _mac(check_secret(operator_secret), _ROLE_LABEL, role.encode())


def agent_credential(role_key_: bytes, agent_id: str) -> bytes:
    """The credential of one agent, from its role's key (32 bytes)."""
    return _mac(check_secret(role_key_), _AGENT_LABEL, agent_id.encode())


def fingerprint(key: bytes) -> str:
    """A short public name of a key (first 8 bytes of its SHA-256, hex), safe to log."""
    return hashlib.sha256(key).hexdigest()[:16]


@dataclass(frozen=True)
class Identity:
    """A credential together with the (role, agent id) it was issued for."""

    role: str
    agent_id: str
    credential: bytes = field(repr=False)


@dataclass(frozen=True)
class Keyring:
    """The key material one endpoint holds (see the module docstring).

    Attributes:
        operator: the operator secret (derives every credential), or None.
        role_keys: ``(role, key)`` pairs: credentials of every agent of those roles.
        own: this endpoint's own credential when it holds neither of the above for itself.
    """

    operator: bytes | None = field(default=None, repr=False)
    role_keys: tuple[tuple[str, bytes], ...] = field(default=(), repr=False)
    own: Identity | None = None

    def __post_init__(self) -> None:
        keys = [k for _, k in self.role_keys]
        keys += [self.operator] if self.operator is not None else []
        keys += [self.own.credential] if self.own is not None else []
        if not keys:
            raise LocalProtocolError("a keyring needs an operator secret, role keys or its own")
        for key in keys:
            check_secret(key)

    @classmethod
    def from_secret(cls, operator_secret: bytes) -> Keyring:
        return cls(operator=check_secret(operator_secret))

    def credential(self, role: str, agent_id: str) -> bytes | None:
        """The credential of (role, agent id), or None if this keyring cannot derive it."""
        if self.own is not None and (self.own.role, self.own.agent_id) == (role, agent_id):
            return self.own.credential
        key = dict(self.role_keys).get(role)
        if key is None and self.operator is not None:
            key = role_key(self.operator, role)
        return None if key is None else agent_credential(key, agent_id)


def as_keyring(material: bytes | Keyring) -> Keyring:
    """A keyring from an operator secret, or the keyring itself."""
    return material if isinstance(material, Keyring) else Keyring.from_secret(material)
