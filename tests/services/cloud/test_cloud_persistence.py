"""SQLite persistence: a restart resumes with the same keyframes, points, merges, sequences."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.geometry import inverse_T, make_T
from services.cloud.atlas.atlas import Atlas, make_key
from services.cloud.store.persistence import CloudStore, PersistenceError
from sim.cloud import circle_poses, default_camera, make_session, make_world, yaw_T


def _covis(atlas):
    snap = atlas.snapshot()
    return {
        tuple(p): int(w)
        for p, w in zip(snap.covisibility.tolist(), snap.covisibility_weight.tolist(), strict=True)
    }


def _two_agents(world_seed, n_poses, turns, T_a1, seeds):
    """Two agents' sessions over one world: agent 0 in the world frame, agent 1 in ``T_a1``."""
    world, cam = make_world(world_seed, n_points=1500), default_camera()
    poses = circle_poses(n_poses, turns=turns)
    return (
        make_session(world, cam, 0, poses, np.eye(4), seed=seeds[0]),
        make_session(world, cam, 1, poses, T_a1, seed=seeds[1]),
    )


def test_restart_resumes_with_the_same_state(tmp_path):
    T_a1 = yaw_T(0.5, [1.0, 0.0, 0.0])
    (k0, m0), (k1, m1) = _two_agents(41, 10, 0.3, T_a1, seeds=(1, 2))
    atlas = Atlas()
    with CloudStore(tmp_path) as store:
        # Batches of messages from two edges, each committed before its acknowledgement.
        for seq, (k, mps) in enumerate([(k0[:5], m0), (k0[5:], [])], start=1):
            keys = [atlas.add_keyframe(x) for x in k]
            pkeys = [atlas.add_map_point(x) for x in mps]
            store.commit(atlas, keys, pkeys, {"edge-a": seq})
        keys = [atlas.add_keyframe(x) for x in k1]
        pkeys = [atlas.add_map_point(x) for x in m1]
        store.commit(atlas, keys, pkeys, {"edge-b": 7})
        atlas.merge_maps(0, 1, inverse_T(T_a1))
        atlas.add_loop(
            atlas.keyframe_keys(agent_id=0)[2], atlas.keyframe_keys(agent_id=1)[2], np.eye(4)
        )
        atlas.remove_keyframe(atlas.keyframe_keys(agent_id=0)[4])
        k = atlas.keyframe_keys(agent_id=1)
        atlas.retire_keyframe(k[6], k[5], other=k[7])  # MBP's removal
        store.save_all(atlas)
    with CloudStore(tmp_path) as store:
        restored = store.load()
        assert store.last_sequences() == {"edge-a": 2, "edge-b": 7}
    assert restored.keyframe_keys() == atlas.keyframe_keys()
    assert restored.map_point_keys() == atlas.map_point_keys()
    for key in atlas.keyframe_keys():
        a, b = atlas.keyframe(key), restored.keyframe(key)
        np.testing.assert_array_equal(a.T_map_body, b.T_map_body)
        np.testing.assert_array_equal(a.descriptors, b.descriptors)
        np.testing.assert_array_equal(a.map_point_keys, b.map_point_keys)
    assert _covis(restored) == _covis(atlas)
    assert restored.map_of_agent(1) == 0
    np.testing.assert_allclose(restored.T_map_agent(1), inverse_T(T_a1))
    assert len(restored.merges()) == 1 and len(restored.loops()) == 1
    assert restored.removed_keyframes() == atlas.removed_keyframes()
    [(key, t, T)] = restored.retired_poses(1)
    assert (key, t) == atlas.retired_poses(1)[0][:2]
    np.testing.assert_allclose(T, atlas.retired_poses(1)[0][2], atol=1e-12)
    # The blend with the other neighbour came back too: moving it moves the record alike.
    k7 = atlas.keyframe_keys(agent_id=1)[6]
    for a in (atlas, restored):
        a.set_keyframe_poses({k7: yaw_T(0.1, [0.2, 0.0, 0.0]) @ a.T_map_body(k7)})
    np.testing.assert_allclose(restored.retired_poses(1)[0][2], atlas.retired_poses(1)[0][2])
    assert not np.allclose(restored.retired_poses(1)[0][2], T, atol=1e-3)
    # A late update of agent 1 still lands in the merged frame after the restart.
    key = restored.add_keyframe(k1[-1])
    np.testing.assert_allclose(restored.T_map_body(key), atlas.T_map_body(key), atol=1e-12)


