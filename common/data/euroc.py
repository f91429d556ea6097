"""Reader for sequences in the EuRoC ASL layout (real downloads and our synthetic sets).

Layout (the sequence root may be given, or ``mav0`` itself)::

    <root>/mav0/cam0/{sensor.yaml, data.csv, data/<ts>.png}
    <root>/mav0/cam1/...                                   (optional)
    <root>/mav0/imu0/{sensor.yaml, data.csv}
    <root>/mav0/state_groundtruth_estimate0/data.csv       (optional)

Frames: EuRoC's ``T_BS`` is ``T_body_sensor``; ground truth ``p_RS_R``/``q_RS`` is the pose
of the body (= IMU) frame in the world frame, i.e. ``T_world_body``. Timestamps are int64
nanoseconds. Every malformed input raises :class:`EurocError` as ``<file>:<line>: <what>``.

IMU samples are kept in memory (numpy, read-only); images are decoded lazily.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.data.calibration_files import (
    SensorCalibration,
    find_calibration,
    read_text,
)
from common.data.calibration_files import read_camera_yaml as read_camera_yaml
from common.data.calibration_files import read_imu_yaml as read_imu_yaml
from common.errors import RecslamError

logger = logging.getLogger(__name__)

CAMERA_CSV_HEADER = "#timestamp [ns],filename"
IMU_CSV_HEADER = (
    "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
)
GROUNDTRUTH_CSV_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], "
    "q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
    "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
    "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
GROUNDTRUTH_DIR = "state_groundtruth_estimate0"


class EurocError(RecslamError):
    """A sequence on disk is missing, malformed or inconsistent."""


def _readonly(a: np.ndarray, dtype: type, shape_tail: tuple[int, ...], what: str) -> np.ndarray:
    arr: np.ndarray = np.array(a, dtype=dtype)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise ValueError(f"{what}: expected shape (K, {shape_tail}), got {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class ImuBatch:
    """IMU samples: ``timestamps_ns`` (K,) int64, ``gyro`` (K, 3) rad/s, ``accel`` (K, 3) m/s²,
    both in the IMU sensor frame."""

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    def __post_init__(self) -> None:
        ts = _readonly(self.timestamps_ns, np.int64, (), "timestamps_ns")
        object.__setattr__(self, "timestamps_ns", ts)
        for name in ("gyro", "accel"):
            arr = _readonly(getattr(self, name), np.float64, (3,), name)
            if len(arr) != len(ts):
                raise ValueError(f"{name} has {len(arr)} rows, timestamps_ns {len(ts)}")
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return len(self.timestamps_ns)


@dataclass(frozen=True, eq=False)
class EurocGroundTruth:
    """EuRoC ``state_groundtruth_estimate0``: body (IMU) state in the world frame.

    ``timestamps_ns`` (K,) int64; ``p_world_body`` (K, 3) m; ``q_world_body_wxyz`` (K, 4)
    Hamilton (w, x, y, z) as stored (not renormalised); ``v_world_body`` (K, 3) m/s;
    ``bias_gyro`` (K, 3) rad/s; ``bias_accel`` (K, 3) m/s². Pose-only files (8 columns)
    give NaN velocities and biases.
    """

    timestamps_ns: np.ndarray
    p_world_body: np.ndarray
    q_world_body_wxyz: np.ndarray
    v_world_body: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray

    def __post_init__(self) -> None:
        ts = _readonly(self.timestamps_ns, np.int64, (), "timestamps_ns")
        object.__setattr__(self, "timestamps_ns", ts)
        dims = {"p_world_body": 3, "q_world_body_wxyz": 4, "v_world_body": 3}
        for name in (
            "p_world_body",
            "q_world_body_wxyz",
            "v_world_body",
            "bias_gyro",
            "bias_accel",
        ):
            arr = _readonly(getattr(self, name), np.float64, (dims.get(name, 3),), name)
            if len(arr) != len(ts):
                raise ValueError(f"{name} has {len(arr)} rows, timestamps_ns {len(ts)}")
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    def T_world_body(self) -> np.ndarray:
        """(K, 4, 4) body-to-world transforms (quaternions normalised)."""
        from common.geometry import quat_wxyz_to_R

        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = quat_wxyz_to_R(self.q_world_body_wxyz)
        T[:, :3, 3] = self.p_world_body
        return T


@dataclass(frozen=True, eq=False)
class CameraStream:
    """One camera's ``data.csv``: ``timestamps_ns`` (N,) int64, absolute ``image_paths`` and
    the 1-based ``csv_lines`` each row came from (for error messages)."""

    csv_path: Path
    timestamps_ns: np.ndarray
    image_paths: tuple[Path, ...]
    csv_lines: tuple[int, ...]

    def __len__(self) -> int:
        return len(self.timestamps_ns)


@dataclass(frozen=True, eq=False)
class EurocFrame:
    """One camera frame with the IMU samples ``previous_frame_ts < t <= timestamp_ns``
    (for frame 0: every IMU sample up to and including its timestamp).
    ``image`` is uint8 (H, W) grayscale, or None when iterated with ``load_images=False``."""

    index: int
    timestamp_ns: int
    image: np.ndarray | None
    imu: ImuBatch


# ---------------------------------------------------------------------------- CSV parsing


def _read_text(path: Path) -> str:
    return read_text(path, EurocError)


def _csv_rows(path: Path, ncols: tuple[int, ...]) -> tuple[list[list[str]], list[int]]:
    """Split a CSV into rows of fields, skipping '#' comments and blank lines.

    Returns (rows, 1-based line numbers). Every row must have one of ``ncols`` fields.
    """
    rows: list[list[str]] = []
    lines: list[int] = []
    for lineno, line in enumerate(_read_text(path).splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        rows.append(line.split(","))
        lines.append(lineno)
    if not rows:
        raise EurocError(f"{path}: no data rows")
    want = len(rows[0]) if len(rows[0]) in ncols else None
    for row, lineno in zip(rows, lines, strict=True):
        if len(row) != want:
            expected = " or ".join(str(n) for n in ncols) if want is None else str(want)
            raise EurocError(f"{path}:{lineno}: expected {expected} columns, found {len(row)}")
    return rows, lines


def _parse_timestamps(path: Path, rows: list[list[str]], lines: list[int]) -> np.ndarray:
    """Column 0 as strictly increasing int64 nanoseconds."""
    try:
        ts = np.array([int(r[0]) for r in rows], dtype=np.int64)
    except (ValueError, OverflowError):
        for row, lineno in zip(rows, lines, strict=True):
            try:
                v = int(row[0])
            except ValueError:
                raise EurocError(
                    f"{path}:{lineno}: timestamp {row[0].strip()!r} is not an integer [ns]"
                ) from None
            if not -(2**63) <= v < 2**63:
                raise EurocError(f"{path}:{lineno}: timestamp {v} overflows int64") from None
        raise
    bad = np.flatnonzero(np.diff(ts) <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        kind = "duplicate" if ts[i] == ts[i - 1] else "decreasing"
        raise EurocError(
            f"{path}:{lines[i]}: {kind} timestamp {ts[i]} "
            f"(previous row, line {lines[i - 1]}, has {ts[i - 1]})"
        )
    return ts


def _parse_floats(path: Path, rows: list[list[str]], lines: list[int]) -> np.ndarray:
    """Columns 1.. as finite float64, shape (N, ncols - 1)."""
    ncols = len(rows[0]) - 1
    try:
        flat = [float(x) for r in rows for x in r[1:]]
        values = np.array(flat, dtype=np.float64).reshape(len(rows), ncols)
        finite = bool(np.isfinite(values).all())
    except ValueError:
        finite = False
    if finite:
        return values
    for row, lineno in zip(rows, lines, strict=True):
        for col, field in enumerate(row[1:], start=2):
            try:
                v = float(field)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise EurocError(
                    f"{path}:{lineno}: column {col} value {field.strip()!r} is not a finite number"
                )
    raise AssertionError("unreachable: a non-finite value was detected but not located")


def read_imu_csv(path: Path | str) -> ImuBatch:
    """Read ``imu0/data.csv`` (timestamp, gyro xyz [rad/s], accel xyz [m/s²])."""
    path = Path(path)
    rows, lines = _csv_rows(path, (7,))
    ts = _parse_timestamps(path, rows, lines)
    values = _parse_floats(path, rows, lines)
    return ImuBatch(timestamps_ns=ts, gyro=values[:, 0:3], accel=values[:, 3:6])


def read_groundtruth(csv_path: Path | str) -> EurocGroundTruth:
    """Read ``state_groundtruth_estimate0/data.csv`` (17 columns: t, p, q_wxyz, v, b_w, b_a).

    Pose-only files with 8 columns (t, p, q_wxyz) are accepted too; their velocities and
    biases are NaN. Quaternion norms must be within 1e-2 of 1 (they are stored unmodified).
    """
    path = Path(csv_path)
    rows, lines = _csv_rows(path, (17, 8))
    ts = _parse_timestamps(path, rows, lines)
    values = _parse_floats(path, rows, lines)
    norms = np.linalg.norm(values[:, 3:7], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-2)
    if len(bad):
        i = int(bad[0])
        raise EurocError(f"{path}:{lines[i]}: quaternion norm {norms[i]:.6g} is not 1")
    if values.shape[1] == 7:
        values = np.concatenate([values, np.full((len(values), 9), np.nan)], axis=1)
    return EurocGroundTruth(
        timestamps_ns=ts,
        p_world_body=values[:, 0:3],
        q_world_body_wxyz=values[:, 3:7],
        v_world_body=values[:, 7:10],
        bias_gyro=values[:, 10:13],
        bias_accel=values[:, 13:16],
    )


def read_camera_csv(path: Path | str, image_dir: Path | str | None = None) -> CameraStream:
    """Read ``camN/data.csv`` (timestamp, filename); images live in ``image_dir``
    (default: ``data/`` next to the CSV) and must exist."""
    path = Path(path)
    image_dir = path.parent / "data" if image_dir is None else Path(image_dir)
    rows, lines = _csv_rows(path, (2,))
    ts = _parse_timestamps(path, rows, lines)
    try:
        present = set(os.listdir(image_dir))
    except OSError:
        raise EurocError(f"{image_dir}: missing image folder (for {path})") from None
    names = [r[1].strip() for r in rows]
    for name, lineno in zip(names, lines, strict=True):
        if not name or name not in present:
            raise EurocError(f"{path}:{lineno}: image {name!r} not found in {image_dir}")
    return CameraStream(
        csv_path=path,
        timestamps_ns=_readonly(ts, np.int64, (), "timestamps_ns"),
        image_paths=tuple(image_dir / n for n in names),
        csv_lines=tuple(lines),
    )


# ---------------------------------------------------------------------------- sequence


def find_mav0(root: Path | str) -> Path:
    """The ``mav0`` folder of a sequence given by its root or by ``mav0`` itself."""
    root = Path(root)
    if not root.is_dir():
        raise EurocError(f"{root}: sequence folder does not exist")
    if (root / "mav0").is_dir():
        return root / "mav0"
    if (root / "imu0").is_dir() or (root / "cam0").is_dir():
        return root
    raise EurocError(f"{root}: no mav0 folder (nor cam0/imu0 inside it): not an EuRoC sequence")


class EurocSequence:
    """One EuRoC-layout sequence: calibrations, timestamps and IMU in memory, lazy images.

    Attributes: ``name``; ``cam0``/``cam1`` (:class:`CameraCalibration`, cam1 may be None);
    ``imu`` (:class:`ImuCalibration`); ``frame_timestamps_ns`` (N,) int64 and ``image_paths``
    of cam0; ``imu_timestamps_ns`` (M,) int64, ``gyro`` (M, 3) rad/s, ``accel`` (M, 3) m/s²;
    ``groundtruth`` (:class:`EurocGroundTruth` or None).
    """

    def __init__(self, root: Path | str, calibration: SensorCalibration | None = None) -> None:
        self.mav0 = find_mav0(Path(root).resolve())
        self.root = self.mav0.parent if self.mav0.name == "mav0" else self.mav0
        self.name = self.root.name
        self._streams: dict[int, CameraStream] = {}
        for cam in (0, 1):
            folder = self.mav0 / f"cam{cam}"
            if cam == 1 and not folder.exists():
                break
            if not folder.is_dir():
                raise EurocError(f"{folder}: missing camera folder")
            self._streams[cam] = read_camera_csv(folder / "data.csv")
        imu_dir = self.mav0 / "imu0"
        if not imu_dir.is_dir():
            raise EurocError(f"{imu_dir}: missing IMU folder")
        if calibration is None:
            calibration = find_calibration(self.root)
        if calibration is None:
            raise EurocError(
                f"{self.root}: no calibration (neither mav0/cam0/sensor.yaml nor a Kalibr "
                "camchain.yaml + imu.yaml): give one with --calibration"
            )
        for cam in list(self._streams):
            if cam >= len(calibration.cameras):
                logger.info("%s: cam%d has no calibration: ignored", self.name, cam)
                del self._streams[cam]
        shift_ns = round(calibration.timeshift_cam_imu_s * 1e9)
        if shift_ns:
            logger.info("%s: camera timestamps shifted by %d ns (Kalibr)", self.name, shift_ns)
            for cam, stream in self._streams.items():
                ts = _readonly(stream.timestamps_ns + shift_ns, np.int64, (), "timestamps_ns")
                self._streams[cam] = dataclasses.replace(stream, timestamps_ns=ts)
        self._imu = read_imu_csv(imu_dir / "data.csv")
        gt_csv = self.mav0 / GROUNDTRUTH_DIR / "data.csv"
        self.groundtruth: EurocGroundTruth | None = (
            read_groundtruth(gt_csv) if (self.mav0 / GROUNDTRUTH_DIR).exists() else None
        )
        ts = self._streams[0].timestamps_ns
        self.calibration_info = calibration.with_camera_rate(timeline_rate(ts))
        self._calibs = dict(enumerate(self.calibration_info.cameras))
        self.imu: ImuCalibration = self.calibration_info.imu
        self.cam0: CameraCalibration = self._calibs[0]
        self.cam1: CameraCalibration | None = self._calibs.get(1) if 1 in self._streams else None
        self.frame_timestamps_ns: np.ndarray = ts
        self.image_paths: tuple[Path, ...] = self._streams[0].image_paths
        self.imu_timestamps_ns: np.ndarray = self._imu.timestamps_ns
        self.gyro: np.ndarray = self._imu.gyro
        self.accel: np.ndarray = self._imu.accel
        if self.imu_timestamps_ns[-1] < ts[0] or self.imu_timestamps_ns[0] > ts[-1]:
            logger.warning("%s: IMU does not overlap the images in time", self.name)
        logger.info(
            "%s: %d frames, %d IMU samples, cameras %s, ground truth %s, %s",
            self.name,
            len(self),
            len(self._imu),
            self.cameras,
            self.groundtruth is not None,
            self.calibration_info.describe(),
        )

    def __len__(self) -> int:
        return len(self.frame_timestamps_ns)

    def __repr__(self) -> str:
        return f"EurocSequence({str(self.root)!r}, frames={len(self)})"

    @property
    def cameras(self) -> list[str]:
        """Camera folder names present, e.g. ``["cam0", "cam1"]``."""
        return [f"cam{c}" for c in self._streams]

    def stream(self, cam: int = 0) -> CameraStream:
        """Timestamps and image paths of camera ``cam``."""
        if cam not in self._streams:
            raise EurocError(f"{self.mav0}: sequence has no cam{cam}")
        return self._streams[cam]

    def calibration(self, cam: int = 0) -> CameraCalibration:
        self.stream(cam)
        return self._calibs[cam]

    def load_image(self, i: int, cam: int = 0) -> np.ndarray:
        """Decode image ``i`` of camera ``cam`` -> uint8 (H, W) grayscale."""
        stream = self.stream(cam)
        path = stream.image_paths[i]
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise EurocError(
                f"{path}: image does not decode (listed at {stream.csv_path}:{stream.csv_lines[i]})"
            )
        check_image_size(image, self._calibs[cam], self.calibration_info, path)
        return image

    def imu_between(self, t0_ns: int | None, t1_ns: int) -> ImuBatch:
        """IMU samples with ``t0_ns < t <= t1_ns`` (``t0_ns=None``: from the first sample)."""
        ts = self.imu_timestamps_ns
        a = 0 if t0_ns is None else int(np.searchsorted(ts, t0_ns, side="right"))
        b = int(np.searchsorted(ts, t1_ns, side="right"))
        b = max(a, b)
        return ImuBatch(ts[a:b], self.gyro[a:b], self.accel[a:b])

    def frames(
        self,
        start: int = 0,
        stop: int | None = None,
        cam: int = 0,
        load_images: bool = True,
        imu_lead_ns: int | Callable[[], int] = 0,
    ) -> Iterator[EurocFrame]:
        """Yield frames ``start..stop-1`` of camera ``cam`` with their IMU batches.

        Frame ``i`` carries the IMU samples after frame ``i - 1``'s up to the first sample at
        or after ``t[i] + imu_lead_ns`` (:func:`frames_with_imu`), whatever ``start`` is, so
        batches tile the IMU timeline; frame 0 carries every sample before (all of the
        pre-roll of real recordings: drop what you do not need).
        """
        ts = self.stream(cam).timestamps_ns
        stop = len(ts) if stop is None else stop
        if not 0 <= start <= stop <= len(ts):
            raise IndexError(f"frames({start}, {stop}) outside 0..{len(ts)}")
        images = (self.load_image(i, cam) if load_images else None for i in range(start, stop))
        return frames_with_imu(ts, self._imu, start, stop, images, imu_lead_ns)

    def summary(self) -> dict[str, Any]:
        """Plain facts for CLI display: frames, durations [s], rates [Hz], cameras, ground truth."""
        return {
            "name": self.name,
            "path": str(self.root),
            "frames": len(self),
            **timeline_summary(self.frame_timestamps_ns, self.imu_timestamps_ns),
            "cameras": self.cameras,
            "resolution": [self.cam0.width, self.cam0.height],
            "calibration": self.calibration_info.describe(),
            "has_groundtruth": self.groundtruth is not None,
            "groundtruth_samples": 0 if self.groundtruth is None else len(self.groundtruth),
        }


def timeline_rate(ts: np.ndarray) -> float:
    """Mean rate [Hz] of increasing int64 ns timestamps (NaN for fewer than two)."""
    span = float(ts[-1] - ts[0]) * 1e-9 if len(ts) else 0.0
    return (len(ts) - 1) / span if span > 0 else float("nan")


def timeline_summary(frame_ts: np.ndarray, imu_ts: np.ndarray) -> dict[str, float]:
    """Durations [s] and mean rates [Hz] of a sequence's frames and IMU samples."""
    return {
        "duration_s": float(frame_ts[-1] - frame_ts[0]) * 1e-9,
        "camera_rate_hz": timeline_rate(frame_ts),
        "imu_samples": len(imu_ts),
        "imu_duration_s": float(imu_ts[-1] - imu_ts[0]) * 1e-9,
        "imu_rate_hz": timeline_rate(imu_ts),
    }


