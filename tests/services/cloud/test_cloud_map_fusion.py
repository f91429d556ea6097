"""MapFusion end to end: two robots with offset maps merge, optimise, prune and persist."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.geometry import inverse_T
from services.cloud.atlas.atlas import make_key, split_key
from services.cloud.config import (
    CloudConfig,
    MergeConfig,
    PlaceRecognitionConfig,
    VerificationConfig,
)
from services.cloud.fusion.map_fusion import MapFusion
from services.cloud.fusion.merge import yaw_of
from services.cloud.optimization.global_optimization import optimize_pose_graph
from services.cloud.store.persistence import CloudStore
from sim.cloud import circle_poses, default_camera, make_session, make_world, yaw_T


@pytest.mark.slow
def test_two_robots_merge_through_the_front_object(tmp_path):
    world = make_world(51)
    cam = default_camera()
    T_a1_world = yaw_T(np.radians(-60.0), [-1.5, 0.5, 0.0])
    s0 = make_session(world, cam, 0, circle_poses(24, turns=1.0), np.eye(4), seed=1)
    s1 = make_session(
        world, cam, 1, circle_poses(12, turns=0.5, phase=2.0), T_a1_world, seed=2, t0=50.0
    )
    cfg = CloudConfig()
    fusion = MapFusion(cam, world.idf, cfg)
    merged = []
    for kfs, mps in (s0, s1):
        for m in mps:
            fusion.add_map_point(m)
        for k in kfs:
            ev = fusion.add_keyframe(k)
            merged += [o.merge for o in ev.outcomes if o.merge is not None]
            for map_id in ev.maps_to_optimize:
                fusion.apply_optimization(
                    optimize_pose_graph(fusion.pose_graph(map_id), cfg.optimization)
                )
    assert len(merged) == 1
    T = merged[0].T_target_source
    T_exp = inverse_T(T_a1_world)
    assert np.linalg.norm(T[:3, 3] - T_exp[:3, 3]) < 0.01
    assert abs(np.degrees(yaw_of(T[:3, :3]) - yaw_of(T_exp[:3, :3]))) < 0.1
    assert fusion.atlas.maps() == [0]
    report = fusion.prune(0)
    assert report.keyframes_after < report.keyframes_before and report.connected_after
    with CloudStore(tmp_path) as store:
        store.save_all(fusion.atlas)
        restored = MapFusion(cam, world.idf, cfg, atlas=store.load())
    assert restored.atlas.keyframe_keys() == fusion.atlas.keyframe_keys()
    assert len(restored.recognizer.db) == len(fusion.atlas.keyframe_keys())


def _fuse(cfg, world, cam, sessions, shed_early=False):
    fusion = MapFusion(cam, world.idf, cfg)
    fusion.recognizer.shed_early = shed_early
    edges = []
    for kfs, mps in sessions:
        for m in mps:
            fusion.add_map_point(m)
        for k in kfs:
            ev = fusion.add_keyframe(k)
            edges += [o.loop for o in ev.outcomes]
            for map_id in ev.maps_to_optimize:
                fusion.apply_optimization(
                    optimize_pose_graph(fusion.pose_graph(map_id), cfg.optimization)
                )
    return fusion, edges


@pytest.mark.slow
def test_early_candidates_close_more_revisits_and_every_one_is_true():
    """Verified at once and confirmed by the query's covisible keyframes (ORB-SLAM3), the
    second robot's revisits are closed at more of its keyframes than when a candidate must
    be consistent over three keyframes; every constraint agrees with the ground truth. (Loops
    do not fuse their points here: a fused revisit is covisible, so the keyframes after it are
    no longer candidates, and the two settings would close different keyframes.)"""
    world = make_world(51)
    cam = default_camera()
    T_a1_world = yaw_T(np.radians(-60.0), [-1.5, 0.5, 0.0])
    poses = {0: circle_poses(24, turns=1.0), 1: circle_poses(12, turns=0.5, phase=2.0)}
    s0 = make_session(world, cam, 0, poses[0], np.eye(4), seed=1)
    s1 = make_session(world, cam, 1, poses[1], T_a1_world, seed=2, t0=50.0)
    found = {}
    no_fusion = MergeConfig(fuse_loop_points=False)
    for early in (0, 1):
        cfg = CloudConfig(
            place_recognition=PlaceRecognitionConfig(early_candidates=early), merge=no_fusion
        )
        fusion, edges = _fuse(cfg, world, cam, (s0, s1))
        assert fusion.atlas.maps() == [0]
        for e in edges:
            (ag_a, i_a), (ag_b, i_b) = split_key(e.key_a), split_key(e.key_b)
            T_true = inverse_T(poses[ag_a][i_a]) @ poses[ag_b][i_b]
            assert np.linalg.norm(e.T_a_b[:3, 3] - T_true[:3, 3]) < 0.05
        found[early] = {split_key(e.key_b) for e in edges}
    assert found[0] <= found[1]
    assert len(found[1]) >= len(found[0]) + 3
    # An overloaded cloud sheds them (services.cloud.core): as without early candidates.
    cfg = CloudConfig(place_recognition=PlaceRecognitionConfig(early_candidates=1), merge=no_fusion)
    _, edges = _fuse(cfg, world, cam, (s0, s1), shed_early=True)
    assert {split_key(e.key_b) for e in edges} == found[0]


def _scaled(session, scale):
    """A session's keyframes and map points with every position scaled by ``scale`` about the
    agent's origin (a visual-inertial map whose metric scale is off; the images agree)."""
    kfs, mps = session
    out = []
    for k in kfs:
        T = k.T_world_body.copy()
        T[:3, 3] *= scale
        out.append(dataclasses.replace(k, T_world_body=T, velocity=scale * k.velocity))
    return out, [dataclasses.replace(m, p_world=scale * m.p_world) for m in mps]


