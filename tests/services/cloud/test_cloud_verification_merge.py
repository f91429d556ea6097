"""Geometric verification (accept true revisits, reject wrong places and perceptual aliasing)
and map merging to the right transform."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.geometry import inverse_T, so3_log
from services.cloud.atlas.atlas import Atlas, make_key
from services.cloud.config import (
    AlignmentMode,
    MergeConfig,
    PlaceRecognitionConfig,
    VerificationConfig,
)
from services.cloud.fusion.merge import MergeError, align_points, apply_match, yaw_of
from services.cloud.fusion.place_recognition import KeyframeDatabase, PlaceRecognizer
from services.cloud.fusion.verification import covisible_agreement, match_by_words, verify_candidate
from sim.cloud import (
    World,
    circle_poses,
    default_camera,
    make_session,
    make_world,
    yaw_T,
)

CAM = default_camera()


@pytest.fixture(scope="module")
def world():
    return make_world(11)


def _atlas(*sessions):
    atlas = Atlas()
    for kfs, mps in sessions:
        for k in kfs:
            atlas.add_keyframe(k)
        for m in mps:
            atlas.add_map_point(m)
    return atlas


def test_word_guided_matching_respects_groups_distance_and_uniqueness():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    b = a.copy()
    b[4] = rng.integers(0, 256, 32, dtype=np.uint8)  # unrelated descriptor
    ga = np.array([0, 1, 2, 3, 4])
    gb = np.array([0, 1, 9, 3, 4])  # keypoint 2 is in another word
    m = match_by_words(a, ga, b, gb, max_hamming=50, ratio=0.75)
    assert sorted(map(tuple, m.tolist())) == [(0, 0), (1, 1), (3, 3)]
    # Two query descriptors competing for one candidate: only the closer one survives.
    a2 = np.stack([a[0], a[0] ^ np.uint8(1)])
    m2 = match_by_words(a2, np.zeros(2), a[:1], np.zeros(1), 50, 0.75)
    assert m2.tolist() == [[0, 0]]


def _match_by_words_brute(desc_a, group_a, desc_b, group_b, max_hamming, ratio):
    """The definition, one query at a time over every candidate (the dense reference)."""
    found = []
    for i in range(desc_a.shape[0]):
        d = [
            (int(np.unpackbits(desc_a[i] ^ desc_b[j]).sum()), j)
            for j in range(desc_b.shape[0])
            if group_b[j] == group_a[i]
        ]
        if not d:
            continue
        d.sort()
        d1, j = d[0]
        if d1 <= max_hamming and (len(d) == 1 or d1 < ratio * d[1][0]):
            found.append((j, d1, i))
    found.sort()  # one-to-one: per candidate the closest query, then the lowest index
    out, taken = [], set()
    for j, _, i in found:
        if j not in taken:
            taken.add(j)
            out.append((i, j))
    return sorted(out)


@pytest.mark.parametrize("seed", range(5))
def test_word_guided_matching_equals_the_dense_definition(seed):
    """Near-duplicates, ties and groups of every size against the one-by-one definition."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    a = base[rng.integers(0, 40, 300)] ^ (rng.random((300, 32)) < 0.02).astype(np.uint8)
    b = base[rng.integers(0, 40, 200)] ^ (rng.random((200, 32)) < 0.02).astype(np.uint8)
    ga, gb = rng.integers(0, 25, 300), rng.integers(0, 25, 200)
    m = match_by_words(a, ga, b, gb, max_hamming=50, ratio=0.8)
    assert sorted(map(tuple, m.tolist())) == _match_by_words_brute(a, ga, b, gb, 50, 0.8)
    assert len(m) > 10


def test_revisit_is_verified_with_the_true_relative_pose(world):
    poses = circle_poses(40, turns=2.0)
    kfs, mps = make_session(world, CAM, 0, poses, np.eye(4), seed=3, dt=1.0)
    atlas = _atlas((kfs, mps))
    q, c = make_key(0, 25), make_key(0, 5)
    res = verify_candidate(atlas, q, c, CAM, VerificationConfig())
    assert res.accepted, res.reason
    assert res.n_inliers >= 100
    T_true = inverse_T(poses[5]) @ poses[25]
    assert np.linalg.norm(res.T_cbody_qbody[:3, 3] - T_true[:3, 3]) < 0.02
    assert np.degrees(np.linalg.norm(so3_log(res.T_cbody_qbody[:3, :3].T @ T_true[:3, :3]))) < 0.3


