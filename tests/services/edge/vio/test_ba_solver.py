"""Schur-complement LM of the local BA against the gtsam reference on synthetic windows."""

import copy
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from common.geometry import so3_exp
from common.preintegration import make_preintegration_params
from services.edge.vio import ba_solver
from services.edge.vio.ba_solver import Observations, SchurLM, reprojection_terms
from services.edge.vio.ba_sparse import sparse_spd_solve
from services.edge.vio.local_ba import bundle_adjust, reprojection_chi2
from services.edge.vio.types import LocalBAConfig, MappingConfig, VioError
from sim.vio import SimConfig, ground_truth_map, simulate


@pytest.fixture(scope="module")
def scene():
    opts = SimConfig(duration_s=5.0, seed=7)
    return opts, simulate(opts)


def _perturbed(scene, n_window: int = 8, seed: int = 0, n_keyframes: int = 16):
    """Ground-truth map of ``n_keyframes``; the newest ``n_window`` and their points
    perturbed."""
    opts, seq = scene
    vmap, cam = ground_truth_map(seq, n_keyframes, opts)
    ids = [kf.id for kf in vmap.keyframe_list()]
    window = ids[-n_window:]
    rng = np.random.default_rng(seed)
    for k in window:
        kf = vmap.keyframes[k]
        kf.T_world_body[:3, :3] = kf.T_world_body[:3, :3] @ so3_exp(rng.normal(0, 0.005, 3))
        kf.T_world_body[:3, 3] += rng.normal(0, 0.03, 3)
    window_points = sorted(
        {p for k in window for p in vmap.keyframes[k].row_of if p in vmap.points}
    )
    for p in window_points:
        vmap.points[p].p_world = vmap.points[p].p_world + rng.normal(0, 0.03, 3)
    return vmap, cam, ids, window


