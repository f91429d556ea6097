"""IMU prediction: gyro rotation, infinite homography on (un)distorted points, propagation."""

from __future__ import annotations

from pathlib import Path

import cv2
import gtsam
import numpy as np
import pytest

from common.calibration import EUROC_IMU, CameraCalibration
from common.camera import PinholeRadtan
from common.geometry import make_T, so3_exp
from common.imu import ImuBuffer, ImuDataError
from services.robot.imu_prediction import (
    ImuPredictionError,
    InertialState,
    MotionPredictor,
    StaticGyroBias,
    gyro_rotation,
    mean_angular_velocity,
    predict_rotation,
    project_points,
    propagate,
    undistort_normalised,
    warp_by_rotation,
)

# EuRoC cam0 (V1_01 sensor.yaml).
T_BODY_CAM = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
EUROC_CAM = CameraCalibration(
    752,
    480,
    458.654,
    457.296,
    367.215,
    248.375,
    (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
    T_BODY_CAM,
)
PINHOLE_CAM = CameraCalibration(752, 480, 458.654, 457.296, 367.215, 248.375, T_body_cam=T_BODY_CAM)


@pytest.fixture(scope="module")
def image(euroc_micro: Path) -> np.ndarray:
    paths = sorted((euroc_micro / "mav0/cam0/data").glob("*.png"))
    assert paths, f"no images in {euroc_micro}/mav0/cam0/data"
    return cv2.imread(str(paths[30]), cv2.IMREAD_GRAYSCALE)


def constant_rate_buffer(w_imu: np.ndarray, t0: int, t1: int, rate_hz: float = 200.0) -> ImuBuffer:
    ts = np.arange(t0 - 20_000_000, t1 + 20_000_000, int(1e9 / rate_hz), dtype=np.int64)
    buf = ImuBuffer(10.0)
    buf.append(ts, np.tile(w_imu, (len(ts), 1)), np.tile([0.0, 0.0, 9.81], (len(ts), 1)))
    return buf


def test_gyro_rotation_of_constant_rate_is_exact() -> None:
    w = np.array([0.3, -0.2, 0.5])
    t0, t1 = 1_000_003_000, 1_050_001_000  # not on sample times
    R = gyro_rotation(constant_rate_buffer(w, t0, t1), t0, t1)
    np.testing.assert_allclose(R, so3_exp(w * (t1 - t0) * 1e-9), atol=1e-12)


def test_mean_angular_velocity_is_time_weighted() -> None:
    # Gyro z ramps linearly 0 -> 1 rad/s over 1 s: mean over [0.25 s, 0.75 s] is 0.5.
    ts = np.arange(0, 1_000_000_001, 5_000_000, dtype=np.int64)
    gyro = np.zeros((len(ts), 3))
    gyro[:, 2] = ts * 1e-9
    buf = ImuBuffer(10.0)
    buf.append(ts, gyro, np.zeros_like(gyro))
    w = mean_angular_velocity(buf, 250_000_000, 750_000_000)
    np.testing.assert_allclose(w, [0.0, 0.0, 0.5], atol=1e-12)
    assert mean_angular_velocity(buf, 0, 100_000_000)[2] == pytest.approx(0.05)


def _to_pixels(xy: np.ndarray) -> np.ndarray:
    return PinholeRadtan.from_calibration(EUROC_CAM).normalized_to_pixels(xy)


def _radtan_pixels_before_issue_15(camera: CameraCalibration, xy: np.ndarray) -> np.ndarray:
    """The robot's own copy of the radial-tangential model, as it was before it called
    ``common.camera`` (the reference the shared model must reproduce)."""
    k1, k2, p1, p2 = camera.distortion
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], axis=1)


def test_projection_through_the_shared_camera_model_is_unchanged() -> None:
    rng = np.random.default_rng(15)
    p_cam = np.c_[rng.uniform(-3.0, 3.0, size=(2000, 2)), rng.uniform(-1.0, 8.0, 2000)]
    got, front = project_points(EUROC_CAM, p_cam)
    assert 0 < front.sum() < len(p_cam) and np.isnan(got[~front]).all()
    want = _radtan_pixels_before_issue_15(EUROC_CAM, p_cam[front, :2] / p_cam[front, 2:3])
    np.testing.assert_allclose(got[front], want, rtol=1e-13, atol=1e-9)


