"""RobotApp's reaction to the edge's messages: conversion, refusal, map changes."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from common.camera import PinholeRadtan
from common.data.euroc import EurocSequence
from common.links import WireFormat
from common.links.robot_edge import (
    FeedbackContent,
    InertialFeedback,
    decode_feedback,
    encode_feedback,
)
from common.protocol.arrays import pack_array
from common.protocol.messages import Blob
from common.vocabulary import Vocabulary
from services.edge.robot_session import RobotSession
from services.robot.app import RobotApp, content_to_state
from services.robot.config import FrontEndConfig, KeyframeDecisionConfig


def feedback(ts: int, map_id: int = 0, n_points: int = 0, **over) -> InertialFeedback:
    fields = dict(
        timestamp_ns=ts,
        map_id=map_id,
        T_world_body=pack_array(np.eye(4), "<f8"),
        velocity_world=pack_array([0.1, 0.2, 0.3], "<f8"),
        bias_gyro=pack_array([0.01, 0.02, 0.03], "<f8"),
        bias_accel=pack_array([0.0, 0.0, 0.1], "<f8"),
        gravity_world=pack_array([0.0, 0.0, -9.81], "<f8"),
        track_ids=pack_array(np.arange(n_points), "<i8"),
        p_world=pack_array(np.ones((n_points, 3)), "<f8"),
    )
    fields.update(over)
    return InertialFeedback(**fields)


def deliver(app: RobotApp, msg) -> None:
    """The edge's message reaches the front end while no frame is tracked."""
    app.receive(msg)
    app.apply_pending()


def test_feedback_conversion_and_refusals(euroc_micro):
    seq = EurocSequence(euroc_micro)
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, Vocabulary.load())
    frames = list(seq.frames(0, 3))
    for fr in frames:
        app.process(fr.timestamp_ns, fr.image, fr.imu)
    t = frames[-1].timestamp_ns
    content = decode_feedback(feedback(t, n_points=2))
    state = content_to_state(content)
    assert np.array_equal(state.v_world_imu, [0.1, 0.2, 0.3]) and content.reset
    assert content.track_numbers.tolist() == [0, 1] and content.p_world.shape == (2, 3)
    assert not decode_feedback(feedback(t)).reset  # raw without points: keeps the set
    # Malformed arrays, a non-rotation, a state older than the IMU buffer: refused, counted.
    deliver(app, feedback(t, velocity_world=b"\x00" * 5))
    deliver(app, feedback(t, T_world_body=pack_array(2 * np.eye(4), "<f8")))
    deliver(app, feedback(t - 10**10))
    deliver(app, feedback(t, track_ids=pack_array([1, 2, 3], "<i8")))
    assert (app.feedback_rejected, app.feedback_applied) == (4, 0)
    assert not app.front_end.vi_initialised
    deliver(app, Blob(0, b"x"))  # not for the robot: ignored
    # Points named by stream track numbers (the edge's naming); an ended track is dropped.
    numbers = app.frame_coder.stream_ids[[0, 5, 9]]
    msg = feedback(t, n_points=4, track_ids=pack_array([*numbers, 10**9], "<i8"))
    deliver(app, msg)
    assert app.feedback_applied == 1 and app.front_end.vi_initialised
    want = set(app.frame_coder.track_ids[[0, 5, 9]].tolist())
    assert set(app.front_end.predictor._landmarks) == want
    deliver(app, feedback(t, map_id=1))  # another map, no points: the old ones are dropped
    assert app.feedback_applied == 2 and len(app.front_end.predictor._landmarks) == 0
    fr = next(seq.frames(3, 4))
    app.process(fr.timestamp_ns, fr.image, fr.imu)
    assert app.frames == 4


