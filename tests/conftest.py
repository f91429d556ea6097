"""Fixtures shared by the whole suite.

``euroc_micro``: the real EuRoC excerpt, found by :func:`lab.datasets.euroc_micro_path`
(``../shared/datasets/euroc-micro-V1_01`` beside the repository or in ``/work/shared``, or
``$RECSLAM_EUROC_MICRO``).
When it is absent a test that needs it is skipped locally, but fails under ``CI=true``: CI
has the shared folder, so a missing excerpt there is a broken setup, not a reason to skip.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from lab.datasets import EUROC_MICRO_ENV, euroc_micro_path, euroc_micro_present, euroc_v2_path


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("true", "1")


@pytest.fixture(scope="session")
def euroc_micro() -> Path:
    """Folder of the real EuRoC excerpt (holds ``mav0``); skip (fail under CI) if absent."""
    path = euroc_micro_path()
    if euroc_micro_present(path):
        return path
    reason = (
        f"real EuRoC excerpt not found at {path} (no mav0/cam0 there); "
        f"set {EUROC_MICRO_ENV} to the folder of euroc-micro-V1_01"
    )
    if _in_ci():
        pytest.fail(f"{reason}. CI=true: a missing dataset fails instead of skipping")
    pytest.skip(reason)


@pytest.fixture(scope="session")
def euroc_v2() -> Path:
    """Folder of the real V2 flights (IMU + ground truth); skip (fail under CI) if absent."""
    path = euroc_v2_path()
    if (path / "V2_01" / "mav0" / "imu0" / "data.csv").is_file():
        return path
    reason = f"real EuRoC V2 flights not found at {path}"
    if _in_ci():
        pytest.fail(f"{reason}. CI=true: a missing dataset fails instead of skipping")
    pytest.skip(reason)
