"""Training material for the ORB vocabulary tree (:meth:`common.vocabulary.Vocabulary.train`):
ORB descriptors, extracted as the robot extracts them on keyframes, over image folders,
EuRoC-layout datasets (``mav0/cam*/data``) or the keyword ``skimage`` (scikit-image's bundled
photographs at several scales, rotations and blurs — how the default vocabulary in
``common/assets`` was trained; independent of every test sequence). ``recslam vocab train``
and ``benchmarks/bench_vocabulary.py`` use it."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from common.vocabulary import VocabularyError

if TYPE_CHECKING:
    import cv2

log = logging.getLogger(__name__)

SKIMAGE_NAMES = (
    "astronaut",
    "coffee",
    "chelsea",
    "rocket",
    "camera",
    "brick",
    "grass",
    "gravel",
    "page",
    "text",
    "coins",
    "moon",
    "hubble_deep_field",
    "immunohistochemistry",
    "retina",
    "cell",
    "clock",
    "cat",
)
SKIMAGE_SCALES = (0.6, 0.85, 1.2, 1.7)
SKIMAGE_ROTATIONS_DEG = (0.0, 25.0)
SKIMAGE_BLURS = (0.0, 1.5)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


def orb_extractor(nfeatures: int = 1000) -> cv2.ORB:
    """ORB as the robot runs it on keyframes (8 levels, scale 1.2)."""
    import cv2

    return cv2.ORB.create(nfeatures=nfeatures, scaleFactor=1.2, nlevels=8)


def _to_gray_u8(img: np.ndarray) -> np.ndarray:
    import cv2

    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3].astype(np.uint8), cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img * (255.0 if img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
    return img


def skimage_variants() -> Iterator[tuple[str, np.ndarray]]:
    """Augmented grey images from scikit-image's data module (name, image)."""
    import cv2
    import skimage.data

    for name in SKIMAGE_NAMES:
        base = _to_gray_u8(np.asarray(getattr(skimage.data, name)()))
        for s in SKIMAGE_SCALES:
            scaled = cv2.resize(base, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            h, w = scaled.shape
            for rot in SKIMAGE_ROTATIONS_DEG:
                m = cv2.getRotationMatrix2D((w / 2, h / 2), rot, 1.0)
                rotated = cv2.warpAffine(scaled, m, (w, h), borderMode=cv2.BORDER_REFLECT)
                for blur in SKIMAGE_BLURS:
                    img = rotated if blur == 0 else cv2.GaussianBlur(rotated, (0, 0), blur)
                    yield f"skimage:{name}@{s}/{rot}/{blur}", img


def image_files(source: Path) -> list[Path]:
    """Images of a folder or of an EuRoC dataset (``mav0/cam*/data``), sorted."""
    if (source / "mav0").is_dir():
        dirs = sorted((source / "mav0").glob("cam*/data"))
    else:
        dirs = [source]
    files: list[Path] = []
    for d in dirs:
        files += sorted(p for p in d.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    return files


def collect_descriptors(sources: list[str], stride: int = 1) -> tuple[list[np.ndarray], str]:
    """ORB descriptors per image over all sources; returns (list, description)."""
    import cv2

    orb = orb_extractor()
    out: list[np.ndarray] = []
    parts = []
    for src in sources:
        if src == "skimage":
            items: Iterator = skimage_variants()
            parts.append(
                f"skimage.data {len(SKIMAGE_NAMES)} photos x scales {SKIMAGE_SCALES} x "
                f"rotations {SKIMAGE_ROTATIONS_DEG} x blurs {SKIMAGE_BLURS}"
            )
        else:
            path = Path(src)
            if not path.exists():
                raise VocabularyError(f"image source {src} does not exist")
            files = image_files(path)[::stride]
            if not files:
                raise VocabularyError(f"no images found under {src}")
            parts.append(f"{src} ({len(files)} images)")
            items = ((str(f), cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)) for f in files)
        for name, img in items:
            if img is None:
                raise VocabularyError(f"cannot read image {name}")
            _, des = orb.detectAndCompute(img, None)
            if des is not None and len(des):
                out.append(des)
    return out, "; ".join(parts)