def coded(app: RobotApp, ts: int, numbers, z=2.0, *, map_id=0, reset: bool, forget=(), at=None):
    """A coded message about the frame at ``at`` (default ``ts``) of ``app``: points of the
    tracks ``numbers`` at depth ``z`` [m] on the rays of their keypoints (body at the origin)."""
    frame = app._anchors[ts if at is None else at]
    numbers = np.asarray(numbers, np.int64)
    uv = frame.of(numbers)
    c = FeedbackContent(
        timestamp_ns=ts,
        map_id=map_id,
        T_world_body=np.eye(4),
        velocity_world=np.zeros(3),
        bias_gyro=np.zeros(3),
        bias_accel=np.zeros(3),
        gravity_world=np.array([0.0, 0.0, -9.81]),
        reset=reset,
        track_numbers=numbers,
        p_world=ray_points(app, uv, np.broadcast_to(z, len(numbers))),
        forget=np.asarray(forget, np.int64),
        keypoints_px=uv,
    )
    return encode_feedback(c, WireFormat.CODED, app.camera)


def ray_points(app: RobotApp, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    """World points (N, 3) at camera depth ``z`` (N,) on the rays of ``uv`` (N, 2), body at
    the origin."""
    xy = PinholeRadtan.from_calibration(app.camera).pixels_to_normalized(uv)
    p_cam = np.concatenate([xy * z[:, None], z[:, None]], axis=1)
    T = app.camera.T_body_cam
    return p_cam @ T[:3, :3].T + T[:3, 3]


def test_robot_keeps_the_keypoints_the_edge_decodes(euroc_micro):
    """The coded feedback's points are sent along the rays of the frame's keypoints: both ends
    must have the same (the robot: what it coded; the edge: what it decoded)."""
    seq = EurocSequence(euroc_micro)
    vocab = Vocabulary.load()
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, vocab, anchor_frames=3)
    session = RobotSession("r", seq.cam0, vocab)
    for fr in seq.frames(0, 5):  # a keyframe, then non-keyframes
        item = session.decode(app.process(fr.timestamp_ns, fr.image, fr.imu))
        mine = app._anchors[fr.timestamp_ns]
        assert np.array_equal(mine.numbers, item.obs.track_ids)
        assert np.array_equal(mine.keypoints_px, item.obs.keypoints_px)
    assert len(app._anchors) == 3


def test_coded_feedback_resets_updates_and_forgets(euroc_micro):
    seq = EurocSequence(euroc_micro)
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, Vocabulary.load())
    frames = list(seq.frames(0, 3))
    for fr in frames:
        app.process(fr.timestamp_ns, fr.image, fr.imu)
    t = frames[-1].timestamp_ns
    s = app.frame_coder.stream_ids
    tid = dict(zip(s.tolist(), app.frame_coder.track_ids.tolist(), strict=True))

    def landmarks() -> dict[int, float]:
        """Tracker id -> camera depth [m] of its landmark (body at the origin)."""
        T_cb = np.linalg.inv(app.camera.T_body_cam)
        return {
            k: round(float((T_cb[:3, :3] @ v + T_cb[:3, 3])[2]), 1)  # depth to 0.25 %
            for k, v in app.front_end.predictor._landmarks.items()
        }

    deliver(app, coded(app, t, s[[0, 5, 9]], reset=True))
    assert app.feedback_applied == 1 and app.front_end.vi_initialised
    assert landmarks() == {tid[int(k)]: 2.0 for k in s[[0, 5, 9]]}
    # update: a new track, a moved one, a forgotten one; the others stay
    deliver(app, coded(app, t, s[[2, 5]], [3.0, 5.0], reset=False, forget=[s[9]]))
    assert landmarks() == {tid[int(s[0])]: 2.0, tid[int(s[2])]: 3.0, tid[int(s[5])]: 5.0}
    # messages that arrive during a frame wait, all of them, and are applied in order
    app.receive(coded(app, t, s[[1]], reset=False))
    app.receive(coded(app, t, [], reset=False, forget=[s[0]]))
    assert app.feedback_applied == 2
    app.apply_pending()
    assert app.feedback_applied == 4 and sorted(landmarks()) == sorted(
        tid[int(k)] for k in s[[1, 2, 5]]
    )
    # refused: a damaged payload (counted, nothing applied); a state too old for the IMU
    # buffer (counted; its points are of a frame the robot no longer keeps: dropped)
    bad = coded(app, t, s[[3]], reset=False)
    deliver(app, dataclasses.replace(bad, landmarks=bad.landmarks[:-1]))
    deliver(app, coded(app, t - 10**10, s[[3]], reset=False, at=t))
    assert (app.feedback_rejected, app.feedback_applied) == (2, 4)
    assert tid[int(s[3])] not in landmarks() and app.feedback_points_unanchored == 1
    # another map: a reset replaces the set; an update of another map drops the old set first
    deliver(app, coded(app, t, s[[4]], map_id=1, reset=False))
    assert sorted(landmarks()) == [tid[int(s[4])]]
    deliver(app, coded(app, t, s[[6, 7]], map_id=1, reset=True))
    assert sorted(landmarks()) == sorted(tid[int(k)] for k in s[[6, 7]])
    decoded = app.codec_timer.snapshot()["decode.InertialFeedbackCoded"]["messages"]
    assert decoded == 7  # all but the damaged one
    fr = next(seq.frames(3, 4))
    app.process(fr.timestamp_ns, fr.image, fr.imu)  # ended tracks' points are dropped
    deliver(app, coded(app, fr.timestamp_ns, [], map_id=1, reset=False))
    assert set(landmarks()) <= set(app.frame_coder.track_ids.tolist())


