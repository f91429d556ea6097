"""One robot's buffered IMU samples: the store the robot's IMU-assisted LK
(:mod:`services.robot.imu_prediction`) and the edge's VIO (:mod:`services.edge.vio`) both
slice between frame times.

Samples are in the IMU frame: ``timestamps_ns`` (K,) int64, strictly increasing; ``gyro``
(K, 3) rad/s; ``accel`` (K, 3) m/s². Between two samples the signal is linear: a slice
``[t0, t1]`` starts and ends with samples interpolated at ``t0`` and ``t1``, and its pieces
(:meth:`ImuSegment.midpoints`) carry the mean of both ends of each piece, which makes
piecewise-constant integration (gtsam's preintegration, the robot's propagation)
second-order accurate for smooth motion (ORB-SLAM3 does the same). Interpolation runs on
times relative to the oldest sample held, so nanosecond timestamps of the epoch (EuRoC's
~1.4e18) lose nothing to float64.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from common.calibration import ImuCalibration
from common.errors import RecslamError


class ImuDataError(RecslamError):
    """Malformed IMU samples, or an interval the buffer holds no samples for."""


@dataclass(frozen=True, eq=False)
class ImuSegment:
    """IMU samples covering ``[t0, t1]`` (end samples interpolated): ``timestamps_ns`` (K,)
    int64, ``gyro`` (K, 3) rad/s, ``accel`` (K, 3) m/s², IMU frame."""

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.timestamps_ns[-1] - self.timestamps_ns[0]) * 1e-9

    def midpoints(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The segment's pieces between consecutive samples: duration (M,) s and the mean of
        both ends of each piece, gyro (M, 3) rad/s and accel (M, 3) m/s² (M = K - 1)."""
        dt = np.diff(self.timestamps_ns).astype(np.float64) * 1e-9
        return dt, 0.5 * (self.gyro[1:] + self.gyro[:-1]), 0.5 * (self.accel[1:] + self.accel[:-1])


def _read_only(a: np.ndarray) -> np.ndarray:
    view = a.view()
    view.flags.writeable = False
    return view


def concat_segments(a: ImuSegment, b: ImuSegment) -> ImuSegment:
    """Join two consecutive segments (``a`` ends where ``b`` starts)."""
    return ImuSegment(
        np.concatenate([a.timestamps_ns, b.timestamps_ns[1:]]),
        np.concatenate([a.gyro, b.gyro[1:]]),
        np.concatenate([a.accel, b.accel[1:]]),
    )


