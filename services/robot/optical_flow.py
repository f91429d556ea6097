"""Pyramidal LK between two frames with the checks of Algorithm 1 (stateless functions).

LK starts at a predicted position (``OPTFLOW_USE_INITIAL_FLOW``); a backward pass started
from the inverse motion model checks the round trip; tracks far from the IMU prediction
(relative to the rest) are dropped; RANSAC on undistorted points removes the remaining
outliers. Also: 1/4-px quantisation, nearest-neighbour association and grid top-up corners.
The stateful front end that uses these is :mod:`services.robot.tracker`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from common.calibration import CameraCalibration
from services.robot.config import FrontEndConfig, LkConfig, RansacModel
from services.robot.imu_prediction import undistort_normalised

BackPrediction = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``(cur_pts (M, 2), rows (M,)) -> (M, 2)``: where tracks now at ``cur_pts`` were predicted to
be in the previous image (the motion model run backwards), for the forward–backward check."""


def quantise(pts: np.ndarray, step: float) -> np.ndarray:
    """Round coordinates (N, 2) to the ``step`` grid (e.g. 0.25 px)."""
    return np.round(np.asarray(pts, dtype=np.float64) / step) * step


@dataclass(frozen=True, eq=False)
class PointTrackResult:
    """LK result for N points: ``cur_pts`` (N, 2) px and the mask ``keep`` (N,) of survivors,
    with the survivors after each stage counted."""

    cur_pts: np.ndarray
    keep: np.ndarray
    n_lk: int
    n_fb: int
    n_imu_consistent: int
    n_inliers: int
    lk_time_s: float
    ransac_time_s: float


def _criteria(config: LkConfig) -> tuple[int, int, float]:
    return (
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
        config.max_iterations,
        config.epsilon,
    )


def ransac_inliers(
    camera: CameraCalibration, pts0: np.ndarray, pts1: np.ndarray, config: LkConfig
) -> np.ndarray:
    """Mask (N,) of correspondences (N, 2) px consistent with one two-view model fitted by
    RANSAC on undistorted points (``config.ransac_model``). Points without undistorted
    coordinates (a fisheye's rays at 90 degrees and more off axis) are dropped."""
    n = len(pts0)
    if n < max(config.min_ransac_points, 8):
        return np.ones(n, dtype=bool)
    x0 = undistort_normalised(camera, pts0)
    x1 = undistort_normalised(camera, pts1)
    usable = np.isfinite(x0).all(axis=1) & np.isfinite(x1).all(axis=1)
    if not usable.all():
        inner = ransac_inliers(camera, np.asarray(pts0)[usable], np.asarray(pts1)[usable], config)
        mask = np.zeros(n, dtype=bool)
        mask[usable] = inner
        return mask
    if np.max(np.abs(x1 - x0)) < 1e-9:
        return np.ones(n, dtype=bool)
    if config.ransac_model is RansacModel.ESSENTIAL:
        focal = 0.5 * (camera.fx + camera.fy)
        _, mask = cv2.findEssentialMat(
            x0,
            x1,
            np.eye(3),
            method=cv2.RANSAC,
            prob=config.ransac_confidence,
            threshold=config.ransac_threshold_px / focal,
        )
    else:
        K = camera.K
        u0 = x0 @ K[:2, :2].T + K[:2, 2]
        u1 = x1 @ K[:2, :2].T + K[:2, 2]
        _, mask = cv2.findFundamentalMat(
            u0, u1, cv2.FM_RANSAC, config.ransac_threshold_px, config.ransac_confidence
        )
    if mask is None:
        return np.zeros(n, dtype=bool)
    return mask.reshape(-1).astype(bool)[:n]


