"""Sensor calibrations as plain frozen data (what EuRoC's ``sensor.yaml`` files state).

Frame convention: ``T_a_b`` maps points from frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``).
EuRoC's ``T_BS`` is therefore ``T_body_sensor``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.errors import RecslamError

CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "radtan": ("k1", "k2", "p1", "p2"),
    "equidistant": ("k1", "k2", "k3", "k4"),
}
"""Distortion models a :class:`CameraCalibration` may name, with their coefficients in order:
``radtan`` is pinhole with radial-tangential distortion (OpenCV's default model, EuRoC's and
Kalibr's ``radtan``); ``equidistant`` is pinhole with Kannala-Brandt equidistant distortion
(OpenCV's ``fisheye`` module, Kalibr's ``equidistant``, TUM-VI, RealSense T265)."""


class CalibrationError(RecslamError):
    """A calibration that cannot describe a real sensor (unknown model, wrong coefficient
    count, non-positive size or focal length)."""


def _frozen_array(a: np.ndarray | list, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.array(a, dtype=np.float64).reshape(shape)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Pinhole camera with a distortion model (see :data:`CAMERA_MODELS`).

    Intrinsics in pixels; ``distortion`` holds the model's coefficients in the order
    :data:`CAMERA_MODELS` names them; ``T_body_cam`` (4, 4) maps camera-frame points to the
    body frame. The projection maths lives in :func:`common.camera.camera_model`.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
    T_body_cam: np.ndarray = field(default_factory=lambda: _frozen_array(np.eye(4), (4, 4)))
    rate_hz: float = 20.0
    model: str = "radtan"

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_body_cam", _frozen_array(self.T_body_cam, (4, 4)))
        object.__setattr__(self, "distortion", tuple(float(d) for d in self.distortion))
        names = CAMERA_MODELS.get(self.model)
        if names is None:
            known = ", ".join(CAMERA_MODELS)
            raise CalibrationError(f"unknown camera model {self.model!r} (known: {known})")
        if len(self.distortion) != len(names):
            raise CalibrationError(
                f"camera model {self.model!r} takes {len(names)} distortion coefficients "
                f"({', '.join(names)}), got {len(self.distortion)}"
            )
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise CalibrationError(f"focal lengths must be positive, got {self.fx}, {self.fy}")

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(4,) OpenCV distortion vector of the model (``cv2`` for radtan, ``cv2.fisheye`` for
        equidistant)."""
        return np.array(self.distortion, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class ImuCalibration:
    """IMU noise model (continuous-time densities) and extrinsic.

    Units: gyro noise rad/s/√Hz, gyro random walk rad/s²/√Hz, accel noise m/s²/√Hz,
    accel random walk m/s³/√Hz. ``T_body_imu`` (4, 4) maps IMU-frame points to the body frame.
    """

    gyro_noise_density: float
    gyro_random_walk: float
    accel_noise_density: float
    accel_random_walk: float
    rate_hz: float = 200.0
    T_body_imu: np.ndarray = field(default_factory=lambda: _frozen_array(np.eye(4), (4, 4)))

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_body_imu", _frozen_array(self.T_body_imu, (4, 4)))


# ADIS16448 as calibrated for EuRoC (imu0/sensor.yaml of every EuRoC sequence).
EUROC_IMU = ImuCalibration(
    gyro_noise_density=1.6968e-04,
    gyro_random_walk=1.9393e-05,
    accel_noise_density=2.0000e-3,
    accel_random_walk=3.0000e-3,
    rate_hz=200.0,
)