def test_undistort_and_distort_round_trip_and_match_opencv() -> None:
    rng = np.random.default_rng(0)
    px = rng.uniform([0, 0], [752, 480], size=(400, 2))
    err = np.linalg.norm(_to_pixels(undistort_normalised(EUROC_CAM, px)) - px, axis=1)
    # OpenCV's 5 fixed-point iterations: exact in the middle, <= 0.3 px in the far corners.
    central = np.linalg.norm(px - [367.2, 248.4], axis=1) < 250
    assert err[central].max() < 0.01 and err.max() < 0.3
    xy = rng.uniform(-0.6, 0.6, size=(50, 2))
    ref, _ = cv2.projectPoints(
        np.c_[xy, np.ones(len(xy))], np.zeros(3), np.zeros(3), EUROC_CAM.K, EUROC_CAM.dist_coeffs
    )
    np.testing.assert_allclose(_to_pixels(xy), ref.reshape(-1, 2), atol=1e-9)


def test_rotation_prediction_is_the_infinite_homography() -> None:
    R = so3_exp(np.radians([1.5, -2.0, 3.0]))
    rng = np.random.default_rng(1)
    px = rng.uniform([50, 50], [700, 430], size=(100, 2))
    H = PINHOLE_CAM.K @ R @ np.linalg.inv(PINHOLE_CAM.K)
    ref = cv2.perspectiveTransform(px.reshape(-1, 1, 2), H).reshape(-1, 2)
    np.testing.assert_allclose(predict_rotation(PINHOLE_CAM, px, R), ref, atol=1e-9)


def test_gyro_prediction_on_synthetic_pure_rotation(image: np.ndarray) -> None:
    """Undistort a real image, rotate it with K R K⁻¹ (OpenCV warp) for a gyro rate of the
    IMU: the predictor's positions are within 1 px of the truth and LK confirms them."""
    undistorted = cv2.undistort(image, EUROC_CAM.K, EUROC_CAM.dist_coeffs)
    predictor = MotionPredictor(PINHOLE_CAM, EUROC_IMU)
    w_imu = np.array([0.6, -0.9, 0.4])  # rad/s, ~65 deg/s
    t0, t1 = 2_000_000_000, 2_050_000_000
    buf = constant_rate_buffer(w_imu, t0, t1)
    predictor.add_imu(buf.timestamps_ns, buf.gyro, buf.accel)
    motion = predictor.predict_motion(t0, t1)
    assert motion.source == "gyro"
    # Independent truth: camera rate = R_cam_imu w_imu, rays turn by the inverse rotation.
    w_cam = T_BODY_CAM[:3, :3].T @ w_imu
    R_true = so3_exp(-w_cam * 0.05)
    H = PINHOLE_CAM.K @ R_true @ np.linalg.inv(PINHOLE_CAM.K)
    warped = cv2.warpPerspective(undistorted, H, (752, 480), flags=cv2.INTER_LINEAR)
    p0 = cv2.goodFeaturesToTrack(undistorted, 300, 0.01, 10).reshape(-1, 2).astype(np.float64)
    truth = cv2.perspectiveTransform(p0.reshape(-1, 1, 2), H).reshape(-1, 2)
    inside = np.all((truth > 20) & (truth < [732, 460]), axis=1)
    p0, truth = p0[inside], truth[inside]
    pred, _ = predictor.predict_points(motion, p0, np.arange(len(p0)))
    assert np.median(np.linalg.norm(truth - p0, axis=1)) > 10.0  # real motion to predict
    assert np.max(np.linalg.norm(pred - truth, axis=1)) < 1.0
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        undistorted,
        warped,
        p0.astype(np.float32),
        pred.astype(np.float32),
        winSize=(9, 9),
        maxLevel=0,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    err = np.linalg.norm(p1.reshape(-1, 2) - truth, axis=1)[status.ravel() == 1]
    assert len(err) > 0.9 * len(p0)
    assert np.median(err) < 0.5


def test_prediction_on_distorted_images(image: np.ndarray) -> None:
    """Same with EuRoC's distortion: predict on distorted pixels, LK on the distorted warp."""
    R = so3_exp(np.radians([0.8, 2.5, -0.5]))
    warped = warp_by_rotation(EUROC_CAM, image, R)
    p0 = cv2.goodFeaturesToTrack(image, 300, 0.01, 10).reshape(-1, 2).astype(np.float64)
    pred = predict_rotation(EUROC_CAM, p0, R)
    inside = np.all((pred > 20) & (pred < [732, 460]), axis=1)
    p0, pred = p0[inside], pred[inside]
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        image,
        warped,
        p0.astype(np.float32),
        pred.astype(np.float32),
        winSize=(9, 9),
        maxLevel=0,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    err = np.linalg.norm(p1.reshape(-1, 2) - pred, axis=1)[status.ravel() == 1]
    assert np.median(np.linalg.norm(pred - p0, axis=1)) > 10.0
    assert np.median(err) < 0.5 and np.percentile(err, 90) < 1.0