def test_sequences_never_go_backwards_and_failed_commit_rolls_back(tmp_path):
    atlas = Atlas()
    with CloudStore(tmp_path) as store:
        store.commit(atlas, edge_sequences={"e": 5})
        store.commit(atlas, edge_sequences={"e": 3})
        assert store.last_sequences() == {"e": 5}
        with pytest.raises(TypeError):
            store.commit(atlas, keyframes=[object()], edge_sequences={"e": 9})
        assert store.last_sequences() == {"e": 5}


def test_corrupt_state_file_is_reported(tmp_path):
    (tmp_path / "cloud.sqlite").write_bytes(b"this is not a database" * 100)
    with pytest.raises(PersistenceError, match=r"cloud\.sqlite"):
        CloudStore(tmp_path)


def test_a_full_database_reports_itself_not_a_failed_rollback(tmp_path):
    """Issue 18: SQLite rolls a transaction back by itself when the disk is full; the error
    the cloud logs (and retries on) is that one, not 'cannot rollback'. What was committed
    before stays, and a commit after space is freed succeeds."""
    import sqlite3

    world = make_world(43, n_points=800)
    keyframes, points = make_session(world, default_camera(), 0, circle_poses(8), np.eye(4), seed=3)
    atlas = Atlas()
    with CloudStore(tmp_path) as store:
        store.commit(atlas, [atlas.add_keyframe(keyframes[0])], [], {"e": 1})
        pages = store._db.execute("PRAGMA page_count").fetchone()[0]
        store._db.execute(f"PRAGMA max_page_count = {pages}")  # the disk is full from here on
        keys = [atlas.add_keyframe(k) for k in keyframes[1:]]
        pkeys = [atlas.add_map_point(p) for p in points]
        with pytest.raises(sqlite3.OperationalError, match="full"):
            store.commit(atlas, keys, pkeys, {"e": 2})
        assert not store._db.in_transaction and store.last_sequences() == {"e": 1}
        store._db.execute(f"PRAGMA max_page_count = {100 * pages}")  # space again
        store.commit(atlas, keys, pkeys, {"e": 2})
        assert store.last_sequences() == {"e": 2}


def test_a_schema_5_state_dir_is_migrated_to_agents_keyed_by_edge(tmp_path):
    """A state dir written before several edges (schema 5: agent_names UNIQUE(name, edge_map))
    opens with its agents kept, and then holds the same robot and map on two edges."""
    import sqlite3

    from services.cloud.store.persistence import DB_NAME, SCHEMA_VERSION

    db = sqlite3.connect(tmp_path / DB_NAME)
    db.executescript(
        "CREATE TABLE meta (name TEXT PRIMARY KEY, value INTEGER NOT NULL);"
        "INSERT INTO meta VALUES ('schema', 5);"
        "CREATE TABLE agent_names (agent INTEGER PRIMARY KEY, name TEXT NOT NULL,"
        " edge_id TEXT NOT NULL, edge_map INTEGER NOT NULL, UNIQUE (name, edge_map));"
        "INSERT INTO agent_names VALUES (0, 'r0', 'edge', 0), (1, 'r1', 'edge', 0);"
    )
    db.commit()
    db.close()
    with CloudStore(tmp_path) as store:
        assert store.agents() == {0: ("r0", "edge", 0), 1: ("r1", "edge", 0)}
        store.commit(Atlas(), agents={2: ("r0", "edge-b", 0)})  # refused by the old key
        assert store.agents()[2] == ("r0", "edge-b", 0)
    with CloudStore(tmp_path) as store:
        assert len(store.agents()) == 3
    db = sqlite3.connect(tmp_path / DB_NAME)
    assert db.execute("SELECT value FROM meta WHERE name='schema'").fetchone() == (SCHEMA_VERSION,)
    with pytest.raises(sqlite3.IntegrityError):  # the new key is enforced
        db.execute("INSERT INTO agent_names VALUES (3, 'r0', 'edge-b', 0, 0)")
    db.close()


