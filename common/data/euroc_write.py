"""Writer for the EuRoC ASL layout, byte-compatible in format with the real downloads.

Floats are written with Python's ``repr`` (shortest string that round-trips exactly), so
``common.data.euroc`` reads back the very same float64 values. Typical use::

    with EurocWriter(out_dir, body_yaml_comment="synthetic robot 0") as w:
        w.add_camera("cam0", calib)
        for t, img in frames:
            w.add_image("cam0", t, img)
        w.write_imu(imu_calib, imu_ts, gyro, accel)
        w.write_groundtruth(gt)
"""

from __future__ import annotations

import logging
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.data.euroc import (
    CAMERA_CSV_HEADER,
    GROUNDTRUTH_CSV_HEADER,
    GROUNDTRUTH_DIR,
    IMU_CSV_HEADER,
    EurocError,
    EurocGroundTruth,
)

logger = logging.getLogger(__name__)

_CAMERAS = ("cam0", "cam1")

EUROC_DISTORTION_MODELS: dict[str, str] = {
    "radtan": "radial-tangential",
    "equidistant": "equidistant",
}
"""``sensor.yaml`` ``distortion_model`` of each calibration model (EuRoC writes
``radial-tangential``; TUM-VI and Kalibr write ``equidistant`` for Kannala-Brandt)."""


def format_float(x: float) -> str:
    """Shortest exact decimal of ``x`` that YAML 1.1 and C parsers both read as a float.

    ``repr`` gives ``1e-05`` for 1e-5, which PyYAML would read as a string: a ``.0`` is
    inserted in that case (``1.0e-05``).
    """
    x = float(x)
    if not np.isfinite(x):
        raise EurocError(f"cannot write non-finite value {x}")
    s = repr(x)
    if "e" in s and "." not in s:
        mantissa, exponent = s.split("e")
        s = f"{mantissa}.0e{exponent}"
    return s


def _yaml_number(x: float) -> str:
    """Integers as EuRoC writes them (``rate_hz: 20``), everything else exactly."""
    x = float(x)
    return str(int(x)) if x.is_integer() and abs(x) < 1e15 else format_float(x)


def _yaml_list(values: np.ndarray | tuple | list) -> str:
    return "[" + ", ".join(format_float(v) for v in values) + "]"


def _yaml_T_BS(T: np.ndarray) -> str:
    rows = [", ".join(format_float(v) for v in row) for row in np.asarray(T, dtype=float)]
    data = ",\n         ".join(rows)
    return f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"


def _yaml_comment(text: str) -> str:
    """A one-line YAML scalar that reads back as ``text``."""
    text = " ".join(text.split())
    return '""' if not text else "'" + text.replace("'", "''") + "'"


def _check_timestamps(ts: np.ndarray, what: str) -> np.ndarray:
    ts = np.asarray(ts)
    if ts.ndim != 1 or not np.issubdtype(ts.dtype, np.integer):
        raise EurocError(f"{what}: timestamps must be a 1-D integer array [ns], got {ts.dtype}")
    ts = ts.astype(np.int64)
    bad = np.flatnonzero(np.diff(ts) <= 0)
    if len(bad):
        i = int(bad[0]) + 1
        raise EurocError(f"{what}: timestamps not strictly increasing at index {i}")
    return ts


def _write_rows(path: Path, header: str, ts: np.ndarray, values: np.ndarray) -> None:
    """``ts`` (N,) int64 and ``values`` (N, C) float64 -> CSV with ``repr`` floats."""
    if not np.isfinite(values).all():
        raise EurocError(f"{path}: refusing to write non-finite values")
    lines = [header]
    for t, row in zip(ts.tolist(), values.tolist(), strict=True):
        lines.append(str(t) + "," + ",".join(map(repr, row)))
    path.write_text("\n".join(lines) + "\n", newline="\n")