def test_propagation_matches_gtsam_preintegration() -> None:
    rng = np.random.default_rng(2)
    ts = np.arange(0, 300_000_001, 5_000_000, dtype=np.int64)
    gyro = rng.normal(0, 0.5, (len(ts), 3))
    accel = rng.normal([0, 0, 9.81], 1.0, (len(ts), 3))
    buf = ImuBuffer(10.0)
    buf.append(ts, gyro, accel)
    bg, ba = np.array([0.01, -0.02, 0.005]), np.array([0.05, 0.02, -0.1])
    R0 = so3_exp([0.1, -0.3, 0.2])
    start = InertialState(12_000_000, R0, [1.0, 2.0, 0.5], [0.3, -0.1, 0.2], bg, ba)
    end = propagate(start, buf, 262_000_000)

    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    params.setAccelerometerCovariance(np.eye(3) * 1e-4)
    params.setGyroscopeCovariance(np.eye(3) * 1e-4)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias(ba, bg))
    for h, w, a in zip(*buf.held_segment(12_000_000, 262_000_000).midpoints(), strict=True):
        pim.integrateMeasurement(a, w, h)
    nav = pim.predict(
        gtsam.NavState(gtsam.Rot3(R0), gtsam.Point3(1.0, 2.0, 0.5), np.array([0.3, -0.1, 0.2])),
        gtsam.imuBias.ConstantBias(ba, bg),
    )
    # Same model; gtsam's tangent-space integration differs at the 1e-7 level.
    np.testing.assert_allclose(end.R_world_imu, nav.attitude().matrix(), atol=1e-6)
    np.testing.assert_allclose(end.v_world_imu, nav.velocity(), atol=1e-6)
    np.testing.assert_allclose(end.p_world_imu, nav.position(), atol=1e-6)
    assert np.linalg.norm(end.v_world_imu - start.v_world_imu) > 0.1  # it did move
    assert end.timestamp_ns == 262_000_000


def test_preintegration_prediction_and_landmark_reprojection() -> None:
    predictor = MotionPredictor(EUROC_CAM, EUROC_IMU)
    w_imu = np.array([0.0, 0.0, 0.8])
    t0, t1 = 5_000_000_000, 5_050_000_000
    ts = np.arange(t0 - 100_000_000, t1 + 20_000_000, 5_000_000, dtype=np.int64)
    # At rest in a world where the IMU z axis points up: accel reads +g along z.
    predictor.add_imu(ts, np.tile(w_imu, (len(ts), 1)), np.tile([0, 0, 9.81], (len(ts), 1)))
    state = InertialState(t0 - 50_000_000, np.eye(3), np.zeros(3), np.zeros(3))
    # Points 3 m and 5 m in front of the camera at t1 (pose known in closed form below).
    T_world_imu = make_T(so3_exp(w_imu * 0.1), np.zeros(3))
    T_cam_world = np.linalg.inv(T_world_imu @ T_BODY_CAM)
    p_cam = np.array([[0.2, -0.1, 3.0], [-0.5, 0.3, 5.0]])
    p_world = (p_cam - T_cam_world[:3, 3]) @ T_cam_world[:3, :3]
    predictor.set_inertial_state(state, np.array([7, 9]), p_world)
    motion = predictor.predict_motion(t0, t1)
    assert motion.source == "preintegration" and motion.T_cam_world is not None
    # Rotation-only part equals the gyro rotation (zero bias).
    R_gyro = gyro_rotation(predictor.buffer, t0, t1)
    R_imu_cam = T_BODY_CAM[:3, :3]
    np.testing.assert_allclose(motion.R_cur_prev, (R_imu_cam.T @ R_gyro @ R_imu_cam).T, atol=1e-9)
    # Pose: rotated by Exp(w (t1 - state.t)) about z, no translation.
    np.testing.assert_allclose(motion.T_cam_world, T_cam_world, atol=1e-9)
    expected = _to_pixels(p_cam[:, :2] / p_cam[:, 2:])
    prev_px = np.array([[100.0, 100.0], [200.0, 200.0], [300.0, 300.0]])
    pred, by_point = predictor.predict_points(motion, prev_px, np.array([9, 1, 7]))
    assert by_point.tolist() == [True, False, True]
    np.testing.assert_allclose(pred[[2, 0]], expected, atol=1e-9)
    rot_only = predict_rotation(EUROC_CAM, prev_px[1:2], motion.R_cur_prev)
    np.testing.assert_allclose(pred[1:2], rot_only, atol=1e-9)


