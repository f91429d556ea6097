"""The edge's feedback sender: policy, landmark deltas, resets (services.edge.feedback)."""

from __future__ import annotations

import numpy as np

from common.calibration import CameraCalibration
from common.links import CodecTimer, WireFormat
from common.links.robot_edge import (
    Anchors,
    InertialFeedback,
    InertialFeedbackCoded,
    decode_feedback,
)
from common.protocol.arrays import pack_array
from services.edge.feedback import FeedbackPolicy, FeedbackSender
from services.edge.robot_session import FeedbackPolicy as ReExported
from services.edge.vio.types import VioState

CAM = CameraCalibration(640, 480, 400.0, 400.0, 320.0, 240.0)  # camera = body, looking +z
BODY = np.array([1.0, 2.0, 0.5])


def seen(ids: np.ndarray, p: np.ndarray) -> Anchors:
    """The frame's tracks as the robot coded them: ``p`` (N, 3) projected from the body."""
    d = p - BODY
    return Anchors(np.asarray(ids), 400.0 * d[:, :2] / d[:, 2:] + [320.0, 240.0])


def state(t: int, map_id: int = 0, v: float = 0.0) -> VioState:
    T = np.eye(4)
    T[:3, 3] = BODY
    return VioState(
        t, map_id, T, np.array([v, 0.0, 0.0]), np.zeros(3), np.zeros(3), np.array([0, 0, -9.81])
    )


class RobotView:
    """The robot's landmark set as the decoded messages describe it (numbers -> point)."""

    def __init__(self) -> None:
        self.points: dict[int, np.ndarray] = {}

    def apply(self, msg, anchors: Anchors, tracked: np.ndarray) -> None:
        """Apply ``msg`` (about the frame of ``anchors``); then drop tracks not in ``tracked``
        (the robot's active tracks)."""
        c = decode_feedback(msg, CAM, anchors)
        if c.reset:
            self.points = {}
        self.points.update(zip(c.track_numbers.tolist(), c.p_world, strict=True))
        for n in c.forget.tolist():
            self.points.pop(n)
        self.points = {n: q for n, q in self.points.items() if n in set(tracked.tolist())}


def test_policy_is_re_exported_for_existing_imports() -> None:
    assert ReExported is FeedbackPolicy


def test_coded_sender_sends_only_deltas_and_resets_when_needed() -> None:
    timer = CodecTimer()
    tx = FeedbackSender(FeedbackPolicy(every_frames=1), WireFormat.CODED, timer, CAM)
    robot = RobotView()
    ids = np.array([12, 10, 11, 30])  # any order in
    p = BODY + np.array([[0.2, 0.1, 1.0], [-0.2, 0.1, 0.8], [0.1, -0.2, 1.2], [0.3, 0.3, 0.9]])
    tracked = np.arange(100)

    def step(frame: int, ids, p, *, map_id: int = 0, tracked=tracked) -> InertialFeedbackCoded:
        frame_seen = seen(ids, p)
        msg = tx.on_state(frame, state(frame, map_id), ids, p, tracked, frame_seen)
        assert isinstance(msg, InertialFeedbackCoded)
        robot.apply(msg, frame_seen, tracked)
        numbers, held = tx.held
        assert sorted(robot.points) == numbers.tolist()  # the sender knows what the robot has
        assert np.array_equal(np.array([robot.points[n] for n in numbers]).reshape(-1, 3), held)
        return msg

    first = decode_feedback(step(0, ids, p))
    assert first.reset and first.track_numbers.tolist() == [10, 11, 12, 30]
    # nothing changed: a state-only message, no landmark bytes at all
    assert step(1, ids, p).landmarks == b""
    # BA nudges of 1 cm are not worth sending; 3 cm are; a new track is
    nudged = p + np.array([[0.01, 0, 0], [0, 0.03, 0], [0, 0, 0], [0, 0, 0]])
    new = BODY + np.array([[0.0, -0.1, 1.1]])
    c = decode_feedback(step(2, np.append(ids, 40), np.vstack([nudged, new])))
    assert not c.reset and c.track_numbers.tolist() == [10, 40] and len(c.forget) == 0
    # track 12 drifts 1.5 cm per frame: sent when 2 cm from what the robot holds, not before
    sent = []
    for k in range(3):
        drift = p.copy()
        drift[1] = nudged[1]  # track 10 where the robot has it
        drift[0, 0] += 0.015 * (k + 1)
        c = decode_feedback(step(3 + k, np.append(ids, 40), np.vstack([drift, new])))
        sent.append(c.track_numbers.tolist())
    assert sent == [[], [12], []]
    # track 11 loses its point while the robot still tracks it: forgotten; track 30 ended on
    # the robot (not in the newest frame): dropped without a word
    keep = np.isin(ids, [10, 12])
    c = decode_feedback(step(6, ids[keep], drift[keep], tracked=np.array([10, 11, 12])))
    assert c.forget.tolist() == [11] and len(c.track_numbers) == 0
    assert sorted(robot.points) == [10, 12]
    # a restart (robot stream restart, VIO re-init, a dropped message) or a new map: a reset
    tx.restart()
    assert decode_feedback(step(7, ids, p)).reset
    c = decode_feedback(step(8, ids[:2], p[:2], map_id=1))
    assert c.reset and sorted(robot.points) == [10, 12]
    # after a reset the robot has the edge's points, on their rays, depth to 0.25 %
    got = np.array([robot.points[12], robot.points[10]])
    assert np.linalg.norm(got - p[:2], axis=1).max() <= 0.0025 * 1.5
    snap = timer.snapshot()["encode.InertialFeedbackCoded"]
    assert snap["messages"] == tx.sent == 9 and tx.resets == 3


def test_raw_sender_builds_the_schema_1_message() -> None:
    tx = FeedbackSender(FeedbackPolicy(), WireFormat.RAW)
    ids = np.array([12, 10])
    p = np.array([[1.0, 2.0, 3.0], [0.5, 0.5, 2.0]])
    s = state(5)
    msg = tx.on_state(0, s, ids, p, ids)
    assert msg == InertialFeedback(
        timestamp_ns=5,
        map_id=0,
        T_world_body=pack_array(s.T_world_body, "<f8"),
        velocity_world=pack_array(s.v_world, "<f8"),
        bias_gyro=pack_array(s.bias_gyro, "<f8"),
        bias_accel=pack_array(s.bias_accel, "<f8"),
        gravity_world=pack_array(s.T_world_body[:3, :3] @ s.gravity_body, "<f8"),
        track_ids=pack_array(ids, "<i8"),
        p_world=pack_array(p, "<f8"),
    )
    assert "encode.InertialFeedback" in tx.codec_timer.snapshot()


def test_policy_thresholds_and_period() -> None:
    tx = FeedbackSender(
        FeedbackPolicy(every_frames=20, velocity_mps=0.1), WireFormat.CODED, None, CAM
    )
    none = np.zeros(0, np.int64)
    sent = [
        tx.on_state(k, state(k, v=0.06 * k if k < 5 else 0.0), none, None, none) is not None
        for k in range(30)
    ]
    # first frame; velocity 0.12 (k=2) and 0.24 (k=4); back to 0 (k=5); period (k=25)
    assert [k for k, s in enumerate(sent) if s] == [0, 2, 4, 5, 25]
