"""The robot's sans-I/O core: the IMU each frame gets, back-pressure, feedback ordering and
every live-input fault, driven with plain values and ``now`` (no sockets, threads or clock)."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from common.data.euroc import ImuBatch, frames_with_imu
from common.geometry import make_T
from common.links.robot_edge import (
    CameraImuOffset,
    RobotFrame,
    encode_pose,
    frame_pose_message,
)
from common.protocol.messages import Blob
from services.robot.core import (
    ApplyFeedback,
    EdgeInput,
    EndOfInput,
    FrameDone,
    ImageInput,
    ImuInput,
    LiveInputConfig,
    PoseOut,
    RobotCore,
    Send,
    TrackFrame,
)

W, H = 64, 48
MS = 1_000_000
T0 = 1_000_000_000_000


def image(value: int = 7) -> np.ndarray:
    return np.full((H, W), value, np.uint8)


def imu(ts) -> ImuInput:
    ts = np.asarray(ts, np.int64)
    k = np.arange(len(ts), dtype=np.float64)[:, None]
    return ImuInput(ts, np.hstack([k, k, k]) * 0.01, np.hstack([k, k, k + 9.8]))


def pose_of(core: RobotCore, t: int, now: float) -> PoseOut:
    (out,) = core.handle(
        EdgeInput(frame_pose_message(t, 0, "tracking", encode_pose(np.eye(4)))), now
    )
    assert isinstance(out, PoseOut)
    return out


def test_each_frame_gets_the_folder_rule_imu_batch() -> None:
    """Fed sample by sample, interleaved as a driver would, the core cuts the very batches the
    folder playback's ``frames_with_imu`` cuts (so a folder run codes the same bytes)."""
    imu_t = T0 + 5 * MS * np.arange(400)  # 200 Hz
    cam_t = T0 + 2 * MS + 50 * MS * np.arange(1, 30)  # 20 Hz, not on the IMU lattice
    g = np.random.default_rng(0).normal(size=(400, 3))
    a = np.random.default_rng(1).normal(size=(400, 3))
    folder = list(frames_with_imu(cam_t, ImuBatch(imu_t, g, a), 0, len(cam_t), [None] * len(cam_t)))
    core = RobotCore(W, H)
    jobs: list[TrackFrame] = []
    i = 0
    for k, t in enumerate(cam_t):
        core.handle(ImageInput(int(t), image()), now=k * 0.05)
        while i < len(imu_t) and (i == 0 or imu_t[i - 1] < t):  # the sample after t comes
            core.handle(ImuInput(imu_t[i : i + 1], g[i : i + 1], a[i : i + 1]), k * 0.05)
            i += 1
        job = core.next_job(k * 0.05)
        assert isinstance(job, TrackFrame)
        jobs.append(job)
    assert len(jobs) == len(folder)
    for job, fr in zip(jobs, folder, strict=True):
        assert job.timestamp_ns == fr.timestamp_ns
        np.testing.assert_array_equal(job.imu.timestamps_ns, fr.imu.timestamps_ns)
        np.testing.assert_array_equal(job.imu.gyro, fr.imu.gyro)
        assert not core._flags  # clean input: no pose is flagged


def test_an_image_waits_for_the_imu_after_it_then_goes_without_it_flagged() -> None:
    core = RobotCore(W, H)
    core.handle(imu([T0, T0 + 5 * MS]), 0.0)
    core.handle(ImageInput(T0 + 8 * MS, image()), 0.0)
    assert core.next_job(0.1) is None  # no sample at or after the frame yet
    assert core.timer() == pytest.approx(0.25)
    job = core.next_job(0.25)
    assert isinstance(job, TrackFrame) and len(job.imu.timestamps_ns) == 2
    assert core.counts["imu_late"] == 1
    assert pose_of(core, T0 + 8 * MS, 0.4).pose.flags == {"imu_late"}
    # the edge's offset makes the next frame wait for IMU up to t + offset
    core.handle(EdgeInput(CameraImuOffset(15 * MS, MS)), 0.5)
    core.handle(ImageInput(T0 + 58 * MS, image()), 0.5)
    core.handle(imu([T0 + 60 * MS]), 0.5)
    # the worker is idle while the frame waits: the offset goes to the front end now
    assert isinstance(core.next_job(0.5), ApplyFeedback)
    assert core.next_job(0.5) is None
    core.handle(imu([T0 + 75 * MS]), 0.5)
    job = core.next_job(0.5)
    assert isinstance(job, TrackFrame) and not job.feedback
    assert job.imu.timestamps_ns.tolist() == [T0 + 60 * MS, T0 + 75 * MS]


