"""Camera-IMU time offset: the estimator on known motion, its online tracker, and the VIO
reading its IMU at ``t + offset``."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.edge.vio.manager import VioManager
from services.edge.vio.time_offset import (
    TimeOffsetConfig,
    TimeOffsetTracker,
    estimate_time_offset,
)
from services.edge.vio.types import TrackingStatus, ViInitConfig, VioConfig
from sim.vio import SimConfig, evaluate_run, simulate

BIAS = np.array([0.02, -0.01, 0.08])  # rad/s, like the real V2 flights' ADIS16448


def _mav(offset_ms: float, seconds: float = 20.0, rate_scale: float = 1.0, seed: int = 0):
    """A MAV-like angular velocity (sums of sines, up to ~1.5 rad/s, periods 1-4 s): frames at
    20 Hz with 1 mrad of rotation noise (camera clock), gyro at 200 Hz on an IMU clock
    ``offset_ms`` ahead, with a bias and white noise."""
    rng = np.random.default_rng(seed)
    amp = rate_scale * np.array([[0.8, 0.5], [0.6, 0.9], [1.0, 0.4]])
    freq = np.array([[1.6, 4.1], [2.3, 5.3], [1.1, 3.7]])

    def omega(t: np.ndarray) -> np.ndarray:
        return np.stack([(amp[k] * np.sin(np.outer(t, freq[k]) + k)).sum(1) for k in range(3)], 1)

    t_fine = np.arange(0.0, seconds, 1e-4)
    steps = Rotation.from_rotvec(omega(t_fine[:-1] + 5e-5) * 1e-4)
    R = [Rotation.identity()]
    for s in steps:  # fine Euler integration: the true orientation
        R.append(R[-1] * s)
    t_cam = np.arange(0.5, seconds - 0.5, 0.05)
    idx = np.round(t_cam / 1e-4).astype(int)
    noise = Rotation.from_rotvec(rng.normal(0, 1e-3, (len(t_cam), 3)))
    R_cam = np.stack([(R[i] * n).as_matrix() for i, n in zip(idx, noise, strict=True)])
    t_imu_true = np.arange(0.0, seconds, 0.005)
    gyro = omega(t_imu_true) + BIAS + rng.normal(0, 2e-3, (len(t_imu_true), 3))
    ns = 1_000_000_000
    return (
        (t_cam * ns).astype(np.int64),
        R_cam,
        ((t_imu_true + offset_ms * 1e-3) * ns).astype(np.int64),
        gyro,
    )


@pytest.mark.slow
@pytest.mark.parametrize("offset_ms", [-20.0, 0.0, 15.0])
def test_the_offset_and_the_gyro_bias_are_found_on_mav_motion(offset_ms: float) -> None:
    t_cam, R, t_imu, gyro = _mav(offset_ms)
    est = estimate_time_offset(t_cam, R, t_imu, gyro, np.zeros(3))
    assert not isinstance(est, str), est
    err_ms = est.offset_ns * 1e-6 - offset_ms
    assert abs(err_ms) < 0.3, est
    assert est.confident and est.sigma_ms < 0.3
    assert abs(err_ms) < 4 * est.sigma_ms + 0.05  # the sigma means something
    assert np.abs(est.bias_gyro - BIAS).max() < 2e-3  # solved with the offset


@pytest.mark.slow
def test_a_flight_that_hardly_turns_gives_no_confident_offset() -> None:
    t_cam, R, t_imu, gyro = _mav(15.0, rate_scale=0.002)
    est = estimate_time_offset(t_cam, R, t_imu, gyro, np.zeros(3))
    assert not isinstance(est, str)
    assert not est.confident and est.sigma_ms > 1.0


def test_too_few_frames_or_no_overlap_is_said() -> None:
    t_cam, R, t_imu, gyro = _mav(0.0, seconds=3.0)
    why = estimate_time_offset(t_cam[:5], R[:5], t_imu, gyro, np.zeros(3))
    assert isinstance(why, str) and "frame pairs" in why
    late = t_imu + 100_000_000_000  # the IMU covers none of the frames
    why = estimate_time_offset(t_cam, R, late, gyro, np.zeros(3))
    assert isinstance(why, str) and "0 frame pairs" in why


@pytest.mark.slow
def test_the_tracker_moves_the_offset_only_on_confident_estimates_of_its_map() -> None:
    t_cam, R, t_imu, gyro = _mav(12.0)
    tracker = TimeOffsetTracker(TimeOffsetConfig(every_s=1.0), offset_ns=0)
    for t, r in zip(t_cam[:60], R[:60], strict=True):  # 3 s: too short to be confident
        tracker.add_frame(int(t), r, map_id=0)
    assert tracker.update(t_imu, gyro, np.zeros(3), force=True) is None
    assert tracker.offset_ns == 0 and not tracker.confident
    assert tracker.last is not None and not tracker.last.confident  # estimated, not applied
    for t, r in zip(t_cam[60:], R[60:], strict=True):
        tracker.add_frame(int(t), r, map_id=0)
    new = tracker.update(t_imu, gyro, np.zeros(3), force=True)
    assert new is not None and abs(new * 1e-6 - 12.0) < 0.3
    assert tracker.offset_ns == new and tracker.updates == 1 and tracker.confident
    # A new map starts a new history: two frames are no estimate.
    tracker.add_frame(int(t_cam[-1]) + 50_000_000, R[-1], map_id=1)
    tracker.add_frame(int(t_cam[-1]) + 100_000_000, R[-1], map_id=1)
    assert tracker.update(t_imu, gyro, np.zeros(3), force=True) is None
    assert tracker.offset_ns == new
    off = TimeOffsetTracker(TimeOffsetConfig(), offset_ns=5_000_000, enabled=False)
    for t, r in zip(t_cam, R, strict=True):
        off.add_frame(int(t), r, map_id=0)
    assert off.update(t_imu, gyro, np.zeros(3), force=True) is None and off.offset_ns == 5_000_000


@pytest.mark.slow
def test_a_flight_that_never_gives_a_confident_offset_is_asked_less_and_less() -> None:
    """Each unconfident estimate waits longer for the next (up to 30 s); a forced one (before
    a VI initialisation, retried every half second) runs at most once per 3 s."""
    t_cam, R, t_imu, gyro = _mav(15.0, seconds=60.0, rate_scale=0.002)
    for force, at_most in ((False, 8), (True, 20)):  # without the backoff: 20, and 1200
        tracker = TimeOffsetTracker(TimeOffsetConfig())
        for t, r in zip(t_cam, R, strict=True):
            tracker.add_frame(int(t), r, map_id=0)
            assert tracker.update(t_imu, gyro, np.zeros(3), force=force) is None
        assert not tracker.confident and tracker.offset_ns == 0
        assert 3 <= tracker.runs <= at_most, (force, tracker.runs)


def _run(seq, shift_ns: int, options: VioConfig):
    """Feed ``seq`` with its IMU stamped ``shift_ns`` later, each frame's batch reaching the
    first sample at or after ``t + shift`` (a robot that batches by the offset)."""
    vio = VioManager(seq.camera, seq.imu, options)
    t_imu = seq.imu_timestamps_ns + shift_ns
    out, j = [], 0
    for fr in seq.frames:
        k = min(int(np.searchsorted(t_imu, fr.timestamp_ns + shift_ns)) + 1, len(t_imu))
        if k > j:
            vio.feed_imu(t_imu[j:k], seq.gyro[j:k], seq.accel[j:k])
        j = max(j, k)
        out.append(vio.feed_frame(fr))
    return vio, out


@pytest.mark.slow
def test_the_vio_reads_its_imu_at_frame_time_plus_the_offset() -> None:
    """An IMU stamped 15 ms late with the offset given gives the synchronised run's poses."""
    seq = simulate(SimConfig(duration_s=8.0, seed=1))
    fixed = VioConfig(estimate_time_offset=False)
    vio0, sync = _run(seq, 0, fixed)
    vio1, late = _run(
        seq, 15_000_000, VioConfig(estimate_time_offset=False, time_offset_ns=15_000_000)
    )
    assert vio0.initialized and vio1.initialized
    assert vio1.time_offset_ns == 15_000_000 and vio1.stats.time_offset_ms == 15.0
    for a, b in zip(sync, late, strict=True):
        assert a.status is b.status
        np.testing.assert_allclose(a.T_world_body, b.T_world_body, atol=1e-9)
    # Not told, the same late IMU gives other poses (the test above can fail).
    _, blind = _run(seq, 15_000_000, fixed)
    moved = max(
        np.abs(a.T_world_body - b.T_world_body).max() for a, b in zip(sync, blind, strict=True)
    )
    assert moved > 1e-4


