"""The edge VIO with a fisheye (equidistant) camera: the same code path as radtan, through the
camera model, on the built-in simulator's tracks."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.data.synth.cameras import FISHEYE_CAM
from services.edge.vio.manager import VioManager
from services.edge.vio.state import PinholeUndistorter
from services.edge.vio.types import FrameObservation
from sim.vio import (
    EUROC_CAMERA,
    SimConfig,
    evaluate_run,
    run_sequence,
    simulate,
)


@pytest.mark.slow
def test_fisheye_end_to_end_20s_ate_and_scale() -> None:
    camera = FISHEYE_CAM.to_calibration(EUROC_CAMERA.T_body_cam, 20.0)
    seq = simulate(SimConfig(duration_s=20.0, seed=0, outlier_ratio=0.05), camera=camera)
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
    camera = FISHEYE_CAM.to_calibration(EUROC_CAMERA.T_body_cam, 20.0)
    undistorter = PinholeUndistorter(camera)
    uv = np.array([[255.5, 255.5], [0.0, 0.0], [400.0, 300.0]])  # centre, corner (115 deg)
    xy = undistorter.normalise(uv)
    assert np.isfinite(xy[[0, 2]]).all() and np.isnan(xy[1]).all()
    vio = VioManager(camera, simulate(SimConfig(duration_s=0.3)).imu)
    obs = FrameObservation(
        timestamp_ns=1, track_ids=np.arange(3), keypoints_px=uv, levels=np.zeros(3, np.uint8)
    )
    vio.feed_frame(obs)  # accepted: the corner feature is dropped before the estimator


@pytest.mark.slow
def test_rows_leaving_the_vio_are_the_robots_rows_when_features_were_left_out() -> None:
    """A fisheye keyframe whose features the VIO partly left out (90 degrees or more off axis)
    still goes up with one point id per robot feature, and each observation row names the
    robot's row of that feature (the uplink indexes the robot's keyframe features with them)."""
    camera = FISHEYE_CAM.to_calibration(EUROC_CAMERA.T_body_cam, 20.0)
    seq = simulate(SimConfig(duration_s=8.0, seed=0), camera=camera)
    undistorter = PinholeUndistorter(camera)
    frames = {}
    vio = VioManager(seq.camera, seq.imu)
    updates = []
    left_out = 0
    corners = np.array([[1.0, 1.0], [510.0, 1.0], [1.0, 510.0], [510.0, 510.0]])  # ~115 deg
    for i, (t, gyro, accel, sim_frame) in enumerate(seq.feed()):
        # Features beyond 90 degrees first, so that every later row shifts if rows get lost.
        frame = dataclasses.replace(
            sim_frame,
            track_ids=np.concatenate([10**7 + 4 * i + np.arange(4), sim_frame.track_ids]),
            keypoints_px=np.concatenate([corners, sim_frame.keypoints_px]),
            levels=np.concatenate([np.zeros(4, np.uint8), sim_frame.levels]),
            descriptors=None
            if sim_frame.descriptors is None
            else np.concatenate([np.zeros((4, 32), np.uint8), sim_frame.descriptors]),
        )
        frames[frame.timestamp_ns] = frame
        left_out += int((~np.isfinite(undistorter.normalise(frame.keypoints_px))).any(1).sum())
        vio.feed_imu(t, gyro, accel)
        vio.feed_frame(frame)
        updates += vio.pop_map_updates()
    assert left_out > 0  # the flight does show features beyond 90 degrees
    kf_frames = {}
    tracks: dict[int, set[int]] = {}
    checked_kf = checked_rows = 0
    for upd in updates:
        for kf in upd.keyframes:
            robot = frames[kf.timestamp_ns]
            kf_frames[kf.keyframe_id] = robot
            assert len(kf.point_ids) == len(robot.track_ids) == len(kf.track_ids)
            kept = kf.track_ids >= 0
            assert (kf.track_ids[kept] == robot.track_ids[kept]).all()
            assert (kf.point_ids[~kept] == -1).all()
            checked_kf += int((~kept).any())
        b = upd.points
        owner = np.repeat(np.arange(len(b)), b.counts)
        for o, kf_id, row in zip(owner, b.keyframe_ids, b.feature_indices, strict=True):
            robot = kf_frames.get(int(kf_id))
            if robot is None:
                continue
            assert 0 <= row < len(robot.track_ids)
            tracks.setdefault(int(b.point_ids[o]), set()).add(int(robot.track_ids[row]))
            checked_rows += 1
    # Each row names a feature the VIO used (never a left-out one), and the rows of one point
    # name one track (the simulator's tracks are its landmarks): shifted rows would not.
    assert not any(t >= 10**7 for ts in tracks.values() for t in ts)
    one_track = np.mean([len(ts) == 1 for ts in tracks.values()])
    assert one_track > 0.95, one_track
    assert checked_kf > 0 and checked_rows > 1000
