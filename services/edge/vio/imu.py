"""IMU buffering and on-manifold preintegration (paper Eq. 4, 13–14) with gtsam.

Between two samples the measurement is the mean of both ends (ORB-SLAM3), which makes the
piecewise-constant integration of gtsam second-order accurate for smooth motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from common.calibration import ImuCalibration
from services.edge.vio.types import VioError


@dataclass(frozen=True, eq=False)
class ImuSegment:
    """IMU samples covering ``[t0, t1]`` exactly (end samples interpolated):
    ``timestamps_ns`` (K,) int64, ``gyro`` (K, 3) rad/s, ``accel`` (K, 3) m/s², IMU frame."""

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.timestamps_ns[-1] - self.timestamps_ns[0]) * 1e-9


class ImuBuffer:
    """Growing store of IMU samples of one robot, sliced between frame times."""

    def __init__(self) -> None:
        self._t = np.zeros(0, dtype=np.int64)
        self._gyro = np.zeros((0, 3))
        self._accel = np.zeros((0, 3))

    def __len__(self) -> int:
        return len(self._t)

    @property
    def last_timestamp_ns(self) -> int | None:
        return int(self._t[-1]) if len(self._t) else None

    def append(self, timestamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Add samples (K,), (K, 3), (K, 3); samples not newer than the last one are dropped."""
        t = np.asarray(timestamps_ns, dtype=np.int64).reshape(-1)
        g = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
        a = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
        if len(g) != len(t) or len(a) != len(t):
            raise VioError(f"feed_imu: {len(t)} timestamps, {len(g)} gyro, {len(a)} accel rows")
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
            raise VioError("feed_imu: non-finite gyro or accel sample")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            raise VioError("feed_imu: timestamps_ns must be strictly increasing")
        if len(self._t):
            keep = t > self._t[-1]
            t, g, a = t[keep], g[keep], a[keep]
        self._t = np.concatenate([self._t, t])
        self._gyro = np.concatenate([self._gyro, g])
        self._accel = np.concatenate([self._accel, a])

    def drop_before(self, t_ns: int) -> None:
        """Forget samples older than the one just before ``t_ns`` (keep one for interpolation)."""
        i = int(np.searchsorted(self._t, t_ns, side="right")) - 1
        if i > 0:
            self._t, self._gyro, self._accel = self._t[i:], self._gyro[i:], self._accel[i:]

    def covers(self, t0_ns: int, t1_ns: int) -> bool:
        return bool(len(self._t) >= 2 and self._t[0] <= t0_ns and self._t[-1] >= t1_ns)

    def segment(self, t0_ns: int, t1_ns: int) -> ImuSegment | None:
        """Samples on ``[t0, t1]`` with linearly interpolated ends, or None if not covered."""
        if t1_ns <= t0_ns or not self.covers(t0_ns, t1_ns):
            return None
        inner = (self._t > t0_ns) & (self._t < t1_ns)
        ts = np.concatenate([[t0_ns], self._t[inner], [t1_ns]]).astype(np.int64)
        tf = self._t.astype(np.float64)
        gyro = np.stack(
            [np.interp(ts.astype(np.float64), tf, self._gyro[:, k]) for k in range(3)], 1
        )
        accel = np.stack(
            [np.interp(ts.astype(np.float64), tf, self._accel[:, k]) for k in range(3)], 1
        )
        return ImuSegment(ts, gyro, accel)


def concat_segments(a: ImuSegment, b: ImuSegment) -> ImuSegment:
    """Join two consecutive segments (``a`` ends where ``b`` starts)."""
    return ImuSegment(
        np.concatenate([a.timestamps_ns, b.timestamps_ns[1:]]),
        np.concatenate([a.gyro, b.gyro[1:]]),
        np.concatenate([a.accel, b.accel[1:]]),
    )


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
    dt = np.diff(segment.timestamps_ns).astype(np.float64) * 1e-9
    gyro = 0.5 * (segment.gyro[1:] + segment.gyro[:-1])
    accel = 0.5 * (segment.accel[1:] + segment.accel[:-1])
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
    from common.geometry import so3_exp

    R = np.eye(3)
    dt = np.diff(segment.timestamps_ns).astype(np.float64) * 1e-9
    w = 0.5 * (segment.gyro[1:] + segment.gyro[:-1]) - bias_gyro
    for k in range(len(dt)):
        R = R @ so3_exp(w[k] * dt[k])
    return R