class EurocWriter:
    """Write one sequence in the EuRoC ASL layout under ``root/mav0``.

    Images are written at once; camera ``data.csv`` rows are buffered and written by
    :meth:`close` (also called on leaving a ``with`` block).
    """

    def __init__(self, root: Path, body_yaml_comment: str = "") -> None:
        self.root = Path(root)
        self.mav0 = self.root / "mav0"
        if self.mav0.exists():
            logger.warning("%s exists: files in it will be overwritten", self.mav0)
        self.mav0.mkdir(parents=True, exist_ok=True)
        (self.mav0 / "body.yaml").write_text(
            f"%YAML:1.0\ncomment: {_yaml_comment(body_yaml_comment)}\n"
        )
        self._calibs: dict[str, CameraCalibration] = {}
        self._rows: dict[str, list[tuple[int, str]]] = {}
        self._closed = False

    def __enter__(self) -> EurocWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def add_camera(self, cam: str, calib: CameraCalibration, comment: str = "") -> None:
        """Create ``mav0/<cam>/`` and its ``sensor.yaml`` (pinhole; ``distortion_model`` of the
        calibration's model, :data:`EUROC_DISTORTION_MODELS`)."""
        if cam not in _CAMERAS:
            raise EurocError(f"camera name must be one of {_CAMERAS}, got {cam!r}")
        if cam in self._calibs:
            raise EurocError(f"{cam} added twice")
        folder = self.mav0 / cam
        (folder / "data").mkdir(parents=True, exist_ok=True)
        text = (
            "%YAML:1.0\n"
            "# General sensor definitions.\n"
            "sensor_type: camera\n"
            f"comment: {_yaml_comment(comment)}\n"
            "\n"
            "# Sensor extrinsics wrt. the body-frame.\n"
            f"{_yaml_T_BS(calib.T_body_cam)}"
            "\n"
            "# Camera specific definitions.\n"
            f"rate_hz: {_yaml_number(calib.rate_hz)}\n"
            f"resolution: [{int(calib.width)}, {int(calib.height)}]\n"
            "camera_model: pinhole\n"
            f"intrinsics: {_yaml_list([calib.fx, calib.fy, calib.cx, calib.cy])}"
            " #fu, fv, cu, cv\n"
            f"distortion_model: {EUROC_DISTORTION_MODELS[calib.model]}\n"
            f"distortion_coefficients: {_yaml_list(calib.distortion)}\n"
        )
        (folder / "sensor.yaml").write_text(text)
        self._calibs[cam] = calib
        self._rows[cam] = []

    def add_image(self, cam: str, timestamp_ns: int, image: np.ndarray) -> None:
        """Write uint8 (H, W) ``image`` as ``mav0/<cam>/data/<timestamp_ns>.png``."""
        if self._closed:
            raise EurocError("writer already closed")
        if cam not in self._calibs:
            raise EurocError(f"{cam} not added: call add_camera first")
        calib = self._calibs[cam]
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.shape != (calib.height, calib.width):
            raise EurocError(
                f"{cam} image must be uint8 {(calib.height, calib.width)}, "
                f"got {image.dtype} {image.shape}"
            )
        t = int(timestamp_ns)
        rows = self._rows[cam]
        if rows and t <= rows[-1][0]:
            raise EurocError(f"{cam}: timestamp {t} not after previous {rows[-1][0]}")
        name = f"{t}.png"
        path = self.mav0 / cam / "data" / name
        if not cv2.imwrite(str(path), image):
            raise EurocError(f"{path}: could not write image")
        rows.append((t, name))

    def write_imu(
        self,
        calib: ImuCalibration,
        timestamps_ns: np.ndarray,
        gyro: np.ndarray,
        accel: np.ndarray,
    ) -> None:
        """Write ``imu0/sensor.yaml`` and ``imu0/data.csv``.

        ``timestamps_ns`` (M,) int, strictly increasing; ``gyro`` (M, 3) rad/s and
        ``accel`` (M, 3) m/s² in the IMU frame.
        """
        ts = _check_timestamps(timestamps_ns, "imu0")
        gyro = np.asarray(gyro, dtype=np.float64)
        accel = np.asarray(accel, dtype=np.float64)
        if gyro.shape != (len(ts), 3) or accel.shape != (len(ts), 3):
            raise EurocError(
                f"imu0: gyro {gyro.shape} and accel {accel.shape} must be ({len(ts)}, 3)"
            )
        folder = self.mav0 / "imu0"
        folder.mkdir(parents=True, exist_ok=True)
        text = (
            "%YAML:1.0\n"
            "#Default imu sensor yaml file\n"
            "sensor_type: imu\n"
            "comment: VI-Sensor IMU (ADIS16448)\n"
            "\n"
            "# Sensor extrinsics wrt. the body-frame.\n"
            f"{_yaml_T_BS(calib.T_body_imu)}"
            f"rate_hz: {_yaml_number(calib.rate_hz)}\n"
            "\n"
            "# inertial sensor noise model parameters (static)\n"
            f"gyroscope_noise_density: {format_float(calib.gyro_noise_density)}"
            '     # [ rad / s / sqrt(Hz) ]   ( gyro "white noise" )\n'
            f"gyroscope_random_walk: {format_float(calib.gyro_random_walk)}"
            "       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )\n"
            f"accelerometer_noise_density: {format_float(calib.accel_noise_density)}"
            '  # [ m / s^2 / sqrt(Hz) ]   ( accel "white noise" )\n'
            f"accelerometer_random_walk: {format_float(calib.accel_random_walk)}"
            "    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )\n"
        )
        (folder / "sensor.yaml").write_text(text)
        _write_rows(folder / "data.csv", IMU_CSV_HEADER, ts, np.hstack([gyro, accel]))

    def write_groundtruth(self, gt: EurocGroundTruth) -> None:
        """Write ``state_groundtruth_estimate0/{sensor.yaml, data.csv}`` (17 columns)."""
        ts = _check_timestamps(gt.timestamps_ns, GROUNDTRUTH_DIR)
        folder = self.mav0 / GROUNDTRUTH_DIR
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "sensor.yaml").write_text(
            "%YAML:1.0\n"
            "# Sensor extrinsics wrt. the body-frame. This is the transformation of the\n"
            "# tracking prima to the body frame.\n"
            "sensor_type: visual-inertial\n"
            "comment: Ground truth state of the body (IMU) frame.\n"
            f"{_yaml_T_BS(np.eye(4))}"
        )
        values = np.hstack(
            [gt.p_world_body, gt.q_world_body_wxyz, gt.v_world_body, gt.bias_gyro, gt.bias_accel]
        )
        _write_rows(folder / "data.csv", GROUNDTRUTH_CSV_HEADER, ts, values)

    def close(self) -> None:
        """Write every added camera's ``data.csv``. Idempotent."""
        if self._closed:
            return
        for cam, rows in self._rows.items():
            lines = [CAMERA_CSV_HEADER] + [f"{t},{name}" for t, name in rows]
            (self.mav0 / cam / "data.csv").write_text("\n".join(lines) + "\n")
            logger.debug("%s: %d images", cam, len(rows))
        self._closed = True