def test_back_pressure_drops_the_oldest_untracked_image_and_keeps_its_imu() -> None:
    core = RobotCore(W, H, LiveInputConfig(max_pending_images=2))
    core.handle(imu(T0 + 5 * MS * np.arange(40)), 0.0)
    for k in range(3):
        assert core.has_room() or k == 2
        core.handle(ImageInput(T0 + (k + 1) * 50 * MS, image(k)), 0.0)
    assert core.counts["dropped_backpressure"] == 1 and core.pending_images == 2
    first = core.next_job(0.0)
    assert isinstance(first, TrackFrame) and first.timestamp_ns == T0 + 100 * MS
    assert first.imu.timestamps_ns[0] == T0  # the dropped frame's IMU went with this one
    assert core.poses.pending == 2  # the dropped frame expects no pose
    assert core.handle(FrameDone(RobotFrame(0, first.timestamp_ns, True, b"f", b"i")), 0.0)
    assert isinstance(core.handle(FrameDone(RobotFrame(1, 1, False, b"", b"")), 0)[0], Send)
    assert core.stats()["frames_sent"] == 2


def test_feedback_waits_for_the_next_frame_or_is_applied_alone() -> None:
    core = RobotCore(W, H)
    core.handle(EdgeInput(Blob(0, b"x")), 0.0)  # not for the robot: ignored
    assert core.next_job(0.0) is None
    core.handle(EdgeInput(CameraImuOffset(-3 * MS, MS)), 0.0)
    job = core.next_job(0.0)
    assert isinstance(job, ApplyFeedback) and len(job.feedback) == 1
    assert core.imu_lead_ns == 0  # a negative offset: the frame's own time


def test_out_of_order_duplicate_and_clock_going_back_are_dropped_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    core = RobotCore(W, H)
    with caplog.at_level(logging.WARNING):
        core.handle(ImageInput(T0 + 100 * MS, image()), 0.0)
        core.handle(ImageInput(T0 + 100 * MS, image()), 0.05)
        core.handle(ImageInput(T0 + 60 * MS, image()), 0.1)
        core.handle(ImageInput(T0 - 5_000 * MS, image()), 0.15)
    c = core.counts
    assert (c["image_duplicate"], c["image_out_of_order"], c["clock_back"]) == (1, 1, 1)
    assert core.pending_images == 1 and core.images_in == 4
    assert "again: dropped" in caplog.text and "clock went back 5.100 s" in caplog.text


def test_a_forward_clock_jump_is_flagged_on_its_pose_and_normal_frames_are_not() -> None:
    core = RobotCore(W, H, LiveInputConfig(max_pending_images=3))
    core.handle(imu(T0 + 5 * MS * np.arange(2000)), 0.0)
    core.handle(ImageInput(T0 + 50 * MS, image()), 0.0)
    core.handle(ImageInput(T0 + 100 * MS, image()), 0.05)  # 50 ms in 50 ms: clean
    core.handle(ImageInput(T0 + 3_100 * MS, image()), 0.1)  # 3 s of camera time in 50 ms
    assert core.counts["clock_jump"] == 1
    for _ in range(3):
        assert isinstance(core.next_job(0.1), TrackFrame)
    assert pose_of(core, T0 + 100 * MS, 0.2).pose.flags == frozenset()
    assert pose_of(core, T0 + 3_100 * MS, 0.2).pose.flags == {"clock_jump"}