def test_the_edges_time_offset_reaches_the_robots_batches_and_prediction(euroc_micro):
    """The edge tells the robot its camera-IMU offset once per change; the robot reads its
    frame times on the IMU clock from then on (its batches reach ``t + offset``), and the IMU
    the edge sends on to the cloud is read at ``t + offset`` (the status tells the cloud)."""
    from common.links.robot_edge import CameraImuOffset
    from services.edge.vio.types import FrameResult, TrackingStatus
    from services.edge.worker import WorkResult

    seq = EurocSequence(euroc_micro)
    vocab = Vocabulary.load()
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, vocab)
    session = RobotSession("r", seq.cam0, vocab)
    frames = seq.frames(0, 6, imu_lead_ns=lambda: max(0, app.time_offset_ns))
    for _ in range(3):
        fr = next(frames)
        session.decode(app.process(fr.timestamp_ns, fr.image, fr.imu))
    res = FrameResult(fr.timestamp_ns, np.eye(4), TrackingStatus.INITIALIZING, 0, 0, False)
    told = session.on_result(WorkResult(2, res, None, (), time_offset_ns=15_000_000))
    again = session.on_result(WorkResult(2, res, None, (), time_offset_ns=15_000_000))
    offsets = [m for m in told.robot if isinstance(m, CameraImuOffset)]
    assert [m.offset_ns for m in offsets] == [15_000_000]
    assert not [m for m in again.robot if isinstance(m, CameraImuOffset)]
    assert "camera-IMU offset +15.0 ms" in session.detail()
    deliver(app, offsets[0])
    assert app.time_offset_ns == 15_000_000
    assert app.front_end.predictor.time_offset_ns == 15_000_000
    for fr in frames:
        assert fr.imu.timestamps_ns[-1] >= fr.timestamp_ns + 15_000_000  # reaches t + offset
        session.decode(app.process(fr.timestamp_ns, fr.image, fr.imu))
    t_a, t_b = seq.frame_timestamps_ns[3], seq.frame_timestamps_ns[5]
    t, _ = session.imu_uplink.window((0, 0), int(t_a), (0, 1), int(t_b), session.time_offset_ns)
    imu_t = seq.imu_timestamps_ns
    expected = imu_t[(imu_t > t_a + 15_000_000) & (imu_t <= t_b + 15_000_000)]
    np.testing.assert_array_equal(t, expected)  # the IMU clock's stamps, read at t + offset
    assert session.status({}).time_offset_ns == 15_000_000  # the cloud reads them with it


