"""Frame encoder and incremental decoder (sans-I/O: bytes in, frames out).

Wire layout of one frame (network byte order, ``HEADER_SIZE`` = 22 bytes)::

    offset size field
    0      2    magic        b"RS"
    2      1    version      PROTOCOL_VERSION
    3      1    flags        bit 0 = retransmission, bit 1 = sealed; other bits must be 0
    4      2    type_id      message type (see ``messages.py``)
    6      4    seq          sequence number of an application message, 0 for control frames
    10     4    ack          cumulative ack: highest sequence the sender's application delivered
    14     4    length       payload length in bytes
    18     4    crc32        CRC-32 of bytes 0..17 followed by the payload
    22     ...  payload      msgpack (see ``messages.py``); sealed: ciphertext + 16-byte tag

After the handshake every frame is sealed (``sealing.py``): its payload is encrypted and
authenticated together with bytes 0..17 of the header, which stay readable.

The decoder validates a header as soon as its 22 bytes have arrived, so a frame whose
declared length exceeds ``max_frame_size`` is refused before any of its payload is buffered.
After the caller has drained every complete frame, the decoder holds less than
``max_frame_size`` bytes.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass

from common.protocol.errors import LocalProtocolError, RemoteProtocolError

MAGIC = b"RS"
PROTOCOL_VERSION = 2
"""2: frames sealed after the handshake, per-identity credentials, ``Reject``."""
FLAG_RETRANSMIT = 0x01
FLAG_SEALED = 0x02
KNOWN_FLAGS = FLAG_RETRANSMIT | FLAG_SEALED
MAX_SEQ = 0xFFFF_FFFF
_PREFIX = struct.Struct("!2sBBHIII")  # everything but the CRC
_CRC = struct.Struct("!I")
HEADER_SIZE = _PREFIX.size + _CRC.size
DEFAULT_MAX_FRAME_SIZE = 8 * 1024 * 1024


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded frame. ``size`` counts header and payload (bytes on the wire)."""

    type_id: int
    flags: int
    seq: int
    ack: int
    payload: bytes

    @property
    def size(self) -> int:
        return HEADER_SIZE + len(self.payload)

    def header(self) -> bytes:
        """Header bytes 0..17 as sent (the associated data of a sealed frame)."""
        return _PREFIX.pack(
            MAGIC, PROTOCOL_VERSION, self.flags, self.type_id, self.seq, self.ack, len(self.payload)
        )


def encode_frame(
    type_id: int,
    payload: bytes,
    *,
    seq: int = 0,
    ack: int = 0,
    flags: int = 0,
    max_frame_size: int = DEFAULT_MAX_FRAME_SIZE,
    seal: Callable[[bytes, bytes], bytes] | None = None,
    seal_overhead: int = 0,
) -> bytes:
    """Return header + payload for one frame.

    ``seal(header, payload) -> sealed`` (see ``sealing.py``) encrypts the payload; the
    frame then carries ``FLAG_SEALED`` and ``len(payload) + seal_overhead`` payload bytes.

    Raises :class:`LocalProtocolError` if a field is out of range or the frame would exceed
    ``max_frame_size`` bytes (header included).
    """
    if not 0 <= type_id <= 0xFFFF:
        raise LocalProtocolError(f"type_id {type_id} out of range 0..65535")
    if not 0 <= seq <= MAX_SEQ or not 0 <= ack <= MAX_SEQ:
        raise LocalProtocolError(f"seq {seq} or ack {ack} out of range 0..{MAX_SEQ}")
    if flags & ~KNOWN_FLAGS:
        raise LocalProtocolError(f"unknown flag bits 0x{flags:02x}")
    length = len(payload) + (seal_overhead if seal is not None else 0)
    if HEADER_SIZE + length > max_frame_size:
        raise LocalProtocolError(
            f"frame of {HEADER_SIZE + length} bytes exceeds max_frame_size {max_frame_size}"
        )
    if seal is not None:
        flags |= FLAG_SEALED
    prefix = _PREFIX.pack(MAGIC, PROTOCOL_VERSION, flags, type_id, seq, ack, length)
    if seal is not None:
        payload = seal(prefix, payload)
        if len(payload) != length:
            raise LocalProtocolError(f"seal() added {len(payload) - length + seal_overhead} B")
    crc = zlib.crc32(payload, zlib.crc32(prefix))
    return prefix + _CRC.pack(crc) + payload


