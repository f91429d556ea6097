"""End-to-end VIO on the built-in simulator: accuracy, tracking loss, input validation."""

import numpy as np
import pytest

from services.edge.vio.manager import VioManager
from services.edge.vio.simulation import SimOptions, evaluate_run, run_sequence, simulate
from services.edge.vio.types import FrameObservation, TrackingStatus, VioError


def test_end_to_end_20s_ate_and_scale():
    seq = simulate(SimOptions(duration_s=20.0, seed=0))
    vio = VioManager(seq.camera, seq.imu)
    results = run_sequence(vio, seq)
    m = evaluate_run(vio, results, seq)
    # Measured when written: frames ATE 3.4 cm, scale 0.985; keyframes ATE 1.3 cm, scale 0.996.
    assert m.n_maps == 1
    assert m.n_tracking > 0.85 * m.n_frames
    assert m.ate_frames_m < 0.10
    assert abs(m.scale_frames - 1.0) < 0.05
    assert m.ate_keyframes_m < 0.05
    assert abs(m.scale_keyframes - 1.0) < 0.02
    state = vio.get_state()
    assert state is not None
    assert np.linalg.norm(state.bias_gyro - np.array(SimOptions().bias_gyro)) < 2e-3
    assert abs(np.linalg.norm(state.gravity_body) - 9.81) < 1e-9
    updates = vio.pop_map_updates()
    assert updates and updates[-1].vi_initialized
    kf = updates[-1].keyframes[-1]
    assert kf.T_world_body.shape == (4, 4) and len(kf.point_ids) == len(kf.track_ids)
    assert vio.pop_map_updates() == []


def test_vi_initialisation_recovers_scale_and_gravity():
    seq = simulate(SimOptions(duration_s=3.5, seed=4))
    vio = VioManager(seq.camera, seq.imu)
    run_sequence(vio, seq)
    assert vio.initialized
    vmap = vio.current_map
    row = {int(t): i for i, t in enumerate(seq.gt_timestamps_ns)}
    kfs = vmap.keyframe_list()
    gt = seq.gt_T_world_body[[row[k.timestamp_ns] for k in kfs]]
    est_d = np.linalg.norm(np.diff([k.T_world_body[:3, 3] for k in kfs], axis=0), axis=1).sum()
    gt_d = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    assert abs(est_d / gt_d - 1.0) < 0.05
    # Gravity: the body "up" seen in the estimated and true world frames agree (yaw-free).
    for kf, T in zip(kfs, gt, strict=True):
        up_est = kf.T_world_body[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        up_gt = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        assert np.degrees(np.arccos(np.clip(up_est @ up_gt, -1, 1))) < 2.0


def test_tracking_loss_starts_a_new_map():
    seq = simulate(SimOptions(duration_s=6.0, seed=5))
    vio = VioManager(seq.camera, seq.imu)
    results = []
    for i, (t, g, a, fr) in enumerate(seq.feed()):
        vio.feed_imu(t, g, a)
        if i >= 60:  # every track replaced: nothing links the frame to the map any more
            fr = FrameObservation(
                fr.timestamp_ns, fr.track_ids + 1_000_000, fr.keypoints_px, fr.levels,
                fr.is_keyframe, fr.descriptors,
            )  # fmt: skip
        results.append(vio.feed_frame(fr))
    assert results[59].map_id == 0
    lost = [r for r in results if r.status == TrackingStatus.LOST]
    assert len(lost) == 1
    assert lost[0].map_id == 1
    assert lost[0].reason.startswith("lost")
    assert results[-1].map_id == 1
    assert vio.current_map is not None and vio.current_map.map_id == 1
    assert len(vio.current_map.keyframes) >= 2  # the new map initialised and grows


def test_rejects_malformed_frames():
    with pytest.raises(VioError, match="keypoints_px"):
        FrameObservation(0, np.arange(3), np.zeros((3, 3)), np.zeros(3))
    with pytest.raises(VioError, match="duplicate"):
        FrameObservation(0, np.array([1, 1]), np.zeros((2, 2)), np.zeros(2))
    seq = simulate(SimOptions(duration_s=0.3))
    vio = VioManager(seq.camera, seq.imu)
    vio.feed_frame(seq.frames[1])
    with pytest.raises(VioError, match="not after"):
        vio.feed_frame(seq.frames[0])
    with pytest.raises(VioError, match="strictly increasing"):
        vio.feed_imu(np.array([5, 4]), np.zeros((2, 3)), np.zeros((2, 3)))
