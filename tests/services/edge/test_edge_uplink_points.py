"""Map-point uplink of one robot session: which points go to the cloud, with which rows.

Hand-computed expectations over a sequence of map updates: first sight by a robot keyframe,
new robot-keyframe rows, rows in the VIO's own keyframes, moves below and above
``point_resend_m`` (1 cm), removals (cull only for points the cloud has), a removed id seen
again, two maps, and one point listed twice in an update.
"""

from __future__ import annotations

import numpy as np

from common.calibration import CameraCalibration
from common.links import WireFormat
from common.links.edge_cloud import CullEvent, MapPointUpdate
from common.protocol.arrays import unpack_array
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.edge.robot_session import EdgeSessionConfig, RobotSession
from services.edge.vio.types import KeyframeSnapshot, MapPointBatch, MapPointSnapshot, MapUpdate

RAW = EdgeSessionConfig(wire=WireFormat.RAW)  # these tests pin the schema-1 uplink

Sent = tuple[list[int], list[list[float]], list[list[int]]]


def _kf(map_id: int, kid: int, robot: bool) -> KeyframeSnapshot:
    return KeyframeSnapshot(
        keyframe_id=kid,
        map_id=map_id,
        timestamp_ns=1000 * (kid + 1),
        T_world_body=np.eye(4),
        v_world=np.zeros(3),
        bias_gyro=np.zeros(3),
        bias_accel=np.zeros(3),
        track_ids=np.arange(3),
        point_ids=np.full(3, -1),
        previous_keyframe_id=None,
        robot_keyframe=robot,
    )


def _pt(pid: int, x: float, obs: dict[int, int], map_id: int = 0) -> MapPointSnapshot:
    """Point ``pid`` at (x, 1, 2) m observed by ``obs`` {keyframe id: feature row}."""
    return MapPointSnapshot(
        pid,
        map_id,
        np.array([x, 1.0, 2.0]),
        np.array(list(obs), np.int64),
        np.array(list(obs.values()), np.int64),
    )


class _Uplink:
    """Feeds map updates to a session and splits what comes out for the cloud."""

    def __init__(self) -> None:
        cam = CameraCalibration(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480)
        self.session = RobotSession("r", cam, Vocabulary.load(), RAW)

    def __call__(
        self,
        points: tuple[MapPointSnapshot, ...],
        removed: tuple[int, ...] = (),
        kfs: tuple[KeyframeSnapshot, ...] = (),
        map_id: int = 0,
    ) -> tuple[Sent | None, list[int] | None]:
        msgs: list[Message] = self.session._uplink(
            MapUpdate(map_id, True, kfs, MapPointBatch.of(points), removed)
        )
        ups = [m for m in msgs if isinstance(m, MapPointUpdate)]
        culls = [m for m in msgs if isinstance(m, CullEvent)]
        assert len(ups) <= 1 and len(culls) <= 1
        sent = None
        if ups:
            (up,) = ups
            assert up.map_id == map_id and up.agent_id == "r"
            ids = unpack_array(up.ids, "<i8")
            p_world = unpack_array(up.p_world, "<f8").reshape(-1, 3)
            rows = unpack_array(up.observations, "<i8").reshape(-1, 3)
            sent = (ids.tolist(), p_world.tolist(), rows.tolist())
        cull = None
        if culls:
            assert culls[0].keyframe_ids == b""
            cull = unpack_array(culls[0].map_point_ids, "<i8").tolist()
        return sent, cull


