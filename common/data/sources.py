"""Where a robot's recording comes from: an EuRoC-layout folder (EuRoC, TUM-VI, our synthetic
sets) or a ROS bag, with the calibration the folder holds or one given explicitly.

:class:`SequenceSource` is what the robot plays (both :class:`~common.data.euroc.EurocSequence`
and :class:`~common.data.rosbag.BagSequence` are one); :func:`open_source` opens one and
checks its first image against the calibration, so that a wrong resolution stops the robot
before it starts.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.data.calibration_files import SensorCalibration, load_calibration
from common.data.euroc import EurocFrame, EurocSequence
from common.errors import RecslamError


class SourceError(RecslamError):
    """The recording to play was named wrongly (no folder, no bag, no calibration)."""


class SequenceSource(Protocol):
    """A camera + IMU recording: calibrations, frame timestamps (N,) int64 ns, and frames
    with their IMU batches (``frames(start, stop)``, see ``EurocSequence.frames``)."""

    name: str
    root: Path
    cam0: CameraCalibration
    imu: ImuCalibration
    calibration_info: SensorCalibration
    frame_timestamps_ns: np.ndarray

    def __len__(self) -> int: ...

    def frames(
        self,
        start: int = 0,
        stop: int | None = None,
        *,
        imu_lead_ns: int | Callable[[], int] = 0,
    ) -> Iterator[EurocFrame]: ...

    def summary(self) -> dict[str, Any]: ...


def open_source(
    dataset: Path | None = None,
    bag: Path | None = None,
    calibration: Path | None = None,
    image_topic: str | None = None,
    imu_topic: str | None = None,
    check_images: bool = True,
) -> SequenceSource:
    """Open a folder (``dataset``) or a bag (``bag``, which needs ``calibration``: a bag holds
    none); ``calibration`` (a file or folder) overrides what the folder holds. With
    ``check_images`` the first frame is decoded and its size compared with the calibration."""
    if (dataset is None) == (bag is None):
        raise SourceError("give a sequence folder or a bag (exactly one)")
    calib = None if calibration is None else load_calibration(_existing(calibration, "calibration"))
    source: SequenceSource
    if bag is not None:
        from common.data.rosbag import BagSequence

        if calib is None:
            raise SourceError(
                f"{bag}: a bag holds no calibration: give one with --calibration FILE "
                "(Kalibr camchain.yaml, EuRoC cam0/sensor.yaml, or a folder holding them)"
            )
        source = BagSequence(_existing(bag, "bag"), calib, image_topic, imu_topic)
    else:
        assert dataset is not None
        if image_topic or imu_topic:
            raise SourceError("--image-topic and --imu-topic apply to --bag only")
        source = EurocSequence(_existing(dataset, "dataset folder"), calib)
    if check_images and len(source):
        next(iter(source.frames(0, 1)))  # decodes and checks the size (names the files)
    return source


def _existing(path: Path, what: str) -> Path:
    if not Path(path).exists():
        raise SourceError(f"{path}: {what} does not exist")
    return Path(path)
