"""PinholeRadtan: distortion round trips and agreement with OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.calibration import CameraCalibration
from common.camera import CameraModelError, PinholeRadtan
from common.data.synth.generate import EUROC_CAM0

CAM = EUROC_CAM0  # EuRoC MH/V cam0 intrinsics and radial-tangential distortion


def _random_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0, 0], [CAM.width - 1, CAM.height - 1], size=(n, 2))
    rays = CAM.unproject(uv)
    depth = rng.uniform(0.3, 20.0, size=(n, 1))
    return rays / rays[:, 2:3] * depth


def test_project_matches_cv2_project_points() -> None:
    p = _random_points(500)
    ours = CAM.project(p)
    cv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), CAM.K, CAM.dist_coeffs)
    np.testing.assert_allclose(ours, cv.reshape(-1, 2), atol=1e-6)


def test_undistort_matches_cv2_and_round_trips_over_whole_image() -> None:
    uv = CAM.pixel_grid()[::97]
    xy = CAM.pixels_to_normalized(uv)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    cv = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), CAM.K, CAM.dist_coeffs, None, None, None, criteria
    )
    np.testing.assert_allclose(xy, cv.reshape(-1, 2), atol=1e-7)
    # Pixel -> ray -> pixel is exact, including the image corners.
    back = CAM.project(CAM.unproject(uv))
    np.testing.assert_allclose(back, uv, atol=1e-8)


def test_distort_undistort_are_inverse() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.7, 0.7, size=(1000, 2))
    np.testing.assert_allclose(CAM.undistort(CAM.distort(xy)), xy, atol=1e-10)


def test_pixel_rays_are_unit_and_centre_ray_is_optical_axis() -> None:
    small = CAM.scaled(0.25)
    rays = small.pixel_rays()
    assert rays.shape == (small.height, small.width, 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=2), 1.0, atol=1e-12)
    centre = small.unproject(np.array([[small.cx, small.cy]]))
    np.testing.assert_allclose(centre, [[0.0, 0.0, 1.0]], atol=1e-12)


def test_scaled_camera_sees_the_same_rays() -> None:
    small = CAM.scaled(0.5)
    p = _random_points(50, seed=2)
    uv_full = CAM.project(p)
    uv_small = small.project(p)
    np.testing.assert_allclose(uv_small + 0.5, 0.5 * (uv_full + 0.5), atol=1e-9)


def test_points_behind_camera_are_nan() -> None:
    uv = CAM.project(np.array([[0.1, 0.2, -1.0], [0.0, 0.0, 2.0]]))
    assert np.isnan(uv[0]).all()
    np.testing.assert_allclose(uv[1], [CAM.cx, CAM.cy])


def test_calibration_round_trip_and_bad_input() -> None:
    calib = CAM.to_calibration(np.eye(4), 20.0)
    assert isinstance(calib, CameraCalibration)
    assert PinholeRadtan.from_calibration(calib) == CAM
    with pytest.raises(CameraModelError, match="p_cam"):
        CAM.project(np.zeros((3, 2)))
    with pytest.raises(CameraModelError, match="focal"):
        PinholeRadtan(10, 10, -1.0, 1.0, 5.0, 5.0)


def test_normalized_to_pixels_is_project_and_inverts_pixels_to_normalized() -> None:
    """The one radtan model the robot's IMU prediction and the VIO simulator call."""
    p = _random_points(300, seed=3)
    xy = p[:, :2] / p[:, 2:3]
    px = CAM.normalized_to_pixels(xy)
    np.testing.assert_array_equal(px, CAM.project(np.c_[xy, np.ones(len(xy))]))
    np.testing.assert_allclose(CAM.pixels_to_normalized(px), xy, atol=1e-10)
    k1, k2, p1, p2 = CAM.dist_coeffs
    x, y = xy.T
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 * r2  # the callers' former copies, term by term
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    np.testing.assert_allclose(
        px, np.c_[CAM.fx * xd + CAM.cx, CAM.fy * yd + CAM.cy], rtol=1e-13, atol=1e-9
    )