class ImuBuffer:
    """Time-ordered IMU samples of one robot, sliced between frame times.

    ``horizon_s``: samples older than this before the newest are forgotten as new ones
    arrive (one is kept before the horizon for interpolation); None keeps every sample until
    :meth:`drop_before`.
    """

    def __init__(self, horizon_s: float | None = None) -> None:
        self.horizon_ns = None if horizon_s is None else int(horizon_s * 1e9)
        self._t = np.zeros(0, dtype=np.int64)
        self._gyro = np.zeros((0, 3))
        self._accel = np.zeros((0, 3))

    def __len__(self) -> int:
        return len(self._t)

    @property
    def timestamps_ns(self) -> np.ndarray:
        """(K,) int64 ns of the samples held (read-only view)."""
        return _read_only(self._t)

    @property
    def gyro(self) -> np.ndarray:
        """(K, 3) rad/s of the samples held (read-only view)."""
        return _read_only(self._gyro)

    @property
    def accel(self) -> np.ndarray:
        """(K, 3) m/s² of the samples held (read-only view)."""
        return _read_only(self._accel)

    @property
    def first_timestamp_ns(self) -> int | None:
        return int(self._t[0]) if len(self._t) else None

    @property
    def last_timestamp_ns(self) -> int | None:
        return int(self._t[-1]) if len(self._t) else None

    def append(self, timestamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Add samples (K,), (K, 3), (K, 3); ones not newer than the newest held are ignored
        (a re-sent batch). ImuDataError on mismatched lengths, non-finite values or
        timestamps that do not strictly increase within the batch."""
        t = np.asarray(timestamps_ns, dtype=np.int64).reshape(-1)
        g = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
        a = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
        if len(g) != len(t) or len(a) != len(t):
            raise ImuDataError(
                f"IMU batch has {len(t)} timestamps, {len(g)} gyro and {len(a)} accel rows"
            )
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
            raise ImuDataError("IMU batch holds a non-finite gyro or accel sample")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            raise ImuDataError("IMU batch timestamps_ns are not strictly increasing")
        if len(self._t):
            keep = t > self._t[-1]
            t, g, a = t[keep], g[keep], a[keep]
        self._t = np.concatenate([self._t, t])
        self._gyro = np.concatenate([self._gyro, g])
        self._accel = np.concatenate([self._accel, a])
        if self.horizon_ns is not None and len(self._t):
            self.drop_before(int(self._t[-1]) - self.horizon_ns)

    def drop_before(self, t_ns: int) -> None:
        """Forget samples older than the one just before ``t_ns`` (kept for interpolation)."""
        i = int(np.searchsorted(self._t, t_ns, side="right")) - 1
        if i > 0:
            self._t, self._gyro, self._accel = self._t[i:], self._gyro[i:], self._accel[i:]

    def noise_density(self, samples: int) -> tuple[float, float]:
        """:func:`measured_noise_density` of the newest ``samples`` samples held."""
        keep = slice(-samples, None)
        return measured_noise_density(self._t[keep], self._gyro[keep], self._accel[keep])

    def covers(self, t0_ns: int, t1_ns: int) -> bool:
        """The samples held span ``[t0, t1]``."""
        return bool(len(self._t) >= 2 and self._t[0] <= t0_ns and self._t[-1] >= t1_ns)

    def segment(self, t0_ns: int, t1_ns: int) -> ImuSegment | None:
        """Samples on ``[t0, t1]`` with interpolated ends; None unless ``t0 < t1`` and the
        buffer covers the interval."""
        if t1_ns <= t0_ns or not self.covers(t0_ns, t1_ns):
            return None
        return self._slice(t0_ns, t1_ns)

    def held_segment(self, t0_ns: int, t1_ns: int) -> ImuSegment:
        """Samples on ``[t0, t1]`` (``t0 <= t1``) with interpolated ends, the first / last
        sample held where the interval reaches beyond the buffer. ImuDataError when the
        buffer is empty or ``t1 < t0``."""
        if t1_ns < t0_ns:
            raise ImuDataError(f"IMU interval ends before it starts ({t0_ns} > {t1_ns})")
        if not len(self._t):
            raise ImuDataError("no IMU samples buffered")
        return self._slice(t0_ns, t1_ns)

    def _slice(self, t0_ns: int, t1_ns: int) -> ImuSegment:
        ts = self._t
        # Only the samples bracketing [t0, t1] take part (O(log K + window), so a buffer that
        # keeps a whole run, as the cloud's, slices as fast as a short one).
        lo = max(int(np.searchsorted(ts, t0_ns, side="right")) - 1, 0)
        hi = min(int(np.searchsorted(ts, t1_ns, side="left")) + 1, len(ts))
        window = ts[lo:hi]
        inner = window[(window > t0_ns) & (window < t1_ns)]
        knots = np.concatenate([[t0_ns], inner, [t1_ns]]).astype(np.int64)
        at = (knots - ts[0]).astype(np.float64)
        held = (window - ts[0]).astype(np.float64)
        gyro = np.stack([np.interp(at, held, self._gyro[lo:hi, k]) for k in range(3)], axis=1)
        accel = np.stack([np.interp(at, held, self._accel[lo:hi, k]) for k in range(3)], axis=1)
        return ImuSegment(knots, gyro, accel)


def measured_noise_density(
    timestamps_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray
) -> tuple[float, float]:
    """White-noise densities (gyro rad/s/√Hz, accel m/s²/√Hz) the samples show: per axis the
    robust standard deviation (1.4826 MAD) of second differences, over √6 (what white noise
    gives them; smooth motion adds ~a·dt², nothing at 200 Hz), times √dt; the largest axis.
    A real sensor's vibration (rotors, motors) shows here, a datasheet does not: EuRoC's
    ADIS16448 measures 20-40x its datasheet in flight. NaN for fewer than 50 samples."""
    ts = np.asarray(timestamps_ns, np.int64)
    if len(ts) < 50:
        return float("nan"), float("nan")
    dt = float(np.median(np.diff(ts))) * 1e-9
    out = []
    for x in (np.asarray(gyro, np.float64), np.asarray(accel, np.float64)):
        d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
        mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0)
        out.append(float((1.4826 * mad / np.sqrt(6.0)).max() * np.sqrt(dt)))
    return out[0], out[1]


def with_measured_noise(
    calibration: ImuCalibration, gyro_nd: float, accel_nd: float, min_ratio: float = 1.5
) -> ImuCalibration:
    """``calibration`` with each white-noise density raised to the measured one where that is
    at least ``min_ratio`` times larger (a datasheet-clean sensor keeps its calibration);
    the random walks are scaled alike (vibration rectifies into slow drift too)."""
    g = gyro_nd / calibration.gyro_noise_density if np.isfinite(gyro_nd) else 0.0
    a = accel_nd / calibration.accel_noise_density if np.isfinite(accel_nd) else 0.0
    g, a = (r if r >= min_ratio else 1.0 for r in (g, a))
    if g == 1.0 and a == 1.0:
        return calibration
    return replace(
        calibration,
        gyro_noise_density=calibration.gyro_noise_density * g,
        gyro_random_walk=calibration.gyro_random_walk * g,
        accel_noise_density=calibration.accel_noise_density * a,
        accel_random_walk=calibration.accel_random_walk * a,
    )