def _same_store(a, b):
    """Two directories hold the same atlas (positions to rounding: a point is stored in its
    reference keyframe's frame, and the two wrote it under different poses of it)."""
    (kfs_a, mps_a, st_a, p_a), (kfs_b, mps_b, st_b, p_b) = _stored(a), _stored(b)
    same = (kfs_a, mps_a, st_a) == (kfs_b, mps_b, st_b) and p_a.keys() == p_b.keys()
    return same and all(np.allclose(p, p_b[k], rtol=0, atol=1e-9) for k, p in p_a.items())


def _stored(path):
    """Everything a store directory holds, as the atlas it loads into (plain comparable data;
    the map points' positions apart)."""
    with CloudStore(path) as store:
        atlas = store.load()
    kfs = {}
    for key in atlas.keyframe_keys():
        v = atlas.keyframe(key)
        arrays = (v.T_map_body, v.velocity, v.bias_gyro, v.bias_accel, v.descriptors)
        arrays += (v.keypoints, v.levels, v.word_ids, v.map_point_keys, v.virtual)
        kfs[key] = (v.map_id, v.timestamp, *(np.asarray(x).tobytes() for x in arrays))
    mps = {}
    for key in atlas.map_point_keys():
        m = atlas.map_point(key)
        mps[key] = (m.map_id, m.ref_kf, m.obs_keyframes.tobytes(), m.obs_indices.tobytes())
    st = atlas.state()
    positions = {key: atlas.map_point(key).p_map for key in atlas.map_point_keys()}
    return (
        kfs,
        mps,
        (st.map_of_agent, len(st.merges), len(st.loops), st.removed_keyframes, dict(st.aliases)),
        positions,
    )


@pytest.mark.slow
def test_incremental_saves_store_what_a_whole_save_stores(tmp_path):
    """After its first whole write, save_all writes only what the atlas changed since (and the
    atlas a store loaded starts as stored): after every kind of change, the directory holds
    exactly what one whole save of the same atlas into a fresh directory holds."""
    T_a1 = yaw_T(0.4, [0.5, 0.2, 0.0])
    (k0, m0), (k1, m1) = _two_agents(43, 12, 0.35, T_a1, seeds=(3, 4))
    live = tmp_path / "live"
    atlas = Atlas()
    store = CloudStore(live)
    checks = 0

    def check(name):
        nonlocal checks
        whole = tmp_path / f"whole-{checks}"
        with CloudStore(whole) as fresh:
            fresh.save_all(atlas)
        assert _same_store(live, whole), name
        checks += 1

    keys = [atlas.add_keyframe(x) for x in k0[:6]]
    store.commit(atlas, keys, [atlas.add_map_point(x) for x in m0])
    store.save_all(atlas)  # the first: whole
    keys = [atlas.add_keyframe(x) for x in k0[6:]] + [atlas.add_keyframe(x) for x in k1]
    pkeys = [atlas.add_map_point(x) for x in m1]
    store.commit(atlas, keys[:3], pkeys[:10])  # part of it committed, the rest unsaved
    store.save_all(atlas)
    check("new keyframes and points")
    atlas.merge_maps(0, 1, inverse_T(T_a1))
    store.save_all(atlas)
    check("merge")
    k = atlas.keyframe_keys(agent_id=1)
    atlas.fuse_map_points(atlas.map_point_keys()[0], atlas.map_point_keys()[1])
    atlas.add_loop(k[1], atlas.keyframe_keys(agent_id=0)[1], np.eye(4))
    store.save_all(atlas)
    check("fused points, loop")
    moved = {key: yaw_T(0.01, [0.01, 0.0, 0.0]) @ atlas.T_map_body(key) for key in k[:5]}
    atlas.set_keyframe_poses(moved)  # an optimisation: poses and the points that follow them
    store.commit_poses(atlas, k[:2], [])  # written in part
    atlas.fuse_map_points(atlas.map_point_keys()[2], atlas.map_point_keys()[3])
    store.commit(atlas)  # the aliases since the last write: from the atlas' log
    atlas.fuse_map_points(atlas.map_point_keys()[2], atlas.map_point_keys()[4])
    store.save_all(atlas)
    check("optimised poses, more fused points")
    atlas.set_map_point_positions({atlas.map_point_keys()[5]: np.array([1.0, 2.0, 3.0])})
    atlas.remove_keyframe(atlas.keyframe_keys(agent_id=0)[3])
    atlas.retire_keyframe(k[7], k[6])
    v = atlas.keyframe(k[2])
    atlas.add_virtual_observations(
        k[2],
        v.keypoints[:2],
        v.levels[:2],
        v.descriptors[:2],
        v.word_ids[:2],
        np.array(atlas.map_point_keys()[-2:]),
    )
    store.save_all(atlas)
    check("MBP: removed, retired, virtual observations")
    store.close()
    store = CloudStore(live)
    atlas = store.load()  # as stored: its changes from here on are the unsaved ones
    atlas.remove_map_point(atlas.map_point_keys()[7])
    atlas.add_keyframe(k1[-1])
    atlas.fuse_map_points(atlas.map_point_keys()[8], atlas.map_point_keys()[9])
    store.save_all(atlas)
    check("after a restart")
    assert len(atlas.state().aliases) == 4
    store.close()


