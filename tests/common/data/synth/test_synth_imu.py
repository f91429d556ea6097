"""IMU simulation: noise-free measurements integrate back to every kind of flight (ring,
families with modifiers, a recorded flight); noise statistics."""

from __future__ import annotations

import numpy as np
import pytest

from common.calibration import EUROC_IMU
from common.data.synth.flights import make_flights, parse_flight
from common.data.synth.imu_sim import ImuNoiseConfig, ideal_imu, simulate_imu
from common.data.synth.recorded import recorded_flights
from common.data.synth.scene import vicon_room
from common.data.synth.trajectory import make_trajectories

SCENE = vicon_room()
REGION = (SCENE.room_lo, SCENE.room_hi)


@pytest.fixture(scope="module")
def traj():
    # The most aggressive of three robots.
    return make_trajectories(SCENE, 3, 20.0, seed=3)[2]


def _family(name: str, robot: int):
    return make_flights(SCENE, REGION, parse_flight(name), 3, 20.0, seed=3)[robot]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "robot", "t0"),
    [
        ("ring", 2, 2.0),
        ("figure8+aggressive", 1, 4.0),
        ("lawnmower+hover", 2, 5.0),
        ("vertical", 0, 2.0),
        ("inward+aggressive", 2, 6.0),
    ],
)
def test_noise_free_imu_integrates_back_to_the_trajectory(
    name: str, robot: int, t0: float, traj, integrate_imu
) -> None:
    flight = traj if name == "ring" else _family(name, robot)
    t1 = t0 + 5.0
    p, v, R = integrate_imu(flight, t0, t1, 0.002 if name == "ring" else 0.005)
    s0, s1 = flight.evaluate(np.array([t0])), flight.evaluate(np.array([t1]))
    travelled = np.linalg.norm(s1.p_world_body[0] - s0.p_world_body[0])
    assert travelled > 1.0  # the test is not trivial
    assert np.linalg.norm(p - s1.p_world_body[0]) < 0.01
    assert np.linalg.norm(v - s1.v_world_body[0]) < 0.005
    assert np.linalg.norm(R.T @ s1.R_world_body[0] - np.eye(3)) < 1e-4


def test_imu_of_a_recorded_flight_integrates_back(hand_made_tum, integrate_imu) -> None:
    (flight,) = recorded_flights(SCENE, REGION, (str(hand_made_tum),), 8.0, "vicon")
    p, v, R = integrate_imu(flight, 1.0, 6.0, 0.005)
    s0, s1 = flight.evaluate(np.array([1.0])), flight.evaluate(np.array([6.0]))
    assert np.linalg.norm(s1.p_world_body[0] - s0.p_world_body[0]) > 1.0
    assert np.linalg.norm(p - s1.p_world_body[0]) < 0.01
    assert np.linalg.norm(v - s1.v_world_body[0]) < 0.005
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
