"""The one IMU buffer the robot's LK prediction and the edge's VIO slice from."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.imu import ImuBuffer, ImuDataError, concat_segments

EPOCH_NS = 1_403_636_579_758_555_392  # a EuRoC V1_01 timestamp: float64 steps are 256 ns here


def linear_samples(t0_ns: int, n: int, step_ns: int = 5_000_000):
    """Samples of a signal linear in time (gyro = 1e-9 * [1, 2, 3] * (t - t0)), so that any
    interpolation between samples is exact."""
    ts = t0_ns + step_ns * np.arange(n, dtype=np.int64)
    rel = (ts - t0_ns).astype(np.float64)[:, None]
    return ts, rel * 1e-9 * np.array([1.0, 2.0, 3.0]), rel * 1e-9 * np.array([-1.0, 0.5, 9.0])


def test_segment_interpolates_its_ends_exactly_at_epoch_timestamps() -> None:
    ts, gyro, accel = linear_samples(EPOCH_NS, 100)
    buf = ImuBuffer()
    buf.append(ts, gyro, accel)
    t0, t1 = EPOCH_NS + 12_345_671, EPOCH_NS + 250_000_003  # between samples, odd ns
    seg = buf.segment(t0, t1)
    assert seg is not None
    assert seg.timestamps_ns[0] == t0 and seg.timestamps_ns[-1] == t1
    inner = ts[(ts > t0) & (ts < t1)]
    np.testing.assert_array_equal(seg.timestamps_ns[1:-1], inner)
    expect = (seg.timestamps_ns - EPOCH_NS).astype(np.float64)[:, None] * 1e-9 * [1.0, 2.0, 3.0]
    # Interpolating on absolute float64 times would be off by up to 256 ns * slope here.
    np.testing.assert_allclose(seg.gyro, expect, rtol=0, atol=1e-15)
    dt, g_mid, _ = seg.midpoints()
    assert dt.sum() == pytest.approx((t1 - t0) * 1e-9, abs=1e-15)
    np.testing.assert_allclose(g_mid, 0.5 * (expect[1:] + expect[:-1]), rtol=0, atol=1e-15)


def test_segment_needs_coverage_held_segment_holds_the_ends() -> None:
    ts, gyro, accel = linear_samples(0, 11)  # 0 .. 50 ms
    buf = ImuBuffer()
    buf.append(ts, gyro, accel)
    assert buf.segment(-1, 10_000_000) is None
    assert buf.segment(0, 50_000_001) is None
    assert buf.segment(20_000_000, 20_000_000) is None
    held = buf.held_segment(40_000_000, 70_000_000)
    np.testing.assert_array_equal(held.gyro[-1], gyro[-1])  # held beyond the newest sample
    assert held.timestamps_ns[-1] == 70_000_000
    same = buf.held_segment(30_000_000, 30_000_000)
    assert same.duration_s == 0.0 and len(same.midpoints()[0]) == 1
    with pytest.raises(ImuDataError, match="ends before it starts"):
        buf.held_segment(2, 1)


def test_horizon_keeps_one_sample_before_it_and_drop_before_too() -> None:
    ts, gyro, accel = linear_samples(0, 1001)  # 0 .. 5 s at 200 Hz
    buf = ImuBuffer(horizon_s=2.0)
    for k in range(0, 1001, 7):
        buf.append(ts[k : k + 7], gyro[k : k + 7], accel[k : k + 7])
    assert buf.last_timestamp_ns == 5_000_000_000
    assert buf.first_timestamp_ns == 3_000_000_000
    assert buf.covers(3_000_000_000, 5_000_000_000)
    buf.drop_before(4_002_000_000)
    assert buf.first_timestamp_ns == 4_000_000_000  # the one just before, for interpolation
    assert len(buf) == 201
    with pytest.raises(ValueError):
        buf.timestamps_ns[0] = 1  # a read-only view


def test_repeated_and_older_samples_are_ignored_bad_ones_refused() -> None:
    ts, gyro, accel = linear_samples(0, 10)
    buf = ImuBuffer()
    buf.append(ts[:6], gyro[:6], accel[:6])
    buf.append(ts[3:], gyro[3:], accel[3:])  # a re-sent overlap
    np.testing.assert_array_equal(buf.timestamps_ns, ts)
    with pytest.raises(ImuDataError, match="strictly increasing"):
        buf.append(np.array([100, 100]) + ts[-1], gyro[:2], accel[:2])
    with pytest.raises(ImuDataError, match="non-finite"):
        buf.append(ts[-1:] + 1, np.full((1, 3), np.nan), accel[:1])
    with pytest.raises(ImuDataError, match="2 timestamps, 1 gyro"):
        buf.append(ts[:2] + 10**9, gyro[:1], accel[:2])
    assert len(buf) == 10
    with pytest.raises(ImuDataError, match="no IMU samples"):
        ImuBuffer().held_segment(0, 1)


@settings(max_examples=50, deadline=None)
@given(a=st.integers(0, 39_999_998), b=st.integers(0, 39_999_998), c=st.integers(0, 39_999_998))
def test_consecutive_segments_concatenate_to_the_whole(a: int, b: int, c: int) -> None:
    t0, t1, t2 = sorted((a, b + 1, c + 2))
    if not t0 < t1 < t2:
        return
    ts, gyro, accel = linear_samples(0, 11, 4_000_000)  # 0 .. 40 ms
    buf = ImuBuffer()
    buf.append(ts, gyro, accel)
    s01, s12, s02 = buf.segment(t0, t1), buf.segment(t1, t2), buf.segment(t0, t2)
    assert s01 is not None and s12 is not None and s02 is not None
    joined = concat_segments(s01, s12)
    inner = set(joined.timestamps_ns.tolist()) - {t1}
    assert inner <= set(s02.timestamps_ns.tolist())
    dt, g, a_ = joined.midpoints()
    dt2, g2, a2 = s02.midpoints()
    # The signal is linear: both integrate to the same total.
    np.testing.assert_allclose((dt[:, None] * g).sum(0), (dt2[:, None] * g2).sum(0), atol=1e-15)
    np.testing.assert_allclose((dt[:, None] * a_).sum(0), (dt2[:, None] * a2).sum(0), atol=1e-15)


def test_batches_of_an_unsynchronised_imu_reach_past_each_frame() -> None:
    """A camera not triggered by the IMU: every frame's batch ends at the first sample at or
    after the frame (so the buffer covers the frame and keyframe intervals get their IMU);
    the batches still tile the timeline, and a lead reaches that much further."""
    from common.data.euroc import ImuBatch, frames_with_imu

    rng = np.random.default_rng(3)
    imu_t = np.cumsum(rng.integers(4_900_000, 5_100_000, 2000)).astype(np.int64)
    frames = imu_t[5] + 3_333_333 + 50_000_000 * np.arange(30, dtype=np.int64)
    imu = ImuBatch(imu_t, rng.normal(size=(2000, 3)), rng.normal(size=(2000, 3)))
    for lead in (0, 15_000_000):
        batches = list(frames_with_imu(frames, imu, 0, len(frames), [None] * 30, lead))
        joined = np.concatenate([b.imu.timestamps_ns for b in batches])
        np.testing.assert_array_equal(joined, imu_t[: len(joined)])
        buf = ImuBuffer()
        for f, b in zip(frames, batches, strict=True):
            buf.append(b.imu.timestamps_ns, b.imu.gyro, b.imu.accel)
            assert b.imu.timestamps_ns[-1] >= f + lead
            assert b.imu.timestamps_ns[-2] < f + lead  # one sample past it, not more
            assert buf.segment(int(frames[0]) + lead, int(f) + lead) is not None or f == frames[0]
    # On synchronised stamps (EuRoC's) the batches are as before: (t[i-1], t[i]].
    sync = imu_t[10 + 10 * np.arange(30)]
    batches = list(frames_with_imu(sync, imu, 0, 30, [None] * 30))
    for i, b in enumerate(batches[1:], start=1):
        assert b.imu.timestamps_ns[0] > sync[i - 1] and b.imu.timestamps_ns[-1] == sync[i]


def test_measured_noise_finds_white_noise_under_motion_and_keeps_clean_calibrations() -> None:
    from common.calibration import EUROC_IMU
    from common.imu import measured_noise_density, with_measured_noise

    rng = np.random.default_rng(7)
    t = np.arange(4000) * 5_000_000
    s = t * 1e-9
    motion = np.stack([np.sin(2 * s), np.cos(3 * s), 0.5 * np.sin(s)], axis=1)  # smooth motion
    for gyro_nd, accel_nd in ((1.7e-4, 2e-3), (5e-3, 0.1)):
        gyro = motion + rng.normal(0, gyro_nd / np.sqrt(0.005), (4000, 3))
        accel = 9.81 + 2 * motion + rng.normal(0, accel_nd / np.sqrt(0.005), (4000, 3))
        g, a = measured_noise_density(t, gyro, accel)
        assert g == pytest.approx(gyro_nd, rel=0.1) and a == pytest.approx(accel_nd, rel=0.1)
    # Datasheet-clean: the calibration stays; 30x / 50x: raised, random walks alike.
    assert with_measured_noise(EUROC_IMU, 1.1 * 1.6968e-4, 2.1e-3) is EUROC_IMU
    raised = with_measured_noise(EUROC_IMU, 30 * 1.6968e-4, 50 * 2e-3)
    assert raised.gyro_noise_density == pytest.approx(30 * 1.6968e-4)
    assert raised.accel_random_walk == pytest.approx(50 * EUROC_IMU.accel_random_walk)
    assert np.isnan(measured_noise_density(t[:10], gyro[:10], accel[:10])[0])
