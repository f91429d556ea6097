"""PinholeEquidistant against cv2.fisheye, its inverses, and both models' projection Jacobians."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.calibration import CameraCalibration
from common.camera import (
    CameraModel,
    CameraModelError,
    PinholeEquidistant,
    PinholeRadtan,
    camera_model,
)
from common.data.synth.generate import EUROC_CAM0

# TUM-VI room cam0 (512x512 equidistant).
FISHEYE = PinholeEquidistant(
    512,
    512,
    190.97847715128717,
    190.9733070521226,
    254.93170605935475,
    256.8974428996504,
    0.0034823894022493434,
    0.0007150348452162257,
    -0.0020532361418706202,
    0.00020293673591811182,
)

finite = st.floats(-1.0, 1.0, allow_nan=False)


def _points(n: int, seed: int, forward_only: bool = True) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    if forward_only:
        p[:, 2] = np.abs(p[:, 2]) + 0.05
    return p * rng.uniform(0.3, 20.0, size=(n, 1))


def test_project_matches_cv2_fisheye_project_points() -> None:
    p = _points(2000, 0)
    cv, _ = cv2.fisheye.projectPoints(
        p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), FISHEYE.K, FISHEYE.dist_coeffs
    )
    np.testing.assert_allclose(FISHEYE.project(p), cv.reshape(-1, 2), rtol=0, atol=1e-9)
    xy = p[:, :2] / p[:, 2:3]
    np.testing.assert_allclose(
        FISHEYE.normalized_to_pixels(xy), cv.reshape(-1, 2), rtol=0, atol=1e-9
    )


def test_undistort_matches_cv2_fisheye_in_front() -> None:
    uv = FISHEYE.pixel_grid()[::53]
    xy = FISHEYE.pixels_to_normalized(uv)
    front = np.isfinite(xy).all(axis=1)
    assert front.mean() > 0.7  # the corners look more than 90 degrees off axis
    cv = cv2.fisheye.undistortPoints(
        uv[front].reshape(-1, 1, 2),
        FISHEYE.K,
        FISHEYE.dist_coeffs,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
    )
    # cv2 stops its own iteration early; compare in pixels through our projection.
    np.testing.assert_allclose(
        FISHEYE.normalized_to_pixels(cv.reshape(-1, 2)), uv[front], atol=1e-4
    )
    np.testing.assert_allclose(FISHEYE.normalized_to_pixels(xy[front]), uv[front], atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.floats(-6.0, 6.0), st.floats(-6.0, 6.0))
def test_undistort_inverts_distort(x: float, y: float) -> None:
    xy = np.array([[x, y]])
    np.testing.assert_allclose(FISHEYE.undistort(FISHEYE.distort(xy)), xy, rtol=1e-10, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, 511.0), st.floats(0.0, 511.0))
def test_unproject_project_round_trip_over_whole_image(u: float, v: float) -> None:
    """Every pixel, the >90 degree corners included, has a unit ray that projects back."""
    uv = np.array([[u, v]])
    ray = FISHEYE.unproject(uv)
    np.testing.assert_allclose(np.linalg.norm(ray, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(FISHEYE.project(ray * 3.7), uv, atol=1e-8)


@settings(max_examples=200, deadline=None)
@given(finite, finite, st.floats(-0.4, 1.0), st.floats(0.2, 30.0))
def test_unproject_of_project_is_the_ray(x: float, y: float, z: float, scale: float) -> None:
    """Any direction up to 113 degrees off axis (behind the image plane too) comes back as its
    unit ray; in front, the normalised point is ``(X / Z, Y / Z)``."""
    p = np.array([[x, y, z]]) * scale
    if np.hypot(x, y) < 1e-3:  # on the axis: straight back has no direction
        return
    uv = FISHEYE.project(p)
    np.testing.assert_allclose(FISHEYE.unproject(uv), p / np.linalg.norm(p), atol=1e-10)
    if z > 0.05:
        np.testing.assert_allclose(
            FISHEYE.pixels_to_normalized(uv), p[:, :2] / p[:, 2:3], rtol=1e-9, atol=1e-9
        )
    elif z < -0.01:
        assert np.isnan(FISHEYE.pixels_to_normalized(uv)).all()


@pytest.mark.parametrize("cam", [FISHEYE, EUROC_CAM0], ids=["equidistant", "radtan"])
def test_project_jacobian_matches_finite_differences(cam: CameraModel) -> None:
    p = _points(400, 5, forward_only=cam is EUROC_CAM0)
    if cam is EUROC_CAM0:
        p = p[np.abs(p[:, :2] / p[:, 2:3]).max(axis=1) < 0.8]
    else:
        p = p[np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2]) < 1.9]
    J = cam.project_jacobian(p)
    assert J.shape == (len(p), 2, 3)
    step = 1e-6 * np.linalg.norm(p, axis=1)
    J_num = np.zeros_like(J)
    for k in range(3):
        d = np.zeros_like(p)
        d[:, k] = step
        J_num[:, :, k] = (cam.project(p + d) - cam.project(p - d)) / (2 * step[:, None])
    scale = np.abs(J_num).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(J / scale, J_num / scale, atol=1e-6)


def test_jacobian_on_axis_and_out_of_view() -> None:
    J = FISHEYE.project_jacobian(np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(J[0], [[FISHEYE.fx / 2, 0, 0], [0, FISHEYE.fy / 2, 0]])
    assert np.isnan(J[1]).all()  # straight back: no direction
    assert np.isnan(FISHEYE.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]]))).all()
    J_r = EUROC_CAM0.project_jacobian(np.array([[0.1, 0.0, -1.0]]))
    assert np.isnan(J_r).all()


def test_fisheye_sees_beyond_ninety_degrees_but_normalised_plane_does_not() -> None:
    corner = np.array([[0.0, 0.0]])
    ray = FISHEYE.unproject(corner)
    assert ray[0, 2] < 0  # TUM-VI's corners look backwards
    assert np.isnan(FISHEYE.pixels_to_normalized(corner)).all()
    assert np.isfinite(FISHEYE.project(ray)).all()
    # A fold-over model is cut at theta_max: beyond it, NaN.
    folding = PinholeEquidistant(100, 100, 50.0, 50.0, 50.0, 50.0, k1=-0.2)
    assert folding.theta_max < np.pi
    behind = np.array([[np.sin(folding.theta_max + 0.1), 0.0, np.cos(folding.theta_max + 0.1)]])
    assert np.isnan(folding.project(behind)).all()


def test_factory_calibration_round_trip_and_scaling() -> None:
    calib = FISHEYE.to_calibration(np.eye(4), 20.0)
    assert calib.model == "equidistant"
    assert camera_model(calib) == FISHEYE
    assert camera_model(EUROC_CAM0.to_calibration(np.eye(4), 20.0)) == EUROC_CAM0
    small = FISHEYE.scaled(0.5)
    p = _points(50, 7)
    np.testing.assert_allclose(small.project(p) + 0.5, 0.5 * (FISHEYE.project(p) + 0.5), atol=1e-9)
    rays = small.pixel_rays()
    assert rays.shape == (256, 256, 3)


def test_bad_shapes_and_parameters_raise() -> None:
    with pytest.raises(CameraModelError, match="p_cam"):
        FISHEYE.project(np.zeros((3, 2)))
    with pytest.raises(CameraModelError, match="p_cam"):
        FISHEYE.project_jacobian(np.zeros(3))
    with pytest.raises(CameraModelError, match="uv"):
        FISHEYE.unproject(np.zeros((2, 3)))
    with pytest.raises(CameraModelError, match="xy"):
        FISHEYE.distort(np.zeros((4,)))
    with pytest.raises(CameraModelError, match="p_cam"):
        EUROC_CAM0.project_jacobian(np.zeros((1, 2)))
    with pytest.raises(CameraModelError, match="focal"):
        PinholeEquidistant(10, 10, 0.0, 1.0, 5.0, 5.0)
    with pytest.raises(CameraModelError, match="size"):
        PinholeEquidistant(0, 10, 1.0, 1.0, 5.0, 5.0)
    with pytest.raises(CameraModelError, match="finite"):
        PinholeEquidistant(10, 10, 1.0, 1.0, 5.0, 5.0, k1=float("nan"))
    with pytest.raises(CameraModelError, match="fold"):
        PinholeEquidistant(10, 10, 1.0, 1.0, 5.0, 5.0, k1=-50.0)
    radtan_calib = CameraCalibration(10, 10, 1.0, 1.0, 5.0, 5.0)
    with pytest.raises(CameraModelError, match="equidistant"):
        PinholeEquidistant.from_calibration(radtan_calib)
    fisheye_calib = FISHEYE.to_calibration(np.eye(4), 20.0)
    with pytest.raises(CameraModelError, match="radtan"):
        PinholeRadtan.from_calibration(fisheye_calib)
