"""The framing every coded link payload shares: a version byte, a range-coded body, a CRC-32.

Layout: ``u8 version | body (whole 32-bit words of the range coder) | u32 CRC-32`` (little
endian) over version and body. The protocol frame has a CRC of its own; this one makes a
payload that was damaged before it was framed (or forged with the frame CRC fixed) fail loudly
instead of decoding into wrong numbers, since a range decoder accepts almost any bytes.

Every decoding failure of a coded payload is a :class:`LinkDecodeError`, a
:class:`~common.protocol.errors.RemoteProtocolError`: the peer sent it, so the connection to
that peer is the one at fault.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from common.codec.entropy import N_SCALES, BitReader, BitWriter, best_scale_index
from common.codec.errors import CodecError
from common.protocol.errors import RemoteProtocolError

_CRC = struct.Struct("<I")


class LinkDecodeError(RemoteProtocolError):
    """A coded link payload that does not decode (truncated, corrupt, inconsistent)."""


def seal(version: int, w: BitWriter) -> bytes:
    """``version`` byte + the writer's body + CRC-32."""
    payload = bytes([version]) + w.finish()
    return payload + _CRC.pack(zlib.crc32(payload))


def open_sealed(data: bytes, version: int | tuple[int, ...], what: str) -> BitReader:
    """The reader of a :func:`seal`-ed payload; LinkDecodeError naming ``what`` if it is
    short, damaged or of another version (``version``: the one, or the ones, accepted; the
    payload's is ``data[0]``)."""
    if len(data) < 5:
        raise LinkDecodeError(f"{what}: coded payload of {len(data)} bytes is too short")
    (crc,) = _CRC.unpack(data[-4:])
    if zlib.crc32(data[:-4]) != crc:
        raise LinkDecodeError(f"{what}: coded payload checksum mismatch (corrupt or truncated)")
    accepted = (version,) if isinstance(version, int) else version
    if data[0] not in accepted:
        expected = " or ".join(str(v) for v in accepted)
        raise LinkDecodeError(f"{what}: coded payload version {data[0]}, expected {expected}")
    try:
        return BitReader(data[1:-4])
    except CodecError as exc:
        raise LinkDecodeError(f"{what}: {exc}") from exc


def put_scaled_signed(w: BitWriter, values: np.ndarray, part: str) -> None:
    """Integers (N,) with a Laplace model whose scale is chosen for them and sent first."""
    v = np.asarray(values, np.int64).ravel()
    s = best_scale_index(v, signed=True) if v.size else 0
    w.put_uniform(np.array([s]), N_SCALES, part)
    w.put_signed(v, s, part, escape_bits=64)


def get_scaled_signed(r: BitReader, n: int) -> np.ndarray:
    """Inverse of :func:`put_scaled_signed` for ``n`` values."""
    s = int(r.get_uniform(1, N_SCALES)[0])
    return r.get_signed(n, s, escape_bits=64)


def put_scaled_geometric(w: BitWriter, values: np.ndarray, part: str) -> None:
    """Non-negative integers (N,) (< 2**32) with a geometric model of a chosen scale."""
    v = np.asarray(values, np.int64).ravel()
    s = best_scale_index(v, signed=False) if v.size else 0
    w.put_uniform(np.array([s]), N_SCALES, part)
    w.put_geometric(v, s, part)


def get_scaled_geometric(r: BitReader, n: int) -> np.ndarray:
    """Inverse of :func:`put_scaled_geometric` for ``n`` values."""
    s = int(r.get_uniform(1, N_SCALES)[0])
    return r.get_geometric(n, s)