class FrameDecoder:
    """Incremental decoder: feed bytes with :meth:`receive_data`, pull :meth:`next_frame`.

    Every malformation raises :class:`RemoteProtocolError` (and only that); after an error
    the decoder is poisoned and keeps raising, because the stream can no longer be trusted.

    Args:
        max_frame_size: largest accepted frame in bytes, header included.
    """

    def __init__(self, max_frame_size: int = DEFAULT_MAX_FRAME_SIZE) -> None:
        if max_frame_size <= HEADER_SIZE:
            raise LocalProtocolError(f"max_frame_size must exceed the {HEADER_SIZE}-byte header")
        self.max_frame_size = max_frame_size
        self._buffer = bytearray()
        self._pos = 0  # start of the undrained bytes in _buffer (compacted on receive)
        self._header: tuple[int, int, int, int, int, int] | None = None
        self._error: RemoteProtocolError | None = None

    @property
    def buffered(self) -> int:
        """Bytes held by the decoder (incomplete frame plus undrained data)."""
        return len(self._buffer) - self._pos

    def receive_data(self, data: bytes) -> None:
        """Append bytes from the stream; validates a pending header immediately."""
        if self._error is not None:
            raise self._error
        if self._pos:
            del self._buffer[: self._pos]
            self._pos = 0
        self._buffer += data
        if self._header is None and len(self._buffer) >= HEADER_SIZE:
            self._parse_header()

    def next_frame(self) -> Frame | None:
        """Return the next complete frame, or None if more bytes are needed."""
        if self._error is not None:
            raise self._error
        if self._header is None:
            if len(self._buffer) - self._pos < HEADER_SIZE:
                return None
            self._parse_header()
        assert self._header is not None
        flags, type_id, seq, ack, length, crc = self._header
        start = self._pos
        end = start + HEADER_SIZE + length
        if len(self._buffer) < end:
            return None
        view = memoryview(self._buffer)
        try:
            prefix = bytes(view[start : start + _PREFIX.size])
            payload = bytes(view[start + HEADER_SIZE : end])
        finally:
            view.release()
        self._pos = end
        if self._pos == len(self._buffer):
            self._buffer.clear()
            self._pos = 0
        self._header = None
        if zlib.crc32(payload, zlib.crc32(prefix)) != crc:
            self._fail(f"CRC mismatch on frame type 0x{type_id:04x} seq {seq}")
        return Frame(type_id=type_id, flags=flags, seq=seq, ack=ack, payload=payload)

    def _parse_header(self) -> None:
        magic, version, flags, type_id, seq, ack, length = _PREFIX.unpack_from(
            self._buffer, self._pos
        )
        (crc,) = _CRC.unpack_from(self._buffer, self._pos + _PREFIX.size)
        if magic != MAGIC:
            self._fail(f"bad magic {magic!r} (expected {MAGIC!r})")
        if version != PROTOCOL_VERSION:
            self._fail(f"unsupported protocol version {version} (speaking {PROTOCOL_VERSION})")
        if flags & ~KNOWN_FLAGS:
            self._fail(f"unknown flag bits 0x{flags:02x}")
        if HEADER_SIZE + length > self.max_frame_size:
            self._fail(
                f"declared frame size {HEADER_SIZE + length} exceeds max_frame_size "
                f"{self.max_frame_size}"
            )
        self._header = (flags, type_id, seq, ack, length, crc)

    def _fail(self, reason: str) -> None:
        self._error = RemoteProtocolError(reason)
        self._buffer.clear()
        self._pos = 0
        self._header = None
        raise self._error
