"""The VIO's own keyframes (made of non-keyframe frames) are not uplinked to the cloud."""

from __future__ import annotations

import numpy as np

from common.calibration import CameraCalibration
from common.links import WireFormat
from common.links.edge_cloud import KeyframeUpdate, MapPointUpdate
from common.protocol.arrays import unpack_array
from common.vocabulary import Vocabulary
from services.edge.robot_session import EdgeSessionConfig, RobotSession
from services.edge.vio.types import KeyframeSnapshot, MapPointBatch, MapPointSnapshot, MapUpdate
from services.edge.worker import WorkResult

RAW = EdgeSessionConfig(wire=WireFormat.RAW)  # these tests pin the schema-1 uplink


def _kf(kid: int, prev: int | None, robot: bool) -> KeyframeSnapshot:
    return KeyframeSnapshot(
        keyframe_id=kid,
        map_id=0,
        timestamp_ns=1000 * (kid + 1),
        T_world_body=np.eye(4),
        v_world=np.zeros(3),
        bias_gyro=np.zeros(3),
        bias_accel=np.zeros(3),
        track_ids=np.arange(3),
        point_ids=np.full(3, -1),
        previous_keyframe_id=prev,
        robot_keyframe=robot,
    )


def test_own_keyframes_stay_on_the_edge() -> None:
    cam = CameraCalibration(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480)
    session = RobotSession("r", cam, Vocabulary.load(), RAW)
    kfs = (_kf(0, None, True), _kf(1, 0, False), _kf(2, 1, False), _kf(3, 2, True))
    point = MapPointSnapshot(7, 0, np.ones(3), np.array([0, 1, 3]), np.array([0, 1, 2]))
    upd = MapUpdate(0, False, kfs, MapPointBatch.of((point,)), ())
    out = session.on_result(WorkResult(0, None, None, (upd,)))
    sent = [m for m in out.cloud if isinstance(m, KeyframeUpdate)]
    assert [m.keyframe_id for m in sent] == [0, 3]
    assert sent[1].previous_keyframe_id == 0  # chained over the own keyframes 1 and 2
    (mpu,) = [m for m in out.cloud if isinstance(m, MapPointUpdate)]
    rows = unpack_array(mpu.observations, "<i8").reshape(-1, 3)
    assert rows[:, 1].tolist() == [0, 3]  # the observation in own keyframe 1 is not sent
    assert session.vio_keyframes == 2


def test_points_seen_only_by_own_keyframes_stay_and_only_new_rows_go() -> None:
    cam = CameraCalibration(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480)
    session = RobotSession("r", cam, Vocabulary.load(), RAW)
    kfs = (_kf(0, None, True), _kf(1, 0, False), _kf(2, 1, False))
    only_own = MapPointSnapshot(8, 0, np.ones(3), np.array([1, 2]), np.array([0, 1]))
    shared = MapPointSnapshot(9, 0, np.ones(3), np.array([0, 1]), np.array([2, 2]))
    out = session.on_result(
        WorkResult(
            0, None, None, (MapUpdate(0, False, kfs, MapPointBatch.of((only_own, shared)), ()),)
        )
    )
    (mpu,) = [m for m in out.cloud if isinstance(m, MapPointUpdate)]
    assert unpack_array(mpu.ids, "<i8").tolist() == [9]
    # Keyframe 3 (a robot keyframe) observes point 9 too: one new row, not the whole list.
    # A new observation in own keyframe 2 alone is no reason to resend.
    shared = MapPointSnapshot(9, 0, np.ones(3), np.array([0, 1, 3]), np.array([2, 2, 5]))
    only_own = MapPointSnapshot(8, 0, np.ones(3), np.array([1, 2]), np.array([0, 1]))
    upd = MapUpdate(0, False, (_kf(3, 2, True),), MapPointBatch.of((only_own, shared)), (8,))
    out = session.on_result(WorkResult(0, None, None, (upd,)))
    (mpu,) = [m for m in out.cloud if isinstance(m, MapPointUpdate)]
    assert unpack_array(mpu.ids, "<i8").tolist() == [9]
    assert unpack_array(mpu.observations, "<i8").reshape(-1, 3).tolist() == [[9, 3, 5]]
    # Point 8 was never sent: its removal needs no cull message.
    assert not any(type(m).__name__ == "CullEvent" for m in out.cloud)