def test_a_different_place_is_rejected(world):
    poses = circle_poses(40, turns=2.0)
    kfs, mps = make_session(world, CAM, 0, poses, np.eye(4), seed=3, dt=1.0)
    atlas = _atlas((kfs, mps))
    res = verify_candidate(atlas, make_key(0, 30), make_key(0, 0), CAM, VerificationConfig())
    assert not res.accepted  # opposite wall: a half turn apart
    assert "matches" in res.reason


def test_perceptual_aliasing_is_rejected_by_geometry(world):
    """Agent 1 flies in a room whose landmarks look exactly like agent 0's (same descriptors
    and words) but sit elsewhere: BoW and descriptors agree, geometry must not."""
    rng = np.random.default_rng(5)
    perm = rng.permutation(world.points.shape[0])
    alias = World(world.points[perm], world.descriptors, world.words, world.n_words, world.idf)
    poses = circle_poses(12, turns=0.3)
    s0 = make_session(world, CAM, 0, poses, np.eye(4), seed=1)
    s1 = make_session(alias, CAM, 1, poses, np.eye(4), seed=2, t0=100.0)
    atlas = _atlas(s0, s1)
    results = [
        verify_candidate(atlas, make_key(1, i), make_key(0, i), CAM, VerificationConfig())
        for i in range(2, 10, 3)
    ]
    assert not any(r.accepted for r in results), [r.reason for r in results]
    # Many descriptor matches were found, so the rejection really is geometric.
    assert all("word matches" not in r.reason for r in results)


def test_align_points_recovers_each_mode():
    rng = np.random.default_rng(2)
    p = rng.normal(size=(50, 3))
    T = yaw_T(0.4, [1.0, 2.0, -0.5])
    np.testing.assert_allclose(
        align_points(p, p @ T[:3, :3].T + T[:3, 3], AlignmentMode.YAW_TRANSLATION), T, atol=1e-10
    )
    from common.geometry import so3_exp

    T6 = np.eye(4)
    T6[:3, :3], T6[:3, 3] = so3_exp([0.2, -0.1, 0.5]), [0.3, 0.0, 1.0]
    np.testing.assert_allclose(
        align_points(p, p @ T6[:3, :3].T + T6[:3, 3], AlignmentMode.SE3), T6, atol=1e-10
    )
    T7 = T6.copy()
    T7[:3, :3] *= 1.7
    np.testing.assert_allclose(
        align_points(p, p @ T7[:3, :3].T + T7[:3, 3], AlignmentMode.SIM3), T7, atol=1e-10
    )
    with pytest.raises(MergeError):
        align_points(p[:2], p[:2], AlignmentMode.SE3)
    line = np.outer(np.arange(6.0), [1.0, 0.5, 0.2])
    with pytest.raises(MergeError, match="collinear"):
        align_points(line, line, AlignmentMode.SIM3)


def test_two_maps_with_known_offset_merge_to_the_right_transform(world):
    T_a1_world = yaw_T(np.radians(35.0), [2.0, -1.0, 0.2])
    poses0 = circle_poses(24, turns=1.0)
    poses1 = circle_poses(12, turns=0.5, phase=np.radians(100.0))
    s0 = make_session(world, CAM, 0, poses0, np.eye(4), seed=1)
    s1 = make_session(world, CAM, 1, poses1, T_a1_world, seed=2, t0=100.0)
    atlas = _atlas(s0, s1)
    pr = PlaceRecognizer(KeyframeDatabase(world.idf), PlaceRecognitionConfig())
    for key in atlas.keyframe_keys(agent_id=0):
        pr.detect(atlas, key)
        pr.add(atlas, key)
    merge = None
    n_points_before = atlas.n_map_points()
    for key in atlas.keyframe_keys(agent_id=1):
        for cand in pr.detect(atlas, key):
            if atlas.map_id_of_keyframe(key) == atlas.map_id_of_keyframe(cand.candidate_key):
                continue
            res = verify_candidate(atlas, key, cand.candidate_key, CAM, VerificationConfig())
            if res.accepted:
                merge = apply_match(atlas, res, MergeConfig()).merge
        pr.add(atlas, key)
        if merge is not None:
            break
    assert merge is not None, "maps were not merged"
    T_expected = inverse_T(T_a1_world)  # agent 1's map frame -> agent 0's (= world)
    T = merge.T_target_source
    assert np.linalg.norm(T[:3, 3] - T_expected[:3, 3]) < 0.01
    assert abs(np.degrees(yaw_of(T[:3, :3]) - yaw_of(T_expected[:3, :3]))) < 0.1
    assert atlas.maps() == [0] and atlas.map_of_agent(1) == 0
    # Agent 1's keyframes now sit at their true poses in map 0, duplicates were fused.
    for i, key in enumerate(atlas.keyframe_keys(agent_id=1)):
        assert np.linalg.norm(atlas.T_map_body(key)[:3, 3] - poses1[i][:3, 3]) < 0.02
    assert merge.fused_points > 100
    assert atlas.n_map_points() == n_points_before - merge.fused_points
    assert len(atlas.loops()) == 1 and atlas.loops()[0].inter_agent


