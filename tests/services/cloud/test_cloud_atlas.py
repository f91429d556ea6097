"""Atlas: ingest in any order, covisibility, spanning tree, merge bookkeeping, snapshots."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.geometry import inverse_T, transform_points
from services.cloud.atlas.atlas import Atlas, AtlasError, KeyframeInput, make_key, split_key
from services.cloud.atlas.map_types import MapPointInput
from sim.cloud import circle_poses, default_camera, make_session, make_world, yaw_T


@pytest.fixture(scope="module")
def session():
    world = make_world(3, n_points=1500)
    kfs, mps = make_session(
        world, default_camera(), 0, circle_poses(16, turns=0.5), np.eye(4), seed=2
    )
    return kfs, mps


def _atlas(kfs, mps) -> Atlas:
    """An atlas holding ``kfs``, then ``mps``."""
    atlas = Atlas()
    for k in kfs:
        atlas.add_keyframe(k)
    for m in mps:
        atlas.add_map_point(m)
    return atlas


def _expected_covisibility(kfs, mps):
    obs_of = {}
    for m in mps:
        obs_of[m.map_point_id] = {int(k) for k, _ in m.observations}
    w = {}
    for kfs_set in obs_of.values():
        s = sorted(kfs_set)
        for i, a in enumerate(s):
            for b in s[i + 1 :]:
                w[(a, b)] = w.get((a, b), 0) + 1
    return w


def _covis_dict(atlas):
    snap = atlas.snapshot()
    return {
        (split_key(a)[1], split_key(b)[1]): int(w)
        for (a, b), w in zip(
            snap.covisibility.tolist(), snap.covisibility_weight.tolist(), strict=True
        )
    }


def test_covisibility_counts_shared_points_in_any_arrival_order(session):
    kfs, mps = session
    expected = _expected_covisibility(kfs, mps)
    in_order = Atlas()
    for k in kfs:
        in_order.add_keyframe(k)
    for m in mps:
        in_order.add_map_point(m)
    reverse = Atlas()
    for m in mps[::-1]:
        reverse.add_map_point(m)
    for k in kfs[::-1]:
        reverse.add_keyframe(k)
    assert _covis_dict(in_order) == expected
    assert _covis_dict(reverse) == expected
    assert in_order.n_map_points() == len(mps)


def test_spanning_tree_is_a_tree_rooted_at_first_keyframe(session):
    kfs, mps = session
    atlas = Atlas()
    for m in mps:
        atlas.add_map_point(m)
    for k in kfs:
        atlas.add_keyframe(k)
    root = make_key(0, kfs[0].keyframe_id)
    assert atlas.spanning_parent(root) == -1
    for key in atlas.keyframe_keys():
        seen = {key}
        node = key
        while atlas.spanning_parent(node) != -1:
            node = atlas.spanning_parent(node)
            assert node not in seen, "cycle in spanning tree"
            seen.add(node)
        assert node == root


def test_snapshot_is_a_read_only_copy(session):
    kfs, mps = session
    atlas = _atlas(kfs, mps)
    snap = atlas.snapshot()
    with pytest.raises(ValueError):
        snap.T_map_body[0, 0, 3] = 5.0
    view = atlas.keyframe(snap.keyframe_keys[0])
    with pytest.raises(ValueError):
        view.map_point_keys[0] = 7
    before = snap.T_map_body.copy()
    atlas.set_keyframe_poses({int(snap.keyframe_keys[0]): yaw_T(0.3, [1.0, 0.0, 0.0])})
    np.testing.assert_array_equal(snap.T_map_body, before)
    assert snap.p_map.shape == (len(mps), 3)


def test_merge_moves_source_map_and_routes_later_keyframes():
    world = make_world(4, n_points=1500)
    cam = default_camera()
    poses = circle_poses(8, turns=0.25)
    T_a1_world = yaw_T(0.7, [1.0, -2.0, 0.3])
    k0, m0 = make_session(world, cam, 0, poses, np.eye(4), seed=1)
    k1, m1 = make_session(world, cam, 1, poses, T_a1_world, seed=2)
    atlas = Atlas()
    for k in k0 + k1[:-1]:
        atlas.add_keyframe(k)
    for m in m0 + m1:
        atlas.add_map_point(m)
    assert atlas.maps() == [0, 1]
    T_0_1 = inverse_T(T_a1_world)
    atlas.merge_maps(0, 1, T_0_1)
    assert atlas.maps() == [0]
    assert atlas.map_of_agent(1) == 0
    np.testing.assert_allclose(atlas.T_map_agent(1), T_0_1, atol=1e-12)
    for i, k in enumerate(k1[:-1]):
        np.testing.assert_allclose(
            atlas.T_map_body(make_key(1, k.keyframe_id)), poses[i], atol=1e-9
        )
    # A keyframe of agent 1 arriving after the merge lands in map 0's frame.
    key = atlas.add_keyframe(k1[-1])
    np.testing.assert_allclose(atlas.T_map_body(key), poses[-1], atol=1e-9)
    mk = make_key(1, m1[0].map_point_id)
    np.testing.assert_allclose(
        atlas.map_point_positions(np.array([mk]))[0],
        transform_points(T_0_1, m1[0].p_world)[0],
        atol=1e-9,
    )
    assert len(atlas.merges()) == 1


def test_bad_keyframe_input_names_the_field():
    with pytest.raises(AtlasError, match="descriptors"):
        KeyframeInput(
            agent_id=0,
            keyframe_id=1,
            timestamp=0.0,
            T_world_body=np.eye(4),
            keypoints=np.zeros((3, 2)),
            levels=np.zeros(3),
            descriptors=np.zeros((3, 31), np.uint8),
            word_ids=np.zeros(3),
            map_point_ids=-np.ones(3),
        )
    with pytest.raises(AtlasError, match="T_world_body"):
        KeyframeInput(
            agent_id=0,
            keyframe_id=1,
            timestamp=0.0,
            T_world_body=np.eye(3),
            keypoints=np.zeros((3, 2)),
            levels=np.zeros(3),
            descriptors=np.zeros((3, 32), np.uint8),
            word_ids=np.zeros(3),
            map_point_ids=-np.ones(3),
        )


def test_remove_keyframe_clears_observations_and_covisibility(session):
    kfs, mps = session
    atlas = _atlas(kfs, mps)
    key = make_key(0, kfs[3].keyframe_id)
    neighbours = [b for b, _ in atlas.covisible(key)]
    atlas.remove_keyframe(key)
    assert not atlas.has_keyframe(key)
    for b in neighbours:
        assert key not in dict(atlas.covisible(b))
    for mk in atlas.map_point_keys():
        assert key not in atlas.map_point_observations(mk)
    # A late update of the pruned keyframe is ignored.
    atlas.add_keyframe(kfs[3])
    assert not atlas.has_keyframe(key)


def test_a_point_whose_reference_goes_follows_the_observer_nearest_in_time(session):
    kfs, mps = session
    # Stamps shuffled: the nearest in time is then often not the oldest key (the old rule).
    order = np.random.default_rng(4).permutation(len(kfs))
    kfs = [
        dataclasses.replace(k, timestamp=kfs[j].timestamp) for k, j in zip(kfs, order, strict=True)
    ]
    atlas = _atlas(kfs, mps)
    stamp = {make_key(0, k.keyframe_id): k.timestamp for k in kfs}
    cases = 0
    for mk in atlas.map_point_keys():
        m = atlas.map_point(mk)
        rest = [k for k in m.obs_keyframes.tolist() if k != m.ref_kf]
        nearest = min(rest, key=lambda k: abs(stamp[k] - stamp[m.ref_kf]), default=None)
        if nearest is None or nearest == min(rest):
            continue  # only points where the oldest observer is not the nearest one
        ref = m.ref_kf
        atlas.remove_observation(mk, ref)
        assert atlas.map_point(mk).ref_kf == nearest, (mk, ref, rest)
        cases += 1
    assert cases >= 5


def test_moved_point_the_cloud_removed_is_not_recreated_without_observers(session):
    """An edge re-sends a point it moved (no new observation rows) after the cloud removed it
    (MBP culled it): no observer-less point appears; a new observation brings it back."""
    kfs, mps = session
    atlas = _atlas(kfs, mps)
    m = mps[0]
    key = make_key(0, m.map_point_id)
    atlas.remove_map_point(key)
    n = atlas.n_map_points()
    moved = MapPointInput(0, m.map_point_id, m.p_world + 0.05)
    atlas.add_map_point(moved)
    assert not atlas.has_map_point(key) and atlas.n_map_points() == n
    # Observations only of a pruned keyframe do not revive it either.
    pruned = int(m.observations[0, 0])
    atlas.remove_keyframe(make_key(0, pruned))
    atlas.add_map_point(MapPointInput(0, m.map_point_id, m.p_world, m.observations[:1]))
    assert not atlas.has_map_point(key)
    # A live keyframe observing it again does.
    live = MapPointInput(0, m.map_point_id, m.p_world, m.observations[1:2])
    atlas.add_map_point(live)
    assert atlas.has_map_point(key)
    assert set(atlas.map_point_observations(key)) == {make_key(0, int(m.observations[1, 0]))}


def test_retired_keyframe_follows_its_anchor_and_passes_to_an_heir(session):
    kfs, mps = session
    atlas = _atlas(kfs, mps)
    keys = atlas.keyframe_keys()
    T_map_r = atlas.T_map_body(keys[5])
    atlas.retire_keyframe(keys[5], keys[4])
    assert not atlas.has_keyframe(keys[5]) and keys[5] in atlas.removed_keyframes()
    [(key, t, T)] = atlas.retired_poses(0)
    assert key == keys[5] and t == kfs[5].timestamp
    np.testing.assert_allclose(T, T_map_r, atol=1e-12)
    # A correction of the anchor moves the retired pose with it (relative pose kept).
    shift = yaw_T(0.2, [0.5, -0.3, 0.1])
    atlas.set_keyframe_poses({keys[4]: shift @ atlas.T_map_body(keys[4])})
    np.testing.assert_allclose(atlas.retired_poses(0)[0][2], shift @ T_map_r, atol=1e-12)
    # Retiring the anchor chains the record onto the anchor's own anchor ...
    atlas.retire_keyframe(keys[4], keys[3])
    poses = {k: T for k, _, T in atlas.retired_poses(0)}
    np.testing.assert_allclose(poses[keys[5]], shift @ T_map_r, atol=1e-12)
    # ... and removing it outright (an edge cull) hands both to the keyframe nearest in time.
    atlas.remove_keyframe(keys[3])
    poses = {k: T for k, _, T in atlas.retired_poses(0)}
    assert set(poses) == {keys[4], keys[5]}
    np.testing.assert_allclose(poses[keys[5]], shift @ T_map_r, atol=1e-12)
    assert atlas.retired_poses(1) == []
    with pytest.raises(AtlasError, match="anchor"):
        atlas.retire_keyframe(keys[7], keys[7])


def test_a_retired_keyframe_between_two_kept_ones_follows_both_by_time(session):
    """A correction of one neighbour only moves the retired keyframe by the share of the way
    it lies towards that neighbour (position interpolated, rotation on the geodesic)."""
    kfs, mps = session
    atlas = _atlas(kfs, mps)
    keys = atlas.keyframe_keys()
    T_map_r = atlas.T_map_body(keys[5])
    atlas.retire_keyframe(keys[5], keys[4], other=keys[6])
    [(_, _, T)] = atlas.retired_poses(0)
    np.testing.assert_allclose(T, T_map_r, atol=1e-9)  # both agree before any correction
    w = (kfs[5].timestamp - kfs[4].timestamp) / (kfs[6].timestamp - kfs[4].timestamp)
    shift = yaw_T(0.2, [0.5, -0.3, 0.1])
    atlas.set_keyframe_poses({keys[6]: shift @ atlas.T_map_body(keys[6])})
    [(_, _, T)] = atlas.retired_poses(0)
    moved = shift @ T_map_r
    np.testing.assert_allclose(T[:3, 3], (1 - w) * T_map_r[:3, 3] + w * moved[:3, 3], atol=1e-9)
    angle = np.arccos(np.clip((np.trace(T_map_r[:3, :3].T @ T[:3, :3]) - 1) / 2, -1, 1))
    assert angle == pytest.approx(0.2 * w, abs=1e-9)
    # The other neighbour goes: the record keeps its anchor alone (rigidly, as before).
    atlas.remove_keyframe(keys[6])
    [(_, _, T)] = atlas.retired_poses(0)
    np.testing.assert_allclose(T, T_map_r, atol=1e-9)
    with pytest.raises(AtlasError, match="other"):
        atlas.retire_keyframe(keys[7], keys[8], other=keys[7])


def test_a_point_a_keyframe_names_before_it_arrives_is_no_map_point_until_it_does(session):
    """Keyframes name their points by id; a point the cloud has not received has no position,
    so it is not a map point (no point at the map's origin for verification, BA or the view)
    until it arrives, and then it has the observation the keyframe named."""
    kfs, mps = session
    kf = kfs[0]
    atlas = Atlas()
    atlas.add_keyframe(kf)
    key = make_key(0, kf.keyframe_id)
    assert atlas.n_map_points() == 0
    assert (atlas.keyframe(key).map_point_keys == -1).all()
    named = int(np.flatnonzero(kf.map_point_ids >= 0)[0])
    pid = int(kf.map_point_ids[named])
    m = next(m for m in mps if m.map_point_id == pid)
    atlas.add_map_point(MapPointInput(0, pid, m.p_world))  # no rows: the keyframe named it
    mkey = make_key(0, pid)
    assert atlas.has_map_point(mkey)
    assert atlas.map_point_observations(mkey) == {key: named}
    assert atlas.keyframe(key).map_point_keys[named] == mkey
    np.testing.assert_allclose(atlas.map_point_positions(np.array([mkey]))[0], m.p_world)
    # A keyframe removed before its named point arrives leaves nothing to link.
    other = Atlas()
    other.add_keyframe(kf)
    other.remove_keyframe(key)
    other.add_map_point(MapPointInput(0, pid, m.p_world))
    assert not other.has_map_point(mkey)


def test_a_batch_of_points_lands_as_the_same_points_one_by_one(session):
    """add_map_points places a whole update at once: the same positions, observations and
    references as adding its points one at a time, for new points (some before their
    keyframes arrive), re-sent moved ones held relative to a moved keyframe, a point listed
    twice (the last wins) and a fused one (its survivor keeps its own position)."""
    kfs, mps = session
    half = len(kfs) // 2
    rng = np.random.default_rng(7)
    moved = [dataclasses.replace(m, p_world=m.p_world + rng.normal(0, 0.01, 3)) for m in mps[::3]]
    twice = [dataclasses.replace(mps[1], p_world=mps[1].p_world + 0.05)]
    fused = [dataclasses.replace(mps[2], p_world=mps[2].p_world + 1.0)]
    feeds = [mps, moved + twice + fused]
    one, batch = Atlas(), Atlas()
    for atlas in (one, batch):
        for k in kfs[:half]:
            atlas.add_keyframe(k)
    for i, f in enumerate(feeds):
        one_keys = [one.add_map_point(m) for m in f]
        assert batch.add_map_points(f) == one_keys  # (a fused point's: its survivor's)
        if i == 0:  # the rest of the keyframes arrive, and the first one moves
            for atlas in (one, batch):
                for k in kfs[half:]:
                    atlas.add_keyframe(k)
                T = atlas.T_map_body(make_key(0, kfs[0].keyframe_id))
                atlas.set_keyframe_poses(
                    {make_key(0, kfs[0].keyframe_id): T @ yaw_T(0.1, [0.1, 0, 0])}
                )
                keep, drop = make_key(0, mps[0].map_point_id), make_key(0, mps[2].map_point_id)
                atlas.fuse_map_points(keep, drop)
    assert one.map_point_keys() == batch.map_point_keys()
    for key in one.map_point_keys():
        a, b = one.map_point(key), batch.map_point(key)
        np.testing.assert_allclose(b.p_map, a.p_map, atol=1e-12)
        np.testing.assert_array_equal(b.obs_keyframes, a.obs_keyframes)
        np.testing.assert_array_equal(b.obs_indices, a.obs_indices)
        assert b.ref_kf == a.ref_kf
    np.testing.assert_allclose(
        batch.map_point(make_key(0, mps[1].map_point_id)).p_map, twice[0].p_world, atol=1e-12
    )
    assert make_key(0, mps[2].map_point_id) not in batch.map_point_keys()  # fused into mps[0]
    assert np.linalg.norm(batch.map_point(keep).p_map - fused[0].p_world) > 0.5


def test_refresh_keyframe_sets_the_state_and_refuses_what_it_lacks(session):
    kfs, mps = session
    atlas = _atlas(kfs[:4], mps)
    atlas.unsaved.take()  # as after a store wrote it
    key = make_key(0, kfs[1].keyframe_id)
    links = atlas.keyframe(key).map_point_keys.copy()
    v = np.array([0.5, 0.0, 0.1])
    assert atlas.refresh_keyframe(0, kfs[1].keyframe_id, kfs[2].T_world_body, v, v / 10, v / 5)
    got = atlas.keyframe(key)
    np.testing.assert_allclose(got.T_map_body, kfs[2].T_world_body, atol=1e-12)
    np.testing.assert_allclose(got.velocity, v, atol=1e-12)
    np.testing.assert_allclose(got.bias_gyro, v / 10)
    np.testing.assert_allclose(got.bias_accel, v / 5)
    np.testing.assert_array_equal(got.map_point_keys, links)  # links untouched
    u = atlas.unsaved.take()
    assert u.poses == {key} and not u.keyframes and not u.points  # its state row only
    assert not atlas.refresh_keyframe(0, kfs[-1].keyframe_id, np.eye(4), v, v, v)  # not held
    with pytest.raises(AtlasError, match="malformed state"):
        atlas.refresh_keyframe(0, kfs[1].keyframe_id, np.eye(3), v, v, v)


def test_a_map_point_input_refuses_ids_a_key_cannot_hold():
    p = np.zeros(3)
    for agent, mp_id, obs in ((-1, 0, []), (0, 2**32, []), (0, 1, [[-1, 0]]), (0, 1, [[2**32, 0]])):
        with pytest.raises(AtlasError, match="bad id"):
            MapPointInput(agent, mp_id, p, np.array(obs, np.int64).reshape(-1, 2))
    with pytest.raises(AtlasError, match="bad id"):
        MapPointInput.batch(0, np.array([1]), p[None], np.array([[-3, 0]]), [0], [1])
