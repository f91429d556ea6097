"""Pose graph (paper Eq. 20, pose-graph stage): loop constraints remove injected drift."""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from common.geometry import inverse_T, so3_exp
from services.cloud.atlas.atlas import Atlas, make_key
from services.cloud.child_process import child_process_init
from services.cloud.config import GlobalOptimizationConfig
from services.cloud.optimization.global_optimization import (
    GlobalOptimizationError,
    PoseGraphProblem,
    apply_pose_graph,
    build_pose_graph,
    optimize_pose_graph,
    up_in_body,
)
from services.cloud.service_config import ProcessConfig
from sim.cloud import circle_poses, default_camera, make_session, make_world, yaw_T


def _rmse(atlas, poses, n):
    est = np.array([atlas.T_map_body(make_key(0, i))[:3, 3] for i in range(n)])
    return float(np.sqrt(np.mean(np.sum((est - poses[:n, :3, 3]) ** 2, axis=1))))


@pytest.fixture(scope="module")
def drifted():
    world = make_world(21, n_points=2500)
    n = 48
    poses = circle_poses(n, turns=1.0)
    drift = yaw_T(np.radians(0.4), [0.01, 0.005, 0.0])
    kfs, mps = make_session(world, default_camera(), 0, poses, np.eye(4), seed=4, drift_T=drift)
    return poses, kfs, mps


def _atlas(kfs, mps, n_loops):
    atlas = Atlas()
    for k in kfs[:-1]:
        atlas.add_keyframe(k)
    for m in mps:
        atlas.add_map_point(m)
    return atlas


def test_loop_constraints_reduce_drift(drifted):
    poses, kfs, mps = drifted
    n = len(kfs)
    atlas = _atlas(kfs, mps, 3)
    # Loop constraints between the end and the start of the lap, measured exactly.
    for q, c in [(n - 2, 0), (n - 3, 1), (n - 4, 2), (n - 2, 1)]:
        atlas.add_loop(make_key(0, c), make_key(0, q), inverse_T(poses[c]) @ poses[q])
    before = _rmse(atlas, poses, n - 1)
    mk = atlas.map_point_keys()[-1]
    p_before = atlas.map_point_positions(np.array([mk]))[0]
    cfg = GlobalOptimizationConfig()
    problem = build_pose_graph(atlas, 0, cfg)
    assert problem.robust.sum() == 4
    result = optimize_pose_graph(problem, cfg)
    assert result.final_error < result.initial_error
    # A keyframe arriving while the optimisation ran is corrected like its predecessor.
    late = atlas.add_keyframe(kfs[-1])
    T_late_before = atlas.T_map_body(late)
    assert apply_pose_graph(atlas, result) == n
    after = _rmse(atlas, poses, n - 1)
    assert before > 0.15
    assert after < 0.25 * before, (before, after)
    assert np.linalg.norm(atlas.T_map_body(late)[:3, 3] - poses[-1][:3, 3]) < np.linalg.norm(
        T_late_before[:3, 3] - poses[-1][:3, 3]
    )
    # The first keyframe is held by the prior; map points moved with their keyframes.
    np.testing.assert_allclose(atlas.T_map_body(make_key(0, 0)), poses[0], atol=1e-6)
    assert not np.allclose(atlas.map_point_positions(np.array([mk]))[0], p_before)


def test_robust_kernel_limits_a_wrong_loop(drifted):
    poses, kfs, mps = drifted
    n = len(kfs)
    atlas = _atlas(kfs, mps, 0)
    for q, c in [(n - 2, 0), (n - 3, 1), (n - 4, 2)]:
        atlas.add_loop(make_key(0, c), make_key(0, q), inverse_T(poses[c]) @ poses[q])
    # One gross outlier constraint (3 m off).
    atlas.add_loop(make_key(0, 10), make_key(0, 30), yaw_T(1.0, [3.0, 0.0, 0.0]))
    cfg = GlobalOptimizationConfig()
    apply_pose_graph(atlas, optimize_pose_graph(build_pose_graph(atlas, 0, cfg), cfg))
    assert _rmse(atlas, poses, n - 1) < 0.2


def test_bad_problem_is_rejected():
    with pytest.raises(GlobalOptimizationError, match="no keyframes"):
        build_pose_graph(Atlas(), 0, GlobalOptimizationConfig())


def _tilt_deg(T: np.ndarray) -> np.ndarray:
    """(N,) angle between each body's up direction now and the world's z, degrees."""
    return np.degrees(np.arccos(np.clip(T[:, 2, 2], -1.0, 1.0)))


def test_attitude_factors_keep_roll_and_pitch_while_the_loop_corrects_yaw() -> None:
    """A square of 12 gravity-aligned keyframes whose odometry drifted in yaw, closed by a
    loop that also carries 1° of spurious roll (as a visual PnP can): with the attitude
    factors the poses keep the roll and pitch they came with (the VIO's, observed through
    the IMU) and still take the loop's yaw; without them the map tilts."""
    n = 12
    a = 2 * np.pi * np.arange(n) / n
    true = np.array([yaw_T(t, np.array([np.cos(t), np.sin(t), 0.0])) for t in a])
    drift = np.array([yaw_T(0.004 * i, np.zeros(3)) @ true[i] for i in range(n)])
    ei = [*range(n - 1), 0]
    ej = [*range(1, n), n - 1]
    meas = [inverse_T(drift[i]) @ drift[j] for i, j in zip(ei[:-1], ej[:-1], strict=True)]
    roll = np.eye(4)
    roll[:3, :3] = so3_exp([np.radians(1.0), 0.0, 0.0])
    meas.append(inverse_T(true[0]) @ true[n - 1] @ roll)
    sig = [[0.01] * 3 + [0.02] * 3] * (n - 1) + [[0.02] * 3 + [0.05] * 3]  # the defaults
    problem = PoseGraphProblem(
        keys=np.arange(n, dtype=np.int64),
        T_world_body=drift,
        edge_i=np.array(ei),
        edge_j=np.array(ej),
        T_i_j=np.array(meas),
        sigmas=np.array(sig, float),
        robust=np.array([False] * (n - 1) + [True]),
        fixed=0,
        up_body=up_in_body(drift),
    )
    held = optimize_pose_graph(problem, GlobalOptimizationConfig())
    free = optimize_pose_graph(problem, GlobalOptimizationConfig(attitude_sigma_rad=0.0))
    assert _tilt_deg(held.T_world_body).max() < 0.05
    assert _tilt_deg(free.T_world_body).max() > 0.3
    # The loop's yaw is taken either way: the last keyframe turns back towards the truth.
    yaw = lambda T: np.arctan2(T[1, 0], T[0, 0])  # noqa: E731
    before = abs(yaw(drift[-1]) - yaw(true[-1]))
    assert abs(yaw(held.T_world_body[-1]) - yaw(true[-1])) < 0.5 * before


def _niceness() -> int:
    return os.nice(0)


@pytest.mark.parametrize("nice", [0, 10])
def test_the_optimizer_process_runs_at_the_configured_niceness(nice: int) -> None:
    """The solves are background work: the optimizer process runs
    ``ProcessConfig.optimizer_nice`` above
    the service, so a shared core goes to the worker that applies the edges' messages."""
    with ProcessPoolExecutor(
        1,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=child_process_init,
        initargs=(os.getpid(), nice),
    ) as pool:
        assert pool.submit(_niceness).result(timeout=60) == os.nice(0) + nice


def test_optimizer_nice_out_of_range_is_refused() -> None:
    with pytest.raises(ValueError, match="optimizer_nice"):
        ProcessConfig(optimizer_nice=-1)
