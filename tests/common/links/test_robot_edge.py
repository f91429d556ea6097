"""The robot <-> edge feedback codec: raw and coded messages into one FeedbackContent."""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import common.links.robot_edge as robot_edge
from common.geometry import so3_exp
from common.links import WireFormat
from common.links.robot_edge import (
    POINT_STEP_M,
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


def content(
    n: int = 20, *, seed: int = 0, reset: bool = True, forget: tuple[int, ...] = ()
) -> FeedbackContent:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = so3_exp(rng.normal(size=3))
    T[:3, 3] = rng.uniform(-30, 30, 3)
    numbers = np.sort(rng.choice(10 * n + 10, n, replace=False)).astype(np.int64) + 1000
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
        p_world=T[:3, 3] + rng.normal(size=(n, 3)) * 3.0,
        forget=np.array(forget, np.int64),
    )


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
    spread=st.sampled_from([0.01, 1.0, 10.0, 300.0]),
)
def test_coded_round_trip_within_the_stated_precision(seed, n, n_forget, reset, spread) -> None:
    rng = np.random.default_rng(seed)
    c = content(n, seed=seed, reset=reset)
    p = c.T_world_body[:3, 3] + rng.normal(size=(n, 3)) * spread
    p = np.clip(p, c.T_world_body[:3, 3] - 900, c.T_world_body[:3, 3] + 900)
    numbers = rng.permutation(c.track_numbers)  # any order in, ascending out
    forget = np.zeros(0, np.int64)
    if not reset:
        forget = np.unique(rng.integers(0, 2**40, n_forget)) + 2**41  # disjoint from numbers
    c = dataclasses.replace(c, track_numbers=numbers, p_world=p, forget=forget)
    assert points_sendable(p, c.T_world_body).all()
    msg = encode_feedback(c, WireFormat.CODED)
    assert isinstance(msg, InertialFeedbackCoded) and len(msg.state) == 76
    d = decode_feedback(wire_round_trip(msg))
    order = np.argsort(numbers)
    assert d.reset == reset and d.map_id == c.map_id and d.timestamp_ns == c.timestamp_ns
    assert np.array_equal(d.track_numbers, numbers[order])
    assert np.array_equal(d.forget, forget)
    # points: <= half a step per axis, exactly what coded_points says the robot holds
    assert np.abs(d.p_world - p[order]).max(initial=0) <= POINT_STEP_M / 2 + 1e-9
    assert np.array_equal(d.p_world, coded_points(p[order], c.T_world_body))
    # state: float32
    assert np.abs(d.T_world_body[:3, :3] - c.T_world_body[:3, :3]).max() < 1e-6
    assert np.abs(d.T_world_body[:3, 3] - c.T_world_body[:3, 3]).max() < 4e-6
    for name in ("velocity_world", "bias_gyro", "bias_accel", "gravity_world"):
        want = getattr(c, name)
        assert np.abs(getattr(d, name) - want).max() <= 1e-7 * np.abs(want).max() + 1e-12
    R = d.T_world_body[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)


def test_nothing_to_say_costs_no_landmark_bytes() -> None:
    c = dataclasses.replace(
        content(0), reset=False, track_numbers=np.zeros(0, np.int64), p_world=np.zeros((0, 3))
    )
    msg = encode_feedback(c, WireFormat.CODED)
    assert msg.landmarks == b"" and len(encode_payload(msg)) < 100
    d = decode_feedback(msg)
    assert not d.reset and len(d.track_numbers) == len(d.forget) == 0


def test_coded_points_are_compact() -> None:
    msg = encode_feedback(content(200), WireFormat.CODED)
    raw = encode_feedback(content(200), WireFormat.RAW)
    assert len(encode_payload(msg)) < len(encode_payload(raw)) / 4


def test_encoder_refuses_what_the_wire_cannot_carry() -> None:
    c = content(3)
    with pytest.raises(ValueError, match="reset"):
        encode_feedback(dataclasses.replace(c, forget=np.array([1])), WireFormat.CODED)
    dup = np.array([5, 5, 6])
    with pytest.raises(ValueError, match="distinct"):
        encode_feedback(dataclasses.replace(c, track_numbers=dup), WireFormat.CODED)
    far = c.p_world.copy()
    far[0, 0] += 5000.0
    assert not points_sendable(far, c.T_world_body)[0]


# ------------------------------------------------------------------ refused input
def coded(**over) -> InertialFeedbackCoded:
    msg = encode_feedback(
        dataclasses.replace(content(30), reset=False, forget=np.array([7, 9])), WireFormat.CODED
    )
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
    monkeypatch.setattr(robot_edge, "_MAX_Q", 10)
    with pytest.raises(RemoteProtocolError, match="landmarks: a point beyond"):
        decode_feedback(msg)


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=200), state=st.binary(min_size=76, max_size=76))
def test_fuzzed_coded_fields_decode_or_raise_remote_errors(data, state) -> None:
    msg = coded()
    for bad in (dataclasses.replace(msg, landmarks=data), dataclasses.replace(msg, state=state)):
        with contextlib.suppress(RemoteProtocolError):
            decode_feedback(bad)


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
