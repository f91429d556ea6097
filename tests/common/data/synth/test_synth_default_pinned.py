"""The default dataset (ring flights, vicon room) stays bit for bit what it was before issue 17's
harder worlds: the digest below was computed on main (fa2acd6) before any of that work.

Running sweeps, tests and committed results rely on the default data not changing; a new
option of the generator must leave it alone. The digest covers every frame's decoded pixels,
the IMU and ground-truth CSVs and ``dataset.json`` of a 2-robot, 1 s dataset of seed 3.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2

from common.data.synth import SynthConfig, generate_dataset

PINNED = "078d0cdcc5fc9ff426d92dc94983fd411bb61c63e3f2188da9f2d69baf5a47e5"


def dataset_digest(out: Path) -> str:
    """SHA-256 over the decoded pixels of every frame, the IMU and ground-truth CSVs and
    ``dataset.json`` (PNG pixels, not PNG bytes, so a zlib change cannot move it)."""
    h = hashlib.sha256()
    for folder in sorted(out.glob("robot*")):
        mav0 = folder / "mav0"
        for png in sorted((mav0 / "cam0" / "data").glob("*.png")):
            img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
            h.update(png.name.encode())
            h.update(img.tobytes())
        for csv in ("imu0/data.csv", "state_groundtruth_estimate0/data.csv", "cam0/data.csv"):
            h.update((mav0 / csv).read_bytes())
    h.update((out / "dataset.json").read_bytes())
    return h.hexdigest()


def test_default_dataset_is_unchanged(tmp_path: Path) -> None:
    generate_dataset(
        tmp_path,
        SynthConfig(robots=2, seconds=1.0, seed=3, progress=False, contact_sheet=False),
    )
    assert dataset_digest(tmp_path) == PINNED