@pytest.mark.slow
def test_estimating_on_a_synchronised_run_keeps_the_offset_near_zero() -> None:
    seq = simulate(SimConfig(duration_s=20.0, seed=0))
    vio, res = _run(seq, 0, VioConfig())
    m = evaluate_run(vio, res, seq)
    assert abs(vio.time_offset_ns) < 1_000_000  # not moved, or moved by less than 1 ms
    assert m.n_maps == 1 and m.ate_keyframes_m < 0.05


def test_an_unconfident_estimate_is_adopted_only_when_it_rejects_the_offset_in_use() -> None:
    """At a first VI initialisation the tracker may take an estimate that lacks only the span:
    when its sigma is within max_sigma_ms and it lies more than k sigmas and a floor from the
    offset in use; never when confident already, never a wide one, never a small move."""
    t_cam, R, t_imu, gyro = _mav(12.0)

    def short(options: TimeOffsetConfig) -> TimeOffsetTracker:
        tracker = TimeOffsetTracker(options, offset_ns=0)
        for t, r in zip(t_cam[:60], R[:60], strict=True):  # 3 s: too short to be confident
            tracker.add_frame(int(t), r, map_id=0)
        assert tracker.update(t_imu, gyro, np.zeros(3), now_only=True) is None
        assert tracker.last is not None and not tracker.last.confident
        return tracker

    tracker = short(TimeOffsetConfig())
    assert tracker.last is not None and tracker.last.sigma_ms <= 1.0
    assert tracker.adopt_last(3.0, 20.0) is None and tracker.offset_ns == 0  # under the floor
    new = tracker.adopt_last(3.0, 5.0)
    assert new is not None and abs(new * 1e-6 - 12.0) < 0.5 and tracker.offset_ns == new
    assert tracker.adopt_last(3.0, 5.0) is None  # nothing left to move
    strict = short(TimeOffsetConfig(max_sigma_ms=1e-6))  # every estimate "wide"
    assert strict.adopt_last(3.0, 5.0) is None and strict.offset_ns == 0
    assert short(TimeOffsetConfig()).adopt_last(0.0, 5.0) is None  # switched off