def test_static_bias_is_time_weighted_mean() -> None:
    buf = constant_rate_buffer(np.array([0.01, 0.02, 0.08]), 0, 1_000_000_000)
    est = StaticGyroBias(min_frames=3)
    est.add_standstill(buf, 0, 50_000_000)
    est.add_standstill(buf, 50_000_000, 100_000_000)
    assert est.bias is None
    est.add_standstill(buf, 100_000_000, 150_000_000)
    np.testing.assert_allclose(est.bias, [0.01, 0.02, 0.08], atol=1e-12)


def test_bad_input_is_rejected() -> None:
    buf = ImuBuffer()
    with pytest.raises(ImuDataError, match="strictly increasing"):
        buf.append(np.array([2, 1]), np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ImuDataError, match="no IMU samples"):
        buf.held_segment(0, 10)
    with pytest.raises(ImuPredictionError, match="rotation"):
        InertialState(0, np.ones((3, 3)), np.zeros(3), np.zeros(3))
    predictor = MotionPredictor(EUROC_CAM, EUROC_IMU)
    predictor.add_imu(np.array([100, 200]), np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ImuPredictionError, match="older than the IMU buffer"):
        predictor.set_inertial_state(InertialState(50, np.eye(3), np.zeros(3), np.zeros(3)))


def test_state_newer_than_previous_frame_falls_back_to_gyro_with_its_bias() -> None:
    predictor = MotionPredictor(EUROC_CAM, EUROC_IMU)
    w_imu = np.array([0.1, 0.2, 0.3])
    t0, t1 = 1_000_000_000, 1_050_000_000
    buf = constant_rate_buffer(w_imu, t0, t1)
    predictor.add_imu(buf.timestamps_ns, buf.gyro, buf.accel)
    bias = np.array([0.1, 0.2, 0.3])  # the whole reading is bias: no rotation
    predictor.set_inertial_state(
        InertialState(t0 + 10_000_000, np.eye(3), np.zeros(3), np.zeros(3), bias_gyro=bias)
    )
    motion = predictor.predict_motion(t0, t1)
    assert motion.source == "gyro"
    np.testing.assert_allclose(motion.R_cur_prev, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("with_state", [False, True])
def test_a_time_offset_reads_frame_times_on_the_imu_clock(with_state: bool) -> None:
    """An IMU stamped 15 ms late with the edge's offset applied predicts as the synchronised
    one does (gyro before VI init, propagated states after); without it, it does not."""
    rng = np.random.default_rng(5)
    ts = np.arange(0, 2_000_000_000, 5_000_000, dtype=np.int64)
    gyro = np.cumsum(rng.normal(0, 0.3, (len(ts), 3)), axis=0) * 0.2  # a turning body
    accel = np.tile([0.0, 0.0, 9.81], (len(ts), 1)) + rng.normal(0, 0.5, (len(ts), 3))
    t0, t1 = 1_000_000_000, 1_050_000_000
    state = InertialState(t0 - 50_000_000, np.eye(3), np.zeros(3), np.zeros(3))
    predictions = []
    for late, offset in ((0, 0), (15_000_000, 15_000_000), (15_000_000, 0)):
        predictor = MotionPredictor(EUROC_CAM, EUROC_IMU)
        predictor.add_imu(ts + late, gyro, accel)
        predictor.set_time_offset(offset)
        if with_state:
            predictor.set_inertial_state(state)
        predictions.append(predictor.predict_motion(t0, t1))
    sync, told, blind = predictions
    assert sync.source == ("preintegration" if with_state else "gyro")
    np.testing.assert_allclose(told.R_cur_prev, sync.R_cur_prev, atol=1e-12)
    if with_state:
        assert sync.T_cam_world is not None and told.T_cam_world is not None
        np.testing.assert_allclose(told.T_cam_world, sync.T_cam_world, atol=1e-12)
    assert np.abs(blind.R_cur_prev - sync.R_cur_prev).max() > 1e-4
    if not with_state:
        return
    # An offset that arrives after the state moves the state's time with it.
    predictor = MotionPredictor(EUROC_CAM, EUROC_IMU)
    predictor.add_imu(ts + 15_000_000, gyro, accel)
    predictor.set_inertial_state(state)
    predictor.set_time_offset(15_000_000)
    late = predictor.predict_motion(t0, t1)
    np.testing.assert_allclose(late.R_cur_prev, predictions[0].R_cur_prev, atol=1e-12)
