"""Full bundle adjustment (paper Eq. 20, full stage) on the cloud's synthetic world: perturbed
keyframes and points come back towards the truth, the first keyframe stays, the result lands
in the atlas; outliers and points seen once stay out; the service runs it off its loop."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest

from common.evaluation.alignment import umeyama
from common.evaluation.tum import read_tum
from common.geometry import inverse_T, so3_exp
from common.protocol import SessionConfig
from common.transport import Client, Delivery, TransportConfig, run
from common.vocabulary import Vocabulary
from services.cloud.atlas.atlas import Atlas, make_key
from services.cloud.config import CloudConfig, FullBAConfig, GlobalOptimizationConfig
from services.cloud.fusion.map_fusion import MapFusion
from services.cloud.optimization.full_ba import (
    FullBAResult,
    apply_full_ba,
    build_full_ba,
    reprojection_rms_px,
    solve_full_ba,
)
from services.cloud.server import CloudServer
from services.cloud.service_config import (
    CloudServiceConfig,
    FullBAScheduleConfig,
    MapViewConfig,
    ProcessConfig,
    StoreConfig,
)
from sim.cloud import (
    circle_poses,
    default_camera,
    encode_keyframe_update,
    encode_map_point_update,
    make_session,
    make_world,
)

N = 16
CAM = default_camera()
CFG = FullBAConfig()
GCFG = GlobalOptimizationConfig()


@pytest.fixture(scope="module")
def session():
    world = make_world(5, n_points=1500)
    poses = circle_poses(N, turns=0.4)
    kfs, mps = make_session(world, CAM, 0, poses, np.eye(4), seed=2)
    return poses, kfs, mps


def _atlas(kfs, mps) -> Atlas:
    atlas = Atlas()
    for k in kfs:
        atlas.add_keyframe(k)
    for m in mps:
        atlas.add_map_point(m)
    return atlas


def _perturb(atlas: Atlas, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    poses = {}
    for k in atlas.keyframe_keys()[1:]:
        D = np.eye(4)
        D[:3, :3] = so3_exp(rng.normal(0.0, 0.01, 3))
        D[:3, 3] = rng.normal(0.0, 0.03, 3)
        poses[k] = atlas.T_map_body(k) @ D
    atlas.set_keyframe_poses(poses)
    pk = np.array(atlas.map_point_keys(), np.int64)
    P = atlas.map_point_positions(pk) + rng.normal(0.0, 0.05, (pk.size, 3))
    atlas.set_map_point_positions(dict(zip(pk.tolist(), P, strict=True)))


def _pose_error(atlas: Atlas, poses: np.ndarray, sim3: bool = False) -> float:
    """RMS position error (m), raw or after a Sim(3) alignment (monocular BA leaves the scale
    to the weak relative-pose terms, so the shape is what it must restore)."""
    est = np.array([atlas.T_map_body(make_key(0, i))[:3, 3] for i in range(N)])
    if sim3:
        est = umeyama(est, poses[:, :3, 3], with_scale=True).apply_points(est)
    return float(np.sqrt(np.mean(np.sum((est - poses[:, :3, 3]) ** 2, axis=1))))


def test_full_ba_brings_perturbed_map_back_and_keeps_first_keyframe(session):
    poses, kfs, mps = session
    atlas = _atlas(kfs, mps)
    _perturb(atlas)
    T0 = atlas.T_map_body(make_key(0, 0))
    err_before = _pose_error(atlas, poses)
    shape_before = _pose_error(atlas, poses, sim3=True)
    rms_before = reprojection_rms_px(atlas, 0, CAM)
    problem = build_full_ba(atlas, 0, CAM, CFG, GCFG)
    # Consecutive keyframes of the agent are tied by relative poses; no loops here.
    assert problem.edge_i.size == N - 1 and not problem.robust.any()
    result = solve_full_ba(problem, CFG, GCFG)
    assert result.final_error < 0.1 * result.initial_error
    assert result.final_rms_px < 1.0 < result.initial_rms_px
    assert apply_full_ba(atlas, result) == N
    assert np.allclose(atlas.T_map_body(make_key(0, 0)), T0, atol=1e-6)
    assert reprojection_rms_px(atlas, 0, CAM) < 0.2 * rms_before
    err_after = _pose_error(atlas, poses)
    shape_after = _pose_error(atlas, poses, sim3=True)
    assert err_after < 0.8 * err_before, (err_before, err_after)
    assert shape_after < 0.5 * shape_before, (shape_before, shape_after)
    # The optimised points are in the atlas.
    got = atlas.map_point_positions(result.point_keys)
    assert np.allclose(got, result.p_world)
    # With attitude factors the keyframes keep the (perturbed) roll and pitch they came with.
    held = solve_full_ba(problem, dataclasses.replace(CFG, attitude_sigma_rad=1e-4), GCFG)
    up = problem.T_world_body[:, 2, :3]
    drift = np.degrees(np.arccos(np.clip((held.T_world_body[:, 2, :3] * up).sum(1), -1, 1)))
    free = np.degrees(np.arccos(np.clip((result.T_world_body[:, 2, :3] * up).sum(1), -1, 1)))
    assert drift.max() < 0.1 and free.max() > 0.5, (drift.max(), free.max())


def test_problem_leaves_out_outliers_and_points_seen_once_and_pickles(session):
    _, kfs, mps = session
    atlas = _atlas(kfs, mps)
    # One point moved behind every camera that sees it: all its observations are dropped.
    bad = atlas.map_point_keys()[0]
    view = atlas.map_point(bad)
    T = atlas.T_map_body(int(view.obs_keyframes[0]))
    atlas.set_map_point_positions({bad: T[:3, 3] - 3.0 * T[:3, 0]})
    problem = build_full_ba(atlas, 0, CAM, CFG, GCFG)
    assert bad not in problem.point_keys.tolist()
    assert problem.dropped_observations >= view.obs_keyframes.size
    counts = np.bincount(problem.obs_point, minlength=problem.point_keys.size)
    assert counts.min() >= 2
    copy = pickle.loads(pickle.dumps(problem))
    assert np.array_equal(copy.obs_xy, problem.obs_xy) and copy.fixed == problem.fixed


def test_wrong_loop_is_left_out_and_budget_bounds_iterations(session):
    _, kfs, mps = session
    atlas = _atlas(kfs, mps)
    a, b = make_key(0, 0), make_key(0, N - 1)
    good = inverse_T(atlas.T_map_body(a)) @ atlas.T_map_body(b)
    wrong = good.copy()
    wrong[:3, 3] += [1.0, 0.0, 0.0]
    atlas.add_loop(a, b, good)
    atlas.add_loop(a, b, wrong)
    problem = build_full_ba(atlas, 0, CAM, CFG, GCFG)
    assert problem.robust.sum() == 2
    result = solve_full_ba(problem, CFG, GCFG)
    assert result.rejected_edges.tolist() == [N]  # the second loop edge, after N - 1 odometry
    one = solve_full_ba(problem, dataclasses.replace(CFG, max_seconds=0.0), GCFG)
    assert one.iterations == 1


def test_map_fusion_dispatches_full_ba_results(session):
    poses, kfs, mps = session
    fusion = MapFusion(CAM, np.ones(10), CloudConfig())
    for m in mps:
        fusion.add_map_point(m)
    for k in kfs:
        fusion.atlas.add_keyframe(k)
    _perturb(fusion.atlas, seed=3)
    before = _pose_error(fusion.atlas, poses)
    result = solve_full_ba(fusion.full_ba_problem(0), CFG, GCFG)
    assert isinstance(result, FullBAResult)
    assert fusion.apply_optimization(result) == N
    assert _pose_error(fusion.atlas, poses) < before


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


SECRET = b"cloud-full-ba-test-secret"
FAST = TransportConfig(reconnect_initial_delay=0.01, reconnect_max_delay=0.2)


def _service_run(tmp_path, vocab, session, enabled: bool) -> np.ndarray:
    """Perturbed keyframes sent over loopback TCP, then the cloud stops (no quiet or periodic
    full BA in this short run, only the one at shutdown); position errors (N,) m of the
    trajectory it wrote."""
    poses, kfs, mps = session
    rng = np.random.default_rng(7)
    sent = []
    for k in kfs:
        D = np.eye(4)
        if k.keyframe_id > 0:
            D[:3, :3] = so3_exp(rng.normal(0.0, 0.01, 3))
            D[:3, 3] = rng.normal(0.0, 0.03, 3)
        sent.append(dataclasses.replace(k, T_world_body=k.T_world_body @ D))
    msgs, inv = [], {}
    for k in sent:
        msg, order = encode_keyframe_update(k, "robot", vocab)
        inv[k.keyframe_id] = np.argsort(order)
        msgs.append(msg)
    msgs.append(encode_map_point_update(mps, "robot", coded_index=inv))
    domain = dataclasses.replace(CloudConfig(), full_ba=FullBAConfig(enabled=enabled))
    cfg = CloudServiceConfig(
        domain=domain,
        store=StoreConfig(output_every_s=0),
        map_view=MapViewConfig(publish_every_s=10.0),
        processes=ProcessConfig(optimizer_process=False),
        full_ba=FullBAScheduleConfig(quiet_s=0.0),
    )
    out = tmp_path / ("on" if enabled else "off")
    cloud = CloudServer(
        SessionConfig("cloud", "cloud", SECRET),
        out / "state",
        CAM,
        vocab,
        cfg,
        results_dir=out / "results",
        transport=FAST,
    )

    async def on_message(d: Delivery) -> None:
        pass

    async def main():
        _, port = await cloud.start()
        client = Client(
            SessionConfig("edge", "edge-a", SECRET), on_message, "127.0.0.1", port, transport=FAST
        )
        await client.start()
        try:
            for m in msgs:
                await client.send(m)
            await client.flush()
        finally:
            await client.close()
            await cloud.stop()

    run(main())
    traj = read_tum(out / "results" / "trajectories" / "robot.tum")
    return np.linalg.norm(traj.p_world_body - poses[:, :3, 3], axis=1)


@pytest.mark.slow
def test_service_runs_full_ba_at_shutdown_before_writing_trajectories(tmp_path, vocab, session):
    err_off = _service_run(tmp_path, vocab, session, enabled=False)
    err_on = _service_run(tmp_path, vocab, session, enabled=True)
    assert err_off[0] < 1e-6 and err_on[0] < 1e-6  # the first keyframe is the map's anchor
    rms_off = float(np.sqrt(np.mean(err_off**2)))
    rms_on = float(np.sqrt(np.mean(err_on**2)))
    assert rms_on < 0.6 * rms_off, (rms_off, rms_on)
