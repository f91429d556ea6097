"""Where the development datasets are: the shared folder beside the repository.

The real EuRoC excerpt (first 95 frames of V1_01, cam0 + full IMU, no ground truth) lives at
``../shared/datasets/euroc-micro-V1_01`` relative to the repository root, or in the team
machines' shared folder ``/work/shared`` (a clone elsewhere, e.g. CI's, still finds it); the
environment variable :data:`EUROC_MICRO_ENV` names another folder. Tests
(``tests/conftest.py``) and benchmarks find it only through :func:`euroc_micro_path`.
"""

from __future__ import annotations

import os
from pathlib import Path

EUROC_MICRO_ENV = "RECSLAM_EUROC_MICRO"
"""Environment variable overriding the location of the EuRoC excerpt."""

REPO_ROOT = Path(__file__).resolve().parents[1]
_EXCERPT = Path("datasets") / "euroc-micro-V1_01"
DEFAULT_EUROC_MICRO = REPO_ROOT.parent / "shared" / _EXCERPT
SHARED_EUROC_MICRO = Path("/work/shared") / _EXCERPT


def euroc_micro_path() -> Path:
    """The EuRoC excerpt's folder (the one holding ``mav0``): ``$RECSLAM_EUROC_MICRO`` if
    set and not empty, else :data:`DEFAULT_EUROC_MICRO` if it is there, else
    :data:`SHARED_EUROC_MICRO`. It may not exist: see :func:`euroc_micro_present`."""
    override = os.environ.get(EUROC_MICRO_ENV, "").strip()
    if override:
        return Path(override).expanduser()
    if euroc_micro_present(DEFAULT_EUROC_MICRO) or not euroc_micro_present(SHARED_EUROC_MICRO):
        return DEFAULT_EUROC_MICRO
    return SHARED_EUROC_MICRO


def euroc_micro_present(path: Path) -> bool:
    """True if ``path`` looks like the excerpt (an EuRoC ASL folder with ``mav0/cam0``)."""
    return (path / "mav0" / "cam0").is_dir()


_FLIGHTS = Path("datasets") / "euroc-V2-flights"
EUROC_V2_FLIGHTS = ("V2_01", "V2_02", "V2_03")
"""The real flights of one room (IMU and ground truth, no images) in the shared folder."""


def euroc_v2_path() -> Path:
    """The folder of the real V2 flights (``V2_0k/mav0/{imu0, state_groundtruth_estimate0}``):
    beside the repository if there, else in ``/work/shared``. It may not exist."""
    beside = REPO_ROOT.parent / "shared" / _FLIGHTS
    return beside if (beside / "V2_01" / "mav0").is_dir() else Path("/work/shared") / _FLIGHTS


def euroc_v2_files(flight: str) -> tuple[Path, Path]:
    """(ground truth csv, IMU csv) of real flight ``flight`` (e.g. ``"V2_01"``)."""
    mav0 = euroc_v2_path() / flight / "mav0"
    return mav0 / "state_groundtruth_estimate0" / "data.csv", mav0 / "imu0" / "data.csv"
