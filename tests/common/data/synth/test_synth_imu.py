"""IMU simulation: noise-free measurements integrate back to the flight; noise statistics."""

from __future__ import annotations

import numpy as np
import pytest

from common.calibration import EUROC_IMU
from common.data.synth.imu_sim import GRAVITY_WORLD, ImuNoiseConfig, ideal_imu, simulate_imu
from common.data.synth.scene import vicon_room
from common.data.synth.trajectory import make_trajectories
from common.geometry import R_to_quat_wxyz, quat_wxyz_to_R


@pytest.fixture(scope="module")
def traj():
    # The most aggressive of three robots.
    return make_trajectories(vicon_room(), 3, 20.0, seed=3)[2]


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _deriv(traj, t: float, y: np.ndarray) -> np.ndarray:
    gyro, accel = ideal_imu(traj, np.array([t]))
    q, v = y[:4], y[4:7]
    R = quat_wxyz_to_R(q / np.linalg.norm(q))
    dq = 0.5 * _qmul(q, np.concatenate([[0.0], gyro[0]]))
    dv = R @ accel[0] + GRAVITY_WORLD
    return np.concatenate([dq, dv, v])


def test_noise_free_imu_integrates_back_to_the_trajectory(traj) -> None:
    t0, t1, h = 2.0, 7.0, 0.002
    s0 = traj.evaluate(np.array([t0]))
    y = np.concatenate([R_to_quat_wxyz(s0.R_world_body[0]), s0.v_world_body[0], s0.p_world_body[0]])
    t = t0
    for _ in range(round((t1 - t0) / h)):
        k1 = _deriv(traj, t, y)
        k2 = _deriv(traj, t + h / 2, y + h / 2 * k1)
        k3 = _deriv(traj, t + h / 2, y + h / 2 * k2)
        k4 = _deriv(traj, t + h, y + h * k3)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += h
    s1 = traj.evaluate(np.array([t1]))
    travelled = np.linalg.norm(s1.p_world_body[0] - s0.p_world_body[0])
    assert travelled > 1.0  # the test is not trivial
    assert np.linalg.norm(y[7:] - s1.p_world_body[0]) < 0.01
    assert np.linalg.norm(y[4:7] - s1.v_world_body[0]) < 0.005
    R = quat_wxyz_to_R(y[:4] / np.linalg.norm(y[:4]))
    assert np.linalg.norm(R.T @ s1.R_world_body[0] - np.eye(3)) < 1e-4


def test_hovering_accelerometer_reads_plus_g(traj) -> None:
    _, accel = ideal_imu(traj, np.array([0.0]))
    assert abs(np.linalg.norm(accel[0]) - 9.81) < 1e-9


def test_noise_and_bias_statistics(traj) -> None:
    n = 40_000
    ts = 1_000_000_000 + 5_000_000 * np.arange(n, dtype=np.int64)
    ts = ts[ts - ts[0] < 19_000_000_000]
    rng = np.random.default_rng(0)
    s = simulate_imu(traj, ts, int(ts[0]), EUROC_IMU, ImuNoiseConfig(), rng)
    white_g = s.gyro - s.gyro_true - s.bias_gyro
    white_a = s.accel - s.accel_true - s.bias_accel
    rate = EUROC_IMU.rate_hz
    np.testing.assert_allclose(
        white_g.std(axis=0), EUROC_IMU.gyro_noise_density * rate**0.5, rtol=0.05
    )
    np.testing.assert_allclose(
        white_a.std(axis=0), EUROC_IMU.accel_noise_density * rate**0.5, rtol=0.05
    )
    steps_g = np.diff(s.bias_gyro, axis=0).std()
    steps_a = np.diff(s.bias_accel, axis=0).std()
    assert steps_g == pytest.approx(EUROC_IMU.gyro_random_walk / rate**0.5, rel=0.05)
    assert steps_a == pytest.approx(EUROC_IMU.accel_random_walk / rate**0.5, rel=0.05)
    quiet = simulate_imu(traj, ts, int(ts[0]), EUROC_IMU, ImuNoiseConfig(enabled=False), rng)
    np.testing.assert_array_equal(quiet.gyro, quiet.gyro_true)
    np.testing.assert_array_equal(quiet.bias_accel, 0.0)
