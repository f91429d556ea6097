"""Shared helpers of the generator's tests: integrating the ideal IMU back along a flight, and a
small hand-made TUM ground truth."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from common.data.synth.imu_sim import GRAVITY_WORLD, ideal_imu
from common.geometry import R_to_quat_wxyz, quat_wxyz_to_R, so3_log

# A 8 s arc of about 0.55 m/s with a slow yaw turn (t x y z qx qy qz qw), typed by hand.
HAND_MADE_TUM = """\
# timestamp tx ty tz qx qy qz qw
1403715273.000 1.500 -0.200 1.100 0.0139 -0.0143 0.7172 0.6966
1403715273.500 1.463 0.023 1.197 0.0209 -0.0078 0.7986 0.6015
1403715274.000 1.353 0.231 1.279 0.0259 -0.0028 0.8673 0.4971
1403715274.500 1.178 0.413 1.333 0.0268 0.0004 0.9225 0.3852
1403715275.000 0.948 0.557 1.350 0.0228 0.0028 0.9633 0.2674
1403715275.500 0.678 0.654 1.327 0.0143 0.0057 0.9893 0.1453
1403715276.000 0.385 0.698 1.269 0.0033 0.0102 0.9997 0.0208
1403715276.500 0.086 0.686 1.184 -0.0071 0.0162 0.9944 -0.1041
1403715277.000 -0.199 0.618 1.085 -0.0141 0.0226 0.9734 -0.2275
1403715277.500 -0.454 0.500 0.989 -0.0160 0.0272 0.9373 -0.3471
1403715278.000 -0.661 0.339 0.911 -0.0126 0.0277 0.8867 -0.4613
1403715278.500 -0.809 0.143 0.862 -0.0059 0.0225 0.8226 -0.5682
1403715279.000 -0.888 -0.073 0.851 0.0013 0.0120 0.7456 -0.6663
1403715279.500 -0.893 -0.297 0.879 0.0060 -0.0019 0.6568 -0.7540
1403715280.000 -0.824 -0.516 0.942 0.0061 -0.0157 0.5576 -0.8300
1403715280.500 -0.685 -0.714 1.030 0.0014 -0.0255 0.4495 -0.8929
1403715281.000 -0.484 -0.881 1.129 -0.0063 -0.0285 0.3345 -0.9419
"""


@pytest.fixture
def hand_made_tum(tmp_path: Path) -> Path:
    path = tmp_path / "hand_made.tum"
    path.write_text(HAND_MADE_TUM)
    return path


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


def _integrate(traj, t0: float, t1: float, h: float = 0.002) -> tuple[np.ndarray, ...]:
    """RK4 of the noise-free IMU of ``traj`` from its true state at ``t0`` to ``t1``:
    (position, velocity, rotation) reached, to compare with the flight's state at ``t1``."""
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
    return y[7:], y[4:7], quat_wxyz_to_R(y[:4] / np.linalg.norm(y[:4]))


@pytest.fixture
def integrate_imu() -> Callable[..., tuple[np.ndarray, ...]]:
    return _integrate


def check_derivatives(traj, t: np.ndarray, h: float = 1e-4) -> None:
    """A flight's velocity, acceleration and body rate at ``t`` (N,) agree with central
    finite differences of its position, velocity and attitude."""
    st, sp, sm = traj.evaluate(t), traj.evaluate(t + h), traj.evaluate(t - h)
    v_num = (sp.p_world_body - sm.p_world_body) / (2 * h)
    a_num = (sp.v_world_body - sm.v_world_body) / (2 * h)
    np.testing.assert_allclose(st.v_world_body, v_num, atol=1e-6)
    np.testing.assert_allclose(st.a_world_body, a_num, atol=1e-5)
    w_num = np.array(
        [so3_log(a.T @ b) / (2 * h) for a, b in zip(sm.R_world_body, sp.R_world_body, strict=True)]
    )
    np.testing.assert_allclose(st.omega_body, w_num, atol=1e-6)


@pytest.fixture
def derivatives_agree() -> Callable[..., None]:
    """:func:`check_derivatives`, for the tests of this folder."""
    return check_derivatives
