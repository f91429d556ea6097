"""Settling of new map points on the coded uplink (``EdgeSessionConfig.point_settle_keyframes``).

Hand-computed expectations with ``settle = 2``: a point first seen by robot keyframe 0 is
held while keyframe 1 goes up (the keyframes' messages do not name it), goes up (once, at
its newest position, with its rows in those keyframes) when keyframe 2 does; a point culled
while held costs nothing (no CullEvent); a point already sent is re-sent on a move as before;
a map the robot leaves releases its held points; the end of the sequence releases the rest.
Every message is read back with the cloud's own decoder.
"""

from __future__ import annotations

import numpy as np

from common.calibration import CameraCalibration
from common.codec import KeyframeFeatures
from common.links.edge_cloud import CullEvent, KeyframeUpdateCoded, MapPointUpdateCoded
from common.links.edge_cloud_payloads import decode_point_ids
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.cloud.fusion.uplink import decode_map_point_update
from services.edge.point_uplink import SentPoints
from services.edge.robot_session import EdgeSessionConfig, RobotSession
from services.edge.vio.types import KeyframeSnapshot, MapPointBatch, MapPointSnapshot, MapUpdate

VOCAB = Vocabulary.load()


def _session(settle: int = 2) -> RobotSession:
    cam = CameraCalibration(fx=400.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480)
    s = RobotSession("r", cam, VOCAB, EdgeSessionConfig(point_settle_keyframes=settle))
    rng = np.random.default_rng(0)
    kp = np.array([[10, 20, 0, 3], [100, 50, 0, 7], [300, 200, 1, 30]], np.int32)
    for k in range(6):
        desc = rng.integers(0, 256, (3, 32), dtype=np.uint8)
        s._kf_features[1000 * (k + 1)] = KeyframeFeatures(
            kp, desc, np.full(3, -1, np.int32)
        ).canonical()
    return s


def _kf(kid: int, point_ids: list[int], map_id: int = 0) -> KeyframeSnapshot:
    z = np.zeros(3)
    ids = np.array(point_ids, np.int64)
    return KeyframeSnapshot(
        kid,
        map_id,
        1000 * (kid + 1),
        np.eye(4),
        z,
        z,
        z,
        np.arange(3),
        ids,
        None,
        robot_keyframe=True,
    )


def _pt(pid: int, x: float, obs: dict[int, int], map_id: int = 0) -> MapPointSnapshot:
    kfs, rows = np.array(list(obs), np.int64), np.array(list(obs.values()), np.int64)
    return MapPointSnapshot(pid, map_id, np.array([x, 0.0, 2.0]), kfs, rows)


def _step(
    s: RobotSession, kfs: tuple, points: tuple, removed: tuple = (), map_id: int = 0
) -> list[Message]:
    return s._uplink(MapUpdate(map_id, True, kfs, MapPointBatch.of(points), removed))


def _points(msgs: list[Message]) -> list[tuple[int, list[int], list[float], list[list[int]]]]:
    """(map id, ids, x of each point, rows [point, keyframe, feature]) of every
    MapPointUpdateCoded, read back by the cloud's decoder."""
    out = []
    for m in msgs:
        if isinstance(m, MapPointUpdateCoded):
            pts = decode_map_point_update(m, 0)
            rows = [[p.map_point_id, *map(int, o)] for p in pts for o in p.observations]
            xs = [round(float(p.p_world[0]), 3) for p in pts]
            out.append((m.map_id, [p.map_point_id for p in pts], xs, rows))
    return out


def _named(msgs: list[Message]) -> list[list[int]]:
    """The feature -> point ids of every KeyframeUpdateCoded, decoded."""
    return [
        decode_point_ids(m.map_point_ids).tolist()
        for m in msgs
        if isinstance(m, KeyframeUpdateCoded)
    ]


