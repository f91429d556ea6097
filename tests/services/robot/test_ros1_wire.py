"""The ROS bridge's socket framing (stdlib, both ends): round trips, split reads, refusals."""

from __future__ import annotations

import numpy as np
import pytest

from common.geometry import make_T, so3_exp
from services.robot.poses import ReceivedPose
from services.robot.ros1 import wire
from services.robot.ros1.source import (
    placement_frame,
    placement_moved,
    placement_of,
    pose_frame,
)


def test_frames_round_trip_through_any_split_of_the_stream() -> None:
    data = (
        wire.imu(5, (0.1, 0.2, 0.3), (1.0, 2.0, 9.81))
        + wire.image(7, 2, 3, 4, "bgr8", bytes(range(8)))
        + wire.odom(9)
        + wire.frame(wire.READY, b"")
    )
    for cut in (1, 3, 17, len(data)):
        reader, out = wire.FrameReader(), []
        for i in range(0, len(data), cut):
            reader.feed(data[i : i + cut])
            out += list(reader.frames())
        assert [k for k, _ in out] == [wire.IMU, wire.IMAGE, wire.ODOM, wire.READY]
        assert wire.read_imu(out[0][1]) == (5, (0.1, 0.2, 0.3), (1.0, 2.0, 9.81))
        assert wire.read_image(out[1][1]) == (7, 2, 3, 4, "bgr8", bytes(range(8)))
        assert wire.read_odom(out[2][1]) == 9


def test_a_pose_frame_carries_position_and_unit_quaternion_and_no_pose_sends_nothing() -> None:
    T = make_T(so3_exp(np.array([0.0, 0.0, np.pi / 2])), np.array([1.0, 2.0, 3.0]))
    data = pose_frame(ReceivedPose(11, 2, "tracking", T, 0.1))
    assert data is not None
    ((kind, payload),) = list(_read(data))
    t, map_id, status, p, q = wire.read_pose(payload)
    assert (kind, t, map_id, status) == (wire.POSE, 11, 2, "tracking")
    assert p == pytest.approx((1.0, 2.0, 3.0))
    assert q == pytest.approx((0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)))  # x y z w, yaw 90°
    assert pose_frame(ReceivedPose(12, 2, "initializing", None, 0.1)) is None


def test_a_placed_pose_gives_the_global_to_map_transform_once_until_it_moves() -> None:
    T_map_body = make_T(so3_exp(np.array([0.1, 0.0, 0.5])), np.array([1.0, -2.0, 0.5]))
    T_global_map = make_T(so3_exp(np.array([0.0, 0.0, np.pi / 2])), np.array([4.0, 0.0, 0.0]))
    pose = ReceivedPose(11, 3, "tracking", T_map_body, 0.1, 0, T_global_map @ T_map_body)
    where = placement_of(pose)
    assert where is not None and where[:2] == (0, 3)
    np.testing.assert_allclose(where[2], T_global_map, atol=1e-12)
    ((kind, payload),) = list(_read(placement_frame(*where)))
    global_map, map_id, p, q = wire.read_placement(payload)
    assert (kind, global_map, map_id) == (wire.PLACEMENT, 0, 3)
    assert p == pytest.approx((4.0, 0.0, 0.0))
    assert q == pytest.approx((0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)))
    assert placement_of(ReceivedPose(12, 3, "tracking", T_map_body, 0.1)) is None  # not placed
    # Sent again only for another map, another global map, or a move beyond 1e-4.
    assert placement_moved(None, where)
    assert not placement_moved(where, (0, 3, T_global_map + 1e-6))
    assert placement_moved(where, (0, 3, T_global_map + 1e-3))
    assert placement_moved(where, (1, 3, T_global_map))


def test_a_stream_that_is_not_the_bridges_is_refused() -> None:
    reader = wire.FrameReader()
    reader.feed(b"GET / HTTP/1.1\r\n")
    with pytest.raises(wire.WireError, match="not a bridge frame"):
        list(reader.frames())


def _read(data: bytes):
    reader = wire.FrameReader()
    reader.feed(data)
    return reader.frames()
