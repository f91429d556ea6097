"""ORB on keyframes, spread evenly over the image (as ORB-SLAM's distribution intends).

OpenCV's ORB detects ``oversample`` × ``n_features`` candidates over its scale pyramid; a
grid of cells then keeps the strongest candidates of every cell in turns (round robin over
cells, strongest first) until ``n_features`` are chosen, so textured corners cannot take all
the budget. Descriptors are computed only for the kept keypoints.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from common.errors import RecslamError
from services.robot.config import OrbConfig

logger = logging.getLogger(__name__)


class OrbExtractorError(RecslamError):
    """Invalid image or configuration for ORB extraction."""


@dataclass(frozen=True, eq=False)
class OrbFeatures:
    """ORB features of one image.

    ``keypoints`` (N, 2) float64 [px, level-0 distorted image]; ``levels`` (N,) uint8 octave σ;
    ``angles`` (N,) float32 [deg, 0..360); ``responses`` (N,) float32;
    ``descriptors`` (N, 32) uint8 (256 bits).
    """

    keypoints: np.ndarray
    levels: np.ndarray
    angles: np.ndarray
    responses: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)


def select_grid(
    keypoints_px: np.ndarray,
    responses: np.ndarray,
    image_shape: tuple[int, int],
    n_keep: int,
    grid_cols: int,
    grid_rows: int,
) -> np.ndarray:
    """Indices of at most ``n_keep`` keypoints chosen evenly over a ``grid_cols`` × ``grid_rows``
    grid: round ``r`` takes the ``r``-th strongest keypoint of every cell that still has one,
    and the last round is filled by response. Returns (K,) int64 indices."""
    n = len(keypoints_px)
    if n <= n_keep:
        return np.argsort(-responses, kind="stable").astype(np.int64)
    h, w = image_shape
    cx = np.clip((keypoints_px[:, 0] * grid_cols / w).astype(np.int64), 0, grid_cols - 1)
    cy = np.clip((keypoints_px[:, 1] * grid_rows / h).astype(np.int64), 0, grid_rows - 1)
    cell = cy * grid_cols + cx
    # Sort by cell, then by response (descending); rank each keypoint within its cell.
    order = np.lexsort((-responses, cell))
    cell_sorted = cell[order]
    starts = np.searchsorted(cell_sorted, cell_sorted, side="left")
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n) - starts
    # Keep all ranks below r*, and the strongest of rank r* to fill exactly n_keep.
    counts = np.bincount(rank)
    cum = np.cumsum(counts)
    r_star = int(np.searchsorted(cum, n_keep, side="left"))
    below = np.flatnonzero(rank < r_star)
    at = np.flatnonzero(rank == r_star)
    need = n_keep - len(below)
    at = at[np.argsort(-responses[at], kind="stable")[:need]]
    return np.concatenate([below, at]).astype(np.int64)


class OrbExtractor:
    """ORB-SLAM3-like ORB: ``n_features`` over ``n_levels`` levels at ``scale_factor``."""

    def __init__(self, config: OrbConfig) -> None:
        if config.n_features <= 0 or config.n_levels <= 0 or config.scale_factor <= 1.0:
            raise OrbExtractorError(f"invalid ORB configuration {config}")
        self.config = config
        self.n_features = config.n_features  # features kept (lowered by an uplink budget)
        self._orb = cv2.ORB.create(
            nfeatures=int(config.n_features * config.oversample),
            scaleFactor=config.scale_factor,
            nlevels=config.n_levels,
            edgeThreshold=config.edge_threshold,
            patchSize=31,
            fastThreshold=config.fast_threshold,
        )

    def extract(
        self,
        image: np.ndarray,
        mask: np.ndarray | None = None,
        prefer_px: np.ndarray | None = None,
        prefer_radius_px: float = 0.0,
    ) -> OrbFeatures:
        """Detect, distribute and describe ORB features on a uint8 (H, W) image. With
        ``prefer_px`` (M, 2) [px] (tracked points, oldest first), the candidate nearest each
        within ``prefer_radius_px`` is kept first (one per point, up to ``n_features``), the
        rest of the budget spread over the grid as usual."""
        if image.dtype != np.uint8 or image.ndim != 2:
            raise OrbExtractorError(
                f"ORB needs a uint8 (H, W) grayscale image, got {image.dtype} {image.shape}"
            )
        cfg = self.config
        kps = self._orb.detect(image, mask)
        if kps:
            pts = np.array([k.pt for k in kps], dtype=np.float64)
            resp = np.array([k.response for k in kps], dtype=np.float32)
            first = np.zeros(0, np.int64)
            rest = np.arange(len(pts))
            if prefer_px is not None and len(prefer_px) and prefer_radius_px > 0:
                _, near = cKDTree(pts).query(prefer_px, distance_upper_bound=prefer_radius_px)
                near = near[near < len(pts)]
                _, at = np.unique(near, return_index=True)
                first = near[np.sort(at)][: self.n_features]  # (in the points' order)
                rest = np.setdiff1d(rest, first)
            n_grid = self.n_features - len(first)
            pick = select_grid(
                pts[rest], resp[rest], image.shape, n_grid, cfg.grid_cols, cfg.grid_rows
            )
            keep = np.concatenate([first, rest[pick]])
            kps = [kps[i] for i in keep]
            kps, desc = self._orb.compute(image, kps)
        if not kps or desc is None:
            return OrbFeatures(
                np.zeros((0, 2)),
                np.zeros(0, np.uint8),
                np.zeros(0, np.float32),
                np.zeros(0, np.float32),
                np.zeros((0, 32), np.uint8),
            )
        return OrbFeatures(
            keypoints=np.array([k.pt for k in kps], dtype=np.float64),
            levels=np.array([k.octave & 0xFF for k in kps], dtype=np.uint8),
            angles=np.array([k.angle for k in kps], dtype=np.float32),
            responses=np.array([k.response for k in kps], dtype=np.float32),
            descriptors=np.ascontiguousarray(desc, dtype=np.uint8),
        )
