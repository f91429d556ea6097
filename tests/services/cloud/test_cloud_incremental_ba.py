"""Incremental visual-inertial global BA (iSAM2): same answer as the batch solve, keyframes
the edge culls, outlier loops, rebuilds, and the service's dispatch."""

from __future__ import annotations

import dataclasses
import uuid

import numpy as np
import pytest

from common.calibration import EUROC_IMU
from common.geometry import inverse_T
from services.cloud.config import FullBAConfig, GlobalOptimizationConfig
from services.cloud.core_actions import SolveKind, SolveRequest, solve
from services.cloud.optimization.full_ba import FullBAProblem, build_full_ba, solve_full_ba
from services.cloud.optimization.incremental_ba import (
    _SOLVERS,
    L,
    V,
    X,
    _held_back,
    forget,
    solve_full_ba_incremental,
)
from sim.cloud import default_camera, map_scale, problem_prefix, vi_circle_atlas

CFG = dataclasses.replace(FullBAConfig(), incremental=True, incremental_min_keyframes=0)
GRAPH = GlobalOptimizationConfig()


def _imu_of(_agent: int):
    return EUROC_IMU


@pytest.fixture
def session():
    name = uuid.uuid4().hex
    yield name
    forget(name)


def _circle(n: int):
    atlas, store, truth = vi_circle_atlas(n, scale=1.03, seed=0)
    problem = build_full_ba(atlas, 0, default_camera(), CFG, GRAPH, store, _imu_of)
    return atlas, store, truth, problem


def _positions_cm(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a[:, :3, 3] - b[:, :3, 3]).max() * 100)


@pytest.mark.slow
@pytest.mark.parametrize("partial", [True, False], ids=["partial-check", "full-check"])
def test_time_ordered_updates_reach_the_batch_solution(session, partial):
    _, _, truth, problem = _circle(160)
    cfg = dataclasses.replace(CFG, partial_relinearization_check=partial)
    modes = []
    for n in range(60, 161, 20):
        res = solve_full_ba_incremental(problem_prefix(problem, n), cfg, GRAPH, session, 0)
        modes.append(res.mode)
        assert res.keys.tolist() == problem.keys[:n].tolist()
        assert res.velocity.shape == (n, 3)
    assert modes == ["isam2-reset"] + ["isam2"] * 5
    batch = solve_full_ba(problem, CFG, GRAPH)
    # The start is scaled by 1.03: both recover the metric scale to the same few 1e-4.
    s_inc = map_scale(res.T_world_body, truth.T_world_body)
    s_batch = map_scale(batch.T_world_body, truth.T_world_body)
    assert abs(s_batch - 1.0) < 0.01
    assert abs(s_inc - s_batch) < 0.002, (s_inc, s_batch)
    assert res.final_rms_px < 1.05 * batch.final_rms_px
    assert _positions_cm(res.T_world_body, batch.T_world_body) < 1.5


def test_the_result_is_the_graph_estimate_read_key_by_key(session):
    _, _, _, problem = _circle(120)
    for n in (80, 120):
        res = solve_full_ba_incremental(problem_prefix(problem, n), CFG, GRAPH, session, 0)
    solver = _SOLVERS[(session, 0)]
    est = solver.isam.calculateEstimate()
    keys = res.keys.tolist()
    T = np.array([est.atPose3(X(solver.slot[k])).matrix() for k in keys])
    np.testing.assert_array_equal(res.T_world_body, T)
    p = np.array([est.atPoint3(L(solver.point_slot[q])) for q in res.point_keys.tolist()])
    np.testing.assert_array_equal(res.p_world, p)
    v = np.array([est.atVector(V(solver.slot[keys[i]])) for i in res.inertial_index.tolist()])
    np.testing.assert_array_equal(res.velocity, v)
    # The next update starts from these poses (not a second read of the estimate).
    assert solver.poses is not None and sorted(solver.poses) == sorted(keys)
    np.testing.assert_array_equal(np.array([solver.poses[k] for k in keys]), T)


