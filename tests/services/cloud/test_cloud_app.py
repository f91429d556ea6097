"""CloudApp without the network: one atlas agent per (robot, edge map), positions persisted
with the effects and handed back to the transport after a restart."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest

from common.geometry import so3_exp
from common.links.edge_cloud import AgentStatus, CullEvent, decode_pose_correction
from common.protocol.arrays import pack_array
from common.vocabulary import Vocabulary
from services.cloud.app import CloudApp
from services.cloud.atlas.atlas import make_key
from services.cloud.fusion.map_fusion import MapFusion
from services.cloud.fusion.uplink import UplinkError
from services.cloud.optimization.mbp import MbpReport
from services.cloud.service_config import CloudServiceConfig, MbpScheduleConfig
from services.cloud.store.persistence import CloudStore
from sim.cloud import (
    circle_poses,
    default_camera,
    encode_keyframe_update,
    make_session,
    make_world,
)

T = TypeVar("T")


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


def _app(path, vocab, cfg: CloudServiceConfig | None = None) -> CloudApp:
    store = CloudStore(path)
    cfg = cfg or CloudServiceConfig()
    return CloudApp(
        MapFusion(default_camera(), vocab.idf, cfg.domain, store.load()), store, vocab, cfg
    )


def test_new_edge_map_of_a_robot_is_a_new_agent_and_survives_restart(tmp_path, vocab):
    world = make_world(8, n_points=1500)
    kfs, _ = make_session(world, default_camera(), 0, circle_poses(4, turns=0.1), np.eye(4))
    app = _app(tmp_path, vocab)
    seq = 0
    for edge_map, ks in ((7, kfs[:2]), (8, kfs[2:])):
        for k in ks:
            seq += 1
            msg, _ = encode_keyframe_update(k, "robot", vocab, edge_map_id=edge_map)
            app.handle("edge-a", msg, b"stream", seq)
    seq += 1
    why = "camera-IMU offset +14.9 ± 0.4 ms"
    status = AgentStatus("robot", 8, "tracking", 10, 2, 0, {}, why, 14_900_000)
    app.handle("edge-a", status, b"stream", seq)
    assert app.agents() == {0: ("robot", "edge-a", 7), 1: ("robot", "edge-a", 8)}
    assert [a.detail for a in app.view().agents if a.edge_id == "edge-a"][-1] == why
    # The robot's IMU is read at keyframe times plus its offset, in both of its maps.
    assert app.fusion.imu.time_offset_ns(0) == app.fusion.imu.time_offset_ns(1) == 14_900_000
    assert app.atlas.maps() == [0, 1]
    # The robot moved on to map 8: its map 7 is a fragment (it may merge with a scale).
    assert app.fusion.superseded_agents == {0}
    assert app.fusion.is_fragment(0) and not app.fusion.is_fragment(1)
    # Corrections: one per edge map, each naming its own map id.
    msgs = [c.message for m in app.atlas.maps() for c in app.corrections(m)]
    assert sorted((c.agent_id, c.map_id) for c in msgs) == [("robot", 7), ("robot", 8)]
    ids, T = decode_pose_correction(msgs[0])
    assert ids.tolist() == [0, 1] and np.allclose(T[0], kfs[0].T_world_body)
    # The edge culls keyframe 3 of map 8.
    seq += 1
    cull = CullEvent("robot", 8, pack_array(np.array([3]), "<i8"), b"")
    app.handle("edge-a", cull, b"stream", seq)
    assert app.atlas.n_keyframes() == 3
    app.close()

    restarted = _app(tmp_path, vocab)
    try:
        assert restarted.agents() == app.agents()
        assert restarted.fusion.superseded_agents == {0}
        assert restarted.atlas.keyframe_keys() == app.atlas.keyframe_keys()
        pos = restarted.positions.load("edge-a")
        assert pos is not None and (pos.stream_id, pos.last_delivered) == (b"stream", seq)
        # A replayed keyframe (an update of a known one) adds nothing.
        msg, _ = encode_keyframe_update(kfs[0], "robot", vocab, edge_map_id=7)
        restarted.handle("edge-a", msg, b"stream", seq + 1)
        assert restarted.atlas.n_keyframes() == 3
        # A replay of the culled keyframe does not resurrect it.
        msg, _ = encode_keyframe_update(kfs[3], "robot", vocab, edge_map_id=8)
        restarted.handle("edge-a", msg, b"stream", seq + 2)
        assert restarted.atlas.n_keyframes() == 3
    finally:
        restarted.close()


def _half_circle_session():
    """One agent's 30 keyframes over half a circle with its map points (MBP has work)."""
    world = make_world(31, n_points=2000)
    return make_session(
        world,
        default_camera(),
        0,
        circle_poses(30, turns=0.5),
        np.eye(4),
        seed=6,
        dt=0.2,
        track_gap=30,
    )