def track_points(
    config: LkConfig,
    camera: CameraCalibration,
    prev_image: np.ndarray,
    cur_image: np.ndarray,
    prev_pts: np.ndarray,
    guess_pts: np.ndarray,
    check_imu: bool,
    back_prediction: BackPrediction | None = None,
) -> PointTrackResult:
    """Track ``prev_pts`` (N, 2) from the previous to the current uint8 (H, W) image, starting
    pyramidal LK at ``guess_pts`` (N, 2); then forward–backward check, IMU consistency (offset
    from the guess, if ``check_imu``) and RANSAC.

    The backward pass tracks the forward results back into the previous image, starting where
    the motion model maps them (``back_prediction(cur_pts, rows)``, e.g. the inverse IMU
    rotation; over ``fb_max_level`` levels) or, without a model, at the forward results
    themselves (over ``max_level`` levels). It never starts at the previous positions: a track
    stuck in a wrong place would then pass by not moving.

    The images go to OpenCV as they are: its Python binding rejects the pyramids that
    ``cv2.buildOpticalFlowPyramid`` returns (``prevImg is not a numpy array``), and building
    the pyramid levels ourselves and calling LK per level measured 1 ms slower per frame than
    letting OpenCV build them (0.15 ms per pyramid at 752×480).
    The backward pass starts at the previous position and needs only ``fb_max_level``.
    """
    n = len(prev_pts)
    if n == 0:
        return PointTrackResult(np.zeros((0, 2)), np.zeros(0, bool), 0, 0, 0, 0, 0.0, 0.0)
    p0 = np.ascontiguousarray(prev_pts, dtype=np.float32).reshape(-1, 1, 2)
    guess = np.ascontiguousarray(guess_pts, dtype=np.float32).reshape(-1, 1, 2)
    win = (config.win_size, config.win_size)
    t0 = time.perf_counter()
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        prev_image,
        cur_image,
        p0,
        guess,
        winSize=win,
        maxLevel=config.max_level,
        criteria=_criteria(config),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    cur = p1.reshape(-1, 2).astype(np.float64)
    h, w = cur_image.shape[:2]
    keep = status.reshape(-1).astype(bool) & np.all(np.isfinite(cur), axis=1)
    keep &= (cur[:, 0] >= 0) & (cur[:, 0] <= w - 1) & (cur[:, 1] >= 0) & (cur[:, 1] <= h - 1)
    n_lk = int(keep.sum())
    if config.check_forward_backward and n_lk:
        idx = np.flatnonzero(keep)
        if back_prediction is None:
            back_guess, fb_level = p1[idx].copy(), config.max_level
        else:
            back_guess = back_prediction(cur[idx], idx).astype(np.float32).reshape(-1, 1, 2)
            fb_level = config.fb_max_level
        back, status_b, _ = cv2.calcOpticalFlowPyrLK(
            cur_image,
            prev_image,
            p1[idx].copy(),
            back_guess,
            winSize=win,
            maxLevel=fb_level,
            criteria=_criteria(config),
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        err = np.linalg.norm(back.reshape(-1, 2) - p0[idx].reshape(-1, 2), axis=1)
        ok = status_b.reshape(-1).astype(bool) & (err <= config.fb_threshold_px)
        keep[idx[~ok]] = False
    lk_time = time.perf_counter() - t0
    n_fb = int(keep.sum())
    if check_imu and n_fb:
        offset = np.linalg.norm(cur - np.asarray(guess_pts, dtype=np.float64), axis=1)
        bound = max(
            config.imu_residual_min_px, config.imu_residual_factor * np.median(offset[keep])
        )
        keep &= offset <= bound
    n_imu = int(keep.sum())
    t1 = time.perf_counter()
    if config.ransac and n_imu:
        idx = np.flatnonzero(keep)
        inl = ransac_inliers(camera, np.asarray(prev_pts)[idx], cur[idx], config)
        keep[idx[~inl]] = False
    ransac_time = time.perf_counter() - t1
    return PointTrackResult(cur, keep, n_lk, n_fb, n_imu, int(keep.sum()), lk_time, ransac_time)


def associate_nearest(
    pts_a: np.ndarray, pts_b: np.ndarray, radius_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest pairs between (Na, 2) and (Nb, 2) within ``radius_px`` (closest
    pairs first). Returns index arrays ``(ia, ib)`` of equal length."""
    if len(pts_a) == 0 or len(pts_b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    tree = cKDTree(pts_b)
    pairs = tree.sparse_distance_matrix(cKDTree(pts_a), radius_px, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(pairs["v"], kind="stable")
    used_a: set[int] = set()
    used_b: set[int] = set()
    ia, ib = [], []
    for k in order:
        b, a = int(pairs["i"][k]), int(pairs["j"][k])
        if a in used_a or b in used_b:
            continue
        used_a.add(a)
        used_b.add(b)
        ia.append(a)
        ib.append(b)
    return np.array(ia, np.int64), np.array(ib, np.int64)


def top_up_corners(
    image: np.ndarray, pts: np.ndarray, config: FrontEndConfig, detector: cv2.Feature2D
) -> np.ndarray:
    """New FAST corners (K, 2) [px] in grid cells holding fewer than ``min_per_cell`` of the
    tracked points (N, 2): the strongest corner of each such cell, away from every track."""
    cfg = config.top_up
    h, w = image.shape
    cols, rows = -(-w // cfg.cell_px), -(-h // cfg.cell_px)
    occ = np.zeros((rows, cols), dtype=np.int64)
    if len(pts):
        c = np.clip((pts[:, 0] // cfg.cell_px).astype(np.int64), 0, cols - 1)
        r = np.clip((pts[:, 1] // cfg.cell_px).astype(np.int64), 0, rows - 1)
        np.add.at(occ, (r, c), 1)
    sparse = occ < cfg.min_per_cell
    if not sparse.any():
        return np.zeros((0, 2))
    cells = np.repeat(np.repeat(sparse, cfg.cell_px, axis=0), cfg.cell_px, axis=1)[:h, :w]
    mask = cells.astype(np.uint8) * 255
    border = config.lk.win_size // 2 + 1
    mask[:border], mask[-border:], mask[:, :border], mask[:, -border:] = 0, 0, 0, 0
    kps = detector.detect(image, mask)
    if not kps:
        return np.zeros((0, 2))
    cand = np.array([k.pt for k in kps], dtype=np.float64)
    resp = np.array([k.response for k in kps], dtype=np.float64)
    if len(pts):
        dist, _ = cKDTree(pts).query(cand, distance_upper_bound=cfg.min_distance_px)
        far = ~np.isfinite(dist)
        cand, resp = cand[far], resp[far]
    cell = (cand[:, 1] // cfg.cell_px).astype(np.int64) * cols + (cand[:, 0] // cfg.cell_px)
    order = np.lexsort((-resp, cell))
    first = np.ones(len(order), dtype=bool)
    first[1:] = cell[order][1:] != cell[order][:-1]
    chosen = order[first]
    chosen = chosen[np.argsort(-resp[chosen], kind="stable")][: cfg.max_new_per_frame]
    return cand[chosen]
