"""Recorded IMUs (``--imu FILE``): the real V2 flights' IMU, aligned to their ground truth,
integrates along it within what the sensor's noise allows, and a misaligned clock would not;
bad files are refused with the file named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.data.synth.recorded import (
    SIGMA_P_RECORDED_IMU_M,
    SIGMA_Q_RECORDED_IMU,
    RecordedFlight,
    read_recording,
)
from common.data.synth.recorded_imu import check_covers, read_recorded_imu
from common.data.synth.trajectory import TrajectoryError
from common.geometry import so3_exp, so3_log


def _rotation_errors(flight: RecordedFlight, t_s, gyro, bias, window_s: float) -> np.ndarray:
    """|log(R_gt(a)^T R_gt(b)) - gyro integrated over [a, b]| [rad] over consecutive windows."""
    errs = []
    for a in np.arange(5.0, 35.0, window_s):
        m = (t_s >= a) & (t_s <= a + window_s)
        R = np.eye(3)
        ts, w = t_s[m], gyro[m] - bias
        for k in range(len(ts) - 1):
            R = R @ so3_exp(0.5 * (w[k] + w[k + 1]) * (ts[k + 1] - ts[k]))
        st = flight.evaluate(np.array([ts[0], ts[-1]]))
        R_gt = st.R_world_body[0].T @ st.R_world_body[1]
        errs.append(np.linalg.norm(so3_log(R_gt.T @ R)))
    return np.array(errs)


def test_aligned_real_imu_integrates_along_its_ground_truth(euroc_v2: Path) -> None:
    gt = euroc_v2 / "V2_01" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    imu = read_recorded_imu(euroc_v2 / "V2_01" / "mav0" / "imu0" / "data.csv", gt)
    flight = RecordedFlight.fit(read_recording(gt), np.zeros(3))
    check_covers(imu, 60.0)
    # The ground truth's biases came along: V2_01's gyro z bias is ~0.08 rad/s.
    bg, _ = imu.biases_at(np.array([10.0]))
    assert 0.06 < bg[0, 2] < 0.1
    # Over 0.5 s windows the gyro (minus the ground truth's bias) gives the ground truth's
    # rotation to about 10 mrad: the Vicon attitude's noise through its smoothing (as much at
    # 0.25 s) and the sensor's noise and few-percent scale factors. Shifting the clock makes
    # it worse at once: +10 ms already, 2x at +50 ms (an unsynchronised camera's offset).
    aligned = np.median(_rotation_errors(flight, imu.t_s, imu.gyro, bg[0], 0.5))
    late10 = np.median(_rotation_errors(flight, imu.t_s + 0.01, imu.gyro, bg[0], 0.5))
    late50 = np.median(_rotation_errors(flight, imu.t_s + 0.05, imu.gyro, bg[0], 0.5))
    assert aligned < 0.012
    assert aligned < late10 < late50 and late50 > 1.6 * aligned
    # Without the bias the error grows by ~0.08 rad per second: the bias is real.
    raw = _rotation_errors(flight, imu.t_s, imu.gyro, np.zeros(3), 1.0)
    assert np.median(raw) > 0.06


def _velocity_change_ratio(flight: RecordedFlight, t_s, accel, bias) -> float:
    """Sum over 0.5 s windows of |accelerometer integrated in the flight's attitude| over
    |the flight's velocity change|: 1 when the images' motion is the one the IMU measured."""
    num = den = 0.0
    for a in np.arange(5.0, 55.0, 0.5):
        m = (t_s >= a) & (t_s <= a + 0.5)
        st = flight.evaluate(t_s[m])
        f = np.einsum("kij,kj->ki", st.R_world_body, accel[m] - bias) + np.array([0, 0, -9.81])
        num += np.linalg.norm((0.5 * (f[1:] + f[:-1]) * np.diff(t_s[m])[:, None]).sum(0))
        den += np.linalg.norm(st.v_world_body[-1] - st.v_world_body[0])
    return num / den


@pytest.mark.slow
def test_flown_with_its_imu_a_recording_keeps_the_motion_the_imu_measured(euroc_v2: Path) -> None:
    """The smoothing that keeps a simulated IMU from differentiating Vicon noise takes real
    motion out of the images; with the recorded IMU the flight is smoothed at the recorder's
    noise and the gyro and accelerometer agree with it (V2_01, measured when written: 8.7 ->
    1.6 mrad per 0.5 s, velocity changes 1.19 -> 1.04 of the flight's)."""
    gt = euroc_v2 / "V2_01" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    imu = read_recorded_imu(euroc_v2 / "V2_01" / "mav0" / "imu0" / "data.csv", gt)
    bg, ba = imu.biases_at(np.array([10.0]))
    rec = read_recording(gt)
    smooth = RecordedFlight.fit(rec, np.zeros(3))
    faithful = RecordedFlight.fit(rec, np.zeros(3), SIGMA_P_RECORDED_IMU_M, SIGMA_Q_RECORDED_IMU)
    rot_smooth = np.median(_rotation_errors(smooth, imu.t_s, imu.gyro, bg[0], 0.5))
    rot_faithful = np.median(_rotation_errors(faithful, imu.t_s, imu.gyro, bg[0], 0.5))
    assert rot_smooth > 0.006 and rot_faithful < 0.003
    assert _velocity_change_ratio(smooth, imu.t_s, imu.accel, ba[0]) > 1.1
    assert 0.95 < _velocity_change_ratio(faithful, imu.t_s, imu.accel, ba[0]) < 1.06
    assert "sigma_p=0.0005" in faithful.describe()["smoothing"]


def test_window_and_time_offset(euroc_v2: Path) -> None:
    gt = euroc_v2 / "V2_02" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    imu = read_recorded_imu(euroc_v2 / "V2_02" / "mav0" / "imu0" / "data.csv", gt)
    t0 = 1_600_000_000_000_000_000
    ts, gyro, accel = imu.window(10.0, t0)
    assert ts[0] >= t0 and ts[-1] <= t0 + 10_000_000_000 and len(ts) > 1990
    assert gyro.shape == accel.shape == (len(ts), 3)
    # The recorder's own sample times, not a grid: EuRoC's are ~5 ms with jitter.
    assert 4.9e6 < np.median(np.diff(ts)) < 5.1e6
    ts15, gyro15, _ = imu.window(10.0, t0, time_offset_ms=15.0)
    np.testing.assert_array_equal(ts15, ts + 15_000_000)
    np.testing.assert_array_equal(gyro15, gyro)


def test_bad_files_are_refused_with_the_file_named(euroc_v2: Path, tmp_path: Path) -> None:
    gt1 = euroc_v2 / "V2_01" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    with pytest.raises(TrajectoryError, match=r"--imu .*nope.csv"):
        read_recorded_imu(tmp_path / "nope.csv", gt1)
    # Another flight's IMU: a different clock, no overlap.
    other = tmp_path / "other.csv"
    lines = (euroc_v2 / "V2_01" / "mav0" / "imu0" / "data.csv").read_text().splitlines()
    shifted = [lines[0]] + [
        ",".join([str(int(r.split(",")[0]) + 10**12), *r.split(",")[1:]]) for r in lines[1:]
    ]
    other.write_text("\n".join(shifted) + "\n")
    with pytest.raises(TrajectoryError, match=r"do not overlap the ground truth"):
        read_recorded_imu(other, gt1)
    # A gap of a second inside the flight.
    gap = tmp_path / "gap.csv"
    gap.write_text("\n".join([lines[0], *lines[1:1000], *lines[1200:]]) + "\n")
    with pytest.raises(TrajectoryError, match=r"a gap of \d+ ms"):
        read_recorded_imu(gap, gt1)
    imu = read_recorded_imu(euroc_v2 / "V2_01" / "mav0" / "imu0" / "data.csv", gt1)
    with pytest.raises(TrajectoryError, match=r"fly it shorter"):
        check_covers(imu, 500.0)