def test_mbp_through_the_app_marks_pruned_items_and_is_durable(tmp_path, vocab):
    kfs, mps = _half_circle_session()
    app = _app(tmp_path, vocab)
    for k in kfs:
        app.fusion.add_keyframe(k, detect=False)
    for m in mps:
        app.fusion.add_map_point(m)
    app.store.save_all(app.atlas)
    report = app.prune(0, final=True)
    assert report.keyframes_after < report.keyframes_before and report.connected_after
    view = app.view()
    assert len(view.pruned_keyframes) == report.keyframes_before - report.keyframes_after
    assert not set(view.atlas.keyframe_keys.tolist()) & view.pruned_keyframes
    kept = app.atlas.keyframe_keys()
    # The trajectory still has every keyframe: the removed ones through their anchors.
    assert app.agents() == {}  # fed below the uplink: no robot names, so read the atlas
    retired = app.atlas.retired_poses(0)
    assert len(retired) + len(kept) == len(kfs)
    truth = {k.timestamp: k.T_world_body for k in kfs}
    for _, t, T in retired:
        np.testing.assert_allclose(T, truth[t], atol=1e-9)
    app.close()
    restarted = _app(tmp_path, vocab)
    try:
        assert restarted.atlas.keyframe_keys() == kept
        assert sorted(t for _, t, _ in restarted.atlas.retired_poses(0)) == sorted(
            t for _, t, _ in retired
        )
    finally:
        restarted.close()


def _pruned(
    path: Path,
    vocab: Vocabulary,
    session: tuple[list, list],
    final: bool,
    read: Callable[[CloudApp, MbpReport], T],
    settle: int,
    **running: Any,
) -> T:
    """``read`` of an app fed ``session`` (keyframes, map points) after one MBP pass (at
    shutdown when ``final``), the pass while running keeping each agent's ``settle`` newest
    keyframes and taking the options ``running`` changes in ``MbpScheduleConfig.running``."""
    schedule = MbpScheduleConfig()
    running_mbp = dataclasses.replace(schedule.running, **running)
    mbp = dataclasses.replace(schedule, settle_keyframes=settle, running=running_mbp)
    app = _app(path, vocab, CloudServiceConfig(mbp=mbp))
    try:
        kfs, mps = session
        for k in kfs:
            app.fusion.add_keyframe(k, detect=False)
        for m in mps:
            app.fusion.add_map_point(m)
        return read(app, app.prune(0, final=final))
    finally:
        app.close()


def _pruned_grid(
    path: Path,
    vocab: Vocabulary,
    read: Callable[[CloudApp, MbpReport], T],
    setting: str,
    values: tuple[Any, ...],
) -> dict[tuple[Any, bool], T]:
    """:func:`_pruned` of the half-circle session (5 newest keyframes settling) for each of
    ``values`` of the running pass's ``setting``, while running and at shutdown:
    ``{(value, final): read}``."""
    session = _half_circle_session()
    return {
        (v, final): _pruned(
            path / f"{v}-{final}",
            vocab,
            session,
            final,
            read,
            5,
            **{setting: v},
        )
        for v in values
        for final in (False, True)
    }