@pytest.mark.parametrize("how", ["save_all", "commit"])
def test_what_a_failed_write_took_is_written_by_the_next_one(tmp_path, monkeypatch, how):
    """A write that fails rolls back and gives the changes it took back to the atlas: the
    next write (a whole save_all, or a commit naming nothing) stores them."""
    world = make_world(44, n_points=800)
    k0, m0 = make_session(world, default_camera(), 0, circle_poses(6, turns=0.2), np.eye(4))
    atlas = Atlas()
    with CloudStore(tmp_path / "live") as store:
        store.save_all(atlas)
        for x in k0:
            atlas.add_keyframe(x)
        for x in m0:
            atlas.add_map_point(x)
        with monkeypatch.context() as m:
            m.setattr(store, "_write_links", lambda *a, **k: 1 / 0)
            with pytest.raises(ZeroDivisionError):
                getattr(store, how)(atlas)  # rolled back
        assert atlas.unsaved.keyframes and atlas.unsaved.points
        getattr(store, how)(atlas)
        assert not atlas.unsaved.keyframes and not atlas.unsaved.points
    with CloudStore(tmp_path / "whole") as fresh:
        fresh.save_all(atlas)
    assert _same_store(tmp_path / "live", tmp_path / "whole")
    assert len(_stored(tmp_path / "live")[0]) == len(k0)


def _point_rows(path):
    import sqlite3

    from services.cloud.store.persistence import DB_NAME

    db = sqlite3.connect(path / DB_NAME)
    try:
        return {k: (bytes(p), r) for k, p, r in db.execute("SELECT key, p, in_ref FROM map_points")}
    finally:
        db.close()