def test_left_out_non_keyframes_keep_the_stream_decodable_and_the_imu_whole(euroc_micro):
    """The uplink's rate control leaves non-keyframes out after tracking them: the edge still
    decodes every frame sent (coded against the last one sent, the same stream numbers at both
    ends) and receives every IMU sample, the left-out frames' with the next frame sent."""
    seq = EurocSequence(euroc_micro)
    vocab = Vocabulary.load()
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, vocab)
    session = RobotSession("r", seq.cam0, vocab)
    imu_in: list[int] = []
    imu_out: list[int] = []
    sent = 0
    numbers: list[set[int]] = []
    for k, fr in enumerate(seq.frames(0, 25)):  # (the last one is sent)
        if k:  # (the first frame's pre-roll is cut to a second on both ends)
            imu_in += fr.imu.timestamps_ns.tolist()
        msg = app.process_if(fr.timestamp_ns, fr.image, fr.imu, send=k % 3 == 0)
        if msg is None:
            continue
        sent += 1
        item = session.decode(msg)
        if k:
            imu_out += item.imu_t_ns.tolist()
        mine = app._anchors[fr.timestamp_ns]
        assert np.array_equal(mine.numbers, item.obs.track_ids)
        assert np.array_equal(mine.keypoints_px, item.obs.keypoints_px)
        numbers.append(set(item.obs.track_ids.tolist()))
    assert app.skipped > 0 and sent + app.skipped == 25 and app.frames == sent
    assert imu_out == imu_in  # nothing lost, nothing twice, in order
    # A track that lived through a gap keeps its number: the edge's VIO sees one feature.
    assert session.frames == sent
    assert all(len(a & b) > 100 for a, b in itertools.pairwise(numbers))


def test_the_robot_predicts_its_pose_from_the_edges_last_state(euroc_micro):
    """``predicted_pose``: none before the edge's first state; then the state propagated with
    the IMU to the frame's time, in the edge's map."""
    seq = EurocSequence(euroc_micro)
    app = RobotApp(FrontEndConfig(), seq.cam0, seq.imu, Vocabulary.load())
    frames = list(seq.frames(0, 3))
    for fr in frames[:2]:
        app.process(fr.timestamp_ns, fr.image, fr.imu)
    t = frames[1].timestamp_ns
    assert app.predicted_pose(t) is None
    deliver(app, feedback(t, map_id=4))
    map_id, T = app.predicted_pose(t)
    assert map_id == 4 and np.allclose(T, np.eye(4))  # the state itself
    app.process(frames[2].timestamp_ns, frames[2].image, frames[2].imu)
    _, T2 = app.predicted_pose(frames[2].timestamp_ns)
    dt = (frames[2].timestamp_ns - t) * 1e-9
    # propagated: it moved, by about the state's velocity (the fabricated state's attitude
    # does not put gravity where this IMU measures it: up to 2 g of error over dt)
    moved = T2[:3, 3] - np.array([0.1, 0.2, 0.3]) * dt
    assert np.linalg.norm(T2[:3, 3]) > 0 and np.linalg.norm(moved) < 0.5 * 2 * 9.81 * dt**2


def test_an_outage_leaves_keyframes_out_and_the_stream_still_decodes(euroc_micro):
    """During an outage the budget leaves keyframes out too: the next frame sent is coded
    against the last one sent, and its tracks that the left-out keyframe started are new."""
    seq = EurocSequence(euroc_micro)
    vocab = Vocabulary.load()
    config = FrontEndConfig(keyframe=KeyframeDecisionConfig(max_interval_s=0.2))
    app = RobotApp(config, seq.cam0, seq.imu, vocab)
    session = RobotSession("r", seq.cam0, vocab)
    left_keyframes = 0
    for k, fr in enumerate(seq.frames(0, 20)):
        outage = 5 <= k < 12
        msg = app.process_if(fr.timestamp_ns, fr.image, fr.imu, not outage, not outage)
        if msg is None:
            left_keyframes += app.front_end._kf_t == fr.timestamp_ns
            continue
        item = session.decode(msg)
        assert np.array_equal(app._anchors[fr.timestamp_ns].numbers, item.obs.track_ids)
    assert left_keyframes >= 1 and session.frames == 13
