"""The robot <-> edge feedback codec: raw and coded messages into one FeedbackContent."""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import common.links.robot_edge as robot_edge
from common.camera import PinholeRadtan
from common.data.synth.cameras import EUROC_CAM0
from common.geometry import so3_exp
from common.links import WireFormat
from common.links.robot_edge import (
    DEPTH_STEP,
    Anchors,
    FeedbackContent,
    InertialFeedback,
    InertialFeedbackCoded,
    coded_points,
    decode_feedback,
    encode_feedback,
    points_sendable,
)
from common.protocol.arrays import pack_array
from common.protocol.errors import RemoteProtocolError
from common.protocol.messages import decode_payload, encode_payload

T_BODY_CAM = np.eye(4)  # a camera turned about the body axes and set off a few cm
T_BODY_CAM[:3, :3] = so3_exp(np.array([0.3, -1.4, 1.2]))
T_BODY_CAM[:3, 3] = [-0.02, -0.06, 0.01]
CAM = EUROC_CAM0.to_calibration(T_BODY_CAM, 20.0)  # EuRoC cam0 intrinsics


def on_rays(T_world_body: np.ndarray, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    """World points (N, 3) at camera depths ``z`` (N,) on the rays of pixels ``uv`` (N, 2)."""
    xy = PinholeRadtan.from_calibration(CAM).pixels_to_normalized(uv)
    p_cam = np.concatenate([xy * z[:, None], z[:, None]], axis=1)
    T_wc = T_world_body @ CAM.T_body_cam
    return p_cam @ T_wc[:3, :3].T + T_wc[:3, 3]


def content(
    n: int = 20, *, seed: int = 0, reset: bool = True, forget: tuple[int, ...] = ()
) -> FeedbackContent:
    """Tracks seen at random pixels, their points at 0.3-30 m on (or 1 px off) their rays."""
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = so3_exp(rng.normal(size=3))
    T[:3, 3] = rng.uniform(-30, 30, 3)
    numbers = np.sort(rng.choice(10 * n + 10, n, replace=False)).astype(np.int64) + 1000
    uv = rng.uniform([5, 5], [747, 475], (n, 2))
    p = on_rays(T, uv + rng.normal(size=(n, 2)), np.exp(rng.uniform(np.log(0.3), np.log(30), n)))
    return FeedbackContent(
        timestamp_ns=1_600_000_000_123_456_789,
        map_id=3,
        T_world_body=T,
        velocity_world=rng.normal(size=3),
        bias_gyro=rng.normal(size=3) * 1e-3,
        bias_accel=rng.normal(size=3) * 1e-2,
        gravity_world=np.array([0.01, -0.02, -9.81]),
        reset=reset,
        track_numbers=numbers,
        p_world=p,
        forget=np.array(forget, np.int64),
        keypoints_px=uv,
    )


def anchors_of(c: FeedbackContent) -> Anchors:
    """What the robot has of the frame: every track of ``c`` and a few others."""
    extra = np.array([1, 2, 3], np.int64)
    uv = np.concatenate([c.keypoints_px, np.full((3, 2), 100.0)])
    return Anchors(np.concatenate([c.track_numbers, extra]), uv)


def encode(c: FeedbackContent):
    return encode_feedback(c, WireFormat.CODED, CAM)


def wire_round_trip(msg):
    return decode_payload(msg.TYPE_ID, encode_payload(msg))


def test_coded_type_id_and_raw_untouched() -> None:
    assert InertialFeedback.TYPE_ID == 0x0301 and InertialFeedbackCoded.TYPE_ID == 0x0302


def test_raw_is_the_schema_1_message_bit_for_bit() -> None:
    c = content()
    old = InertialFeedback(  # what RobotSession._feedback built before the coded wire
        timestamp_ns=c.timestamp_ns,
        map_id=c.map_id,
        T_world_body=pack_array(c.T_world_body, "<f8"),
        velocity_world=pack_array(c.velocity_world, "<f8"),
        bias_gyro=pack_array(c.bias_gyro, "<f8"),
        bias_accel=pack_array(c.bias_accel, "<f8"),
        gravity_world=pack_array(c.gravity_world, "<f8"),
        track_ids=pack_array(c.track_numbers, "<i8"),
        p_world=pack_array(c.p_world, "<f8"),
    )
    raw = encode_feedback(c, WireFormat.RAW)
    assert raw == old and encode_payload(raw) == encode_payload(old)
    back = decode_feedback(wire_round_trip(raw))
    assert back.reset and np.array_equal(back.p_world, c.p_world)
    assert np.array_equal(back.track_numbers, c.track_numbers)
    assert np.array_equal(back.T_world_body, c.T_world_body)
    with pytest.raises(ValueError):
        encode_feedback(dataclasses.replace(c, reset=False), WireFormat.RAW)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    n=st.integers(0, 300),
    n_forget=st.integers(0, 40),
    reset=st.booleans(),
)
def test_coded_round_trip_within_the_stated_precision(seed, n, n_forget, reset) -> None:
    rng = np.random.default_rng(seed)
    c = content(n, seed=seed, reset=reset)
    perm = rng.permutation(n)  # any order in, ascending out
    forget = np.zeros(0, np.int64)
    if not reset:
        forget = np.unique(rng.integers(0, 2**40, n_forget)) + 2**41  # disjoint from numbers
    c = dataclasses.replace(
        c,
        track_numbers=c.track_numbers[perm],
        p_world=c.p_world[perm],
        keypoints_px=c.keypoints_px[perm],
        forget=forget,
    )
    assert points_sendable(c.p_world, c.T_world_body, c.keypoints_px, CAM).all()
    msg = encode(c)
    assert isinstance(msg, InertialFeedbackCoded) and len(msg.state) == 76
    d = decode_feedback(wire_round_trip(msg), CAM, anchors_of(c))
    order = np.argsort(c.track_numbers)
    assert d.reset == reset and d.map_id == c.map_id and d.timestamp_ns == c.timestamp_ns
    assert np.array_equal(d.track_numbers, c.track_numbers[order])
    assert np.array_equal(d.forget, forget)
    # points: on the ray of their keypoint, at the depth to DEPTH_STEP / 2, exactly what
    # coded_points says the robot holds
    T_cw = np.linalg.inv(d.T_world_body @ CAM.T_body_cam)
    got = d.p_world @ T_cw[:3, :3].T + T_cw[:3, 3]
    want = c.p_world[order] @ T_cw[:3, :3].T + T_cw[:3, 3]
    assert np.abs(got[:, 2] / want[:, 2] - 1).max(initial=0) <= DEPTH_STEP / 2 + 1e-9
    px = PinholeRadtan.from_calibration(CAM).project(got)
    assert np.abs(px - c.keypoints_px[order]).max(initial=0) < 1e-6
    held = coded_points(c.p_world[order], c.T_world_body, c.keypoints_px[order], CAM)
    assert np.array_equal(d.p_world, held)
    assert np.array_equal(d.keypoints_px if n else c.keypoints_px[:0], c.keypoints_px[order])
    # state: float32
    assert np.abs(d.T_world_body[:3, :3] - c.T_world_body[:3, :3]).max() < 1e-6
    assert np.abs(d.T_world_body[:3, 3] - c.T_world_body[:3, 3]).max() < 4e-6
    for name in ("velocity_world", "bias_gyro", "bias_accel", "gravity_world"):
        want = getattr(c, name)
        assert np.abs(getattr(d, name) - want).max() <= 1e-7 * np.abs(want).max() + 1e-12
    R = d.T_world_body[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_points_need_the_robots_keypoints() -> None:
    c = content(10)
    msg = encode(c)
    assert np.isnan(decode_feedback(msg).p_world).all()  # no camera, no anchors
    some = Anchors(c.track_numbers[:4], c.keypoints_px[:4])
    d = decode_feedback(msg, CAM, some)
    assert np.isfinite(d.p_world[:4]).all() and np.isnan(d.p_world[4:]).all()
    with pytest.raises(ValueError, match="camera"):
        encode_feedback(c, WireFormat.CODED)
    behind = c.p_world.copy()
    behind[0] = c.T_world_body[:3, 3] - 5.0 * (c.T_world_body @ CAM.T_body_cam)[:3, 2]
    ok = points_sendable(behind, c.T_world_body, c.keypoints_px, CAM)
    assert not ok[0] and ok[1:].all()
    with pytest.raises(ValueError, match="sendable"):
        encode(dataclasses.replace(c, p_world=behind))


def test_nothing_to_say_costs_no_landmark_bytes() -> None:
    c = dataclasses.replace(
        content(0), reset=False, track_numbers=np.zeros(0, np.int64), p_world=np.zeros((0, 3))
    )
    msg = encode(c)
    assert msg.landmarks == b"" and len(encode_payload(msg)) < 100
    d = decode_feedback(msg)
    assert not d.reset and len(d.track_numbers) == len(d.forget) == 0


def test_coded_points_are_compact() -> None:
    msg = encode(content(200))
    raw = encode_feedback(content(200), WireFormat.RAW)
    assert len(encode_payload(msg)) < len(encode_payload(raw)) / 10


def test_encoder_refuses_what_the_wire_cannot_carry() -> None:
    c = content(3)
    with pytest.raises(ValueError, match="reset"):
        encode(dataclasses.replace(c, forget=np.array([1])))
    with pytest.raises(ValueError, match="distinct"):
        encode(dataclasses.replace(c, track_numbers=np.array([5, 5, 6])))


# ------------------------------------------------------------------ refused input
def coded(**over) -> InertialFeedbackCoded:
    msg = encode(dataclasses.replace(content(30), reset=False, forget=np.array([7, 9])))
    return dataclasses.replace(msg, **over)


@pytest.mark.parametrize(
    "over, match",
    [
        (dict(state=b"\x00" * 75), "state: 75 bytes"),
        (dict(state=b"\x00" * 76), "state: the rotation is not a unit quaternion"),
        (dict(state=b"\xff" * 76), "state: non-finite"),
        (dict(landmarks=b"\x01\x02"), "landmarks: coded payload of 2 bytes"),
        (dict(reset=True), "landmarks: a reset that forgets"),
    ],
)
def test_bad_coded_fields_are_the_peers_fault(over, match) -> None:
    with pytest.raises(RemoteProtocolError, match=match):
        decode_feedback(coded(**over))


def test_truncated_or_corrupt_landmarks_are_refused() -> None:
    msg = coded()
    for cut in (1, 4, len(msg.landmarks) // 2):
        with pytest.raises(RemoteProtocolError, match=r"InertialFeedbackCoded\.landmarks"):
            decode_feedback(dataclasses.replace(msg, landmarks=msg.landmarks[:-cut]))
    flipped = bytearray(msg.landmarks)
    flipped[len(flipped) // 2] ^= 0x10
    with pytest.raises(RemoteProtocolError, match="checksum"):
        decode_feedback(dataclasses.replace(msg, landmarks=bytes(flipped)))


def test_counts_and_ranges_over_the_limits_are_refused(monkeypatch) -> None:
    msg = coded()
    monkeypatch.setattr(robot_edge, "MAX_FEEDBACK_POINTS", 10)
    with pytest.raises(RemoteProtocolError, match="landmarks: count 30 exceeds the limit 10"):
        decode_feedback(msg)
    monkeypatch.undo()
    monkeypatch.setattr(robot_edge, "_Q_MAX", -1000)
    with pytest.raises(RemoteProtocolError, match="landmarks: a depth beyond"):
        decode_feedback(msg)


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=200), state=st.binary(min_size=76, max_size=76))
def test_fuzzed_coded_fields_decode_or_raise_remote_errors(data, state) -> None:
    msg = coded()
    for bad in (dataclasses.replace(msg, landmarks=data), dataclasses.replace(msg, state=state)):
        with contextlib.suppress(RemoteProtocolError):
            decode_feedback(bad, CAM, anchors_of(content(30)))


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("T_world_body", b"\x00" * 127, "T_world_body: 127 bytes"),
        ("T_world_body", b"", "T_world_body: 0 poses"),
        ("velocity_world", pack_array(np.zeros((2, 3)), "<f8"), "velocity_world: 2 rows"),
        ("track_ids", pack_array([1, 2, 3], "<i8"), "p_world: 20 points for 3 track ids"),
    ],
)
def test_bad_raw_fields_are_the_peers_fault(field, value, match) -> None:
    raw = encode_feedback(content(), WireFormat.RAW)
    with pytest.raises(RemoteProtocolError, match=match):
        decode_feedback(dataclasses.replace(raw, **{field: value}))
