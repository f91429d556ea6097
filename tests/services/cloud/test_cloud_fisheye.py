"""Verification's pycolmap camera (OPENCV for radtan, OPENCV_FISHEYE for equidistant) projects
and unprojects exactly as the one camera model, so its pixel thresholds hold for a fisheye."""

from __future__ import annotations

import numpy as np
import pytest

from common.calibration import CameraCalibration
from common.camera import camera_model
from common.data.synth.cameras import EUROC_CAM0, FISHEYE_CAM
from services.cloud.fusion.verification import VerificationError, colmap_camera


@pytest.mark.parametrize("model", [FISHEYE_CAM, EUROC_CAM0], ids=["equidistant", "radtan"])
def test_pycolmap_camera_projects_like_the_model(model) -> None:
    calib = model.to_calibration(np.eye(4), 20.0)
    col = colmap_camera(calib)
    rng = np.random.default_rng(0)
    uv = rng.uniform([20, 20], [model.width - 20, model.height - 20], size=(300, 2))
    xy = camera_model(calib).pixels_to_normalized(uv)
    front = np.isfinite(xy).all(axis=1)  # a fisheye's corners look more than 90 degrees off
    assert front.mean() > 0.8
    uv, xy = uv[front], xy[front]
    p_cam = np.c_[xy, np.ones(len(xy))] * rng.uniform(0.5, 10.0, (len(xy), 1))
    np.testing.assert_allclose(col.img_from_cam(p_cam), uv, atol=1e-6)
    np.testing.assert_allclose(col.cam_from_img(uv), xy, atol=1e-8)


def test_unknown_model_has_no_pycolmap_camera() -> None:
    calib = CameraCalibration(10, 10, 1.0, 1.0, 5.0, 5.0)
    object.__setattr__(calib, "model", "fov")  # a model added to the calibration only
    with pytest.raises(VerificationError, match="fov"):
        colmap_camera(calib)
