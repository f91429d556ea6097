"""Camera models behind one interface (:class:`CameraModel`): pinhole with radial-tangential
distortion (:class:`PinholeRadtan`) and pinhole with equidistant fisheye distortion
(:class:`PinholeEquidistant`). Consumers build the model a calibration names with
:func:`camera_model` and never do distortion maths themselves.
"""

from __future__ import annotations

from common.calibration import CameraCalibration
from common.camera.base import CameraModel, CameraModelError
from common.camera.equidistant import PinholeEquidistant
from common.camera.radtan import PinholeRadtan

__all__ = [
    "CameraModel",
    "CameraModelError",
    "PinholeEquidistant",
    "PinholeRadtan",
    "camera_model",
]


def camera_model(calib: CameraCalibration) -> CameraModel:
    """The projection model ``calib.model`` names, with ``calib``'s parameters."""
    if calib.model == "radtan":
        return PinholeRadtan.from_calibration(calib)
    if calib.model == "equidistant":
        return PinholeEquidistant.from_calibration(calib)
    raise CameraModelError(f"camera model {calib.model!r} is not implemented")