def test_rejected_match_cannot_be_merged(world):
    poses = circle_poses(40, turns=2.0)
    atlas = _atlas(make_session(world, CAM, 0, poses[:32], np.eye(4), seed=3, dt=1.0))
    res = verify_candidate(atlas, make_key(0, 30), make_key(0, 0), CAM, VerificationConfig())
    with pytest.raises(MergeError, match="rejected"):
        apply_match(atlas, res, MergeConfig())


def test_covisible_keyframes_confirm_a_true_revisit_and_not_a_wrong_pose(world):
    """ORB-SLAM3's covisibility check: the query's covisible keyframes, each at its own pose,
    see the candidate group's points where the verified transform puts them; the same check
    with that transform 2 degrees off (about the map's origin) finds no agreeing keyframe."""
    poses = circle_poses(40, turns=2.0)
    kfs, mps = make_session(world, CAM, 0, poses, np.eye(4), seed=3, dt=1.0)
    atlas = _atlas((kfs, mps))
    cfg = VerificationConfig()
    res = verify_candidate(atlas, make_key(0, 25), make_key(0, 5), CAM, cfg)
    assert res.accepted, res.reason
    agree, checked = covisible_agreement(atlas, res, CAM, cfg)
    assert agree == checked == cfg.covisible_agree  # stops once enough agree
    off = yaw_T(np.radians(2.0), [0.0, 0.0, 0.0])
    wrong = dataclasses.replace(res, T_cmap_qmap=off @ res.T_cmap_qmap)
    assert covisible_agreement(atlas, wrong, CAM, cfg) == (0, cfg.covisible_checks - 1)


def test_a_loop_within_one_map_fuses_its_verified_point_pairs(world):
    """A revisit (the second lap's points are new: the track broke) fuses the verified pairs
    into the first lap's points, each pair one landmark; ``fuse_loop_points`` off only adds the
    loop constraint."""
    poses = circle_poses(40, turns=2.0)
    session = make_session(world, CAM, 0, poses, np.eye(4), seed=3, dt=1.0)
    q, c = make_key(0, 25), make_key(0, 5)

    def first_lap_points_of_q(atlas: Atlas) -> int:
        mk = atlas.keyframe(q).map_point_keys
        return sum(
            any(k <= make_key(0, 19) for k in atlas.map_point_observations(m))
            for m in mk[mk >= 0].tolist()
        )

    off = _atlas(session)
    res = verify_candidate(off, q, c, CAM, VerificationConfig())
    assert res.accepted, res.reason
    n_points = off.n_map_points()
    assert first_lap_points_of_q(off) == 0  # not closed in the map yet
    out = apply_match(off, res, MergeConfig(fuse_loop_points=False))
    assert out.fused_points == 0 and off.n_map_points() == n_points and len(off.loops()) == 1

    atlas = _atlas(session)
    pairs = res.point_pairs
    distance = np.linalg.norm(
        atlas.map_point_positions(pairs[:, 0]) - atlas.map_point_positions(pairs[:, 1]), axis=1
    )
    assert np.all(distance < 0.05)  # each pair one landmark (no drift here)
    out = apply_match(atlas, res, MergeConfig())
    assert out.merge is None and len(atlas.loops()) == 1
    assert out.fused_points >= 50 and atlas.n_map_points() == n_points - out.fused_points
    assert not any(atlas.has_map_point(a) for a in pairs[:, 0].tolist())
    assert first_lap_points_of_q(atlas) >= 50  # the two laps now share points


def test_align_points_recovers_yaw_translation_and_scale():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(50, 3))
    T = yaw_T(-0.7, [0.5, -1.0, 0.3])
    T[:3, :3] *= 0.93
    q = p @ T[:3, :3].T + T[:3, 3]
    mode = AlignmentMode.YAW_TRANSLATION_SCALE
    np.testing.assert_allclose(align_points(p, q, mode), T, atol=1e-10)
    rigid = align_points(p, q, AlignmentMode.YAW_TRANSLATION)
    assert abs(np.linalg.det(rigid[:3, :3]) - 1.0) < 1e-12  # the 4-DoF fit stays rigid
    with pytest.raises(MergeError, match="coincide"):
        align_points(np.ones((5, 3)), q[:5], mode)