def _angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    c = np.clip((np.trace(R_a.T @ R_b) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def _both(vmap, window, cam, params, **kw):
    """Run the gtsam and the Schur solver on copies; (maps, stats) per solver."""
    out = {}
    for solver in ("gtsam", "schur"):
        vm = copy.deepcopy(vmap)
        opts = replace(LocalBAConfig(), solver=solver)
        out[solver] = (vm, bundle_adjust(vm, window, cam, params, opts, MappingConfig(), **kw))
    return out


def _assert_agree(out, keyframe_ids):
    (vg, sg), (vs, ss) = out["gtsam"], out["schur"]
    assert ss.n_observations == sg.n_observations and ss.n_points == sg.n_points
    assert ss.error_before == pytest.approx(sg.error_before, rel=1e-9)
    assert ss.error_after == pytest.approx(sg.error_after, rel=0.01)
    assert ss.culled_observations == sg.culled_observations
    for k in keyframe_ids:
        Tg, Ts = vg.keyframes[k].T_world_body, vs.keyframes[k].T_world_body
        assert np.linalg.norm(Tg[:3, 3] - Ts[:3, 3]) < 1e-3
        assert _angle_deg(Tg[:3, :3], Ts[:3, :3]) < 0.05
        assert np.linalg.norm(vg.keyframes[k].v_world - vs.keyframes[k].v_world) < 1e-3
        assert np.linalg.norm(vg.keyframes[k].bias_gyro - vs.keyframes[k].bias_gyro) < 1e-4
    assert set(vg.points) == set(vs.points)
    d = [np.linalg.norm(vg.points[p].p_world - vs.points[p].p_world) for p in vg.points]
    assert max(d) < 3e-3


@pytest.mark.parametrize("use_imu", [False, True])
def test_schur_agrees_with_gtsam_and_keeps_fixed_keyframes(scene, use_imu):
    _, seq = scene
    vmap, cam, ids, window = _perturbed(scene)
    outside = [k for k in ids if k not in window]
    params = make_preintegration_params(seq.imu, 9.81, 1e-4) if use_imu else None
    out = _both(vmap, window, cam, params)
    _assert_agree(out, window)
    vs, stats = out["schur"]
    assert stats.n_fixed >= 1
    assert stats.error_after < 0.2 * stats.error_before
    chi2_before = reprojection_chi2(vmap, window, cam)
    assert reprojection_chi2(vs, window, cam) < 0.2 * chi2_before
    for k in outside:  # constants of the Schur solver: bit-identical
        assert np.array_equal(vs.keyframes[k].T_world_body, vmap.keyframes[k].T_world_body)


def test_schur_agrees_with_gtsam_on_a_gauge_held_visual_inertial_window(scene):
    """No keyframe outside the window: the gauge keyframe holds the map; the bias prior on the
    first keyframe and every velocity/bias are variables (the VI refinements' problem)."""
    _, seq = scene
    vmap, cam, ids, _ = _perturbed(scene, n_window=16, seed=1)
    params = make_preintegration_params(seq.imu, 9.81, 1e-4)
    out = _both(vmap, ids, cam, params, gauge_ids=(ids[0],), max_iterations=10)
    _assert_agree(out, ids)
    vs, stats = out["schur"]
    assert stats.n_fixed == 1
    assert np.array_equal(vs.keyframes[ids[0]].T_world_body, vmap.keyframes[ids[0]].T_world_body)
    assert stats.error_after < 0.2 * stats.error_before


def test_points_only_problem_when_every_pose_is_a_gauge(scene):
    """Mono-init BA of two keyframes, both held: only points move (no camera-side system)."""
    vmap, cam, pair, _ = _perturbed(scene, n_window=2, seed=2, n_keyframes=2)
    out = _both(vmap, pair, cam, None, gauge_ids=tuple(pair))
    _assert_agree(out, pair)
    vs, stats = out["schur"]
    assert stats.error_after < 0.5 * stats.error_before
    for k in pair:
        assert np.array_equal(vs.keyframes[k].T_world_body, vmap.keyframes[k].T_world_body)


def test_reprojection_linearisation_matches_gtsam_factors(scene):
    """Cost, whitened IRLS Jacobians and right-hand side of every observation equal those of
    gtsam's robust GenericProjectionFactorCal3_S2 (one point put behind its camera)."""
    vmap, cam, _, window = _perturbed(scene, n_window=3, seed=3)
    kfs = [vmap.keyframes[k] for k in window]
    pose, point, xy, sigma, P = [], [], [], [], []
    for i, kf in enumerate(kfs):
        for t, r in list(kf.row_of.items())[:15]:
            mp = vmap.point_of(t)
            if mp is None:
                continue
            pose.append(i)
            point.append(len(P))
            P.append(mp.p_world + np.random.default_rng(len(P)).normal(0, 0.05, 3))
            xy.append(kf.xy[r])
            sigma.append(kf.sigma[r])
    P = np.array(P)
    T_wc = kfs[0].T_world_body @ cam.T_body_cam
    P[0] = T_wc[:3, 3] - 2.0 * T_wc[:3, 2]  # 2 m behind the first camera
    obs = Observations(np.array(pose), np.array(point), np.array(xy), np.array(sigma))
    T = np.array([kf.T_world_body for kf in kfs])
    k = 2.4477
    cost, J, b = reprojection_terms(T, P, obs, cam.T_body_cam, k)
    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    values = gtsam.Values()
    for i, kf in enumerate(kfs):
        values.insert(X(i), gtsam.Pose3(kf.T_world_body))
    total = 0.0
    for m in range(len(pose)):
        values.insert(L(m), P[m])
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(k),
            gtsam.noiseModel.Isotropic.Sigma(2, sigma[m]),
        )
        f = gtsam.GenericProjectionFactorCal3_S2(
            xy[m], noise, X(pose[m]), L(m), K, gtsam.Pose3(cam.T_body_cam)
        )
        total += f.error(values)
        gfg = gtsam.GaussianFactorGraph()
        gfg.push_back(f.linearize(values))
        ordering = gtsam.Ordering()
        ordering.push_back(X(pose[m]))
        ordering.push_back(L(m))
        A, b_ref = gfg.jacobian(ordering)
        assert np.allclose(J[m], A, rtol=1e-6, atol=1e-9 * max(np.abs(A).max(), 1.0))
        assert np.allclose(b[m], np.ravel(b_ref), rtol=1e-9, atol=1e-12)
    assert cost == pytest.approx(total, rel=1e-10)
    assert np.all(J[0] == 0.0)  # behind the camera: gtsam's zero Jacobians


def test_schur_lm_stops_at_max_iterations_and_reports_its_costs(scene):
    vmap, cam, ids, window = _perturbed(scene, seed=4)
    obs_kf = {k: i for i, k in enumerate(ids)}
    pose, point, xy, sigma, P = [], [], [], [], []
    for mp in vmap.points.values():
        seen = [(k, r) for k, r in mp.observations.items() if k in obs_kf]
        if len(seen) < 2:
            continue
        for k, r in seen:
            pose.append(obs_kf[k])
            point.append(len(P))
            xy.append(vmap.keyframes[k].xy[r])
            sigma.append(vmap.keyframes[k].sigma[r])
        P.append(mp.p_world)
    obs = Observations(np.array(pose), np.array(point), np.array(xy), np.array(sigma))
    values = gtsam.Values()
    for k, i in obs_kf.items():
        values.insert(X(i), gtsam.Pose3(vmap.keyframes[k].T_world_body))
    free = [X(obs_kf[k]) for k in window]
    problem = SchurLM(
        gtsam.NonlinearFactorGraph(),
        values,
        free,
        [X(i) for i in range(len(ids))],
        np.array(P),
        obs,
        cam.T_body_cam,
        2.4477,
    )
    one = problem.optimize(max_iterations=1, relative_error_tol=0.0)
    many = problem.optimize(max_iterations=20, relative_error_tol=1e-6)
    assert one.iterations == 1
    assert 1 < many.iterations <= 20
    assert one.error_before == pytest.approx(problem.cost(values, np.array(P)))
    assert many.error_after < one.error_after < one.error_before
    assert many.error_after == pytest.approx(problem.cost(many.values, many.p_world))


def test_large_windows_fall_back_to_gtsam_and_unknown_solvers_are_rejected(scene):
    vmap, cam, _, window = _perturbed(scene, seed=5)
    results = []
    for opts in (LocalBAConfig(solver="gtsam"), LocalBAConfig(schur_max_keyframes=4)):
        vm = copy.deepcopy(vmap)
        results.append((vm, bundle_adjust(vm, window, cam, None, opts, MappingConfig())))
    (va, sa), (vb, sb) = results
    assert sa == sb  # 8 free keyframes > 4: the gtsam path, bit for bit
    for k in window:
        assert np.array_equal(va.keyframes[k].T_world_body, vb.keyframes[k].T_world_body)
    with pytest.raises(VioError, match="solver"):
        LocalBAConfig(solver="ceres")


def test_big_visual_inertial_window_uses_the_sparse_system_and_agrees_with_gtsam(monkeypatch):
    """A 60-keyframe window with IMU (894 camera-side dimensions, the gauge pose held), as
    the VI refinements over every keyframe: the Schur solver's sparse reduced camera system
    gives gtsam's solution, and the dense one's to rounding."""
    opts = SimConfig(duration_s=15.0, seed=7)
    seq = simulate(opts)
    vmap, cam, ids, _ = _perturbed((opts, seq), n_window=60, seed=6, n_keyframes=60)
    assert len(ids) == 60
    params = make_preintegration_params(seq.imu, 9.81, 1e-4)
    kw = {"gauge_ids": (ids[0],), "max_iterations": 10}
    sparse_solves = []

    def counting_solve(S, rhs):
        sparse_solves.append(S.shape)
        return sparse_spd_solve(S, rhs)

    monkeypatch.setattr(ba_solver, "sparse_spd_solve", counting_solve)
    out = _both(vmap, ids, cam, params, **kw)
    assert sparse_solves and all(shape == (60 * 15 - 6,) * 2 for shape in sparse_solves)
    _assert_agree(out, ids)
    vs, stats = out["schur"]
    assert stats.error_after < 0.2 * stats.error_before
    n_sparse = len(sparse_solves)
    monkeypatch.setattr(ba_solver, "SPARSE_MIN_DIM", 10**6)  # the dense reduced system
    vd = copy.deepcopy(vmap)
    dense = bundle_adjust(vd, ids, cam, params, LocalBAConfig(), MappingConfig(), **kw)
    assert len(sparse_solves) == n_sparse
    assert dense.error_after == pytest.approx(stats.error_after, rel=1e-9)
    for k in ids:
        T_d, T_s = vd.keyframes[k].T_world_body, vs.keyframes[k].T_world_body
        assert np.allclose(T_d, T_s, atol=1e-7)
