"""Property-based hostility tests: random and mutated byte streams never raise anything but
the protocol's own RemoteProtocolError, never hang, and never grow the decoder's buffer
beyond one frame. Example counts add up to > 10,000 per run."""

from __future__ import annotations

import itertools

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.protocol import Blob, RemoteProtocolError, Session, SessionConfig
from common.protocol.framing import HEADER_SIZE, PROTOCOL_VERSION, FrameDecoder, encode_frame
from common.protocol.messages import (
    Close,
    Hello,
    Message,
    decode_payload,
    encode_payload,
    registered_types,
)

MAX_FRAME = 2048


def fuzz(examples: int) -> settings:
    return settings(
        max_examples=examples, deadline=None, suppress_health_check=[HealthCheck.too_slow]
    )


TYPE_IDS = sorted(registered_types())
SECRET = b"fuzz-secret-0123456789"


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in itertools.pairwise(points)]


def drain(decoder: FrameDecoder, chunks: list[bytes]) -> list:
    """Feed chunks, pull frames; returns frames or stops at the protocol's error."""
    frames = []
    try:
        for chunk in chunks:
            decoder.receive_data(chunk)
            for _ in range(len(chunk) // HEADER_SIZE + 2):  # bounded: no hang possible
                frame = decoder.next_frame()
                if frame is None:
                    break
                frames.append(frame)
            else:
                raise AssertionError("decoder produced more frames than bytes allow")
            assert decoder.buffered < MAX_FRAME + 1  # memory stays bounded
    except RemoteProtocolError:
        pass
    return frames


@pytest.mark.slow
@fuzz(3000)
@given(st.binary(max_size=6000), st.lists(st.integers(0, 10_000), max_size=8))
def test_random_bytes_only_raise_remote_protocol_error(data, cuts):
    drain(FrameDecoder(MAX_FRAME), chunked(data, cuts))


def _valid_frames(draw_payloads: list[tuple[int, bytes, int, int]]) -> bytes:
    return b"".join(
        encode_frame(t, p, seq=s, ack=a, max_frame_size=MAX_FRAME) for t, p, s, a in draw_payloads
    )


frame_specs = st.lists(
    st.tuples(
        st.sampled_from(TYPE_IDS),
        st.binary(max_size=300),
        st.integers(0, 2**32 - 1),
        st.integers(0, 2**32 - 1),
    ),
    min_size=1,
    max_size=6,
)
mutations = st.lists(
    st.tuples(
        st.sampled_from(["flip", "insert", "delete", "truncate"]),
        st.integers(0, 10**6),
        st.integers(0, 255),
    ),
    min_size=1,
    max_size=4,
)


def mutate(data: bytes, ops: list[tuple[str, int, int]]) -> bytes:
    buf = bytearray(data)
    for op, pos, val in ops:
        if not buf:
            break
        i = pos % len(buf)
        if op == "flip":
            buf[i] ^= 1 << (val % 8)
        elif op == "insert":
            buf[i:i] = bytes([val])
        elif op == "delete":
            del buf[i]
        else:
            del buf[i:]
    return bytes(buf)


@pytest.mark.slow
@fuzz(3000)
@given(frame_specs, mutations, st.lists(st.integers(0, 10_000), max_size=6))
def test_mutated_valid_streams(specs, ops, cuts):
    clean = _valid_frames(specs)
    dirty = mutate(clean, ops)
    frames = drain(FrameDecoder(MAX_FRAME), chunked(dirty, cuts))
    # whatever decodes passed the CRC: an unmodified prefix of what was encoded
    assert [(f.type_id, f.payload, f.seq, f.ack) for f in frames] == specs[: len(frames)]
    if not clean.startswith(dirty) and not dirty.startswith(clean):
        assert len(frames) < len(specs)  # the damaged frame itself never comes out


@fuzz(1500)
@given(frame_specs)
def test_valid_streams_decode_exactly(specs):
    frames = drain(FrameDecoder(MAX_FRAME), [_valid_frames(specs)])
    assert [(f.type_id, f.payload, f.seq, f.ack) for f in frames] == specs


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.binary(max_size=40),
    lambda inner: (
        st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=5), inner, max_size=4)
    ),
    max_leaves=20,
)


@pytest.mark.slow
@fuzz(2000)
@given(st.sampled_from(TYPE_IDS), msgpack_values | st.binary(max_size=60))
def test_payload_decoder_rejects_wrong_shapes_with_remote_error(type_id, value):
    payload = value if isinstance(value, bytes) else msgpack.packb(value, use_bin_type=True)
    try:
        msg = decode_payload(type_id, payload)
    except RemoteProtocolError:
        return
    assert isinstance(msg, Message)
    assert decode_payload(type_id, encode_payload(msg)) == msg  # what passes is well-typed


@pytest.mark.slow
@fuzz(1500)
@given(
    st.lists(
        st.tuples(
            st.sampled_from([*TYPE_IDS, 0x0999]),
            st.binary(max_size=200),
            st.integers(0, 20),
            st.integers(0, 20),
        ),
        max_size=5,
    ),
    st.booleans(),
)
def test_session_survives_hostile_frames(specs, established):
    """A server session (fresh, or established with a real client) fed well-framed garbage
    only ever raises RemoteProtocolError."""
    server = Session(SessionConfig("edge", "e", SECRET), client=False, now=0.0)
    if established:
        client_cfg = SessionConfig("robot", "r", SECRET)
        client = Session(client_cfg, client=True, now=0.0, link=client_cfg.new_link())
        server.receive_data(b"".join(client.data_to_send(0.0)), 0.0)
        client.receive_data(b"".join(server.data_to_send(0.0)), 0.0)
        server.receive_data(b"".join(client.data_to_send(0.0)), 0.0)
        server.next_event()
        server.attach(client_cfg.new_link(), 0.0)
    stream = b"".join(encode_frame(t, p, seq=s, ack=a) for t, p, s, a in specs)
    try:
        server.receive_data(stream, 0.0)
        server.handle_timer(1.0)
    except RemoteProtocolError:
        assert server.closed
    while server.next_event() is not None:
        pass


@fuzz(500)
@given(
    st.integers(0, 2**63 - 1),
    st.binary(max_size=500),
    st.text(min_size=1, max_size=64),
    st.text(max_size=300),
)
def test_message_round_trip(channel, data, name, reason):
    for msg in (
        Blob(channel, data),
        Close(channel, reason),
        Hello(
            PROTOCOL_VERSION, 1, name, name, data, data, channel, data, channel, channel, channel
        ),
    ):
        assert decode_payload(msg.TYPE_ID, encode_payload(msg)) == msg