def _removed(app: CloudApp, report: MbpReport) -> set[int]:
    return set(report.removed_keyframes)


def test_mbp_while_running_keeps_the_unsettled_newest_keyframes(tmp_path, vocab):
    """A pass while running never removes an agent's ``MbpScheduleConfig.settle_keyframes`` newest
    keyframes (still in the edge's reach); the final pass at shutdown may."""
    session = _half_circle_session()
    newest = {make_key(0, k.keyframe_id) for k in session[0][-12:]}
    removed = {
        final: _pruned(tmp_path / str(final), vocab, session, final, _removed, settle=12)
        for final in (False, True)
    }
    assert removed[False] and not removed[False] & newest
    assert removed[True] & newest  # at shutdown only keep_recent (5) are protected


@pytest.mark.slow
def test_mbp_while_running_removes_only_at_its_own_cover_ratio(tmp_path, vocab):
    """The running pass's ``cover_ratio`` rules the passes while running, not the pass at
    shutdown: one above 1 (no keyframe can be covered that well) removes nothing while
    running."""
    removed = _pruned_grid(tmp_path, vocab, _removed, "cover_ratio", (0.5, 1.01))
    assert removed[0.5, False] and not removed[1.01, False]
    assert removed[1.01, True] == removed[0.5, True]


def test_mbp_while_running_keeps_the_points_left_with_one_observer(tmp_path, vocab):
    """A pass while running removes only the points left without an observer (the running pass's
    ``min_observations`` 1: a later keyframe or loop may see them again); one at 2 and the pass at
    shutdown remove those left with one too."""

    def observers(app: CloudApp, report: MbpReport) -> np.ndarray:
        assert report.removed_keyframes
        return np.bincount(
            [len(app.atlas.map_point_observations(m)) for m in app.atlas.map_point_keys()]
        )

    counts = _pruned_grid(tmp_path, vocab, observers, "min_observations", (1, 2))
    assert counts[1, False][0] == 0 and counts[1, False][1] > 0
    for case in ((2, False), (1, True), (2, True)):
        assert counts[case][:2].sum() == 0


def test_mbp_while_running_keeps_its_agents_keyframes_close_in_time(tmp_path, vocab):
    """A pass while running keeps each agent's kept keyframes within
    the running pass's ``max_interval_s`` (the full BA's IMU intervals); the pass at shutdown and a
    limit of None do not."""

    def widest_gap(app: CloudApp, report: MbpReport) -> float:
        assert report.removed_keyframes
        stamps = sorted(app.atlas.keyframe(k).timestamp for k in app.atlas.keyframe_keys())
        return float(np.max(np.diff(stamps)))

    # The session's keyframes are 0.2 s apart.
    gap = _pruned_grid(tmp_path, vocab, widest_gap, "max_interval_s", (0.5, None))
    assert gap[0.5, False] <= 0.5 + 1e-9
    assert gap[None, False] > 0.5 and gap[0.5, True] > 0.5


def test_applied_optimisation_is_durable(tmp_path, vocab):
    from common.geometry import inverse_T
    from services.cloud.optimization.global_optimization import optimize_pose_graph
    from sim.cloud import yaw_T

    world = make_world(12, n_points=2000)
    poses = circle_poses(10, turns=0.3)
    kfs, mps = make_session(
        world,
        default_camera(),
        0,
        poses,
        np.eye(4),
        seed=2,
        drift_T=yaw_T(np.radians(0.5), np.array([0.01, 0.0, 0.0])),
    )
    app = _app(tmp_path, vocab)
    for m in mps:
        app.fusion.add_map_point(m)
    for k in kfs:
        app.fusion.add_keyframe(k, detect=False)
    app.store.save_all(app.atlas)
    keys = app.atlas.keyframe_keys()
    # A loop constraint from the truth pulls the last keyframe back: every pose moves.
    app.atlas.add_loop(keys[0], keys[-1], inverse_T(poses[0]) @ poses[-1])
    problem, token = app.optimization_problem(0)
    corrections = app.apply_optimization(
        0, optimize_pose_graph(problem, app.config.domain.optimization), token
    )
    assert corrections == []  # no robot names: the keyframes came in without messages
    T = {k: app.atlas.T_map_body(k) for k in keys}
    mk = app.atlas.map_point_keys()
    P = app.atlas.map_point_positions(np.array(mk))
    assert np.linalg.norm(T[keys[-1]][:3, 3] - kfs[-1].T_world_body[:3, 3]) > 0.01
    app.close()
    restarted = _app(tmp_path, vocab)
    try:
        for k in keys:
            assert np.allclose(restarted.atlas.T_map_body(k), T[k])
        assert np.allclose(restarted.atlas.map_point_positions(np.array(mk)), P)
    finally:
        restarted.close()