def test_points_follow_their_keyframe_without_rewriting_their_rows(tmp_path):
    """A pose graph moves points rigidly with their reference keyframe: writing it back
    updates keyframe poses only, and the reloaded points are where the atlas moved them; so
    does a pose-only update of a keyframe from the edge."""
    world = make_world(45, n_points=1200)
    k0, m0 = make_session(world, default_camera(), 0, circle_poses(8, turns=0.25), np.eye(4))
    atlas = Atlas()
    store = CloudStore(tmp_path)
    keys = [atlas.add_keyframe(x) for x in k0]
    pkeys = [atlas.add_map_point(x) for x in m0]
    store.commit(atlas, keys, pkeys)
    before = _point_rows(tmp_path)
    moved = {k: yaw_T(0.05, [0.1, -0.2, 0.0]) @ atlas.T_map_body(k) for k in keys[:4]}
    atlas.set_keyframe_poses(moved)
    assert not atlas.unsaved.positions and atlas.unsaved.poses == set(moved)
    store.commit_poses(atlas)
    assert _point_rows(tmp_path) == before  # no point row written
    reloaded = CloudStore(tmp_path).load()
    moved_points = {m for m in pkeys if atlas.map_point(m).ref_kf in moved}
    assert moved_points
    for m in pkeys:
        assert np.allclose(reloaded.map_point(m).p_map, atlas.map_point(m).p_map, atol=1e-9)
    # A pose-only update (the edge's KeyframePoses): the points it references follow it
    # (held relative to it), and no point row is written.
    followers = [m for m in pkeys if atlas.map_point(m).ref_kf == keys[1]]
    assert followers
    p_before = {m: atlas.map_point(m).p_map for m in followers}
    T_old = atlas.T_map_body(keys[1])
    T = yaw_T(-0.1, [0.0, 0.2, 0.0]) @ k0[1].T_world_body
    atlas.add_keyframe(dataclasses.replace(k0[1], T_world_body=T))
    T_new = atlas.T_map_body(keys[1])
    for m in followers:
        expect = (T_new @ inverse_T(T_old) @ np.append(p_before[m], 1.0))[:3]
        assert np.allclose(atlas.map_point(m).p_map, expect, atol=1e-9)
    store.commit(atlas, [keys[1]])
    assert _point_rows(tmp_path) == before
    reloaded = CloudStore(tmp_path).load()
    for m in pkeys:
        assert np.allclose(reloaded.map_point(m).p_map, atlas.map_point(m).p_map, atol=1e-9)


def test_a_schema_6_state_dir_keeps_its_map_frame_positions(tmp_path):
    """Schema 6 stored every position in the map frame: its rows load as they were (in_ref 0)."""
    import sqlite3

    from services.cloud.store.persistence import DB_NAME, SCHEMA_VERSION

    db = sqlite3.connect(tmp_path / DB_NAME)
    db.executescript(
        "CREATE TABLE meta (name TEXT PRIMARY KEY, value INTEGER NOT NULL);"
        "INSERT INTO meta VALUES ('schema', 6);"
        "CREATE TABLE map_points (key INTEGER PRIMARY KEY, agent INTEGER NOT NULL,"
        " map_point_id INTEGER NOT NULL, map_id INTEGER NOT NULL, ref_kf INTEGER NOT NULL,"
        " p BLOB NOT NULL, data BLOB NOT NULL);"
    )
    p = np.array([1.5, -2.0, 0.25], "<f8")
    db.execute("INSERT INTO map_points VALUES (7, 0, 7, 0, -1, ?, ?)", (p.tobytes(), b""))
    db.commit()
    db.close()
    with CloudStore(tmp_path) as store:
        atlas = store.load()
    assert np.array_equal(atlas.map_point(7).p_map, p)
    db = sqlite3.connect(tmp_path / DB_NAME)
    assert db.execute("SELECT value FROM meta WHERE name='schema'").fetchone() == (SCHEMA_VERSION,)
    db.close()


def test_a_schema_7_state_dir_gets_the_blend_columns_of_its_retired_keyframes(tmp_path):
    import sqlite3

    from services.cloud.store.persistence import DB_NAME, SCHEMA_VERSION

    db = sqlite3.connect(tmp_path / DB_NAME)
    db.executescript(
        "CREATE TABLE meta (name TEXT PRIMARY KEY, value INTEGER NOT NULL);"
        "INSERT INTO meta VALUES ('schema', 7);"
        "CREATE TABLE retired_keyframes (key INTEGER PRIMARY KEY, agent INTEGER NOT NULL,"
        " timestamp REAL NOT NULL, anchor INTEGER NOT NULL, T BLOB NOT NULL);"
    )
    db.execute("INSERT INTO retired_keyframes VALUES (5, 0, 1.0, 4, ?)", (np.eye(4).tobytes(),))
    db.commit()
    db.close()
    with CloudStore(tmp_path) as store:
        store.load()
    db = sqlite3.connect(tmp_path / DB_NAME)
    assert db.execute("SELECT value FROM meta WHERE name='schema'").fetchone() == (SCHEMA_VERSION,)
    row = db.execute("SELECT key, other, T_other, w_other FROM retired_keyframes").fetchone()
    assert row == (5, None, None, 0.0)
    db.close()


