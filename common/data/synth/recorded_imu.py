"""Recorded IMUs: fly a real sensor along its own flight (``recslam dataset synth --imu FILE``).

A recorded flight (:mod:`~common.data.synth.recorded`) gives the images; the IMU recorded on
the same flight replaces the simulated one, with its real biases, vibration and sample timing.
The recorded IMU and the ground truth share the recorder's clock (EuRoC's ``imu0`` and
``state_groundtruth_estimate0`` do), so alignment is a shift: a sample taken ``dt`` after the
ground truth's first pose is written ``dt`` after the robot's first timestamp (the generator's
time 0 is the recording's first pose). Samples keep their own times (no resampling, no
smoothing); those inside ``[0, seconds]`` of the flight are written.

An unsynchronised sensor (``--time-offset-ms TD``): the IMU clock runs ``TD`` ahead of the
camera's, ``t_imu = t_cam + TD`` (the convention of OpenVINS' ``calib_camimu_dt`` and
VINS-Fusion's ``td``). Images and ground truth keep the camera clock; every IMU timestamp
(simulated or recorded) is written ``TD`` later than the instant it measured.

The world frame is only shifted (never rotated) when a recorded flight is placed in a world,
so a body-frame IMU stays valid. The ground truth's biases, when its file has them (EuRoC's
17-column files do), are written to the dataset's ground truth, so estimated biases can be
scored against them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.data.euroc import read_groundtruth, read_imu_csv
from common.data.synth.trajectory import TrajectoryError
from common.errors import RecslamError


@dataclass(frozen=True, eq=False)
class RecordedImu:
    """A recorded IMU on its flight's time: ``t_s`` (M,) [s] from the ground truth's first
    pose, ``gyro`` (M, 3) rad/s, ``accel`` (M, 3) m/s² in the IMU (body) frame; the ground
    truth's biases ``bias_t_s`` (K,) [s] with ``bias_gyro`` / ``bias_accel`` (K, 3) (empty
    when the file has none)."""

    source: str
    groundtruth: str
    t_s: np.ndarray = field(repr=False)
    gyro: np.ndarray = field(repr=False)
    accel: np.ndarray = field(repr=False)
    bias_t_s: np.ndarray = field(repr=False)
    bias_gyro: np.ndarray = field(repr=False)
    bias_accel: np.ndarray = field(repr=False)

    def window(
        self, seconds: float, t0_ns: int, time_offset_ms: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(timestamps (M,) int64 [ns] on the written clock, gyro (M, 3), accel (M, 3)) of
        the samples inside ``[0, seconds]`` of the flight; the flight's time 0 is ``t0_ns``
        on the camera clock and the IMU clock is ``time_offset_ms`` ahead of it."""
        keep = (self.t_s >= -1e-9) & (self.t_s <= seconds + 1e-9)
        shift_ns = round(time_offset_ms * 1e6)
        ts = t0_ns + shift_ns + np.round(self.t_s[keep] * 1e9).astype(np.int64)
        return ts, self.gyro[keep], self.accel[keep]

    def biases_at(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The ground truth's (gyro, accel) biases (K, 3) at flight times ``t_s`` (K,) [s],
        linearly interpolated (held at the ends); NaN when the file has none."""
        t_s = np.asarray(t_s, np.float64)
        if not len(self.bias_t_s):
            nan = np.full((len(t_s), 3), np.nan)
            return nan, nan.copy()
        bg = np.stack([np.interp(t_s, self.bias_t_s, self.bias_gyro[:, k]) for k in range(3)], 1)
        ba = np.stack([np.interp(t_s, self.bias_t_s, self.bias_accel[:, k]) for k in range(3)], 1)
        return bg, ba

    def describe(self) -> dict[str, str]:
        """What ``dataset.json`` records of this IMU."""
        return {"source": self.source, "clock": f"aligned to the ground truth {self.groundtruth}"}


def read_recorded_imu(imu_path: Path | str, groundtruth_path: Path | str) -> RecordedImu:
    """The IMU in ``imu_path`` (EuRoC ``imu0/data.csv``) on the time of the ground truth in
    ``groundtruth_path`` (EuRoC ``data.csv``, or TUM: seconds in the first column), which must
    share its clock; TrajectoryError names the file and what is wrong with it."""
    from common.data.synth.recorded import detect_format

    try:
        imu = read_imu_csv(imu_path)
    except (RecslamError, ValueError) as exc:
        raise TrajectoryError(f"--imu {imu_path}: {exc}") from None
    except OSError as exc:
        raise TrajectoryError(f"--imu {imu_path}: cannot read it ({exc})") from None
    gt_path = Path(groundtruth_path)
    empty = np.zeros((0, 3))
    if detect_format(gt_path) == "euroc":
        try:
            gt = read_groundtruth(gt_path)
        except RecslamError as exc:
            raise TrajectoryError(f"--trajectory {gt_path}: {exc}") from None
        gt_ts = gt.timestamps_ns
        has_bias = bool(np.all(np.isfinite(gt.bias_gyro)) and np.all(np.isfinite(gt.bias_accel)))
        bias_t = (gt_ts - gt_ts[0]) * 1e-9 if has_bias else np.zeros(0)
        bg = np.asarray(gt.bias_gyro) if has_bias else empty
        ba = np.asarray(gt.bias_accel) if has_bias else empty
    else:
        from common.evaluation.tum import read_tum

        try:
            gt_ts = read_tum(gt_path).timestamps_ns
        except RecslamError as exc:
            raise TrajectoryError(f"--trajectory {gt_path}: {exc}") from None
        bias_t, bg, ba = np.zeros(0), empty, empty
    t_imu = (imu.timestamps_ns - int(gt_ts[0])) * 1e-9
    flight_s = (int(gt_ts[-1]) - int(gt_ts[0])) * 1e-9
    inside = (t_imu >= 0.0) & (t_imu <= flight_s)
    if inside.sum() < 2:
        raise TrajectoryError(
            f"--imu {imu_path}: its {len(t_imu)} samples ({imu.timestamps_ns[0]} to "
            f"{imu.timestamps_ns[-1]} ns) do not overlap the ground truth {gt_path} "
            f"({gt_ts[0]} to {gt_ts[-1]} ns): not recorded on that flight, or another clock"
        )
    gaps = np.diff(imu.timestamps_ns[inside]) * 1e-9
    if gaps.max() > 0.05:
        k = int(np.argmax(gaps))
        raise TrajectoryError(
            f"--imu {imu_path}: a gap of {gaps[k] * 1e3:.0f} ms at {t_imu[inside][k]:.2f} s "
            "into the flight (more than 50 ms)"
        )
    return RecordedImu(
        str(imu_path),
        str(gt_path),
        t_imu,
        np.asarray(imu.gyro),
        np.asarray(imu.accel),
        bias_t,
        bg,
        ba,
    )


def check_covers(imu: RecordedImu, seconds: float) -> None:
    """TrajectoryError unless ``imu`` has samples over the whole ``[0, seconds]``."""
    inside = imu.t_s[(imu.t_s >= 0.0) & (imu.t_s <= seconds + 1e-9)]
    if not len(inside) or inside[0] > 0.02 or inside[-1] < seconds - 0.02:
        span = f"{inside[0]:.2f} to {inside[-1]:.2f} s" if len(inside) else "nothing"
        raise TrajectoryError(
            f"--imu {imu.source}: covers {span} of the flight, not [0, {seconds:g}] s: "
            "fly it shorter"
        )