@pytest.mark.slow
def test_a_fragment_off_in_scale_merges_back_with_its_scale():
    """Agent 1's map is 12 % too small (as a map an edge began after a tracking loss). While
    its robot still uses it, its point pairs disagree with agent 0's through the verified pose
    and it does not merge; once the robot has moved on to a newer map (a fragment), it merges
    into agent 0's map with a scale, whichever of the two queries the other, its keyframes
    land at their true poses and agent 0's stay where they were."""
    world = make_world(51)
    cam = default_camera()
    T_a1_world = yaw_T(np.radians(35.0), [2.0, -1.0, 0.2])
    poses0 = circle_poses(24, turns=1.0)
    poses1 = circle_poses(12, turns=0.5, phase=np.radians(100.0))
    s0 = make_session(world, cam, 0, poses0, np.eye(4), seed=1)
    s1 = _scaled(make_session(world, cam, 1, poses1, T_a1_world, seed=2, t0=100.0), 0.88)
    strict = VerificationConfig(agreement_distance_m=0.05)  # the maps are a few metres across
    cfg = CloudConfig(verification=strict, merge=MergeConfig(min_3d_pairs=10))

    def fuse(order, superseded):
        fusion = MapFusion(cam, world.idf, cfg)
        fusion.superseded_agents = set(superseded)
        merges = []
        for kfs, mps in order:
            for m in mps:
                fusion.add_map_point(m)
            for k in kfs:
                merges += [o.merge for o in fusion.add_keyframe(k).outcomes if o.merge]
        return fusion, merges

    active, none = fuse((s1, s0), ())
    assert none == [] and len(active.atlas.maps()) == 2
    assert active.verification_counts["3D agreement"] > 0
    # The fragment as the candidate (the robot left it; another robot finds its places).
    fusion, merges = fuse((s1, s0), {1})
    atlas = fusion.atlas
    assert len(merges) == 1 and atlas.maps() == [0] and merges[0].source_map == 1
    T = merges[0].T_target_source
    assert abs(np.cbrt(np.linalg.det(T[:3, :3])) - 1 / 0.88) < 0.01
    keys0, keys1 = atlas.keyframe_keys(agent_id=0), atlas.keyframe_keys(agent_id=1)
    for i, key in enumerate(keys0):  # agent 0's map did not move
        np.testing.assert_allclose(atlas.T_map_body(key), poses0[i], atol=1e-9)
    for i, key in enumerate(keys1):  # agent 1's keyframes at their true poses in it
        T_kf = atlas.T_map_body(key)
        np.testing.assert_allclose(T_kf[:3, :3] @ T_kf[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.norm(T_kf[:3, 3] - poses1[i][:3, 3]) < 0.01
    # The merge's loop constraint, measured in the fragment's units, is in metres now.
    loop = atlas.loops()[0]
    (ag_a, i_a), (ag_b, i_b) = split_key(loop.key_a), split_key(loop.key_b)
    pose = {0: poses0, 1: poses1}
    T_true = inverse_T(pose[ag_a][i_a]) @ pose[ag_b][i_b]
    assert np.linalg.norm(loop.T_a_b[:3, 3] - T_true[:3, 3]) < 0.01
    # The fragment as the query (a message of the old map still in flight): it takes the
    # scale too; the keyframes it had then land at their true poses.
    fusion, merges = fuse((s0, s1), {1})
    assert len(merges) == 1 and merges[0].source_map == 1
    T = merges[0].T_target_source
    assert abs(np.cbrt(np.linalg.det(T[:3, :3])) - 1 / 0.88) < 0.01
    upto = split_key(merges[0].query_key)[1]
    for i in range(upto + 1):
        T_kf = fusion.atlas.T_map_body(make_key(1, i))
        assert np.linalg.norm(T_kf[:3, 3] - poses1[i][:3, 3]) < 0.01


def test_fragment_max_scale_change_must_be_a_fraction():
    with pytest.raises(ValueError, match="fragment_max_scale_change"):
        MergeConfig(fragment_max_scale_change=1.0)
