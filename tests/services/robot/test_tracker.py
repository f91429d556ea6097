"""Robot front end on the real EuRoC excerpt and on synthetic motion (Algorithm 1)."""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.data.euroc import EurocSequence, ImuBatch
from common.geometry import so3_exp
from services.robot.config import (
    FrontEndConfig,
    KeyframeDecisionConfig,
    PredictionMode,
    TrackingMode,
)
from services.robot.imu_prediction import InertialState, R_imu_cam_from, warp_by_rotation
from services.robot.keyframe_decision import KeyframeReason, decide_keyframe
from services.robot.tracker import FrontEnd, FrontEndError, TrackedFrame


@pytest.fixture(scope="module")
def seq(euroc_micro: Path) -> EurocSequence:
    return EurocSequence(euroc_micro)


@pytest.fixture(scope="module")
def frames(seq: EurocSequence) -> list:
    return list(seq.frames())


@pytest.fixture(scope="module")
def run(seq: EurocSequence, frames: list) -> tuple[FrontEnd, list[TrackedFrame]]:
    fe = FrontEnd(FrontEndConfig(), seq.cam0, seq.imu)
    return fe, [fe.process(f.image, f.timestamp_ns, f.imu) for f in frames]


def test_keeps_tracks_over_the_excerpt(run) -> None:
    _, outs = run
    assert outs[0].is_keyframe and outs[0].keyframe_reason is KeyframeReason.FIRST_FRAME
    assert len(outs[0]) == 1000
    for out in outs[1:]:
        assert out.stats.n_inliers > 800
        assert len(out) > 800
        if not out.is_keyframe:
            assert out.descriptors is None and out.angles is None
            assert out.stats.prediction == "gyro"


def test_keyframes_follow_the_decision_rule(run) -> None:
    fe, outs = run
    cfg = fe.config.keyframe
    kf_n, kf_t = None, None
    for out in outs:
        dt = None if kf_t is None else (out.timestamp_ns - kf_t) * 1e-9
        expected = decide_keyframe(cfg, out.stats.n_tracked_keyframe, kf_n, dt)
        assert out.is_keyframe == expected.is_keyframe
        assert out.keyframe_reason is expected.reason
        if out.is_keyframe:
            kf_n, kf_t = len(out), out.timestamp_ns
            assert out.descriptors.shape == (len(out), 32)
            assert out.angles.shape == (len(out),)
            np.testing.assert_array_equal(out.keyframe_feature_index, np.arange(len(out)))
    n_kf = sum(o.is_keyframe for o in outs)
    assert 4 <= n_kf <= 6  # 4.7 s of standstill, max 1 s between keyframes
    assert all(o.keyframe_reason is KeyframeReason.MAX_INTERVAL for o in outs[1:] if o.is_keyframe)


def test_track_identity_persists(run) -> None:
    _, outs = run
    for prev, out in itertools.pairwise(outs):
        mask = out.survived_mask_vs_previous
        assert mask.shape == (len(prev),)
        if out.is_keyframe:
            # Continuing identities are exactly the previous tracks the mask marks.
            cont = np.intersect1d(out.track_ids, prev.track_ids)
            np.testing.assert_array_equal(np.sort(prev.track_ids[mask]), cont)
            assert len(cont) > 500
            assert np.all(out.levels == out.levels)  # levels come from ORB (checked in ORB tests)
        else:
            n = int(mask.sum())
            np.testing.assert_array_equal(out.track_ids[:n], prev.track_ids[mask])
            np.testing.assert_array_equal(
                out.keyframe_feature_index[:n], prev.keyframe_feature_index[mask]
            )
            np.testing.assert_array_equal(out.levels[:n], prev.levels[mask])
            assert np.all(out.keyframe_feature_index[n:] == -1)  # top-up corners
            assert np.all(out.track_ids[n:] > prev.track_ids.max())
            assert out.keyframe_id == prev.keyframe_id
            # The MAV stands still (motors vibrate the image by < 1 px): survivors stay put.
            step = np.linalg.norm(out.keypoints[:n] - prev.keypoints[mask], axis=1)
            assert np.median(step) < 1.0
        assert len(np.unique(out.track_ids)) == len(out)
    # Some keyframe-0 features are still tracked at the end, under the same identity.
    assert len(np.intersect1d(outs[0].track_ids, outs[-1].track_ids)) > 300


def test_keypoints_on_quarter_pixel_grid_and_used_as_sent(run) -> None:
    fe, outs = run
    for out in outs:
        quarters = out.keypoints * 4.0
        np.testing.assert_array_equal(quarters, np.round(quarters))
        assert out.levels.dtype == np.uint8
        assert out.track_ids.dtype == np.int64
    np.testing.assert_array_equal(fe._pts, outs[-1].keypoints)  # next frame starts from these


def test_learns_gyro_bias_at_standstill(run, seq: EurocSequence, frames: list) -> None:
    fe, _ = run
    bias = fe.predictor.static_bias.bias
    t0, t1 = frames[0].timestamp_ns, frames[-1].timestamp_ns
    sel = (seq.imu_timestamps_ns > t0) & (seq.imu_timestamps_ns <= t1)
    np.testing.assert_allclose(bias, seq.gyro[sel].mean(axis=0), atol=2e-3)
    assert np.linalg.norm(bias) > 0.05  # the ADIS16448 bias is large (~4.6 deg/s)