def test_imu_gaps_are_flagged_and_bad_samples_dropped(caplog: pytest.LogCaptureFixture) -> None:
    core = RobotCore(W, H, LiveInputConfig(imu_gap_s=0.05))
    with caplog.at_level(logging.WARNING):
        core.handle(imu(T0 + 5 * MS * np.arange(11)), 0.0)  # to T0 + 50 ms
        core.handle(imu([T0 + 50 * MS, T0 + 40 * MS]), 0.0)  # duplicate, out of order
        bad = imu([T0 + 55 * MS])
        core.handle(ImuInput(bad.timestamps_ns, np.full((1, 3), np.nan), bad.accel), 0.0)
        core.handle(ImageInput(T0 + 50 * MS, image()), 0.0)
        core.handle(imu([T0 + 200 * MS, T0 + 205 * MS]), 0.0)  # a 150 ms hole
        core.handle(ImageInput(T0 + 200 * MS, image()), 0.15)
    assert core.counts["imu_out_of_order"] == 2 and core.counts["imu_invalid"] == 1
    assert core.counts["imu_gap"] == 1 and "IMU gap of 0.150 s" in caplog.text
    first, second = core.next_job(0.2), core.next_job(0.2)
    assert isinstance(first, TrackFrame) and isinstance(second, TrackFrame)
    assert second.imu.timestamps_ns.tolist() == [T0 + 200 * MS]
    assert pose_of(core, T0 + 50 * MS, 0.3).pose.flags == frozenset()
    assert pose_of(core, T0 + 200 * MS, 0.3).pose.flags == {"imu_gap"}


def test_a_stalled_driver_is_warned_once_and_its_return_too(
    caplog: pytest.LogCaptureFixture,
) -> None:
    core = RobotCore(W, H, LiveInputConfig(stall_s=1.0))
    core.handle(imu([T0]), 0.0)
    core.handle(ImageInput(T0 + 1 * MS, image()), 0.0)
    # an image waiting for tracking: the robot is the bottleneck, not the driver
    core.on_timer(5.0)
    assert core.counts["image_stall"] == 0
    core.handle(imu([T0 + 5 * MS]), 0.0)
    assert isinstance(core.next_job(0.0), TrackFrame)
    assert core.timer() == pytest.approx(1.0)
    with caplog.at_level(logging.WARNING):
        core.on_timer(1.5)
        core.on_timer(3.0)  # still the same stall: not again
        assert (core.counts["image_stall"], core.counts["imu_stall"]) == (1, 1)
        assert "no image for 1.5 s" in caplog.text
        core.handle(ImageInput(T0 + 4_000 * MS, image()), 4.0)
    assert "images again after 4.0 s" in caplog.text
    core.handle(EndOfInput(), 4.0)
    assert isinstance(core.next_job(4.0), TrackFrame)  # the end: no more waiting for IMU
    assert core.timer() is None


def test_images_of_the_wrong_size_type_or_encoding_are_dropped_colour_converted() -> None:
    core = RobotCore(W, H, LiveInputConfig(max_pending_images=3))
    core.handle(ImageInput(T0 + 1, np.zeros((H + 1, W), np.uint8)), 0.0)
    core.handle(ImageInput(T0 + 2, np.zeros((H, W), np.uint16)), 0.0)
    core.handle(ImageInput(T0 + 3, bytes(W * H), "yuv422", H, W, W), 0.0)
    core.handle(ImageInput(T0 + 4, bytes(W * H - 1), "mono8", H, W, W), 0.0)
    assert core.counts["image_invalid"] == 4 and core.pending_images == 0
    bgr = np.zeros((H, W, 3), np.uint8)
    bgr[..., 2] = 200  # red
    core.handle(ImageInput(T0 + 5, bgr.tobytes(), "bgr8", H, W, 3 * W), 0.0)
    mono16 = np.full((H, W), 0x1234, "<u2")
    core.handle(ImageInput(T0 + 6, mono16.tobytes(), "mono16", H, W, 2 * W), 0.0)
    core.handle(ImageInput(T0 + 7, np.zeros((H, W, 1), np.uint8)), 0.0)
    core.handle(EndOfInput(), 0.0)
    jobs = [core.next_job(0.0) for _ in range(3)]
    assert all(isinstance(j, TrackFrame) for j in jobs)
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(jobs[0].image, grey)  # type: ignore[union-attr]
    assert int(jobs[1].image[0, 0]) == 0x12  # type: ignore[union-attr]
    assert jobs[2].image.shape == (H, W)  # type: ignore[union-attr]


def test_a_pose_without_its_capture_still_arrives_and_malformed_ones_do_not() -> None:
    core = RobotCore(W, H)
    out = core.handle(
        EdgeInput(frame_pose_message(5, 0, "tracking", encode_pose(make_T(np.eye(3), [1, 2, 3])))),
        1.0,
    )
    assert isinstance(out[0], PoseOut) and out[0].pose.latency_s is None
    assert core.handle(EdgeInput(frame_pose_message(6, 0, "tracking", b"\x00")), 1.0) == []
    assert core.stats()["poses"]["rejected"] == 1