def test_re_sent_points_rewrite_their_positions_only(tmp_path):
    """The edge re-sends points that local BA moved: a commit without keys writes their new
    positions (not their observation blobs), a new observation rewrites the whole row, and
    the reloaded atlas holds both."""
    import sqlite3

    from services.cloud.store.persistence import DB_NAME

    world = make_world(46, n_points=800)
    k0, m0 = make_session(world, default_camera(), 0, circle_poses(6, turns=0.2), np.eye(4))
    atlas = Atlas()
    store = CloudStore(tmp_path)
    keys = [atlas.add_keyframe(x) for x in k0]
    pkeys = atlas.add_map_points(m0)
    store.commit(atlas, keys, pkeys)
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.executescript(  # a log of every whole-row write from here on
        "CREATE TABLE row_writes (key INTEGER);"
        "CREATE TRIGGER w_ins AFTER INSERT ON map_points "
        "BEGIN INSERT INTO row_writes VALUES (new.key); END;"
        "CREATE TRIGGER w_upd AFTER UPDATE OF data ON map_points "
        "BEGIN INSERT INTO row_writes VALUES (new.key); END;"
    )
    moved = [dataclasses.replace(m, p_world=m.p_world + 0.01) for m in m0[:50]]
    assert atlas.add_map_points(moved) == pkeys[:50]
    store.commit(atlas)
    assert not list(db.execute("SELECT key FROM row_writes"))  # positions only
    # a new observation of a known point: its whole row
    v = atlas.keyframe(keys[-1])
    free = int(np.flatnonzero(v.map_point_keys < 0)[0])
    linked = next(m for m in m0[50:] if k0[-1].keyframe_id not in m.observations[:, 0])
    obs = np.vstack([linked.observations, [[k0[-1].keyframe_id, free]]])
    atlas.add_map_points([dataclasses.replace(linked, observations=obs)])
    store.commit(atlas)
    key = make_key(linked.agent_id, linked.map_point_id)
    assert [k for (k,) in db.execute("SELECT key FROM row_writes")] == [key]
    assert keys[-1] in CloudStore(tmp_path).load().map_point_observations(key)
    reloaded_p = {m: CloudStore(tmp_path).load().map_point(m).p_map for m in pkeys[:50]}
    for m, mp_in in zip(pkeys[:50], moved, strict=True):
        assert np.allclose(reloaded_p[m], mp_in.p_world, atol=1e-9)
        assert np.allclose(atlas.map_point(m).p_map, mp_in.p_world, atol=1e-9)
    db.close()


