"""The cloud receives each robot's sensors from its edge and uses that robot's own camera:
keyframes decode with its image size and verification / merging project with its intrinsics
and extrinsic; the sensors persist with the state."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from common.calibration import EUROC_IMU, CameraCalibration
from common.codec import CodecConfig
from common.geometry import inverse_T, make_T
from common.links.edge_cloud import agent_sensors_message
from common.links.sensors import Sensors
from common.vocabulary import Vocabulary
from services.cloud.app import open_app
from services.cloud.config import CloudConfig, FullBAConfig, MbpConfig
from services.cloud.core import CloudCore
from services.cloud.fusion.merge import yaw_of
from services.cloud.service_config import CloudServiceConfig, OptimizationScheduleConfig
from sim.cloud import (
    R_BODY_CAM,
    circle_poses,
    default_camera,
    encode_session,
    make_session,
    make_world,
    yaw_T,
)

CAM_B = CameraCalibration(
    width=640,
    height=480,
    fx=330.0,
    fy=331.5,
    cx=318.2,
    cy=243.7,
    distortion=(-0.21, 0.04, 5e-4, -3e-4),
    T_body_cam=make_T(R_BODY_CAM, np.array([0.12, -0.03, 0.02])),
)
"""Robot r1's camera: another size, other intrinsics, distortion and mounting than r0's."""
T_R1_WORLD = yaw_T(np.radians(-60.0), np.array([-1.5, 0.5, 0.0]))
CFG = CloudServiceConfig(
    domain=CloudConfig(full_ba=FullBAConfig(enabled=False), mbp=MbpConfig(enabled=False)),
    schedule=OptimizationScheduleConfig(every_keyframes=1000),
)


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def steps(vocab) -> dict[str, list[list]]:
    """Per robot, per keyframe, what its edge sends: r0 sees with the EuRoC-like camera, r1
    (its map offset by a yaw and a shift, overlapping r0's) with :data:`CAM_B`."""
    world = make_world(51)
    r0 = make_session(world, default_camera(), 0, circle_poses(24, turns=1.0), np.eye(4), seed=1)
    poses = circle_poses(12, turns=0.5, phase=2.0)
    r1 = make_session(world, CAM_B, 1, poses, T_R1_WORLD, seed=2, t0=50.0)
    codec_b = CodecConfig(image_width=CAM_B.width, image_height=CAM_B.height)
    return {
        "r0": encode_session(*r0, "r0", vocab, 7),
        "r1": encode_session(*r1, "r1", vocab, 7, codec=codec_b),
    }


def _run(tmp_path, vocab, steps, cameras: dict[str, CameraCalibration]):
    """A fresh cloud (fallback camera: r0's) fed the sensors of ``cameras`` then every
    keyframe of r0 and r1; the app, still open."""
    app = open_app(tmp_path, default_camera(), vocab, CFG)
    core = CloudCore(app)
    seq = 0
    for name, cam in cameras.items():
        seq += 1
        core.handle("edge", agent_sensors_message(name, Sensors(cam, EUROC_IMU)), b"s", seq, 0.0)
    for name in ("r0", "r1"):
        for group in steps[name]:
            for msg in group:
                seq += 1
                core.handle("edge", msg, b"s", seq, 1.0)
    return app


@pytest.mark.slow
def test_each_robot_is_decoded_and_verified_with_its_own_camera(tmp_path, vocab, steps):
    app = _run(tmp_path, vocab, steps, {"r0": default_camera(), "r1": CAM_B})
    try:
        agents = {name: aid for aid, (name, _, _) in app.agents().items()}
        assert app.fusion.camera_of(agents["r1"]) is app.sensors.camera("r1")
        assert app.fusion.camera_of(agents["r1"]).width == 640
        # Keyframes decoded on r1's 640x480 grid (the default 752x480 would misplace them).
        kf = app.atlas.keyframe(app.atlas.keyframe_keys(agent_id=agents["r1"])[0])
        assert kf.keypoints[:, 0].max() < 640 and kf.keypoints.min() >= 0
        # Verified with r1's intrinsics and extrinsic: the maps merged, at the true offset.
        assert app.atlas.maps() == [0]
        merges = app.atlas.merges()
        assert len(merges) == 1
        T = merges[0].T_target_source
        T_exp = inverse_T(T_R1_WORLD)
        assert np.linalg.norm(T[:3, 3] - T_exp[:3, 3]) < 0.02
        assert abs(np.degrees(yaw_of(T[:3, :3]) - yaw_of(T_exp[:3, :3]))) < 0.2
    finally:
        app.close()
    # Persisted with the state: a restarted cloud projects r1 with CAM_B again.
    again = open_app(tmp_path, default_camera(), vocab, CFG)
    try:
        cam = again.fusion.camera_of(agents["r1"])
        assert Sensors(cam, EUROC_IMU).same_as(Sensors(CAM_B, EUROC_IMU))
        assert again.sensors.codec("r1").image_width == 640
    finally:
        again.close()


@pytest.mark.slow
def test_wrong_intrinsics_do_not_verify(tmp_path, vocab, steps):
    """Control: told r1 has r0's focal lengths and mounting (same image size), the cloud's
    verification of r1's keyframes against r0's map fails: the camera in use is the robot's."""
    wrong = dataclasses.replace(default_camera(), width=640, cx=CAM_B.cx, cy=CAM_B.cy)
    app = _run(tmp_path, vocab, steps, {"r1": wrong})
    try:
        assert app.atlas.maps() == [0, 1]
    finally:
        app.close()


def test_a_repeat_is_a_no_op_and_a_conflict_keeps_the_first(tmp_path, vocab, caplog):
    app = open_app(tmp_path, default_camera(), vocab, CFG)
    try:
        first = Sensors(CAM_B, EUROC_IMU)
        app.handle("edge", agent_sensors_message("r1", first), b"s", 1)
        app.handle("edge", agent_sensors_message("r1", first), b"s", 2)
        other = Sensors(dataclasses.replace(CAM_B, fx=300.0), EUROC_IMU)
        with caplog.at_level(logging.ERROR):
            app.handle("edge", agent_sensors_message("r1", other), b"s", 3)
        assert "other sensors" in caplog.text
        cam = app.sensors.camera("r1")
        assert cam is not None and cam.fx == CAM_B.fx
        pos = app.positions.load("edge")
        assert pos is not None and pos.last_delivered == 3
    finally:
        app.close()