def test_ground_truth_is_associated_by_time_and_aligned_onto_the_keyframes(tmp_path, vocab):
    """The robot's reference (200 Hz, in the world frame) comes back in the map frame of its
    keyframes; stamps further than ``max_dt_ns`` from every keyframe give no alignment."""
    from common.evaluation.trajectory import Trajectory
    from common.geometry import R_to_quat_wxyz

    world = make_world(8, n_points=1500)
    T_agent_world = np.eye(4)
    T_agent_world[:3, :3] = so3_exp([0.0, 0.0, 0.7])
    T_agent_world[:3, 3] = [1.0, -2.0, 0.3]
    truth = circle_poses(12, turns=0.5)
    kfs, _ = make_session(world, default_camera(), 0, truth, T_agent_world, dt=0.5)
    app = _app(tmp_path, vocab)
    try:
        for seq, k in enumerate(kfs, start=1):
            msg, _ = encode_keyframe_update(k, "robot", vocab, edge_map_id=0)
            app.handle("edge-a", msg, b"stream", seq)
        # A 200 Hz reference through the keyframe positions, its clock 2 ms ahead.
        t_kf = np.array([k.timestamp for k in kfs])
        t = np.arange(round(t_kf[0] * 200), round(t_kf[-1] * 200) + 1) / 200
        p_ref = np.stack([np.interp(t, t_kf, truth[:, c, 3]) for c in range(3)], axis=1)
        t_ref = t + 0.002
        q = R_to_quat_wxyz(np.repeat(np.eye(3)[None], len(t_ref), 0))
        ref = Trajectory(np.round(t_ref * 1e9).astype(np.int64), p_ref, q, "robot")
        (gt,) = app.ground_truth({"robot": ref})
        assert gt.agent_id == 0
        idx = np.searchsorted(gt.timestamp, t_kf)
        p_kf = np.array([k.T_world_body[:3, 3] for k in kfs])
        assert np.max(np.linalg.norm(gt.p_world[idx] - p_kf, axis=1)) < 1e-6
        assert app.ground_truth({"robot": ref}, max_dt_ns=1_000_000) == ()
    finally:
        app.close()


