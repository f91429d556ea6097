"""Edge messages <-> cloud inputs: lossless round trip, coded words, clear errors; the durable
positions and robot names of the state directory."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.codec.types import CodecConfig
from common.links.edge_cloud import CullEvent, decode_pose_correction, encode_pose_correction
from common.protocol.arrays import pack_array
from common.vocabulary import Vocabulary
from services.cloud.atlas.atlas import Atlas
from services.cloud.fusion.uplink import (
    UplinkError,
    decode_cull_event,
    decode_keyframe_update,
    decode_map_point_update,
)
from services.cloud.store.persistence import CloudStore
from sim.cloud import (
    circle_poses,
    default_camera,
    encode_keyframe_update,
    encode_map_point_update,
    make_session,
    make_world,
)


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def session():
    world = make_world(5, n_points=1500)
    return make_session(world, default_camera(), 3, circle_poses(3, turns=0.1), np.eye(4), seed=9)


def test_keyframe_round_trip_is_lossless_up_to_the_keypoint_grid(vocab, session):
    kfs, _ = session
    kf = kfs[1]
    msg, order = encode_keyframe_update(kf, "robot-3", vocab, edge_map_id=2)
    d = decode_keyframe_update(msg, 3, vocab)
    out = d.keyframe
    assert out is not None and d.agent_name == "robot-3" and d.edge_map_id == 2
    assert np.array_equal(out.descriptors, kf.descriptors[order])
    assert np.array_equal(out.map_point_ids, kf.map_point_ids[order])
    assert np.array_equal(out.levels, kf.levels[order])
    # Keypoints snap to integer pixels of their pyramid level (1.2**level px at most).
    step = CodecConfig().level_scale(out.levels)
    assert np.all(np.abs(out.keypoints - kf.keypoints[order]) <= 0.5 * step[:, None] + 1e-9)
    # Word ids are the codec's: Vocabulary.lookup of the (lossless) descriptors.
    assert np.array_equal(out.word_ids, vocab.lookup(kf.descriptors[order]))
    assert np.allclose(out.T_world_body, kf.T_world_body)
    assert d.timestamp_ns == round(kf.timestamp * 1e9)


def test_map_points_keep_coded_feature_indices(vocab, session):
    kfs, mps = session
    inv = {}
    for k in kfs:
        _, order = encode_keyframe_update(k, "r", vocab)
        inv[k.keyframe_id] = np.argsort(order)
    msg = encode_map_point_update(mps[:20], "r", coded_index=inv)
    back = decode_map_point_update(msg, 3)
    assert [p.map_point_id for p in back] == [p.map_point_id for p in mps[:20]]
    for p_in, p_out in zip(mps[:20], back, strict=True):
        assert np.allclose(p_in.p_world, p_out.p_world)
        kf_ids = p_in.observations[:, 0]
        coded = [inv[k][i] for k, i in p_in.observations.tolist()]
        assert sorted(zip(kf_ids.tolist(), coded, strict=True)) == sorted(
            map(tuple, p_out.observations.tolist())
        )


def test_malformed_messages_name_the_field(vocab, session):
    kfs, mps = session
    msg, _ = encode_keyframe_update(kfs[0], "robot-3", vocab)
    bad_pose = dataclasses.replace(msg, T_world_body=pack_array(np.zeros(3), "<f8"))
    with pytest.raises(UplinkError, match="T_world_body"):
        decode_keyframe_update(bad_pose, 0, vocab)
    flipped = bytearray(msg.features)
    flipped[20] ^= 0xFF
    with pytest.raises(UplinkError, match="features"):
        decode_keyframe_update(dataclasses.replace(msg, features=bytes(flipped)), 0, vocab)
    short_ids = dataclasses.replace(msg, map_point_ids=pack_array(np.zeros(3), "<i8"))
    with pytest.raises(UplinkError, match="map point ids"):
        decode_keyframe_update(short_ids, 0, vocab)
    mp = encode_map_point_update(mps[:3], "robot-3")
    with pytest.raises(UplinkError, match="positions"):
        decode_map_point_update(dataclasses.replace(mp, p_world=mp.p_world[:24]), 0)
    p_nan = np.frombuffer(mp.p_world, "<f8").copy()
    p_nan[4] = np.nan
    nan_msg = dataclasses.replace(mp, p_world=p_nan.astype("<f8").tobytes())
    with pytest.raises(UplinkError, match="non-finite"):
        decode_map_point_update(nan_msg, 0)
    with pytest.raises(UplinkError, match="negative"):
        decode_cull_event(CullEvent("r", 0, pack_array(np.array([-1]), "<i8"), b""))


def test_pose_correction_round_trip():
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    T[:, :3, 3] = np.arange(9).reshape(3, 3)
    msg = encode_pose_correction("r", 4, np.array([5, 6, 7]), T, coded=False)
    ids, back = decode_pose_correction(msg)
    assert ids.tolist() == [5, 6, 7] and np.array_equal(back, T)


def test_positions_and_robot_names_persist_in_the_same_store(tmp_path):
    atlas = Atlas()
    with CloudStore(tmp_path) as store:
        store.commit(atlas, positions={"edge-a": (b"s1", 4)}, agents={0: ("r0", "edge-a", 7)})
        store.commit(atlas, positions={"edge-a": (b"s2", 1)})  # edge restarted: new stream
    with CloudStore(tmp_path) as store:
        assert store.positions() == {"edge-a": (b"s2", 1)}
        assert store.agents() == {0: ("r0", "edge-a", 7)}


def test_slightly_non_orthonormal_poses_are_repaired_and_gross_ones_rejected(vocab, session):
    kfs, _ = session
    msg, _ = encode_keyframe_update(kfs[0], "robot-3", vocab)
    T = np.array(kfs[0].T_world_body)
    drifted = T.copy()
    drifted[:3, :3] *= 1.0 + 3e-4  # off by ~6e-4: what composed float corrections can do
    for features in (msg.features, b""):  # full keyframe and pose-only update
        m = dataclasses.replace(msg, T_world_body=pack_array(drifted, "<f8"), features=features)
        R = decode_keyframe_update(m, 0, vocab).T_world_body[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
        assert np.allclose(R, T[:3, :3], atol=1e-6)
    gross = T.copy()
    gross[:3, :3] *= 1.1
    with pytest.raises(UplinkError, match="not orthonormal"):
        decode_keyframe_update(
            dataclasses.replace(msg, T_world_body=pack_array(gross, "<f8")), 0, vocab
        )