@pytest.mark.slow
def test_a_map_is_refined_when_its_offset_moves_and_its_first_init_can_wait_for_it() -> None:
    """An IMU 15 ms late, the offset estimated (this smooth simulated flight only gives
    estimates of sigma ~3 ms: taken as confident here): once the estimate moves the offset, the
    map is refined at once on the re-sliced IMU (one VI run more than with that switched off);
    with a wait, the first VI initialisation comes after the offset moved, not before."""
    seq = simulate(SimConfig(duration_s=14.0, seed=1))
    loose = TimeOffsetConfig(max_sigma_ms=5.0)
    runs = {}
    for name, vi in (
        ("off", ViInitConfig(refine_on_offset_change_ms=0.0)),
        ("on", ViInitConfig()),
        ("wait", ViInitConfig(wait_for_time_offset_s=8.0)),
    ):
        vio, res = _run(seq, 15_000_000, VioConfig(vi_init=vi, time_offset=loose))
        assert abs(vio.time_offset_ns) > 2_000_000, name  # the estimate moved it
        vmap = vio.current_map
        assert vmap is not None and vmap.vi_initialized
        first_tracked = next(r.timestamp_ns for r in res if r.status is TrackingStatus.TRACKING)
        runs[name] = (vmap.vi_init_runs, len(vio.stats.vi_init_s), vmap, first_tracked, vio)
    # The refinement on the moved offset is an extra run; the schedule's count is the same.
    assert runs["on"][1] == runs["off"][1] + 1 and runs["on"][0] == runs["off"][0]
    on_vio = runs["on"][4]
    assert runs["on"][2].vi_time_offset_ns == on_vio.time_offset_ns  # refined on it
    # Waiting: the first init is later, on the moved offset.
    assert runs["wait"][3] > runs["on"][3]
    assert abs(runs["wait"][2].vi_time_offset_ns) > 2_000_000
