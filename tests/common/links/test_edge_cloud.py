"""The edge -> cloud codecs (schema 2): round trips within the stated precision, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.codec.entropy import BitWriter
from common.geometry import so3_exp
from common.links.body import LinkDecodeError, seal
from common.links.edge_cloud import (
    PoseCorrection,
    PoseCorrectionCoded,
    decode_pose_correction,
    encode_pose_correction,
)
from common.links.edge_cloud_payloads import (
    POSITION_STEP_M,
    FrameAnchor,
    KeyframeStates,
    PointBatch,
    _put_ids,
    decode_point_ids,
    decode_points,
    decode_states,
    encode_point_ids,
    encode_points,
    encode_states,
)
from common.protocol.errors import RemoteProtocolError


def _states(seed: int, k: int) -> KeyframeStates:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (k, 1, 1))
    for i in range(k):
        T[i, :3, :3] = so3_exp(rng.normal(size=3))
        T[i, :3, 3] = rng.normal(size=3) * 5
    ids = rng.choice(10_000, k, replace=False)
    v, bg, ba = rng.normal(size=(k, 3)), rng.normal(size=(k, 3)) * 1e-3, rng.normal(size=(k, 3))
    return KeyframeStates(ids, T, v, bg, ba * 0.1)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 40))
def test_states_round_trip_within_float32(seed: int, k: int) -> None:
    s = _states(seed, k)
    d = decode_states(encode_states(s))
    order = np.argsort(s.keyframe_ids)
    assert np.array_equal(d.keyframe_ids, s.keyframe_ids[order])
    assert np.abs(d.T_world_body - s.T_world_body[order]).max(initial=0) < 1e-5
    assert np.allclose(d.velocity_world, s.velocity_world[order], rtol=1e-6, atol=1e-6)
    R = d.T_world_body[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-12)


def test_states_and_points_carry_their_anchor() -> None:
    s = _states(3, 4)
    anchor = FrameAnchor(123456, s.T_world_body[1])
    d = decode_states(encode_states(KeyframeStates(*_fields(s), anchor)))
    assert d.anchor is not None and d.anchor.keyframe_id == 123456
    assert np.abs(d.anchor.T_world_body - s.T_world_body[1]).max() < 1e-5
    assert decode_states(encode_states(s)).anchor is None
    batch = PointBatch(np.array([4, 9]), np.ones((2, 3)), np.array([[9, 2, 0]]), anchor)
    got = decode_points(encode_points(batch)).anchor
    assert got is not None and got.keyframe_id == 123456
    assert decode_points(encode_points(PointBatch(*_fields(batch)[:3]))).anchor is None
    with pytest.raises(ValueError, match="anchor"):
        encode_states(KeyframeStates(*_fields(s), FrameAnchor(1, np.full((4, 4), np.nan))))


def _fields(x: KeyframeStates | PointBatch) -> tuple:
    if isinstance(x, KeyframeStates):
        return x.keyframe_ids, x.T_world_body, x.velocity_world, x.bias_gyro, x.bias_accel
    return x.ids, x.p_world, x.observations


def test_version_1_states_without_an_anchor_still_decode() -> None:
    """What older recordings and edge journals hold: the rows, no anchor flag."""
    w = BitWriter()
    _put_ids(w, np.array([42]))
    row = np.array([1.0, 2.0, 3.0, 1.0, 0, 0, 0, 0.1, 0.2, 0.3, 0, 0, 0, 0, 0, 0], "<f4")
    w.put_raw(row.view("<u4").astype(np.uint64), 32, "state")
    d = decode_states(seal(1, w))
    assert d.keyframe_ids.tolist() == [42] and d.anchor is None
    assert np.allclose(d.T_world_body[0, :3, 3], [1, 2, 3])
    with pytest.raises(LinkDecodeError, match="version 9, expected 1 or 2"):
        decode_states(seal(9, w))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(-1, 2**40), max_size=300))
def test_point_ids_round_trip_exactly(ids: list[int]) -> None:
    a = np.array(ids, np.int64)
    assert np.array_equal(decode_point_ids(encode_point_ids(a)), a)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.integers(0, 300), st.integers(0, 600))
def test_points_round_trip_on_the_grid(seed: int, n: int, n_obs: int) -> None:
    rng = np.random.default_rng(seed)
    ids = rng.choice(1_000_000, n, replace=False)
    p = rng.normal(size=(n, 3)) * 3
    obs = np.zeros((0, 3), np.int64)
    if n:
        obs = np.stack(
            [rng.choice(ids, n_obs), rng.integers(0, 30, n_obs), rng.integers(0, 1000, n_obs)], 1
        )
        _, first = np.unique(obs[:, 1:], axis=0, return_index=True)
        obs = obs[np.sort(first)]
    d = decode_points(encode_points(PointBatch(ids, p, obs)))
    order = np.argsort(ids)
    assert np.array_equal(d.ids, ids[order])
    assert np.abs(d.p_world - p[order]).max(initial=0) <= POSITION_STEP_M / 2 + 1e-9
    want = obs[np.lexsort((obs[:, 2], obs[:, 1]))]
    assert np.array_equal(d.observations, want)


def test_points_of_a_typical_batch_cost_far_less_than_raw() -> None:
    rng = np.random.default_rng(3)
    ids = np.arange(5000, 5600)
    p = rng.normal(size=(600, 3)) * 2
    obs = np.stack([ids, np.full(600, 40), np.sort(rng.choice(1000, 600, replace=False))], 1)
    coded = encode_points(PointBatch(ids, p, obs))
    raw = 600 * (8 + 24) + 600 * 24
    assert len(coded) * 4 < raw, (len(coded), raw)


@pytest.mark.parametrize(
    "codec",
    [
        lambda: (encode_states(_states(1, 5)), decode_states),
        lambda: (encode_point_ids(np.array([-1, 4, 9, -1, 2])), decode_point_ids),
        lambda: (
            encode_points(PointBatch(np.arange(4), np.zeros((4, 3)), np.array([[1, 2, 3]]))),
            decode_points,
        ),
    ],
)
def test_damaged_payloads_are_the_peers_fault(codec) -> None:
    data, decode = codec()
    flipped = data[:5] + bytes([data[5] ^ 1]) + data[6:]
    for bad in (data[:-1], data[:3], b"", bytes([data[0] ^ 0x55]) + data[1:], flipped):
        with pytest.raises(RemoteProtocolError):
            decode(bad)
    assert issubclass(LinkDecodeError, RemoteProtocolError)


def test_encoders_refuse_inconsistent_input() -> None:
    with pytest.raises(ValueError):
        encode_points(PointBatch(np.array([1, 1]), np.zeros((2, 3)), np.zeros((0, 3))))
    with pytest.raises(ValueError):
        encode_points(PointBatch(np.array([1]), np.zeros((1, 3)), np.array([[7, 0, 0]])))
    with pytest.raises(ValueError):
        encode_point_ids(np.array([-2]))


def test_pose_corrections_round_trip_in_both_forms() -> None:
    s = _states(4, 6)
    for coded in (True, False):
        msg = encode_pose_correction("r", 2, s.keyframe_ids, s.T_world_body, coded)
        assert isinstance(msg, PoseCorrectionCoded if coded else PoseCorrection)
        ids, T = decode_pose_correction(msg)
        order = np.argsort(s.keyframe_ids) if coded else np.arange(6)
        assert np.array_equal(ids, s.keyframe_ids[order])
        assert np.abs(T - s.T_world_body[order]).max() < (1e-5 if coded else 1e-15)
    coded_msg = encode_pose_correction("r", 2, s.keyframe_ids, s.T_world_body)
    raw_msg = encode_pose_correction("r", 2, s.keyframe_ids, s.T_world_body, coded=False)
    assert len(coded_msg.poses) * 3 < len(raw_msg.T_world_body) + len(raw_msg.keyframe_ids)
    with pytest.raises(RemoteProtocolError):
        decode_pose_correction(PoseCorrectionCoded("r", 2, coded_msg.poses[:-2]))
    with pytest.raises(RemoteProtocolError):
        bad = PoseCorrection("r", 2, raw_msg.keyframe_ids[:8], raw_msg.T_world_body)
        decode_pose_correction(bad)
