"""Challenge-response authentication with a shared secret (HMAC-SHA256, both directions).

Transcript (no secret ever crosses the wire):

1. client -> server ``Hello`` with a fresh 32-byte client nonce;
2. server -> client ``Challenge`` with a fresh server nonce and
   ``mac_s = HMAC(K, "recslam/server" | len|hello | len|challenge-with-empty-mac)``;
3. client checks ``mac_s`` (the server knows K), answers ``Auth`` with
   ``mac_c = HMAC(K, "recslam/client" | len|hello | len|challenge)``;
4. server checks ``mac_c`` (the client knows K) and only then reveals its resume position.

Distinct labels stop reflection; both nonces stop replay; comparisons are constant-time.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import struct

from common.protocol.errors import LocalProtocolError

NONCE_SIZE = 32
MAC_SIZE = 32
MIN_SECRET_SIZE = 16
_SERVER_LABEL = b"recslam/server"
_CLIENT_LABEL = b"recslam/client"


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
