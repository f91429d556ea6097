"""The edge VIO with a fisheye (equidistant) camera: the same code path as radtan, through the
camera model, on the built-in simulator's tracks."""

from __future__ import annotations

import numpy as np

from common.data.synth.cameras import FISHEYE_CAM
from services.edge.vio.manager import VioManager
from services.edge.vio.simulation import (
    EUROC_CAM0,
    SimOptions,
    evaluate_run,
    run_sequence,
    simulate,
)
from services.edge.vio.state import PinholeUndistorter
from services.edge.vio.types import FrameObservation


def test_fisheye_end_to_end_20s_ate_and_scale() -> None:
    camera = FISHEYE_CAM.to_calibration(EUROC_CAM0.T_body_cam, 20.0)
    seq = simulate(SimOptions(duration_s=20.0, seed=0, outlier_ratio=0.05), camera=camera)
    assert max(np.abs(f.keypoints_px - 255.5).max() for f in seq.frames) > 200  # wide angles
    vio = VioManager(seq.camera, seq.imu)
    m = evaluate_run(vio, run_sequence(vio, seq), seq)
    # Measured when written: frames ATE 4.3 cm, scale 0.986; keyframes 3.4 cm, scale 0.983
    # (EuRoC cam0 on the same flight: 5.0 cm, 0.994; 1.8 cm, 0.989).
    assert m.n_maps == 1
    assert m.n_tracking > 0.8 * m.n_frames
    assert m.ate_frames_m < 0.10
    assert abs(m.scale_frames - 1.0) < 0.05
    assert m.ate_keyframes_m < 0.06
    assert abs(m.scale_keyframes - 1.0) < 0.03


def test_features_looking_ninety_degrees_off_axis_are_dropped() -> None:
    camera = FISHEYE_CAM.to_calibration(EUROC_CAM0.T_body_cam, 20.0)
    undistorter = PinholeUndistorter(camera)
    uv = np.array([[255.5, 255.5], [0.0, 0.0], [400.0, 300.0]])  # centre, corner (115 deg)
    xy = undistorter.normalise(uv)
    assert np.isfinite(xy[[0, 2]]).all() and np.isnan(xy[1]).all()
    vio = VioManager(camera, simulate(SimOptions(duration_s=0.3)).imu)
    obs = FrameObservation(
        timestamp_ns=1, track_ids=np.arange(3), keypoints_px=uv, levels=np.zeros(3, np.uint8)
    )
    vio.feed_frame(obs)  # accepted: the corner feature is dropped before the estimator
