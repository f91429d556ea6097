"""Map backbone profiling: fewer keyframes, a connected covisibility graph, folded observations,
loop constraints moved onto the keyframes that absorb their ends."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from common.geometry import inverse_T, make_T, transform_points
from services.cloud.atlas.atlas import Atlas, make_key
from services.cloud.atlas.map_types import MapPointInput
from services.cloud.config import MbpConfig
from services.cloud.optimization.mbp import (
    INERTIAL,
    PROTECTED,
    REASONS,
    backbone,
    covisibility_components,
    loop_anchors,
    run_mbp,
    select_backbone,
)
from sim.cloud import circle_poses, default_camera, make_session, make_world

CAM = default_camera()


@pytest.fixture(scope="module")
def dense():
    world = make_world(31, n_points=3000)
    return make_session(
        world, CAM, 0, circle_poses(90, turns=1.0), np.eye(4), seed=6, dt=0.2, track_gap=200
    )


@pytest.fixture(scope="module")
def chain():
    # Sparse keyframes, as the robots send them: 24 degrees of yaw apart (the camera sees about
    # 78), consecutive keyframes share about 60 % of their points, every other one about a
    # hundred and nothing further apart: a chain-like covisibility graph.
    world = make_world(5, n_points=3000)
    return make_session(
        world, CAM, 0, circle_poses(30, turns=2.0), np.eye(4), seed=1, dt=0.5, track_gap=2
    )


def _atlas(kfs, mps):
    atlas = Atlas()
    for k in kfs:
        atlas.add_keyframe(k)
    for m in mps:
        atlas.add_map_point(m)
    return atlas


def _points(atlas, key):
    mk = atlas.keyframe(key).map_point_keys
    return set(mk[mk >= 0].tolist())


@pytest.mark.slow
def test_mbp_removes_40_percent_keeps_graph_connected_and_folds_observations(dense):
    kfs, mps = dense
    atlas = _atlas(kfs, mps)
    report = run_mbp(atlas, 0, CAM, MbpConfig())
    assert report.keyframes_before == 90
    assert report.keyframes_after <= 0.6 * report.keyframes_before
    assert report.connected_before and report.connected_after
    assert covisibility_components(atlas, atlas.keyframe_keys()) == 1
    assert report.virtual_observations > 0
    assert report.map_points_after <= report.map_points_before
    assert atlas.has_keyframe(make_key(0, 0))  # the anchor is protected
    for key in report.removed_keyframes:
        assert not atlas.has_keyframe(key)
    # Removed keyframes are retired: their poses stay (through kept anchors), unchanged.
    retired = {k: T for k, _, T in atlas.retired_poses(0)}
    assert set(retired) == set(report.removed_keyframes)
    for k in kfs:
        key = make_key(0, k.keyframe_id)
        if key in retired:
            np.testing.assert_allclose(retired[key], k.T_world_body, atol=1e-9)
    # Every surviving map point keeps at least two observations.
    for mk in atlas.map_point_keys():
        assert len(atlas.map_point_observations(mk)) >= 2
    # Virtual observations sit where their point projects (those of culled points are unbound).
    kept = [atlas.keyframe(k) for k in atlas.keyframe_keys()]
    virt = next(k for k in kept if (k.virtual & (k.map_point_keys >= 0)).any())
    i = np.flatnonzero(virt.virtual & (virt.map_point_keys >= 0))
    p_cam = transform_points(
        inverse_T(np.asarray(virt.T_map_body) @ CAM.T_body_cam),
        atlas.map_point_positions(virt.map_point_keys[i]),
    )
    uv, _ = cv2.projectPoints(p_cam, np.zeros(3), np.zeros(3), CAM.K, CAM.dist_coeffs)
    np.testing.assert_allclose(uv.reshape(-1, 2), virt.keypoints[i], atol=1e-6)


def test_sparse_chain_loses_40_percent_every_removed_keyframe_covered_and_connected(chain):
    kfs, mps = chain
    atlas = _atlas(kfs, mps)
    cfg = MbpConfig()
    keys = atlas.keyframe_keys()
    # A chain: each keyframe shares 60-75 % of its points with a neighbour (a connected
    # dominating set of such a path keeps every interior keyframe).
    share = [
        len(_points(atlas, a) & _points(atlas, b)) / len(_points(atlas, a))
        for a, b in itertools.pairwise(keys[1:])
    ]
    assert 0.6 <= np.median(share) <= 0.75
    bb = backbone(atlas, 0, cfg, keep_recent=1)
    removed = [k for k in keys if k not in bb.kept]
    assert len(removed) >= 0.4 * len(keys)
    seen_by_kept = set().union(*(_points(atlas, k) for k in bb.kept))
    for r in removed:
        own = _points(atlas, r)
        assert len(own & seen_by_kept) >= cfg.cover_ratio * len(own)
        a = bb.absorbers[r][0]
        assert a in bb.kept and len(own & _points(atlas, a)) >= cfg.min_shared
    report = run_mbp(atlas, 0, CAM, cfg, keep_recent=1)
    assert set(report.removed_keyframes) == set(removed)
    assert report.connected_after
    assert covisibility_components(atlas, atlas.keyframe_keys(), cfg.min_shared) == 1
    assert report.virtual_observations > 0


def test_every_kept_keyframe_has_a_reason(chain):
    kfs, mps = chain
    atlas = _atlas(kfs, mps)
    bb = backbone(atlas, 0, MbpConfig(), keep_recent=3)
    keys = atlas.keyframe_keys()
    assert set(bb.reasons) == set(bb.kept) and set(bb.reasons.values()) <= set(REASONS)
    for k in [keys[0], *keys[-3:]]:
        assert bb.reasons[k] == PROTECTED
    assert sum(r == PROTECTED for r in bb.reasons.values()) == 4
    assert select_backbone(atlas, 0, MbpConfig(), keep_recent=3) == set(bb.kept)
    # A second pass over what the first kept removes nothing more.
    run_mbp(atlas, 0, CAM, MbpConfig(), keep_recent=3)
    assert select_backbone(atlas, 0, MbpConfig(), keep_recent=3) == set(atlas.keyframe_keys())


def test_loop_constraints_of_removed_keyframes_move_to_their_absorbers(chain):
    kfs, mps = chain
    atlas = _atlas(kfs, mps)
    bb = backbone(atlas, 0, MbpConfig(), keep_recent=1)
    keys = atlas.keyframe_keys()
    removed = [k for k in keys if k not in bb.kept]
    r1, r2 = removed[0], removed[-1]
    anchor = loop_anchors(atlas, 0, bb.kept)
    a1, a2 = anchor[r1], anchor[r2]
    # The kept neighbour in the agent's sequence (the chain: the next or the previous key).
    assert a1 in bb.kept and abs(a1 - r1) == 1 and abs(a2 - r2) == 1
    ends = {a1, a2}
    kept_far = next(k for k in sorted(bb.kept) if k > keys[len(keys) // 2] and k not in ends)
    # Measurements a little off the current estimates, as a verified loop is.
    off = make_T(np.eye(3), [0.01, -0.02, 0.005])
    T = {k: atlas.T_map_body(k) for k in keys}
    atlas.add_loop(r1, kept_far, inverse_T(T[r1]) @ T[kept_far] @ off)
    atlas.add_loop(r1, r2, inverse_T(T[r1]) @ T[r2] @ off)
    atlas.add_loop(r1, a1, off)  # both ends collapse onto one keyframe
    report = run_mbp(atlas, 0, CAM, MbpConfig(), keep_recent=1)
    assert report.loops_moved == 2
    loops = {(e.key_a, e.key_b): e for e in atlas.loops()}
    assert set(loops) == {(a1, kept_far), (a1, a2)}
    # T_a_b = T_a_r T_r_b: the same constraint, expressed between the kept keyframes.
    want = inverse_T(T[a1]) @ T[r1] @ inverse_T(T[r1]) @ T[kept_far] @ off
    np.testing.assert_allclose(loops[(a1, kept_far)].T_a_b, want, atol=1e-9)
    want = inverse_T(T[a1]) @ T[r2] @ off @ inverse_T(T[r2]) @ T[a2]
    np.testing.assert_allclose(loops[(a1, a2)].T_a_b, want, atol=1e-9)


def test_a_moved_loop_that_repeats_a_kept_one_is_dropped(chain):
    kfs, mps = chain
    atlas = _atlas(kfs, mps)
    bb = backbone(atlas, 0, MbpConfig(), keep_recent=1)
    anchor = loop_anchors(atlas, 0, bb.kept)
    r, a = next(iter(sorted(anchor.items())))
    b = max(k for k in bb.kept if k != a)
    T_a_b = inverse_T(atlas.T_map_body(a)) @ atlas.T_map_body(b)
    atlas.add_loop(a, b, T_a_b)
    atlas.add_loop(r, b, inverse_T(atlas.T_map_body(r)) @ atlas.T_map_body(b))
    report = run_mbp(atlas, 0, CAM, MbpConfig(), keep_recent=1)
    assert report.loops_moved == 0
    [e] = atlas.loops()
    assert (e.key_a, e.key_b) == (a, b)
    np.testing.assert_array_equal(e.T_a_b, T_a_b)


def test_mbp_disabled_changes_nothing(dense):
    kfs, mps = dense
    atlas = _atlas(kfs, mps)
    report = run_mbp(atlas, 0, CAM, MbpConfig(enabled=False))
    assert report.keyframes_after == report.keyframes_before == atlas.n_keyframes()
    assert report.removed_keyframes == ()


def test_points_only_one_keyframe_sees_do_not_keep_it(chain):
    """Coverage counts the points at least two keyframes see (the full BA's points): binding
    every free keypoint of every keyframe to a point only it sees (a seventh of its points)
    changes nothing in the selection."""
    kfs, mps = chain
    atlas = _atlas(kfs, mps)
    before = backbone(atlas, 0, MbpConfig(), keep_recent=1)
    next_id = 1 + max(m.map_point_id for m in mps)
    singles = []
    for k in kfs:
        free = np.flatnonzero(atlas.keyframe(make_key(0, k.keyframe_id)).map_point_keys < 0)
        assert free.size >= 0.1 * len(k.keypoints)
        for i in free.tolist():
            singles.append(
                MapPointInput(0, next_id, np.zeros(3), np.array([[k.keyframe_id, i]], np.int64))
            )
            next_id += 1
    atlas.add_map_points(singles)
    assert sum(len(atlas.map_point_observations(m)) == 1 for m in atlas.map_point_keys()) == len(
        singles
    )
    after = backbone(atlas, 0, MbpConfig(), keep_recent=1)
    assert after.kept == before.kept and after.absorbers == before.absorbers


def test_max_interval_keeps_the_imu_chain(dense):
    """With ``max_interval_s`` the kept keyframes of an agent stay that close in time (the
    full BA's IMU factors still bridge them); the keyframes kept for it say so."""
    kfs, mps = dense  # 0.2 s apart

    def gaps(bb) -> np.ndarray:
        stamp = {make_key(0, k.keyframe_id): k.timestamp for k in kfs}
        return np.diff(sorted(stamp[k] for k in bb.kept))

    free = backbone(_atlas(kfs, mps), 0, MbpConfig(), keep_recent=1)
    assert gaps(free).max() > 1.0
    held = backbone(_atlas(kfs, mps), 0, MbpConfig(max_interval_s=0.7), keep_recent=1)
    assert gaps(held).max() <= 0.7 + 1e-9
    assert INERTIAL in held.reasons.values() and len(held.kept) > len(free.kept)
    assert len(held.kept) <= 0.5 * len(kfs)  # it still prunes
