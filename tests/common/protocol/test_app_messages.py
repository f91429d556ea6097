"""Application messages round-trip through the codec of the wire, arrays included."""

import numpy as np
import pytest

from common.links.edge_cloud import KeyframeUpdate, PoseCorrection
from common.links.robot_edge import InertialFeedback
from common.protocol.arrays import pack_array, unpack_array
from common.protocol.errors import RemoteProtocolError
from common.protocol.messages import decode_payload, encode_payload


def test_array_round_trip_and_size_check() -> None:
    a = np.arange(12, dtype=np.float64).reshape(4, 3)
    b = unpack_array(pack_array(a, "<f8"), "<f8", (3,))
    np.testing.assert_array_equal(a, b)
    with pytest.raises(RemoteProtocolError, match="whole number"):
        unpack_array(b"\x00" * 23, "<f8", (3,), field="p_world")


def test_keyframe_update_round_trip() -> None:
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    msg = KeyframeUpdate(
        agent_id="robot0",
        map_id=0,
        keyframe_id=7,
        previous_keyframe_id=6,
        timestamp_ns=123,
        T_world_body=pack_array(T, "<f8"),
        velocity_world=pack_array(np.zeros(3), "<f8"),
        bias_gyro=pack_array(np.zeros(3), "<f8"),
        bias_accel=pack_array(np.zeros(3), "<f8"),
        features=b"\xf5\x01",
        map_point_ids=pack_array(np.array([-1, 4]), "<i8"),
        imu=pack_array(np.zeros((2, 7)), "<f8"),
    )
    out = decode_payload(KeyframeUpdate.TYPE_ID, encode_payload(msg))
    assert out == msg
    np.testing.assert_array_equal(unpack_array(out.T_world_body, "<f8", (4, 4))[0], T)


def test_wrong_field_type_from_peer_is_remote_error() -> None:
    good = PoseCorrection("a", 0, b"", b"")
    payload = encode_payload(good)
    assert decode_payload(PoseCorrection.TYPE_ID, payload) == good
    bad = InertialFeedback(1, 0, b"", b"", b"", b"", b"", b"", b"")
    with pytest.raises(RemoteProtocolError):
        decode_payload(PoseCorrection.TYPE_ID, encode_payload(bad))
