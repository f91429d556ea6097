"""Sensor calibrations as plain frozen data (what EuRoC's ``sensor.yaml`` files state).

Frame convention: ``T_a_b`` maps points from frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``).
EuRoC's ``T_BS`` is therefore ``T_body_sensor``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _frozen_array(a: np.ndarray | list, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.array(a, dtype=np.float64).reshape(shape)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Pinhole camera with radial-tangential distortion (k1, k2, p1, p2).

    Intrinsics in pixels; ``T_body_cam`` (4, 4) maps camera-frame points to the body frame.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    T_body_cam: np.ndarray = field(default_factory=lambda: _frozen_array(np.eye(4), (4, 4)))
    rate_hz: float = 20.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_body_cam", _frozen_array(self.T_body_cam, (4, 4)))
        object.__setattr__(self, "distortion", tuple(float(d) for d in self.distortion))

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(4,) OpenCV distortion vector (k1, k2, p1, p2)."""
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
