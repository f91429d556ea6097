"""On-manifold IMU preintegration (paper Eq. 4, 13–14) with gtsam, over the segments that
:class:`common.imu.ImuBuffer` slices (each piece's measurement the mean of both ends, as
ORB-SLAM3 integrates). One copy for both users: the edge's VIO (``services.edge.vio``) and
the cloud's visual-inertial global BA (``services.cloud.optimization.inertial``).
"""

from __future__ import annotations

import gtsam
import numpy as np

from common.calibration import ImuCalibration
from common.geometry import so3_exp
from common.imu import ImuSegment


def make_preintegration_params(
    imu: ImuCalibration, gravity_mps2: float, integration_sigma: float
) -> gtsam.PreintegrationCombinedParams:
    """gtsam parameters (Z-up gravity) from continuous-time noise densities."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(gravity_mps2)
    p.setGyroscopeCovariance(np.eye(3) * imu.gyro_noise_density**2)
    p.setAccelerometerCovariance(np.eye(3) * imu.accel_noise_density**2)
    p.setIntegrationCovariance(np.eye(3) * integration_sigma**2)
    p.setBiasOmegaCovariance(np.eye(3) * imu.gyro_random_walk**2)
    p.setBiasAccCovariance(np.eye(3) * imu.accel_random_walk**2)
    return p


def make_bias(bias_accel: np.ndarray, bias_gyro: np.ndarray) -> gtsam.imuBias.ConstantBias:
    return gtsam.imuBias.ConstantBias(np.asarray(bias_accel, float), np.asarray(bias_gyro, float))


def preintegrate(
    params: gtsam.PreintegrationCombinedParams,
    segment: ImuSegment,
    bias_accel: np.ndarray,
    bias_gyro: np.ndarray,
) -> gtsam.PreintegratedCombinedMeasurements:
    """Preintegrate a segment around the given bias (mid-point measurements)."""
    pim = gtsam.PreintegratedCombinedMeasurements(params, make_bias(bias_accel, bias_gyro))
    dt, gyro, accel = segment.midpoints()
    for k in range(len(dt)):
        if dt[k] > 0:
            pim.integrateMeasurement(accel[k], gyro[k], dt[k])
    return pim


def predict_state(
    pim: gtsam.PreintegratedCombinedMeasurements,
    T_world_body: np.ndarray,
    v_world: np.ndarray,
    bias_accel: np.ndarray,
    bias_gyro: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """IMU prediction of the end state: ``(T_world_body (4, 4), v_world (3,))``."""
    nav = gtsam.NavState(gtsam.Pose3(T_world_body), np.asarray(v_world, float))
    out = pim.predict(nav, make_bias(bias_accel, bias_gyro))
    return out.pose().matrix(), np.asarray(out.velocity(), float)


def integrate_gyro(segment: ImuSegment, bias_gyro: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) ``R_body0_body1`` over a segment from the gyro alone."""
    R = np.eye(3)
    dt, gyro, _ = segment.midpoints()
    for h, w in zip(dt, gyro - bias_gyro, strict=True):
        R = R @ so3_exp(w * h)
    return R