def test_baselines(seq: EurocSequence, frames: list) -> None:
    subset = frames[:25]
    plain = FrontEnd(
        dataclasses.replace(FrontEndConfig(), prediction=PredictionMode.NONE), seq.cam0, seq.imu
    )
    outs = [plain.process(f.image, f.timestamp_ns, f.imu) for f in subset]
    assert all(o.stats.prediction == "none" and o.stats.n_predicted == 0 for o in outs[1:])
    assert min(o.stats.n_inliers for o in outs[1:]) > 800

    orb = FrontEnd(
        dataclasses.replace(FrontEndConfig(), tracking=TrackingMode.ORB_MATCHING), seq.cam0, seq.imu
    )
    outs = [orb.process(f.image, f.timestamp_ns, f.imu) for f in subset]
    assert all(o.descriptors is not None and o.descriptors.shape == (len(o), 32) for o in outs)
    assert min(o.stats.n_inliers for o in outs[1:]) > 300
    assert len(np.intersect1d(outs[1].track_ids, outs[0].track_ids)) > 300

    every = FrontEnd(
        dataclasses.replace(FrontEndConfig(), keyframe=KeyframeDecisionConfig(every_frame=True)),
        seq.cam0,
        seq.imu,
    )
    outs = [every.process(f.image, f.timestamp_ns, f.imu) for f in subset[:6]]
    assert all(o.is_keyframe for o in outs)
    assert [o.keyframe_id for o in outs] == list(range(6))
    assert all(o.survived_mask_vs_previous.sum() > 500 for o in outs[1:])


def test_inertial_state_switches_to_preintegration(seq: EurocSequence, frames: list) -> None:
    fe = FrontEnd(FrontEndConfig(), seq.cam0, seq.imu)
    outs = [fe.process(f.image, f.timestamp_ns, f.imu) for f in frames[:10]]
    # A standstill state: gravity along the mean specific force, biases from the data.
    t = frames[9].timestamp_ns
    sel = (seq.imu_timestamps_ns > frames[0].timestamp_ns) & (seq.imu_timestamps_ns <= t)
    a_mean, g_mean = seq.accel[sel].mean(axis=0), seq.gyro[sel].mean(axis=0)
    z = a_mean / np.linalg.norm(a_mean)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R_imu_world = np.stack([x, np.cross(z, x), z])  # rows: world axes in the IMU frame
    R_world_imu = R_imu_world.T
    bias_accel = a_mean - R_imu_world @ np.array([0.0, 0.0, 9.81])
    state = InertialState(t, R_world_imu, np.zeros(3), np.zeros(3), g_mean, bias_accel)
    # 3D points for half of the tracks: back-project at 4 m with the state's camera pose.
    last = outs[-1]
    T_imu_cam = np.linalg.inv(seq.imu.T_body_imu) @ seq.cam0.T_body_cam
    ids = last.track_ids[::2]
    xy = cv2.undistortPoints(
        last.keypoints[::2].reshape(-1, 1, 2), seq.cam0.K, seq.cam0.dist_coeffs
    ).reshape(-1, 2)
    p_cam = np.c_[xy, np.ones(len(xy))] * 4.0
    p_imu = p_cam @ T_imu_cam[:3, :3].T + T_imu_cam[:3, 3]
    fe.set_inertial_state(state, ids, p_imu @ R_world_imu.T)
    assert fe.vi_initialised
    after = [fe.process(f.image, f.timestamp_ns, f.imu) for f in frames[10:20]]
    assert all(o.stats.prediction == "preintegration" for o in after if o.stats.n_previous)
    assert after[0].stats.n_predicted_3d == len(ids)
    assert min(o.stats.n_inliers for o in after) > 800


@pytest.mark.slow
def test_imu_prediction_beats_plain_lk_under_fast_rotation(seq: EurocSequence, frames) -> None:
    """Real frames re-rendered with a fast camera swing (and the matching gyro): the IMU-
    assisted tracker keeps more tracks than plain LK on the same frames."""
    cam = seq.cam0
    R_imu_cam = R_imu_cam_from(cam, seq.imu)
    axis = np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1])
    rate = np.radians(120.0)  # rad/s about a fixed axis, 6 deg per frame
    t_ref = frames[0].timestamp_ns
    images, imus = [], []
    for f in frames[:8]:
        angle = rate * (f.timestamp_ns - t_ref) * 1e-9
        images.append(warp_by_rotation(cam, f.image, so3_exp(-angle * axis)))
        w_imu = R_imu_cam @ (rate * axis)
        imus.append(ImuBatch(f.imu.timestamps_ns, f.imu.gyro + w_imu, f.imu.accel))
    counts = {}
    for mode in (PredictionMode.IMU, PredictionMode.NONE):
        fe = FrontEnd(dataclasses.replace(FrontEndConfig(), prediction=mode), cam, seq.imu)
        outs = [
            fe.process(img, f.timestamp_ns, imu)
            for img, imu, f in zip(images, imus, frames, strict=False)
        ]
        counts[mode] = np.array([o.stats.n_inliers for o in outs[1:]])
    assert counts[PredictionMode.IMU].sum() > 1.2 * counts[PredictionMode.NONE].sum()


def test_rejects_bad_input(seq: EurocSequence, frames: list) -> None:
    fe = FrontEnd(FrontEndConfig(), seq.cam0, seq.imu)
    with pytest.raises(FrontEndError, match="752x480"):
        fe.process(np.zeros((100, 100), np.uint8), 1)
    with pytest.raises(FrontEndError, match="uint8"):
        fe.process(np.zeros((480, 752), np.float32), 1)
    fe.process(frames[0].image, frames[0].timestamp_ns, frames[0].imu)
    with pytest.raises(FrontEndError, match="increase"):
        fe.process(frames[1].image, frames[0].timestamp_ns, frames[1].imu)
