"""Two-view initialisation on synthetic correspondences."""

import numpy as np

from common.geometry import so3_exp, so3_log
from services.edge.vio.mono_init import two_view_geometry
from services.edge.vio.types import MonoInitConfig

FOCAL = 458.0


def _views(points_c0: np.ndarray, R: np.ndarray, t: np.ndarray, noise_px: float, seed: int):
    rng = np.random.default_rng(seed)
    p1 = points_c0 @ R.T + t
    x0 = points_c0[:, :2] / points_c0[:, 2:3] + rng.normal(0, noise_px / FOCAL, (len(p1), 2))
    x1 = p1[:, :2] / p1[:, 2:3] + rng.normal(0, noise_px / FOCAL, (len(p1), 2))
    return x0, x1


def test_essential_model_recovers_motion_of_a_3d_scene():
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-2, 2, (150, 2)), rng.uniform(3, 7, 150)]
    R = so3_exp([0.02, -0.05, 0.01])
    t = np.array([-0.4, 0.05, 0.02])
    x0, x1 = _views(pts, R, t, 0.5, 2)
    res, reason = two_view_geometry(x0, x1, FOCAL, MonoInitConfig())
    assert res is not None, reason
    assert res.model == "E"
    assert np.degrees(np.linalg.norm(so3_log(res.R_c1_c0.T @ R))) < 0.3
    cos = res.t_c1_c0 @ t / (np.linalg.norm(res.t_c1_c0) * np.linalg.norm(t))
    assert np.degrees(np.arccos(min(cos, 1.0))) < 3.0
    # Arbitrary scale: median depth of the triangulated points is 1.
    assert abs(np.median(res.p_c0[res.good, 2]) - 1.0) < 1e-9
    assert res.good.sum() >= 100


def test_homography_model_chosen_for_a_plane():
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-2, 2, (150, 2)), np.full(150, 4.0)]
    R = so3_exp([0.0, -0.06, 0.0])
    t = np.array([-0.6, 0.0, 0.0])
    x0, x1 = _views(pts, R, t, 0.5, 4)
    res, reason = two_view_geometry(x0, x1, FOCAL, MonoInitConfig())
    assert res is not None, reason
    assert res.model == "H"
    assert np.degrees(np.linalg.norm(so3_log(res.R_c1_c0.T @ R))) < 0.5


def test_rejects_pure_rotation_for_lack_of_parallax():
    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(-2, 2, (150, 2)), rng.uniform(3, 7, 150)]
    x0, x1 = _views(pts, so3_exp([0.0, 0.05, 0.0]), np.zeros(3), 0.5, 6)
    res, reason = two_view_geometry(x0, x1, FOCAL, MonoInitConfig())
    assert res is None
    assert reason