def test_one_robot_on_two_edges_is_two_agents_each_corrected_through_its_own_edge(tmp_path, vocab):
    """Several edges, one cloud: the agent key is (edge, robot, edge map). A robot that moved
    from edge-a to edge-b (same name, both edges number its map 0) is two agents; a pose
    correction of each goes to the edge that serves it; the identities survive a restart;
    edge-b cannot cull edge-a's keyframes."""
    world = make_world(8, n_points=1500)
    kfs, _ = make_session(world, default_camera(), 0, circle_poses(4, turns=0.1), np.eye(4))
    app = _app(tmp_path, vocab)
    for seq, (edge, k) in enumerate(zip(["edge-a"] * 2 + ["edge-b"] * 2, kfs, strict=True), 1):
        msg, _ = encode_keyframe_update(k, "robot", vocab, edge_map_id=0)
        app.handle(edge, msg, edge.encode(), seq)
    assert app.agents() == {0: ("robot", "edge-a", 0), 1: ("robot", "edge-b", 0)}
    routed = {c.edge_id: c.message.agent_id for m in app.atlas.maps() for c in app.corrections(m)}
    assert routed == {"edge-a": "robot", "edge-b": "robot"}
    for m in app.atlas.maps():
        for c in app.corrections(m):
            ids, _ = decode_pose_correction(c.message)
            assert ids.tolist() == ([0, 1] if c.edge_id == "edge-a" else [2, 3])
    with pytest.raises(UplinkError, match="has no agent"):
        app.handle("edge-b", CullEvent("robot", 7, pack_array(np.array([0]), "<i8"), b""), b"b", 9)
    assert app.atlas.n_keyframes() == 4
    app.close()
    restarted = _app(tmp_path, vocab)
    try:
        assert restarted.agents() == app.agents()
        assert restarted.fusion.superseded_agents == {0}
        # edge-b's next keyframe lands in its agent, not in edge-a's.
        msg, _ = encode_keyframe_update(kfs[0], "robot", vocab, edge_map_id=0)
        restarted.handle("edge-b", msg, b"b", 10)
        assert restarted.atlas.has_keyframe(make_key(1, kfs[0].keyframe_id))
        assert restarted.agents() == app.agents()
        assert restarted.fusion.superseded_agents == {0}
    finally:
        restarted.close()


def test_carried_descriptors_come_from_the_previous_keyframe_also_after_a_restart(tmp_path, vocab):
    """A keyframe whose features carry descriptors of the robot's previous uplinked keyframe
    (the edge sends their rows instead) decodes to the same descriptors: from the keyframe
    just received, or, after a restart, from the atlas; naming a keyframe the cloud does not
    have is refused with the reason."""
    from common.codec import FeatureDecoder, encode_standalone_keyframe

    world = make_world(8, n_points=1500)
    kfs, _ = make_session(world, default_camera(), 0, circle_poses(4, turns=0.05), np.eye(4))
    first, _ = encode_keyframe_update(kfs[0], "robot", vocab, edge_map_id=7)
    feats0 = FeatureDecoder(vocab).decode(first.features)
    rows = [2, 5, 9]

    def carrying(k, prev_id: int):
        """kfs[k]'s message whose features 0-2 carry rows 2, 5, 9 of kfs[prev_id]'s."""
        msg, _ = encode_keyframe_update(
            k, "robot", vocab, edge_map_id=7, previous_keyframe_id=prev_id
        )
        feats = FeatureDecoder(vocab).decode(msg.features)
        desc = feats.descriptors.copy()
        desc[:3] = feats0.descriptors[rows]
        feats = dataclasses.replace(feats, descriptors=desc)
        carried = np.full(len(feats), -1)
        carried[:3] = rows
        payload = encode_standalone_keyframe(vocab, feats, None, carried)
        assert len(payload) < len(encode_standalone_keyframe(vocab, feats))
        return dataclasses.replace(msg, features=payload), desc

    app = _app(tmp_path, vocab)
    app.handle("edge-a", first, b"stream", 1)
    msg, desc = carrying(kfs[1], kfs[0].keyframe_id)
    app.handle("edge-a", msg, b"stream", 2)  # the keyframe just received
    assert np.array_equal(app.atlas.keyframe(make_key(0, kfs[1].keyframe_id)).descriptors, desc)
    app.close()
    restarted = _app(tmp_path, vocab)
    try:
        msg, desc = carrying(kfs[2], kfs[0].keyframe_id)
        restarted.handle("edge-a", msg, b"stream", 3)  # from the atlas
        key = make_key(0, kfs[2].keyframe_id)
        assert np.array_equal(restarted.atlas.keyframe(key).descriptors, desc)
        msg, _ = carrying(kfs[3], 99)
        with pytest.raises(UplinkError, match="keyframe 99, which the cloud does not have"):
            restarted.handle("edge-a", msg, b"stream", 4)
    finally:
        restarted.close()
