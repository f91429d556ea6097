"""Frame layout, limits and the decoder's blame and memory guarantees."""

from __future__ import annotations

import struct
import zlib

import pytest

from common.protocol import LocalProtocolError, RemoteProtocolError
from common.protocol.framing import (
    FLAG_RETRANSMIT,
    HEADER_SIZE,
    MAGIC,
    PROTOCOL_VERSION,
    FrameDecoder,
    encode_frame,
)


def test_header_layout_is_the_documented_one():
    frame = encode_frame(0x0102, b"hello", seq=7, ack=5, flags=FLAG_RETRANSMIT)
    assert HEADER_SIZE == 22 and len(frame) == 27
    magic, version, flags, type_id, seq, ack, length, crc = struct.unpack("!2sBBHIIII", frame[:22])
    assert (magic, version, flags, type_id, seq, ack, length) == (
        MAGIC,
        PROTOCOL_VERSION,
        1,
        0x0102,
        7,
        5,
        5,
    )
    assert crc == zlib.crc32(frame[:18] + b"hello")


def test_round_trip_byte_by_byte():
    frames = [encode_frame(i + 1, bytes([i]) * i, seq=i, ack=i // 2) for i in range(20)]
    dec = FrameDecoder()
    out = []
    for byte in b"".join(frames):
        dec.receive_data(bytes([byte]))
        while (f := dec.next_frame()) is not None:
            out.append(f)
    assert [(f.type_id, f.payload, f.seq, f.ack) for f in out] == [
        (i + 1, bytes([i]) * i, i, i // 2) for i in range(20)
    ]
    assert out[3].size == HEADER_SIZE + 3 and dec.buffered == 0


def test_oversized_frame_refused_before_its_payload_arrives():
    dec = FrameDecoder(max_frame_size=1000)
    header = encode_frame(1, b"x" * 2000, max_frame_size=10_000)[:HEADER_SIZE]
    with pytest.raises(RemoteProtocolError, match="exceeds max_frame_size 1000"):
        dec.receive_data(header)
    assert dec.buffered == 0
    with pytest.raises(RemoteProtocolError):  # poisoned: the stream cannot be trusted
        dec.receive_data(encode_frame(1, b""))


def test_local_limits_raise_local_errors():
    with pytest.raises(LocalProtocolError, match="max_frame_size"):
        encode_frame(1, b"x" * 100, max_frame_size=100)
    with pytest.raises(LocalProtocolError):
        encode_frame(1, b"", seq=2**32)
    with pytest.raises(LocalProtocolError):
        encode_frame(1, b"", flags=0x80)
    with pytest.raises(LocalProtocolError):
        FrameDecoder(max_frame_size=HEADER_SIZE)


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda f: b"XX" + f[2:], "bad magic"),
        (lambda f: f[:2] + b"\x09" + f[3:], "protocol version 9"),
        (lambda f: f[:3] + b"\x40" + f[4:], "unknown flag"),
        (lambda f: f[:-1] + bytes([f[-1] ^ 1]), "CRC mismatch"),
        (lambda f: f[:10] + b"\0\0\0\x09" + f[14:], "CRC mismatch"),  # ack changed
    ],
)
def test_corruption_is_the_remote_peers_fault(mutate, match):
    dec = FrameDecoder()
    with pytest.raises(RemoteProtocolError, match=match):
        dec.receive_data(mutate(encode_frame(5, b"payload", seq=1)))
        dec.next_frame()


def test_buffer_holds_at_most_one_incomplete_frame():
    dec = FrameDecoder(max_frame_size=500)
    stream = b"".join(encode_frame(1, b"y" * 400) for _ in range(50))
    for i in range(0, len(stream), 333):
        dec.receive_data(stream[i : i + 333])
        while dec.next_frame() is not None:
            pass
        assert dec.buffered < 500