def frames_with_imu(
    timestamps_ns: np.ndarray,
    imu: ImuBatch,
    start: int,
    stop: int,
    images: Iterable[np.ndarray | None],
    imu_lead_ns: int | Callable[[], int] = 0,
) -> Iterator[EurocFrame]:
    """Frames ``start..stop-1`` (``images`` gives theirs, in order) with their IMU batches:
    frame ``i`` carries the samples after frame ``i - 1``'s up to and including the first one
    at or after ``t[i] + imu_lead_ns`` (frame 0 every sample up to there). One rule for every
    sequence source (folder or bag).

    The sample after the frame is what lets the edge interpolate the IMU at the frame's time
    (ORB-SLAM3 and OpenVINS wait for it too): with a camera not triggered by the IMU (EuRoC's
    is, the generator's recorded IMUs and most robots' are not) a batch that ended before the
    frame left the interval between keyframes uncovered, and no keyframe had IMU to its
    predecessor. ``imu_lead_ns``: how far past the frame (on the IMU clock: the camera-IMU
    time offset ``t_imu - t_cam``, when the IMU runs ahead) the batch must reach; a callable is
    asked at each frame (a robot learning the offset from its edge)."""
    ts = imu.timestamps_ns

    def end(i: int) -> int:
        lead = imu_lead_ns() if callable(imu_lead_ns) else imu_lead_ns
        return min(
            int(np.searchsorted(ts, int(timestamps_ns[i]) + int(lead), side="left")) + 1, len(ts)
        )

    try:
        b = 0 if start == 0 else end(start - 1)
        for i, image in zip(range(start, stop), images, strict=True):
            a, b = b, max(b, end(i))  # a lead that grows never re-sends, one that shrinks waits
            yield EurocFrame(
                index=i,
                timestamp_ns=int(timestamps_ns[i]),
                image=image,
                imu=ImuBatch(imu.timestamps_ns[a:b], imu.gyro[a:b], imu.accel[a:b]),
            )
    finally:  # closing the frames closes the images' source (a bag reader) now, here
        close = getattr(images, "close", None)
        if close is not None:
            close()


def check_image_size(
    image: np.ndarray, camera: CameraCalibration, calibration: SensorCalibration, where: object
) -> None:
    """EurocError unless ``image`` (H, W) has the calibrated resolution (names the file)."""
    if image.shape[:2] != (camera.height, camera.width):
        source = calibration.sources[0].name
        raise EurocError(
            f"{where}: image is {image.shape[1]}x{image.shape[0]}, "
            f"{source} says {camera.width}x{camera.height} (resolution of {calibration.sources[0]})"
        )
