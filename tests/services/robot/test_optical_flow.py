"""Stateless LK steps: forward–backward check, IMU consistency, RANSAC, association, top-up."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from common.calibration import CameraCalibration
from services.robot.config import FrontEndConfig, LkConfig, RansacModel
from services.robot.optical_flow import (
    associate_nearest,
    quantise,
    ransac_inliers,
    top_up_corners,
    track_points,
)

CAM = CameraCalibration(320, 240, 300.0, 300.0, 160.0, 120.0)


def _textured(seed: int, shape=(240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, shape).astype(np.float32)
    return cv2.normalize(
        cv2.GaussianBlur(noise, (0, 0), 2.0), None, 0, 255, cv2.NORM_MINMAX
    ).astype(np.uint8)


def test_forward_backward_rejects_planted_wrong_track() -> None:
    cam = CAM
    prev = _textured(3)
    shift = np.array([2.0, 1.0])
    cur = cv2.warpAffine(prev, np.float32([[1, 0, shift[0]], [0, 1, shift[1]]]), (320, 240))
    grid = np.stack(np.meshgrid(np.arange(40, 281, 40), np.arange(40, 201, 40)), -1).reshape(-1, 2)
    pts = grid.astype(np.float64)
    guess = pts + shift
    planted = 7
    guess[planted] = pts[planted] + [23.0, -17.0]  # an initial guess in the wrong place
    lk = LkConfig(win_size=9, max_level=0, ransac=False)
    no_fb = track_points(
        dataclasses.replace(lk, check_forward_backward=False), cam, prev, cur, pts, guess, False
    )
    assert no_fb.keep[planted]  # LK alone accepts it ...
    assert np.linalg.norm(no_fb.cur_pts[planted] - pts[planted] - shift) > 5.0  # ... wrongly
    res = track_points(lk, cam, prev, cur, pts, guess, False)
    assert not res.keep[planted]
    good = np.delete(np.arange(len(pts)), planted)
    assert res.keep[good].all()
    np.testing.assert_allclose(res.cur_pts[good], pts[good] + shift, atol=0.1)


def test_imu_consistency_rejects_track_far_from_prediction() -> None:
    cam = CAM
    prev = _textured(4)
    cur = prev.copy()
    pts = np.stack(np.meshgrid(np.arange(40, 281, 40), np.arange(40, 201, 40)), -1)
    pts = pts.reshape(-1, 2).astype(np.float64)
    guess = pts.copy()
    guess[5] += [12.0, 0.0]  # prediction says it moved 12 px; the image says it did not
    lk = LkConfig(win_size=15, max_level=3, ransac=False, imu_residual_min_px=5.0)
    unchecked = track_points(lk, cam, prev, cur, pts, guess, False)
    assert unchecked.keep[5]  # LK found the true place despite the prediction
    np.testing.assert_allclose(unchecked.cur_pts[5], pts[5], atol=0.1)
    res = track_points(lk, cam, prev, cur, pts, guess, True)
    assert not res.keep[5] and res.keep.sum() == len(pts) - 1


def test_quantise_to_quarter_pixel() -> None:
    q = quantise(np.array([[1.12, 2.38], [-0.13, 5.874]]), 0.25)
    np.testing.assert_array_equal(q, [[1.0, 2.5], [-0.25, 5.75]])


def test_associate_nearest_is_one_to_one_within_radius() -> None:
    a = np.array([[0.0, 0.0], [10.0, 0.0], [50.0, 50.0]])
    b = np.array([[0.5, 0.0], [1.0, 0.0], [10.0, 2.0], [80.0, 80.0]])
    ia, ib = associate_nearest(a, b, radius_px=3.0)
    pairs = dict(zip(ia.tolist(), ib.tolist(), strict=True))
    assert pairs == {0: 0, 1: 2}  # closest pair first; b[1] left over; a[2] has none in reach


def test_ransac_drops_planted_outliers() -> None:
    rng = np.random.default_rng(5)
    p_cam = np.c_[rng.uniform(-2, 2, (200, 2)), rng.uniform(3, 8, 200)]
    R = cv2.Rodrigues(np.array([0.02, -0.03, 0.01]))[0]
    t = np.array([0.2, 0.0, 0.05])
    x0 = p_cam[:, :2] / p_cam[:, 2:]
    q = p_cam @ R.T + t
    x1 = q[:, :2] / q[:, 2:]
    px0, px1 = x0 * 300 + [160, 120], x1 * 300 + [160, 120]
    px1[:20] += rng.uniform(8, 20, (20, 2)) * rng.choice([-1, 1], (20, 2))
    for model in RansacModel:
        inl = ransac_inliers(CAM, px0, px1, LkConfig(ransac_model=model))
        assert not inl[:20].any(), model
        assert inl[20:].mean() > 0.95, model


def test_top_up_fills_empty_cells_only() -> None:
    image = _textured(6, (240, 336))
    cfg = FrontEndConfig()
    fast = cv2.FastFeatureDetector_create(threshold=10)
    # Tracks cover the left half: new corners appear only on the right, away from the tracks.
    tracked = np.stack(np.meshgrid(np.arange(10, 168, 8), np.arange(10, 240, 8)), -1)
    tracked = tracked.reshape(-1, 2).astype(np.float64)
    new = top_up_corners(image, tracked, cfg, fast)
    assert len(new) > 5
    assert np.all(new[:, 0] >= 168)
    cells = {(int(x // 48), int(y // 48)) for x, y in new}
    assert len(cells) == len(new)  # at most one per sparse cell
