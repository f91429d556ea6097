"""Numpy arrays inside messages: raw little-endian bytes with a dtype and row shape.

Bulk numbers travel as msgpack ``bin`` (``bytes`` fields), never as lists. The dtype and the
trailing shape are part of each message's documented schema, not of the payload, so a field
costs only its data. Decoding checks the size and raises :class:`RemoteProtocolError` when a
peer sent a field that does not fit.
"""

from __future__ import annotations

import numpy as np

from common.protocol.errors import RemoteProtocolError


def pack_array(a: np.ndarray, dtype: str) -> bytes:
    """C-order bytes of ``a`` converted to ``dtype`` (e.g. ``"<f8"``, ``"<i8"``, ``"u1"``)."""
    return np.ascontiguousarray(a, dtype=np.dtype(dtype)).tobytes()


def unpack_array(
    data: bytes, dtype: str, row_shape: tuple[int, ...] = (), field: str = "array"
) -> np.ndarray:
    """Inverse of :func:`pack_array`: a read-only array of shape ``(N, *row_shape)``.

    Raises RemoteProtocolError if ``len(data)`` is not a whole number of rows.
    """
    dt = np.dtype(dtype)
    row = dt.itemsize * int(np.prod(row_shape, dtype=np.int64))
    if row == 0 or len(data) % row:
        raise RemoteProtocolError(
            f"{field}: {len(data)} bytes is not a whole number of {dtype}{list(row_shape)} rows"
        )
    out = np.frombuffer(data, dtype=dt).reshape((-1, *row_shape))
    return out.astype(dt.newbyteorder("="), copy=False)