def test_keyframe_state_refreshes_and_new_links_leave_the_features_unwritten(tmp_path):
    """The edge re-sends a keyframe's state many times and its new observations link to it:
    neither rewrites the keyframe's features (its ``data`` blob); the reloaded atlas has the
    newest state and every link (rebuilt from the points' observations)."""
    import sqlite3

    from services.cloud.store.persistence import DB_NAME

    world = make_world(46, n_points=800)
    k0, m0 = make_session(world, default_camera(), 0, circle_poses(6, turns=0.2), np.eye(4))
    atlas = Atlas()
    store = CloudStore(tmp_path)
    keys = [atlas.add_keyframe(x) for x in k0]
    store.commit(atlas, keys, atlas.add_map_points(m0))
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.executescript(  # a log of every write of a keyframe's features from here on
        "CREATE TABLE data_writes (key INTEGER);"
        "CREATE TRIGGER d_ins AFTER INSERT ON keyframes "
        "BEGIN INSERT INTO data_writes VALUES (new.key); END;"
        "CREATE TRIGGER d_upd AFTER UPDATE OF data ON keyframes "
        "BEGIN INSERT INTO data_writes VALUES (new.key); END;"
    )
    refreshed = dataclasses.replace(
        k0[-1],
        T_world_body=k0[-1].T_world_body @ make_T(np.eye(3), np.array([0.0, 0.0, 0.02])),
        velocity=np.array([0.3, -0.2, 0.1]),
        bias_gyro=np.array([1e-3, 2e-3, 3e-3]),
        bias_accel=np.array([0.01, 0.02, 0.03]),
    )
    atlas.add_keyframe(refreshed)
    v = atlas.keyframe(keys[-1])
    free = int(np.flatnonzero(v.map_point_keys < 0)[0])
    linked = next(m for m in m0 if k0[-1].keyframe_id not in m.observations[:, 0])
    obs = np.vstack([linked.observations, [[k0[-1].keyframe_id, free]]])
    atlas.add_map_points([dataclasses.replace(linked, observations=obs)])
    store.commit(atlas)
    assert not list(db.execute("SELECT key FROM data_writes"))
    db.close()
    reloaded = CloudStore(tmp_path).load()
    r = reloaded.keyframe(keys[-1])
    np.testing.assert_allclose(r.T_map_body, refreshed.T_world_body, atol=1e-12)
    for name in ("velocity", "bias_gyro", "bias_accel"):
        np.testing.assert_allclose(getattr(r, name), getattr(refreshed, name), atol=1e-12)
    np.testing.assert_array_equal(r.map_point_keys, atlas.keyframe(keys[-1]).map_point_keys)
    assert r.map_point_keys[free] == make_key(linked.agent_id, linked.map_point_id)


def test_a_schema_8_state_dir_keeps_its_keyframes_states_and_gets_the_state_column(tmp_path):
    """A schema-8 store (the keyframe's state only in its features blob) opens as schema 9:
    each keyframe's velocity and biases come from the blob until a refresh writes its state
    column."""
    import sqlite3

    from services.cloud.store.persistence import DB_NAME, SCHEMA_VERSION

    world = make_world(46, n_points=400)
    k0, m0 = make_session(world, default_camera(), 0, circle_poses(4, turns=0.2), np.eye(4))
    k0 = [dataclasses.replace(k, velocity=np.array([0.1 * i, 0.2, 0.3])) for i, k in enumerate(k0)]
    atlas = Atlas()
    keys = [atlas.add_keyframe(k) for k in k0]
    with CloudStore(tmp_path) as store:
        store.commit(atlas, keys, atlas.add_map_points(m0))
    db = sqlite3.connect(tmp_path / DB_NAME)
    db.executescript(
        "ALTER TABLE keyframes DROP COLUMN state; UPDATE meta SET value = 8 WHERE name='schema';"
    )
    db.close()
    with CloudStore(tmp_path) as store:
        old = store.load()
        for k, key in zip(k0, keys, strict=True):
            np.testing.assert_allclose(old.keyframe(key).velocity, k.velocity)
        v = np.array([9.0, 8.0, 7.0])
        assert old.refresh_keyframe(0, k0[1].keyframe_id, k0[1].T_world_body, v, v, v)
        store.commit(old)
    db = sqlite3.connect(tmp_path / DB_NAME)
    assert db.execute("SELECT value FROM meta WHERE name='schema'").fetchone() == (SCHEMA_VERSION,)
    states = dict(db.execute("SELECT key, state IS NOT NULL FROM keyframes"))
    db.close()
    assert states == {k: int(k == keys[1]) for k in keys}  # (NULL: the blob's state)
    again = CloudStore(tmp_path).load()
    np.testing.assert_allclose(again.keyframe(keys[1]).velocity, v)
    np.testing.assert_allclose(again.keyframe(keys[2]).velocity, k0[2].velocity)


def test_an_in_memory_store_keeps_nothing_and_needs_no_folder(tmp_path, monkeypatch) -> None:
    """``CloudStore(None)`` (``open_app(None, ...)``): the same schema in memory, for tests and
    replays that drive the app as h11's tests drive its state machine; no file is made."""
    from services.cloud.store.persistence import CloudStore

    monkeypatch.chdir(tmp_path)
    store = CloudStore(None)
    assert store.load().n_keyframes() == 0
    store.close()
    assert list(tmp_path.iterdir()) == []
