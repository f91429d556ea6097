"""Camera presets of the synthetic generator: one per robot, so a team may mix cameras.

``euroc`` is EuRoC's cam0 (752x480 radial-tangential, EuRoC's mount: the generator's default);
``wide`` a 640x480 radial-tangential camera with about twice EuRoC's field of view, mounted
pitched 15 degrees down and 4 cm to the side; ``fisheye`` a TUM-VI-like 512x512 equidistant
camera (about 190 degrees across the diagonal) on EuRoC's mount. Mounts are ``T_body_cam``
(4, 4), body = IMU frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.calibration import CameraCalibration
from common.camera import CameraModel, PinholeEquidistant, PinholeRadtan
from common.data.synth.trajectory import T_IMU_CAM
from common.errors import RecslamError

# EuRoC cam0 (V1_01): intrinsics [px] and radial-tangential distortion.
EUROC_CAM0 = PinholeRadtan(
    752,
    480,
    458.654,
    457.296,
    367.215,
    248.375,
    -0.28340811,
    0.07395907,
    0.00019359,
    1.76187114e-05,
)

WIDE_CAM = PinholeRadtan(640, 480, 320.0, 320.0, 319.5, 239.5, -0.05, 0.004, 0.0, 0.0)
"""640x480 radtan, 90 x 74 degrees (EuRoC cam0: 79 x 55 degrees, but much stronger barrel)."""

# TUM-VI room sequences' cam0 (512x512 equidistant), rounded.
FISHEYE_CAM = PinholeEquidistant(
    512, 512, 190.0, 190.0, 255.5, 255.5, 0.0034, 0.0007, -0.0021, 0.0002
)
"""512x512 equidistant, TUM-VI-like: 77 degrees off axis at the edge centres, 115 at the
corners (those pixels look backwards)."""


def _pitched_mount(pitch_down_deg: float, shift_x_m: float) -> np.ndarray:
    """EuRoC's mount turned ``pitch_down_deg`` about the camera's x axis (optical axis towards
    +y_cam, image down) and shifted along the camera's x axis [m]."""
    a = np.radians(pitch_down_deg)
    T_cam_new = np.eye(4)
    T_cam_new[:3, :3] = [[1.0, 0.0, 0.0], [0.0, np.cos(a), np.sin(a)], [0.0, -np.sin(a), np.cos(a)]]
    T_cam_new[0, 3] = shift_x_m
    T = T_IMU_CAM @ T_cam_new
    T.setflags(write=False)
    return T


class CameraPresetError(RecslamError):
    """Unknown camera preset name."""


@dataclass(frozen=True, eq=False)
class CameraPreset:
    """A robot's camera: ``model`` (intrinsics and distortion), ``T_body_cam`` (4, 4) its
    mount, ``comment`` for its ``sensor.yaml``."""

    name: str
    model: CameraModel
    T_body_cam: np.ndarray
    comment: str

    def calibration(self, rate_hz: float) -> CameraCalibration:
        """The calibration a robot with this camera states (``cam0/sensor.yaml``)."""
        return self.model.to_calibration(self.T_body_cam, rate_hz)


CAMERA_PRESETS: dict[str, CameraPreset] = {
    "euroc": CameraPreset("euroc", EUROC_CAM0, T_IMU_CAM, "synthetic EuRoC-like cam0"),
    "wide": CameraPreset(
        "wide", WIDE_CAM, _pitched_mount(15.0, 0.04), "synthetic wide-angle cam0, pitched down"
    ),
    "fisheye": CameraPreset(
        "fisheye", FISHEYE_CAM, T_IMU_CAM, "synthetic TUM-VI-like equidistant fisheye cam0"
    ),
}
"""Presets by name (``recslam dataset synth --cameras euroc,wide,fisheye``)."""


def camera_preset(name: str) -> CameraPreset:
    """The preset called ``name``, else :class:`CameraPresetError`."""
    preset = CAMERA_PRESETS.get(name)
    if preset is None:
        known = ", ".join(CAMERA_PRESETS)
        raise CameraPresetError(f"unknown camera preset {name!r} (known: {known})")
    return preset
