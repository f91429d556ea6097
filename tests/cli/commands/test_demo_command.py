"""``recslam demo``'s dataset step: a synthetic dataset is reused unless the command asks for
other robots, length, seed or cameras than it was built with (a setting not given matches
any: a seed-17 dataset is never rebuilt as the default one, a mixed team never as all-EuRoC)."""

from __future__ import annotations

import json
from pathlib import Path

from recslam.commands.demo import _dataset_matches


def _meta(folder: Path, cameras: list[str] | None) -> Path:
    config: dict = {"robots": 3, "seconds": 60.0, "seed": 0}
    if cameras is not None:
        config["cameras"] = cameras
    info = {"robots": 3, "seconds": 60.0, "seed": 0, "config": config}
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "dataset.json").write_text(json.dumps(info))
    return folder


def test_default_dataset_matches_default_cameras_only(tmp_path) -> None:
    folder = _meta(tmp_path / "default", None)
    assert _dataset_matches(folder, 3, 60.0, 0)
    assert _dataset_matches(folder, 3, 60.0, 0, ())
    assert not _dataset_matches(folder, 3, 60.0, 0, ("euroc", "wide", "fisheye"))
    assert not _dataset_matches(folder, 3, 60.0, 1)


def test_mixed_dataset_matches_its_cameras_only(tmp_path) -> None:
    folder = _meta(tmp_path / "mixed", ["euroc", "wide", "fisheye"])
    assert _dataset_matches(folder, 3, 60.0, 0, ("euroc", "wide", "fisheye"))
    assert _dataset_matches(folder, 3, 60.0, 0)  # no --cameras: reused as it is
    assert not _dataset_matches(folder, 3, 60.0, 0, ())
    assert not _dataset_matches(folder, 3, 60.0, 0, ("euroc", "fisheye", "wide"))


def test_settings_not_given_match_any(tmp_path) -> None:
    folder = _meta(tmp_path / "default", None)
    assert _dataset_matches(folder, None, None, None)
    assert _dataset_matches(folder, None, 60.0, None)
    assert not _dataset_matches(folder, None, 40.0, None)
    assert not _dataset_matches(folder, None, None, 17)
    assert not _dataset_matches(tmp_path / "missing", None, None, None)
