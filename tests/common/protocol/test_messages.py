"""Message registry, payload encoding and field type checks (blame split)."""

from __future__ import annotations

import dataclasses

import msgpack
import pytest

from common.protocol import Blob, LocalProtocolError, RemoteProtocolError
from common.protocol.framing import PROTOCOL_VERSION
from common.protocol.messages import (
    CONTROL_MAX_TYPE_ID,
    Close,
    Hello,
    _converter,
    decode_payload,
    encode_payload,
    message,
    message_class,
    registered_types,
)


def test_registry_ids_are_stable():
    types = registered_types()
    assert {t: c.__name__ for t, c in types.items() if t <= 0x0100} == {
        1: "Hello",
        2: "Challenge",
        3: "Auth",
        4: "Welcome",
        5: "Ack",
        6: "Heartbeat",
        7: "Close",
        8: "Reject",
        0x0100: "Blob",
    }
    assert all((t <= CONTROL_MAX_TYPE_ID) == c.CONTROL for t, c in types.items())
    assert message_class(0x0100) is Blob
    with pytest.raises(RemoteProtocolError, match="unknown message type 0x7777"):
        message_class(0x7777)


def test_type_ids_cannot_be_reused():
    with pytest.raises(ValueError, match="already used by"):

        @message(0x0100)
        class Impostor:
            x: int


def test_messages_are_frozen_and_bulk_data_is_msgpack_bin():
    blob = Blob(3, b"\x00\x01" * 10)
    with pytest.raises(dataclasses.FrozenInstanceError):
        blob.channel = 4  # type: ignore[misc]
    raw = encode_payload(blob)
    assert raw[2] == 0xC4  # bin 8, not an array of numbers
    assert msgpack.unpackb(raw) == [3, b"\x00\x01" * 10]
    assert decode_payload(Blob.TYPE_ID, raw) == blob


def test_wrong_field_types_blame_the_right_side():
    with pytest.raises(LocalProtocolError, match="Blob: data: expected bytes, got list"):
        encode_payload(Blob(1, [1, 2, 3]))  # type: ignore[arg-type]
    with pytest.raises(LocalProtocolError, match="channel: expected int"):
        encode_payload(Blob(True, b""))  # bool is not an int on the wire
    for bad in ([1, [1, 2]], ["1", b""], [1], [1, b"", 3], {"channel": 1}, [1.5, b""]):
        with pytest.raises(RemoteProtocolError):
            decode_payload(Blob.TYPE_ID, msgpack.packb(bad, use_bin_type=True))
    with pytest.raises(RemoteProtocolError, match="undecodable"):
        decode_payload(Blob.TYPE_ID, b"\xc1")
    with pytest.raises(RemoteProtocolError, match="undecodable"):
        decode_payload(Blob.TYPE_ID, msgpack.packb([1, b""]) + b"\x00")  # trailing bytes
    with pytest.raises(RemoteProtocolError, match="ext type"):
        decode_payload(Blob.TYPE_ID, msgpack.packb([1, msgpack.ExtType(1, b"x")]))


def test_control_messages_round_trip():
    hello = Hello(
        PROTOCOL_VERSION, 1, "robot", "r-1", b"n" * 32, b"s" * 16, 5, b"", 0, 1024, 1 << 20
    )
    for msg in (hello, Close(2, "bye")):
        assert decode_payload(msg.TYPE_ID, encode_payload(msg)) == msg


@dataclasses.dataclass(frozen=True)
class _Pose:
    t_ns: int
    q_wxyz: tuple[float, float, float, float]


@pytest.mark.parametrize(
    ("annotation", "value", "wire"),
    [
        (tuple[float, ...], (1.0, 2.5), [1.0, 2.5]),
        (tuple[int, str], (1, "a"), [1, "a"]),
        (dict[str, int], {"a": 1}, {"a": 1}),
        (bytes | None, None, None),
        (_Pose, _Pose(5, (1.0, 0.0, 0.0, 0.0)), [5, [1.0, 0.0, 0.0, 0.0]]),
        (tuple[_Pose, ...], (_Pose(1, (1.0, 0.0, 0.0, 0.0)),), [[1, [1.0, 0.0, 0.0, 0.0]]]),
    ],
)
def test_structured_field_annotations(annotation, value, wire):
    enc, dec = _converter(annotation, encode=True), _converter(annotation, encode=False)
    assert enc(value, "f") == wire
    assert dec(msgpack.unpackb(msgpack.packb(wire)), "f") == value


def test_structured_fields_reject_wrong_shapes():
    dec = _converter(tuple[float, float], encode=False)
    with pytest.raises(Exception, match="expected array of 2"):
        dec([1.0], "f")
    with pytest.raises(Exception, match="map keys must be str"):
        _converter(dict[str, int], encode=False)({1: 1}, "f")
    with pytest.raises(TypeError, match="unsupported field annotation"):
        _converter(list[int], encode=True)
