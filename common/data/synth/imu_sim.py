"""IMU measurements derived analytically from a trajectory, with EuRoC-like noise.

Specific force ``a_imu = R_world_imu^T (a_world - g_world)`` with ``g_world = (0, 0, -9.81)``
and the angular rate of the IMU frame expressed in itself. The body frame is the IMU frame
(as in EuRoC). Noise (per :class:`~common.calibration.ImuCalibration` densities): white noise
of discrete std ``density * sqrt(rate)`` and a bias random walk with steps of std
``random_walk * sqrt(dt)``; measurements are ``true + bias + white``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.calibration import ImuCalibration
from common.data.synth.trajectory import Motion

GRAVITY_WORLD = np.array([0.0, 0.0, -9.81])


@dataclass(frozen=True)
class ImuNoiseConfig:
    """``enabled``: add noise and biases at all. Initial biases are drawn with std
    ``initial_gyro_bias_std`` [rad/s] and ``initial_accel_bias_std`` [m/s²] per axis."""

    enabled: bool = True
    initial_gyro_bias_std: float = 0.005
    initial_accel_bias_std: float = 0.05


@dataclass(frozen=True, eq=False)
class ImuSamples:
    """Samples at ``timestamps_ns`` (M,) int64: measured ``gyro`` (M, 3) rad/s and ``accel``
    (M, 3) m/s², the noise-free ``gyro_true``/``accel_true``, and the biases in effect
    ``bias_gyro``/``bias_accel`` (M, 3)."""

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gyro_true: np.ndarray
    accel_true: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray


def ideal_imu(traj: Motion, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (gyro (K, 3) rad/s, accel (K, 3) m/s²) in the IMU (= body) frame."""
    st = traj.evaluate(t)
    f_world = st.a_world_body - GRAVITY_WORLD
    accel = np.einsum("kji,kj->ki", st.R_world_body, f_world)
    return st.omega_body.copy(), accel


def simulate_imu(
    traj: Motion,
    timestamps_ns: np.ndarray,
    t0_ns: int,
    calib: ImuCalibration,
    noise: ImuNoiseConfig,
    rng: np.random.Generator,
) -> ImuSamples:
    """Measurements at ``timestamps_ns`` (trajectory time ``(ts - t0_ns) * 1e-9`` s)."""
    ts = np.asarray(timestamps_ns, dtype=np.int64)
    t = (ts - t0_ns) * 1e-9
    gyro_true, accel_true = ideal_imu(traj, t)
    m = len(ts)
    if not noise.enabled:
        zeros = np.zeros((m, 3))
        return ImuSamples(ts, gyro_true, accel_true, gyro_true, accel_true, zeros, zeros.copy())
    dt = 1.0 / calib.rate_hz
    bg0 = rng.normal(0.0, noise.initial_gyro_bias_std, 3)
    ba0 = rng.normal(0.0, noise.initial_accel_bias_std, 3)
    steps_g = rng.normal(0.0, calib.gyro_random_walk * np.sqrt(dt), (m, 3))
    steps_a = rng.normal(0.0, calib.accel_random_walk * np.sqrt(dt), (m, 3))
    steps_g[0] = steps_a[0] = 0.0
    bias_g = bg0 + np.cumsum(steps_g, axis=0)
    bias_a = ba0 + np.cumsum(steps_a, axis=0)
    white_g = rng.normal(0.0, calib.gyro_noise_density * np.sqrt(calib.rate_hz), (m, 3))
    white_a = rng.normal(0.0, calib.accel_noise_density * np.sqrt(calib.rate_hz), (m, 3))
    return ImuSamples(
        ts,
        gyro_true + bias_g + white_g,
        accel_true + bias_a + white_a,
        gyro_true,
        accel_true,
        bias_g,
        bias_a,
    )
