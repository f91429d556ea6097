"""The coded edge -> cloud uplink of one robot session (``EdgeSessionConfig.wire`` CODED).

Hand-computed expectations: a new keyframe goes as KeyframeUpdateCoded and the observations
its point ids carry are not sent again as rows; a keyframe that moved goes in one
KeyframePoses, and the points anchored on it follow it without being re-sent unless they moved
beyond ``point_resend_m`` relative to it; a state change under the thresholds sends nothing.
Points go up at once here (``point_settle_keyframes=0``; settling: test_edge_point_settling).
Every message is read back with the cloud's own decoders.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.calibration import CameraCalibration
from common.codec import KeyframeFeatures
from common.geometry import make_T, so3_exp
from common.links.edge_cloud import (
    KeyframePoses,
    KeyframeUpdateCoded,
    MapPointUpdateCoded,
    pack_frame_poses,
    read_frame_poses,
)
from common.protocol.errors import RemoteProtocolError
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.cloud.fusion.uplink import (
    decode_keyframe_poses,
    decode_keyframe_update,
    decode_map_point_update,
)
from services.edge.robot_session import EdgeSessionConfig, RobotSession
from services.edge.vio.types import (
    FrameResult,
    KeyframeSnapshot,
    MapPointBatch,
    MapPointSnapshot,
    MapUpdate,
    TrackingStatus,
)

VOCAB = Vocabulary.load()


def _session() -> RobotSession:
    cam = CameraCalibration(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480)
    s = RobotSession("r", cam, VOCAB, EdgeSessionConfig(point_settle_keyframes=0))
    rng = np.random.default_rng(0)
    kp = np.array([[10, 20, 0, 3], [100, 50, 0, 7], [300, 200, 1, 30]], np.int32)
    desc = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    s._kf_features[1000] = KeyframeFeatures(kp, desc, np.full(3, -1, np.int32)).canonical()
    return s


def _kf(T: np.ndarray, point_ids: list[int]) -> KeyframeSnapshot:
    z = np.zeros(3)
    ids = np.array(point_ids, np.int64)
    return KeyframeSnapshot(0, 0, 1000, T, z, z, z, np.arange(3), ids, None, robot_keyframe=True)


def _pt(pid: int, p: np.ndarray, obs: dict[int, int]) -> MapPointSnapshot:
    kfs, rows = np.array(list(obs), np.int64), np.array(list(obs.values()), np.int64)
    return MapPointSnapshot(pid, 0, np.asarray(p, float), kfs, rows)


def _step(s: RobotSession, kfs: tuple, points: tuple) -> list[Message]:
    return s._uplink(MapUpdate(0, True, kfs, MapPointBatch.of(points), ()))


def _of(msgs: list[Message], cls: type) -> list:
    return [m for m in msgs if isinstance(m, cls)]


def test_coded_uplink_sends_each_fact_once_and_points_follow_their_keyframe() -> None:
    s = _session()
    p5, p3 = np.array([1.0, 0.5, 3.0]), np.array([-0.5, 0.2, 2.0])
    msgs = _step(s, (_kf(np.eye(4), [5, -1, 3]),), (_pt(5, p5, {0: 0}), _pt(3, p3, {0: 2})))
    (kf,) = _of(msgs, KeyframeUpdateCoded)
    d = decode_keyframe_update(kf, 0, VOCAB)
    assert d.keyframe is not None and d.map_point_ids.tolist() == [5, -1, 3]
    (up,) = _of(msgs, MapPointUpdateCoded)
    (pts,) = [decode_map_point_update(up, 0)]
    assert [p.map_point_id for p in pts] == [3, 5]
    assert all(len(p.observations) == 0 for p in pts)  # carried by the keyframe already
    assert np.abs(pts[1].p_world - p5).max() <= 5e-4  # the 1 mm grid

    # The keyframe moves by 5 cm and 0.1 rad; point 5 moves with it exactly, point 3 moves
    # 3 cm more than that: only the keyframe's state and point 3 go.
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.0, 0.0, 0.1]))
    T[:3, 3] = [0.05, 0.0, 0.0]
    follow5 = T[:3, :3] @ p5 + T[:3, 3]
    moved3 = T[:3, :3] @ p3 + T[:3, 3] + np.array([0.0, 0.03, 0.0])
    msgs = _step(s, (_kf(T, [5, -1, 3]),), (_pt(5, follow5, {0: 0}), _pt(3, moved3, {0: 2})))
    assert not _of(msgs, KeyframeUpdateCoded)
    (poses,) = _of(msgs, KeyframePoses)
    (upd,) = decode_keyframe_poses(poses)
    assert upd.keyframe_id == 0 and upd.keyframe is None
    assert np.abs(upd.T_world_body - T).max() < 1e-6
    (up,) = _of(msgs, MapPointUpdateCoded)
    assert [p.map_point_id for p in decode_map_point_update(up, 0)] == [3]

    # Half a millimetre and 1e-4 rad: under the thresholds, nothing goes.
    T2 = T.copy()
    T2[:3, 3] += [0.0005, 0.0, 0.0]
    T2[:3, :3] = so3_exp(np.array([0.0, 0.0, 0.1001]))
    assert _step(s, (_kf(T2, [5, -1, 3]),), (_pt(5, follow5, {0: 0}), _pt(3, moved3, {0: 2}))) == []


def test_messages_are_anchored_on_the_newest_keyframe_the_cloud_has_where_it_is_here() -> None:
    """The anchor (``FrameAnchor``) is the newest uplinked keyframe that the update leaves
    alone and that local BA has not nudged since it was sent; a correction the VIO applied
    moves it as it moved the keyframe."""
    s = _session()
    feats = s._kf_features[1000]
    for ts in (1001, 1002, 1003):
        s._kf_features[ts] = feats

    def kf(kf_id: int, T: np.ndarray) -> KeyframeSnapshot:
        z, ids = np.zeros(3), np.array([-1, -1, -1], np.int64)
        return KeyframeSnapshot(kf_id, 0, 1000 + kf_id, T, z, z, z, np.arange(3), ids, None)

    def at(x: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, 3] = [x, 0.0, 0.0]
        return T

    def anchors(msgs: list[Message]) -> set:
        # (every keyframe here has the same features: each carries the previous one's)
        desc = s._kf_features[1000].descriptors
        got = {
            decode_keyframe_update(m, 0, VOCAB, carried_from=lambda _k: desc).anchor
            for m in _of(msgs, KeyframeUpdateCoded)
        }
        got |= {decode_keyframe_poses(m)[0].anchor for m in _of(msgs, KeyframePoses)}
        return {None if a is None else (a.keyframe_id, round(a.T_world_body[0, 3], 4)) for a in got}

    assert anchors(_step(s, (kf(0, at(0.0)), kf(1, at(0.1))), ())) == {None}  # none sent yet
    # Keyframe 2 is new and local BA nudged keyframe 1 by 0.5 mm (not re-sent): keyframe 0.
    msgs = _step(s, (kf(2, at(0.2)), kf(1, at(0.1005))), ())
    assert anchors(msgs) == {(0, 0.0)}
    # The VIO applies a correction of +3 cm to every keyframe; keyframe 1 is still off what
    # the cloud has, so keyframe 2 is the anchor, where the correction moved it.
    C = at(0.03)
    s._follow_correction(0, {0: C, 1: C, 2: C})
    assert anchors(_step(s, (kf(3, at(0.33)),), ())) == {(2, 0.23)}
    # Keyframe 1 moves beyond the threshold: re-sent, and the newest anchor again after.
    msgs = _step(s, (kf(1, at(0.15)),), ())
    assert anchors(msgs) == {(3, 0.33)}
    assert max(s._agreed[0]) == 3 and s._agreed[0][1][0, 3] == 0.15


def test_tracked_frames_go_up_relative_to_the_newest_keyframe_the_cloud_has() -> None:
    """After keyframe 0 is uplinked, tracked frames go as FramePoses (every
    ``frame_poses_every``, and the rest at the robot's end), each relative to keyframe 0's
    sent pose: the cloud's keyframe pose times the relative pose is the VIO's frame pose."""
    s = _session()
    T_kf = make_T(so3_exp(np.array([0.0, 0.0, 0.3])), np.array([1.0, 2.0, 0.5]))
    _step(s, (_kf(T_kf, [5, -1, 3]),), ())
    frames = [
        make_T(so3_exp(np.array([0.0, 0.01 * k, 0.3])), np.array([1.0 + 0.05 * k, 2.0, 0.5]))
        for k in range(25)
    ]
    sent = []
    for k, T in enumerate(frames):
        r = FrameResult(1050 + 50 * k, T, TrackingStatus.TRACKING, 0, 100, False)
        sent += s._frame_relative(r)
    s._frame_relative(FrameResult(9999, np.eye(4), TrackingStatus.INITIALIZING, 0, 0, False))
    assert len(sent) == 1  # 20 frames a batch
    sent += s.release_frame_poses()
    assert len(sent) == 2 and s.release_frame_poses() == []
    t, t_kf, rel = (np.concatenate(x) for x in zip(*map(read_frame_poses, sent), strict=True))
    assert t.tolist() == [1050 + 50 * k for k in range(25)] and set(t_kf.tolist()) == {1000}
    placed = T_kf @ rel
    assert np.abs(placed - np.array(frames)).max() < 1e-5  # float32


def test_frame_poses_refuse_arrays_that_disagree() -> None:
    msg = pack_frame_poses(
        "r", 0, np.arange(3), np.zeros(3, np.int64), np.tile(np.eye(4), (3, 1, 1))
    )
    with pytest.raises(RemoteProtocolError, match="3 frames, 2 keyframe times"):
        read_frame_poses(
            dataclasses.replace(msg, keyframe_timestamps_ns=msg.keyframe_timestamps_ns[:16])
        )
    bad = np.zeros((3, 7), "<f4").tobytes()  # zero quaternions
    with pytest.raises(RemoteProtocolError, match="unit quaternions"):
        read_frame_poses(dataclasses.replace(msg, poses=bad))
