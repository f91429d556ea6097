"""The edge's coded payloads land through their FrameAnchor (``services.cloud.fusion.rebase``).

The cloud corrects an agent's keyframes (as a pose graph would) while the edge, not having
applied that correction yet, sends a pose update and points in its old frame, anchored on a
keyframe the correction moved: they land moved by the same correction. The same payloads in
the corrected frame land where they say; without an anchor, or with one the cloud does not
have, they land through the agent's fixed transform as before.
"""

from __future__ import annotations

import numpy as np
import pytest

from common.geometry import so3_exp
from common.links.edge_cloud import KeyframePoses, MapPointUpdateCoded
from common.links.edge_cloud_payloads import (
    FrameAnchor,
    KeyframeStates,
    PointBatch,
    encode_points,
    encode_states,
)
from common.vocabulary import Vocabulary
from services.cloud.app import CloudApp
from services.cloud.atlas.atlas import make_key
from services.cloud.fusion.map_fusion import MapFusion
from services.cloud.service_config import CloudServiceConfig
from services.cloud.store.persistence import CloudStore
from sim.cloud import (
    circle_poses,
    default_camera,
    encode_keyframe_update,
    make_session,
    make_world,
)


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


def _correction() -> np.ndarray:
    """A loop's correction of the agent's frame: 4 cm and 2 degrees."""
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.0, 0.0, np.deg2rad(2.0)]))
    T[:3, 3] = [0.04, -0.01, 0.0]
    return T


def _app_with_corrected_keyframes(tmp_path, vocab):
    world = make_world(8, n_points=1500)
    kfs, _ = make_session(world, default_camera(), 0, circle_poses(4, turns=0.1), np.eye(4))
    store = CloudStore(tmp_path)
    cfg = CloudServiceConfig()
    app = CloudApp(
        MapFusion(default_camera(), vocab.idf, cfg.domain, store.load()), store, vocab, cfg
    )
    for seq, k in enumerate(kfs, 1):
        msg, order = encode_keyframe_update(k, "robot", vocab)
        app.handle("edge", msg, b"s", seq)
    free = int(np.flatnonzero(kfs[-1].map_point_ids[order] < 0)[0])  # a coded feature of
    # keyframe 3 without a map point: the new point's observation
    # The cloud corrects every keyframe by C (the agent's map frame is the atlas' here).
    C = _correction()
    keys = [make_key(0, k.keyframe_id) for k in kfs]
    app.atlas.set_keyframe_poses({key: C @ app.atlas.T_map_body(key) for key in keys})
    return app, kfs, C, len(kfs), free


def _poses(kf_id: int, T: np.ndarray, anchor: FrameAnchor | None) -> KeyframePoses:
    z = np.zeros((1, 3))
    states = KeyframeStates(np.array([kf_id]), T[None], z, z, z, anchor)
    return KeyframePoses("robot", 0, encode_states(states))


def _points(p: np.ndarray, feature: int, anchor: FrameAnchor | None) -> MapPointUpdateCoded:
    batch = PointBatch(np.array([900000]), p[None], np.array([[900000, 3, feature]]), anchor)
    return MapPointUpdateCoded("robot", 0, encode_points(batch))


def test_a_payload_in_the_frame_before_a_correction_lands_moved_by_it(tmp_path, vocab):
    app, kfs, C, seq, free = _app_with_corrected_keyframes(tmp_path, vocab)
    before = app.rebase.summary()
    try:
        # Local BA moved keyframe 3 by 1 cm in the edge's old frame; anchored on keyframe 0
        # at the pose the edge still has for it (before the correction).
        T3 = kfs[3].T_world_body.copy()
        T3[:3, 3] += [0.01, 0.0, 0.0]
        old_frame = FrameAnchor(0, kfs[0].T_world_body)
        app.handle("edge", _poses(3, T3, old_frame), b"s", seq + 1)
        key3 = make_key(0, 3)
        assert np.abs(app.atlas.T_map_body(key3) - C @ T3).max() < 1e-5
        p = kfs[3].T_world_body[:3, 3] + np.array([0.0, 0.0, 2.0])
        app.handle("edge", _points(p, free, old_frame), b"s", seq + 2)
        mp = make_key(0, 900000)
        got = app.atlas.map_point_positions(np.array([mp]))[0]
        assert np.abs(got - (C[:3, :3] @ p + C[:3, 3])).max() < 1e-3  # the 1 mm grid
        s = app.rebase.summary()
        assert s["anchored"] - before["anchored"] == 2 and s["moved"] - before["moved"] == 2
        assert s["max_m"] == pytest.approx(float(np.linalg.norm(C[:3, 3])), abs=1e-5)

        # The edge applied the correction: the same payloads in the new frame land as sent.
        new_frame = FrameAnchor(0, C @ kfs[0].T_world_body)
        app.handle("edge", _poses(3, C @ T3, new_frame), b"s", seq + 3)
        assert np.abs(app.atlas.T_map_body(key3) - C @ T3).max() < 1e-5
        assert app.rebase.summary()["moved"] - before["moved"] == 2  # the identity: not moved
    finally:
        app.close()


def test_without_an_anchor_or_with_an_unknown_one_a_payload_lands_as_sent(tmp_path, vocab):
    app, kfs, C, seq, _ = _app_with_corrected_keyframes(tmp_path, vocab)
    before = app.rebase.summary()
    try:
        T3 = kfs[3].T_world_body.copy()
        app.handle("edge", _poses(3, T3, None), b"s", seq + 1)
        assert np.abs(app.atlas.T_map_body(make_key(0, 3)) - T3).max() < 1e-5
        app.handle("edge", _poses(3, C @ T3, FrameAnchor(77, np.eye(4))), b"s", seq + 2)
        assert np.abs(app.atlas.T_map_body(make_key(0, 3)) - C @ T3).max() < 1e-5
        s = {k: v - before[k] for k, v in app.rebase.summary().items()}
        assert (s["anchored"], s["unanchored"], s["missing"]) == (0, 1, 1)
    finally:
        app.close()
