"""Visual-inertial initialisation: scale and gravity from the inertial-only MAP estimate."""

from dataclasses import replace

import numpy as np

from common.geometry import make_T, so3_exp
from common.preintegration import make_preintegration_params
from services.edge.vio.vi_init import inertial_only_map, subsample_keyframes
from sim.vio import SimConfig, ground_truth_map, simulate


def _visual_frame_keyframes(n_keyframes: int, pos_noise_m: float, rot_noise_deg: float):
    """Ground-truth keyframes moved into an arbitrary up-to-scale 'visual' frame."""
    opts = SimConfig(duration_s=6.0, seed=3)
    seq = simulate(opts)
    vmap, _ = ground_truth_map(seq, n_keyframes, opts)
    rng = np.random.default_rng(0)
    R_vw = so3_exp([0.3, -1.2, 0.5])
    s_vw = 0.25  # visual map is 4x smaller than the world
    kfs = []
    for kf in vmap.keyframe_list():
        R = kf.T_world_body[:3, :3] @ so3_exp(rng.normal(0, np.radians(rot_noise_deg), 3))
        p = kf.T_world_body[:3, 3] + rng.normal(0, pos_noise_m, 3)
        kfs.append(replace(kf, T_world_body=make_T(R_vw @ R, s_vw * R_vw @ p)))
    return seq, kfs, R_vw, s_vw


def _gravity_error_deg(R_world_v: np.ndarray, R_vw: np.ndarray) -> float:
    g_est_v = R_world_v.T @ np.array([0.0, 0.0, -1.0])
    g_true_v = R_vw @ np.array([0.0, 0.0, -1.0])
    return float(np.degrees(np.arccos(np.clip(g_est_v @ g_true_v, -1.0, 1.0))))


def test_inertial_only_map_recovers_scale_gravity_and_gyro_bias():
    seq, kfs, R_vw, s_vw = _visual_frame_keyframes(12, 0.0, 0.0)
    params = make_preintegration_params(seq.imu, 9.81, 1e-4)
    # Accelerometer bias left free (sigma 0.1 m/s²): exact poses make it observable.
    res, reason = inertial_only_map(kfs, params, 9.81, np.zeros(3), np.zeros(3), 0.1, 0.1)
    assert res is not None, reason
    assert abs(res.scale * s_vw - 1.0) < 0.02
    assert _gravity_error_deg(res.R_world_v, R_vw) < 1.0
    assert np.linalg.norm(res.bias_gyro - np.array(SimConfig().bias_gyro)) < 5e-4


def test_inertial_only_map_with_noisy_visual_poses_within_bounds():
    # 1 cm / 0.05 deg pose noise, 4 s: the visual-noise-aware weighting keeps the scale.
    seq, kfs, R_vw, s_vw = _visual_frame_keyframes(17, 0.01, 0.05)
    params = make_preintegration_params(seq.imu, 9.81, 1e-4)
    sub = subsample_keyframes(kfs, 0.5)
    assert len(sub) < len(kfs)
    res, reason = inertial_only_map(
        sub, params, 9.81, np.zeros(3), np.zeros(3), 1e-5, 0.1, 0.01 * s_vw, np.radians(0.05)
    )
    assert res is not None, reason
    assert abs(res.scale * s_vw - 1.0) < 0.05
    assert _gravity_error_deg(res.R_world_v, R_vw) < 2.0


def test_inertial_only_map_rejects_too_few_keyframes():
    seq, kfs, _, _ = _visual_frame_keyframes(2, 0.0, 0.0)
    params = make_preintegration_params(seq.imu, 9.81, 1e-4)
    res, reason = inertial_only_map(kfs, params, 9.81, np.zeros(3), np.zeros(3), 1e-5, 0.1)
    assert res is None
    assert "keyframes" in reason