def test_points_go_up_when_first_seen_reobserved_or_moved_and_culls_follow_them() -> None:
    up = _Uplink()
    # Keyframes 0, 1, 3 are the robot's; 2 is the VIO's own (never uplinked, nor its rows).
    kfs = (_kf(0, 0, True), _kf(0, 1, True), _kf(0, 2, False))
    sent, cull = up(
        (_pt(5, 0.0, {0: 4, 1: 7}), _pt(3, 0.5, {2: 1, 1: 2}), _pt(9, 0.9, {2: 3})), kfs=kfs
    )
    # In update order (not id order); point 9 is seen by the own keyframe only.
    assert sent == (
        [5, 3],
        [[0.0, 1.0, 2.0], [0.5, 1.0, 2.0]],
        [[5, 0, 4], [5, 1, 7], [3, 1, 2]],
    )
    assert cull is None

    # 4 mm and 9 mm: below 1 cm, same robot rows -> nothing. A new row in the own keyframe
    # 2 is no reason either.
    sent, _ = up((_pt(5, 0.004, {0: 4, 1: 7}), _pt(3, 0.509, {2: 1, 1: 2}), _pt(9, 0.9, {2: 5})))
    assert sent is None

    # Point 5: 12 mm from where it was last sent (the 4 mm step above was not sent) -> it
    # goes with no rows. Point 3 gains robot keyframe 3: only that row goes, at its new
    # place. Point 9 is first seen by a robot keyframe: its robot row only. New point 7.
    sent, _ = up(
        (
            _pt(5, 0.012, {0: 4, 1: 7}),
            _pt(3, 0.509, {2: 1, 1: 2, 3: 6}),
            _pt(9, 0.9, {2: 5, 3: 8}),
            _pt(7, 0.7, {3: 0}),
        ),
        kfs=(_kf(0, 3, True),),
    )
    assert sent == (
        [5, 3, 9, 7],
        [[0.012, 1.0, 2.0], [0.509, 1.0, 2.0], [0.9, 1.0, 2.0], [0.7, 1.0, 2.0]],
        [[3, 3, 6], [9, 3, 8], [7, 3, 0]],
    )

    # Point 3 at 0.518: 18 mm from its first position but 9 mm from the last one sent -> no.
    # Point 7 loses keyframe 3's row and gets it back at another feature row: the cloud has
    # that (point, keyframe) pair already -> no. Point 5 at 0.0215 (9.5 mm) -> no.
    sent, _ = up((_pt(3, 0.518, {1: 2, 3: 6}), _pt(7, 0.7, {}), _pt(5, 0.0215, {0: 4, 1: 7})))
    assert sent is None
    sent, _ = up((_pt(7, 0.7, {3: 9}),))
    assert sent is None

    # Removals: a cull lists the removed points the cloud has, in the given order, each once.
    sent, cull = up((), removed=(9, 42, 5, 9, 8))
    assert sent is None and cull == [9, 5]
    sent, cull = up((), removed=(5, 42))
    assert sent is None and cull is None

    # Point 5 again (a new point to the cloud: every robot row); a move of point 3 > 1 cm.
    sent, cull = up((_pt(5, 0.3, {1: 1, 3: 2}), _pt(3, 0.52, {1: 2, 3: 6})), removed=(3,))
    assert sent == ([5, 3], [[0.3, 1.0, 2.0], [0.52, 1.0, 2.0]], [[5, 1, 1], [5, 3, 2]])
    assert cull == [3]  # removed after it was sent in the same update
    sent, _ = up((_pt(3, 0.52, {1: 2, 3: 6}),))
    assert sent == ([3], [[0.52, 1.0, 2.0]], [[3, 1, 2], [3, 3, 6]])  # new to the cloud
    # The cloud's point 5 (since its removal) has no row of keyframe 0 yet.
    sent, _ = up((_pt(5, 0.3, {0: 4, 1: 1, 3: 2}),))
    assert sent == ([5], [[0.3, 1.0, 2.0]], [[5, 0, 4]])


def test_each_map_keeps_its_own_points_and_own_keyframes() -> None:
    up = _Uplink()
    up((_pt(5, 0.0, {0: 1}),), kfs=(_kf(0, 0, True), _kf(0, 1, False)))
    # Map 1: keyframe 1 is a robot keyframe there, and point 5 is new to map 1.
    sent, _ = up((_pt(5, 0.0, {0: 1, 1: 2}, map_id=1),), kfs=(_kf(1, 1, True),), map_id=1)
    assert sent == ([5], [[0.0, 1.0, 2.0]], [[5, 0, 1], [5, 1, 2]])
    sent, cull = up((_pt(5, 0.0, {0: 1, 1: 2}),), removed=(5,))
    assert sent is None and cull == [5]  # map 0's keyframe 1 is still the VIO's own
    sent, cull = up((_pt(5, 0.0, {0: 1, 1: 2}, map_id=1),), map_id=1)
    assert sent is None and cull is None  # map 1's point 5 survives map 0's cull


def test_a_point_listed_twice_in_one_update_is_taken_in_order() -> None:
    up = _Uplink()
    sent, _ = up((_pt(11, 0.0, {0: 1}), _pt(4, 0.0, {0: 2}), _pt(11, 0.005, {0: 1, 1: 3})))
    assert sent == (
        [11, 4, 11],
        [[0.0, 1.0, 2.0], [0.0, 1.0, 2.0], [0.005, 1.0, 2.0]],
        [[11, 0, 1], [4, 0, 2], [11, 1, 3]],
    )
    sent, _ = up((_pt(11, 0.012, {0: 1, 1: 3}),))  # 7 mm from the last sent, 12 from the first
    assert sent is None
