"""ORB on keyframes: ORB-SLAM3 settings, even spread over the image, level and angle kept."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.robot.config import OrbConfig
from services.robot.orb_extractor import OrbExtractor, OrbExtractorError, select_grid


@pytest.fixture(scope="module")
def image(euroc_micro: Path) -> np.ndarray:
    paths = sorted((euroc_micro / "mav0/cam0/data").glob("*.png"))
    assert paths, f"no images in {euroc_micro}/mav0/cam0/data"
    return cv2.imread(str(paths[10]), cv2.IMREAD_GRAYSCALE)


def _occupied_cells(pts: np.ndarray, shape: tuple[int, int], cols=16, rows=10) -> int:
    h, w = shape
    cells = (pts[:, 1] * rows // h).astype(int) * cols + (pts[:, 0] * cols // w).astype(int)
    return len(np.unique(cells))


def test_orb_slam3_defaults_and_fields(image: np.ndarray) -> None:
    feats = OrbExtractor(OrbConfig()).extract(image)
    assert len(feats) == 1000
    assert feats.descriptors.shape == (1000, 32) and feats.descriptors.dtype == np.uint8
    assert feats.levels.dtype == np.uint8 and feats.levels.max() <= 7
    assert len(np.unique(feats.levels)) >= 5  # several scales are used
    assert np.all((feats.angles >= 0) & (feats.angles < 360))
    assert np.all(feats.keypoints >= 0)
    assert np.all(feats.keypoints < [image.shape[1], image.shape[0]])


def test_grid_spreads_features_more_than_plain_orb(image: np.ndarray) -> None:
    ours = OrbExtractor(OrbConfig()).extract(image).keypoints
    plain = cv2.ORB_create(1000, 1.2, 8).detect(image)
    plain_pts = np.array([k.pt for k in plain])
    assert _occupied_cells(ours, image.shape) > _occupied_cells(plain_pts, image.shape)


def test_select_grid_round_robin() -> None:
    # Cell 0 holds 10 strong points, cell 1 holds 2 weak ones: keeping 4 takes both weak ones.
    pts = np.array([[0.5 + 0.9 * i, 1.0] for i in range(10)] + [[15.0, 1.0], [16.0, 1.0]])
    resp = np.array([10.0 + i for i in range(10)] + [1.0, 2.0])
    keep = select_grid(pts, resp, (10, 20), n_keep=4, grid_cols=2, grid_rows=1)
    assert len(keep) == 4 and len(set(keep.tolist())) == 4
    assert {10, 11} <= set(keep.tolist())
    assert {9, 8} <= set(keep.tolist())  # the strongest two of the crowded cell


def test_rejects_colour_image(image: np.ndarray) -> None:
    with pytest.raises(OrbExtractorError):
        OrbExtractor(OrbConfig()).extract(np.dstack([image] * 3))


def test_preferred_points_keep_their_corner_first(image: np.ndarray) -> None:
    """``prefer_px`` (tracked points): each keeps the corner detected within the radius, even
    where the grid alone would have dropped it; the budget and the spread hold otherwise."""
    ex = OrbExtractor(OrbConfig(n_features=300))
    candidates = np.array([k.pt for k in ex._orb.detect(image, None)])  # (oversampled)
    plain = ex.extract(image)
    dropped = np.array(
        [p for p in candidates if np.min(np.linalg.norm(plain.keypoints - p, axis=1)) > 3]
    )[:100]
    assert len(dropped) == 100  # corners the grid leaves out at 300 features
    prefer = dropped + 1.0  # (tracked points: near, not on, their corner)
    feats = ex.extract(image, prefer_px=prefer, prefer_radius_px=3.0)
    assert len(feats) == 300
    d = np.linalg.norm(prefer[:, None] - feats.keypoints[None], axis=2).min(axis=1)
    assert np.mean(d <= 3.0) > 0.9
    assert np.linalg.norm(plain.keypoints[:, None] - dropped[None], axis=2).min(0).min() > 3
    same = ex.extract(image, prefer_px=np.zeros((0, 2)), prefer_radius_px=3.0)
    np.testing.assert_array_equal(same.keypoints, plain.keypoints)  # nothing preferred
