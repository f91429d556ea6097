"""Local bundle adjustment on a perturbed synthetic window."""

import numpy as np
import pytest

from common.geometry import so3_exp
from common.preintegration import make_preintegration_params
from services.edge.vio.local_ba import bundle_adjust, reprojection_chi2
from services.edge.vio.types import LocalBAConfig, MappingConfig
from sim.vio import SimConfig, ground_truth_map, simulate


@pytest.fixture(scope="module")
def scene():
    opts = SimConfig(duration_s=5.0, seed=7)
    return opts, simulate(opts)


@pytest.mark.parametrize("use_imu", [False, True])
def test_local_ba_lowers_error_and_keeps_fixed_keyframes(scene, use_imu):
    opts, seq = scene
    vmap, cam = ground_truth_map(seq, 16, opts)
    ids = [kf.id for kf in vmap.keyframe_list()]
    window, outside = ids[-8:], ids[:-8]
    fixed_before = {k: vmap.keyframes[k].T_world_body.copy() for k in outside}
    true_pose = {k: vmap.keyframes[k].T_world_body.copy() for k in window}
    rng = np.random.default_rng(0)
    for k in window:
        kf = vmap.keyframes[k]
        kf.T_world_body[:3, :3] = kf.T_world_body[:3, :3] @ so3_exp(rng.normal(0, 0.005, 3))
        kf.T_world_body[:3, 3] += rng.normal(0, 0.03, 3)
    window_points = {p for k in window for p in vmap.keyframes[k].row_of if p in vmap.points}
    for p in window_points:
        vmap.points[p].p_world = vmap.points[p].p_world + rng.normal(0, 0.03, 3)
    chi2_before = reprojection_chi2(vmap, window, cam)
    params = make_preintegration_params(seq.imu, 9.81, 1e-4) if use_imu else None
    stats = bundle_adjust(vmap, window, cam, params, LocalBAConfig(), MappingConfig())
    chi2_after = reprojection_chi2(vmap, window, cam)
    assert stats.n_fixed >= 1
    assert stats.error_after < 0.2 * stats.error_before
    assert chi2_after < 0.2 * chi2_before
    assert chi2_after < 2.0  # 0.5 px noise against a 1 px model: about 0.5 expected
    for k, T in fixed_before.items():
        assert np.allclose(vmap.keyframes[k].T_world_body, T, atol=1e-5)
    # The window moves back towards the truth (fixed observers hold the gauge).
    err = [
        np.linalg.norm(vmap.keyframes[k].T_world_body[:3, 3] - true_pose[k][:3, 3]) for k in window
    ]
    assert np.median(err) < 0.02


def test_visual_inertial_ba_recovers_a_wrong_scale(scene):
    opts, seq = scene
    vmap, cam = ground_truth_map(seq, 16, opts)
    ids = [kf.id for kf in vmap.keyframe_list()]
    for kf in vmap.keyframe_list():
        kf.T_world_body[:3, 3] *= 1.3
        kf.v_world = kf.v_world * 1.3
        kf.bias_accel = np.zeros(3)
        kf.bias_gyro = np.zeros(3)
    for mp in vmap.points.values():
        mp.p_world = mp.p_world * 1.3
    params = make_preintegration_params(seq.imu, 9.81, 1e-4)
    bundle_adjust(
        vmap,
        ids,
        cam,
        params,
        LocalBAConfig(),
        MappingConfig(),
        gauge_ids=(ids[0],),
        max_iterations=30,
    )
    kfs = vmap.keyframe_list()
    gt = {int(t): i for i, t in enumerate(seq.gt_timestamps_ns)}
    est = np.array([kf.T_world_body[:3, 3] for kf in kfs])
    ref = seq.gt_T_world_body[[gt[kf.timestamp_ns] for kf in kfs], :3, 3]
    span_est = np.linalg.norm(est - est[0], axis=1).sum()
    span_gt = np.linalg.norm(ref - ref[0], axis=1).sum()
    assert abs(span_est / span_gt - 1.0) < 0.03
    assert np.linalg.norm(kfs[-1].bias_gyro - np.array(opts.bias_gyro)) < 1e-3