@pytest.mark.slow
def test_a_relinearisation_budget_holds_back_the_smallest_steps_and_still_converges(session):
    _, _, truth, problem = _circle(160)
    # One update per solve leaves a pending step for the next one to relinearise.
    cfg = dataclasses.replace(CFG, relinearize_budget=40, incremental_max_updates=1)
    for n in range(60, 141, 20):
        solve_full_ba_incremental(problem_prefix(problem, n), cfg, GRAPH, session, 0)
    isam = _SOLVERS[(session, 0)].isam
    keys = list(isam.getLinearizationPoint().keys())
    delta = isam.getDelta()
    step = {k: float(np.abs(delta.at(k)).max()) for k in keys}
    over = {k for k, v in step.items() if v >= cfg.relinearize_threshold}
    assert len(over) > 40  # the next update would relinearise more than the budget
    held = _held_back(isam, cfg)
    assert held is not None and held.size() == len(over) - 40
    held_keys = set()
    while not held.empty():
        held_keys.add(held.front())
        held.pop_front()
    assert held_keys <= over
    let_go = over - held_keys
    assert min(step[k] for k in let_go) >= max(step[k] for k in held_keys)
    assert _held_back(isam, dataclasses.replace(cfg, relinearize_budget=len(over))) is None
    assert _held_back(isam, CFG) is None  # no budget by default
    res = solve_full_ba_incremental(
        problem, dataclasses.replace(cfg, incremental_max_updates=8), GRAPH, session, 0
    )
    assert res.mode == "isam2"
    assert abs(map_scale(res.T_world_body, truth.T_world_body) - 1.0) < 0.01


def test_culled_keyframes_leave_the_graph_and_an_imu_term_spans_them(session):
    atlas, store, _, problem = _circle(80)
    first = solve_full_ba_incremental(problem, CFG, GRAPH, session, 0)
    assert first.mode == "isam2-reset"
    gone = problem.keys[40:42].tolist()
    for k in gone:
        atlas.remove_keyframe(int(k))
    culled = build_full_ba(atlas, 0, default_camera(), CFG, GRAPH, store, _imu_of)
    assert culled.imu is not None
    pairs = set(zip(culled.imu.pair_i.tolist(), culled.imu.pair_j.tolist(), strict=True))
    assert (39, 40) in pairs  # keyframe 39 to the old 42 (now index 40): 0.75 s of IMU
    res = solve_full_ba_incremental(culled, CFG, GRAPH, session, 0)
    assert res.mode == "isam2"
    assert not set(gone) & set(res.keys.tolist())
    batch = solve_full_ba(culled, CFG, GRAPH)
    assert _positions_cm(res.T_world_body, batch.T_world_body) < 1.0
    assert res.final_rms_px < 1.05 * batch.final_rms_px


def _without_rows(problem: FullBAProblem, rows: np.ndarray) -> FullBAProblem:
    keep = np.setdiff1d(np.arange(problem.obs_kf.size), rows)
    return dataclasses.replace(
        problem,
        obs_kf=problem.obs_kf[keep],
        obs_point=problem.obs_point[keep],
        obs_xy=problem.obs_xy[keep],
        obs_sigma=problem.obs_sigma[keep],
    )


def test_only_a_keyframe_whose_observations_changed_has_its_terms_redone(session):
    _, _, _, problem = _circle(60)
    solve_full_ba_incremental(problem, CFG, GRAPH, session, 0)
    solver = _SOLVERS[(session, 0)]
    before = {k: dict(v) for k, v in solver.obs_factors.items()}
    k = int(problem.keys[30])
    drop = np.flatnonzero(problem.obs_kf == 30)[:3]
    gone = set(problem.point_keys[problem.obs_point[drop]].tolist())
    assert solve_full_ba_incremental(_without_rows(problem, drop), CFG, GRAPH, session, 0).mode == (
        "isam2"
    )
    after = solver.obs_factors
    assert after[k] == {p: i for p, i in before[k].items() if p not in gone}
    assert {q: v for q, v in after.items() if q != k} == {q: v for q, v in before.items() if q != k}
    # Observed again: new terms for those three, the others untouched.
    solve_full_ba_incremental(problem, CFG, GRAPH, session, 0)
    assert set(after[k]) == set(before[k])
    assert all(after[k][p] != before[k][p] for p in gone)
    assert all(after[k][p] == before[k][p] for p in set(before[k]) - gone)