def test_new_points_wait_until_settled_and_go_up_once_at_their_newest_position() -> None:
    s = _session(settle=2)
    # Keyframe 0 sees points 1 and 2, which are held: its message names neither (the cloud
    # never hears of a point without its position), so their rows in it go with the points.
    msgs = _step(s, (_kf(0, [1, 2, -1]),), (_pt(1, 0.10, {0: 0}), _pt(2, 0.20, {0: 1})))
    assert _points(msgs) == [] and _named(msgs) == [[-1, -1, -1]]
    # Keyframe 1: local BA moved both; point 1 also seen at row 2 of keyframe 1; still held
    # (1 keyframe after its first).
    msgs = _step(s, (_kf(1, [-1, -1, 1]),), (_pt(1, 0.15, {0: 0, 1: 2}), _pt(2, 0.25, {0: 1})))
    assert _points(msgs) == [] and _named(msgs) == [[-1, -1, -1]]
    # Point 2 is culled while held: the cloud never heard of it, so no CullEvent.
    msgs = _step(s, (), (), removed=(2,))
    assert not [m for m in msgs if isinstance(m, CullEvent)] and _points(msgs) == []
    # Keyframe 2 goes up: point 1 has settled and goes up once, at its newest position, with
    # both rows. Point 1 is not in this update (it left the window). Keyframe 3 then names it.
    msgs = _step(s, (_kf(2, [-1, -1, -1]),), ())
    assert _points(msgs) == [(0, [1], [0.15], [[1, 0, 0], [1, 1, 2]])]
    msgs = _step(s, (_kf(3, [1, -1, -1]),), (_pt(1, 0.15, {0: 0, 1: 2, 3: 0}),))
    assert _named(msgs) == [[1, -1, -1]] and _points(msgs) == []  # the row went with keyframe 3
    # Sent now: a small move sends nothing, a move beyond point_resend_m (1 cm) re-sends it.
    assert _points(_step(s, (), (_pt(1, 0.155, {0: 0, 1: 2}),))) == []
    assert _points(_step(s, (), (_pt(1, 0.17, {0: 0, 1: 2}),))) == [(0, [1], [0.17], [])]


def test_a_map_left_behind_and_the_sequence_end_release_the_held_points() -> None:
    s = _session(settle=2)
    assert _points(_step(s, (_kf(0, [4, -1, -1]),), (_pt(4, 0.4, {0: 0}),))) == []
    # The VIO starts map 1: map 0 gets no more keyframes, so its held point goes up now.
    msgs = _step(s, (_kf(3, [7, -1, -1], map_id=1),), (_pt(7, 0.7, {3: 0}, map_id=1),), map_id=1)
    assert _points(msgs) == [(0, [4], [0.4], [[4, 0, 0]])]
    # The sequence ends: map 1's held point goes up too, then nothing is left.
    assert _points(s.release_points()) == [(1, [7], [0.7], [[7, 3, 0]])]
    assert s.release_points() == []


def test_settle_zero_sends_at_once_and_negative_is_refused() -> None:
    s = _session(settle=0)
    msgs = _step(s, (_kf(0, [1, -1, -1]),), (_pt(1, 0.1, {0: 0}),))
    assert _points(msgs) == [(0, [1], [0.1], [])]
    try:
        SentPoints(-1)
    except ValueError as exc:
        assert "settle_keyframes" in str(exc)
    else:
        raise AssertionError("SentPoints(-1) accepted")


def test_held_points_move_with_the_corrections_the_vio_applied() -> None:
    """A correction the VIO applies while a point is held moves the point with its first
    observer's correction (as the VIO moved it), so it goes up where the VIO has it."""
    book = SentPoints(settle_keyframes=2)
    own = np.zeros(0, np.int64)
    book.add_keys(np.zeros(0, np.int64), 0)  # robot keyframes 0 and 5 went up
    book.add_keys(np.zeros(0, np.int64), 5)
    first = MapPointBatch.of([_pt(1, 0.1, {0: 0}), _pt(2, 0.2, {5: 0})])
    assert book.select(first, own, 0.01) is None and book.n_held == 2
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.0]  # keyframe 0 moved 1 m along x; keyframe 5 not corrected
    book.move_held({0: T})
    book.add_keys(np.zeros(0, np.int64), 7)
    out = book.select(MapPointBatch.of([]), own, 0.01)
    assert out is not None
    ids, p_world, _ = out
    assert ids.tolist() == [1] and np.allclose(p_world[0], [1.1, 0.0, 2.0])
    assert book.n_held == 1  # point 2 (first seen by keyframe 5) still settling
    book.move_held({5: T})
    (ids, p_world, _) = book.release(own, 0.01) or (None, None, None)
    assert ids is not None and ids.tolist() == [2] and np.allclose(p_world[0], [1.2, 0.0, 2.0])
