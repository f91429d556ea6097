"""Authenticated encryption of every frame after the handshake (ChaCha20-Poly1305).

Both sides derive four values from the peer's credential and the handshake transcript
(:func:`session_keys`): a key and a 96-bit IV per direction. The *n*-th sealed frame of a
direction (counted from 0 on that connection) uses the nonce ``IV xor n``, as TLS 1.3 does
with its record sequence number, so the nonce is implicit: a frame that is modified,
injected, dropped, replayed or reordered fails :meth:`FrameSealer.open` and the connection
is closed. A new connection runs a new handshake with fresh nonces, hence new keys: frames
of one connection cannot be replayed into another.

The 22-byte frame header stays in the clear (the receiver needs its length) and is the
AEAD's associated data, so none of its fields can be changed either; the payload is
encrypted and followed by the 16-byte tag (the header's length counts it).

ChaCha20-Poly1305 rather than AES-GCM: robot computers are often ARM boards without AES
instructions, where ChaCha20 is several times faster; on x86 both run at GB/s.
"""

from __future__ import annotations

import dataclasses
import hashlib
import struct
from collections.abc import Callable

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from common.protocol.errors import LocalProtocolError, RemoteProtocolError
from common.protocol.framing import FLAG_SEALED, Frame

TAG_SIZE = 16
KEY_SIZE = 32
IV_SIZE = 12
_INFO = b"recslam/session-keys v1"
_MAX_FRAMES = 1 << 64


class FrameSealer:
    """Seals (or opens) the frames of one direction of one connection, in order.

    Args:
        key: 32-byte ChaCha20-Poly1305 key of this direction.
        iv: 12-byte IV of this direction; frame *n* uses ``iv xor n``.
    """

    def __init__(self, key: bytes, iv: bytes) -> None:
        if len(key) != KEY_SIZE or len(iv) != IV_SIZE:
            raise LocalProtocolError(f"sealing needs a {KEY_SIZE}-byte key and {IV_SIZE}-byte IV")
        self._aead = ChaCha20Poly1305(key)
        self._iv = int.from_bytes(iv, "big")
        self.count = 0  # frames sealed / opened so far

    def _nonce(self) -> bytes:
        if self.count >= _MAX_FRAMES:
            raise LocalProtocolError("2**64 frames on one connection: reconnect for new keys")
        nonce = (self._iv ^ self.count).to_bytes(IV_SIZE, "big")
        self.count += 1
        return nonce

    def seal(self, header: bytes, payload: bytes) -> bytes:
        """Ciphertext + tag of ``payload``, bound to ``header`` and to its place in order."""
        return self._aead.encrypt(self._nonce(), payload, header)

    def open(self, header: bytes, sealed: bytes, what: str) -> bytes:
        """The payload, or RemoteProtocolError if the frame is not the next one sealed by
        the peer with this key (modified, injected, dropped, replayed or reordered)."""
        index = self.count
        try:
            return self._aead.decrypt(self._nonce(), sealed, header)
        except InvalidTag:
            raise RemoteProtocolError(
                f"{what} (sealed frame {index}) failed authentication: modified, injected, "
                "replayed or reordered on the way"
            ) from None


def session_keys(
    credential: bytes, hello_payload: bytes, challenge_payload: bytes
) -> tuple[FrameSealer, FrameSealer]:
    """(client->server, server->client) sealers of one connection.

    HKDF-SHA256 over the credential both sides proved, salted with a hash of the Hello (client
    nonce, identity, resume position) and the signed Challenge (server nonce and identity).
    """
    transcript = hashlib.sha256()
    for part in (hello_payload, challenge_payload):
        transcript.update(struct.pack("!I", len(part)))
        transcript.update(part)
    okm = HKDF(
        algorithm=hashes.SHA256(),
        length=2 * (KEY_SIZE + IV_SIZE),
        salt=transcript.digest(),
        info=_INFO,
    ).derive(credential)
    k_cs, k_sc = okm[:KEY_SIZE], okm[KEY_SIZE : 2 * KEY_SIZE]
    iv_cs = okm[2 * KEY_SIZE : 2 * KEY_SIZE + IV_SIZE]
    iv_sc = okm[2 * KEY_SIZE + IV_SIZE :]
    return FrameSealer(k_cs, iv_cs), FrameSealer(k_sc, iv_sc)


class ConnectionKeys:
    """The sealing state of one connection: nothing until :meth:`start`, then every frame
    sent is sealed (:attr:`seal`) and every frame received must open (:meth:`open`)."""

    def __init__(self) -> None:
        self.tx: FrameSealer | None = None
        self.rx: FrameSealer | None = None

    def start(self, credential: bytes, hello: bytes, challenge: bytes, client: bool) -> None:
        c2s, s2c = session_keys(credential, hello, challenge)
        self.tx, self.rx = (c2s, s2c) if client else (s2c, c2s)

    @property
    def seal(self) -> Callable[[bytes, bytes], bytes] | None:
        return self.tx.seal if self.tx is not None else None

    def open(self, frame: Frame, name: str, unsealed_ok: bool = False) -> Frame:
        """The frame with its payload opened; RemoteProtocolError for a sealed frame before
        the keys, an unsealed one after them (unless ``unsealed_ok``), or one that fails."""
        if self.rx is None:
            if frame.flags & FLAG_SEALED:
                raise RemoteProtocolError(f"sealed {name} before the handshake agreed keys")
            return frame
        if not frame.flags & FLAG_SEALED:
            if unsealed_ok:
                return frame
            raise RemoteProtocolError(
                f"unsealed {name} after the handshake (injected, or frame sealing is off at "
                "the peer)"
            )
        payload = self.rx.open(frame.header(), frame.payload, name)
        return dataclasses.replace(frame, flags=frame.flags & ~FLAG_SEALED, payload=payload)