def _with_loop(problem: FullBAProblem, i: int, j: int, T_i_j: np.ndarray) -> FullBAProblem:
    sig = np.array([GRAPH.loop_sigma_rot_rad] * 3 + [GRAPH.loop_sigma_trans_m] * 3)
    return dataclasses.replace(
        problem,
        edge_i=np.append(problem.edge_i, i),
        edge_j=np.append(problem.edge_j, j),
        T_i_j=np.concatenate([problem.T_i_j.reshape(-1, 4, 4), T_i_j[None]]),
        sigmas=np.concatenate([problem.sigmas.reshape(-1, 6), sig[None]]),
        robust=np.append(problem.robust, True),
    )


def test_an_outlier_loop_is_left_out_once_and_a_consistent_one_kept(session):
    _, _, truth, problem = _circle(80)
    solve_full_ba_incremental(problem_prefix(problem, 60), CFG, GRAPH, session, 0)
    T = truth.T_world_body
    good = inverse_T(T[5]) @ T[70]
    bad = good.copy()
    bad[:3, 3] += [1.5, -1.0, 0.5]
    p = _with_loop(_with_loop(problem, 5, 70, good), 10, 75, bad)
    n_edges = p.edge_i.shape[0]
    res = solve_full_ba_incremental(p, CFG, GRAPH, session, 0)
    assert res.mode == "isam2"
    assert res.rejected_edges.tolist() == [n_edges - 1]
    again = solve_full_ba_incremental(p, CFG, GRAPH, session, 0)  # decided once, kept out
    assert again.rejected_edges.tolist() == [n_edges - 1]


def test_a_new_agent_or_held_keyframe_rebuilds_the_graph(session):
    _, _, _, problem = _circle(60)
    assert solve_full_ba_incremental(problem, CFG, GRAPH, session, 0).mode == "isam2-reset"
    assert solve_full_ba_incremental(problem, CFG, GRAPH, session, 0).mode == "isam2"
    moved = dataclasses.replace(problem, fixed=3)
    assert solve_full_ba_incremental(moved, CFG, GRAPH, session, 0).mode == "isam2-reset"
    # Another map of the same session has a graph of its own.
    assert solve_full_ba_incremental(problem, CFG, GRAPH, session, 1).mode == "isam2-reset"


def test_the_service_request_dispatches_on_the_switch(session):
    _, _, _, problem = _circle(40)
    off = dataclasses.replace(FullBAConfig(), incremental=False)
    batch = SolveRequest(0, SolveKind.FULL_BA, problem, 0, GRAPH, off, session)
    inc = dataclasses.replace(batch, full_ba=CFG)
    assert [solve(batch).mode, solve(batch).mode] == ["batch", "batch"]
    assert [solve(inc).mode, solve(inc).mode] == ["isam2-reset", "isam2"]


def test_a_map_under_the_size_threshold_is_solved_in_batch_and_drops_its_graph(session):
    _, _, _, problem = _circle(60)
    small = dataclasses.replace(CFG, incremental_min_keyframes=50)
    modes = [
        solve_full_ba_incremental(problem_prefix(problem, n), small, GRAPH, session, 0).mode
        for n in (40, 55, 60, 45)
    ]
    assert modes == ["batch", "isam2-reset", "isam2", "batch"]
    assert (session, 0) not in _SOLVERS  # grown again, it starts from a fresh graph
    assert FullBAConfig().incremental and FullBAConfig().incremental_min_keyframes > 0
