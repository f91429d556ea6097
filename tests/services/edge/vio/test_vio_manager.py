"""End-to-end VIO on the built-in simulator: accuracy, tracking loss, input validation."""

from dataclasses import replace

import numpy as np
import pytest

from common.geometry import umeyama_alignment
from services.edge.vio.manager import VioManager
from services.edge.vio.types import (
    FrameObservation,
    TrackingConfig,
    TrackingStatus,
    VioConfig,
    VioError,
)
from sim.vio import SimConfig, evaluate_run, run_sequence, simulate


@pytest.mark.slow
def test_end_to_end_20s_ate_and_scale():
    # 5 % of the observations of every frame are gross outliers (5-30 px), as bad LK tracks.
    seq = simulate(SimConfig(duration_s=20.0, seed=0, outlier_ratio=0.05))
    vio = VioManager(seq.camera, seq.imu)
    results = run_sequence(vio, seq)
    m = evaluate_run(vio, results, seq)
    # Measured when written: frames ATE 3.0 cm, scale 0.983 (the first seconds after VI init
    # carry the init's scale error); keyframes ATE 0.4 cm, scale 0.997.
    assert m.n_maps == 1
    assert m.n_tracking > 0.8 * m.n_frames  # the rest: before VI initialisation
    assert m.ate_frames_m < 0.10
    assert abs(m.scale_frames - 1.0) < 0.05
    assert m.ate_keyframes_m < 0.05
    assert abs(m.scale_keyframes - 1.0) < 0.02
    state = vio.get_state()
    assert state is not None
    assert np.linalg.norm(state.bias_gyro - np.array(SimConfig().bias_gyro)) < 2e-3
    assert abs(np.linalg.norm(state.gravity_body) - 9.81) < 1e-9
    updates = vio.pop_map_updates()
    assert updates and updates[-1].vi_initialized
    kf = updates[-1].keyframes[-1]
    assert kf.T_world_body.shape == (4, 4) and len(kf.point_ids) == len(kf.track_ids)
    assert vio.pop_map_updates() == []


@pytest.mark.parametrize("seed", [0, 2, 4])
def test_vi_initialisation_recovers_scale_and_gravity(seed):
    seq = simulate(SimConfig(duration_s=6.0, seed=seed))
    vio = VioManager(seq.camera, seq.imu)
    for t, g, a, fr in seq.feed():
        vio.feed_imu(t, g, a)
        vio.feed_frame(fr)
        if vio.initialized:
            break
    assert vio.initialized
    vmap = vio.current_map
    row = {int(t): i for i, t in enumerate(seq.gt_timestamps_ns)}
    kfs = vmap.keyframe_list()
    gt = seq.gt_T_world_body[[row[k.timestamp_ns] for k in kfs]]
    est = np.array([k.T_world_body[:3, 3] for k in kfs])
    _, _, scale = umeyama_alignment(est, gt[:, :3, 3], with_scale=True)
    assert abs(scale - 1.0) < 0.05  # measured 1.026 / 0.985 / 0.977
    # Gravity: the body "up" seen in the estimated and true world frames agree (yaw-free).
    for kf, T in zip(kfs, gt, strict=True):
        up_est = kf.T_world_body[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        up_gt = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        assert np.degrees(np.arccos(np.clip(up_est @ up_gt, -1, 1))) < 2.0


def _lose_tracks(seed: int, options: VioConfig | None, new_descriptors: bool) -> tuple:
    """6 s of the simulator; from frame 61 (3 s, after VI initialisation; a non-keyframe:
    the simulator's robot keyframes are every fifth frame) every track is
    renamed, so nothing links a frame to the map by its tracks any more (a robot's tracker
    restarted, or a gap no track survived); with ``new_descriptors`` the keyframes' ORB
    descriptors are replaced by random ones too (another place)."""
    seq = simulate(SimConfig(duration_s=6.0, seed=seed))
    vio = VioManager(seq.camera, seq.imu, options)
    rng = np.random.default_rng(0)
    results = []
    for i, (t, g, a, fr) in enumerate(seq.feed()):
        vio.feed_imu(t, g, a)
        if i >= 61:
            desc = fr.descriptors
            if new_descriptors and desc is not None:
                desc = rng.integers(0, 256, desc.shape, dtype=np.uint8)
            fr = FrameObservation(
                fr.timestamp_ns,
                fr.track_ids + 1_000_000,
                fr.keypoints_px,
                fr.levels,
                fr.is_keyframe,
                desc,
            )
        results.append(vio.feed_frame(fr))
        if i == 60:
            assert vio.initialized
    return vio, results


NO_LOST_BRIDGE = VioConfig(tracking=replace(TrackingConfig(), bridge_while_lost=False))


def test_a_keyframe_relocalises_a_recently_lost_map():
    """The map is kept while the IMU predicts the pose; the next robot keyframe's features are
    found in the local map by projection (their descriptors) and tracking goes on in map 0."""
    vio, results = _lose_tracks(5, NO_LOST_BRIDGE, new_descriptors=False)
    assert results[60].map_id == 0
    lost = [r for r in results if r.status == TrackingStatus.LOST]
    assert lost, "renamed tracks must lose the frame at first"
    assert all("kept" in r.reason and r.map_id == 0 for r in lost)
    assert all(r.status == TrackingStatus.TRACKING for r in results[61 + len(lost) :])
    assert results[-1].map_id == 0 and vio.stats.maps_started == 0  # (counts new maps)
    assert vio.stats.relocalised == 1 and vio.stats.frames_lost_kept == len(lost)
    assert len(lost) == 4  # frames 61-64: frame 65, the next robot keyframe, relocalises


def test_tracking_loss_starts_a_new_map_after_the_recently_lost_time():
    options = VioConfig(
        tracking=replace(TrackingConfig(), recently_lost_s=1.0, bridge_while_lost=False)
    )
    vio, results = _lose_tracks(5, options, new_descriptors=True)
    lost = [r for r in results if r.status == TrackingStatus.LOST]
    kept = [r for r in lost if "kept" in r.reason]
    assert kept and all(r.map_id == 0 for r in kept)
    assert (kept[-1].timestamp_ns - kept[0].timestamp_ns) * 1e-9 < 1.0
    assert lost[len(kept)].map_id == 1 and "kept" not in lost[len(kept)].reason
    assert vio.stats.relocalised == 0
    assert vio.current_map is not None and vio.current_map.map_id == 1
    assert len(vio.current_map.keyframes) >= 2  # the new map initialised and grows


def test_without_a_recently_lost_time_a_loss_starts_a_new_map_at_once():
    options = VioConfig(tracking=replace(TrackingConfig(), recently_lost_s=0.0))
    _, results = _lose_tracks(5, options, new_descriptors=False)
    lost = [r for r in results if r.status == TrackingStatus.LOST]
    assert len(lost) == 1
    assert lost[0].map_id == 1 and lost[0].reason.startswith("lost")
    assert results[-1].map_id == 1


def test_a_recently_lost_map_is_bridged_back_by_the_frames_after_a_failed_bridge():
    """Every track renamed and the descriptors of another place (nothing to relocalise by):
    the first frame's bridge finds no track an earlier keyframe saw, but its keyframe stays,
    and the frames after it bridge from it until their shared tracks, triangulated between
    IMU poses, hold the map again: no new map, the poses stay with the ground truth. Without
    (``bridge_while_lost=False``) a new map starts once the recently lost time is over."""
    vio, results = _lose_tracks(5, None, new_descriptors=True)
    lost = [r for r in results if r.status == TrackingStatus.LOST]
    assert lost and all(r.map_id == 0 and "kept" in r.reason for r in lost)
    back = results[61 + len(lost)]
    assert back.status == TrackingStatus.TRACKING and back.reason.startswith("IMU-bridged")
    assert all(
        r.status == TrackingStatus.TRACKING and r.map_id == 0 for r in results[61 + len(lost) :]
    )
    assert vio.stats.maps_started == 0 and vio.stats.bridged_back == 1
    assert vio.stats.relocalised == 0
    seq = simulate(SimConfig(duration_s=6.0, seed=5))
    row = {int(t): i for i, t in enumerate(seq.gt_timestamps_ns)}
    gt = seq.gt_T_world_body
    # relative to the last frame tracked before the loss (the map's frame is the VIO's own)
    T0, G0 = results[60].T_world_body, gt[row[results[60].timestamp_ns]]
    for r in results[61 + len(lost) :]:
        moved = r.T_world_body[:3, 3] - T0[:3, 3]
        moved_gt = gt[row[r.timestamp_ns], :3, 3] - G0[:3, 3]
        assert abs(np.linalg.norm(moved) - np.linalg.norm(moved_gt)) < 0.05  # m
    options = VioConfig(
        tracking=replace(TrackingConfig(), recently_lost_s=1.0, bridge_while_lost=False)
    )
    vio, _ = _lose_tracks(5, options, new_descriptors=True)
    assert vio.stats.maps_started == 1 and vio.stats.bridged_back == 0


def test_bridges_stop_where_the_imu_alone_no_longer_holds_the_position():
    """The IMU-only time a bridge may span follows the accelerometer noise the VIO weighs the
    IMU by: the generator's (0.002 m/s^2/sqrt(Hz)) ~31 s, a real MAV's in flight (~0.11) ~2 s,
    for 0.2 m; with a bound too tight for any gap the lost map is not bridged back."""
    seq = simulate(SimConfig(duration_s=0.3, seed=5))
    vio = VioManager(seq.camera, seq.imu)
    vio.stats.imu_noise_used = (1e-4, 0.002)
    assert 30.0 < vio.imu_only_limit_s() < 32.0
    vio.stats.imu_noise_used = (4e-3, 0.109)
    assert 2.0 < vio.imu_only_limit_s() < 2.2
    tight = VioConfig(
        tracking=replace(TrackingConfig(), bridge_max_sigma_m=1e-4, recently_lost_s=1.0)
    )
    vio, _ = _lose_tracks(5, tight, new_descriptors=True)
    assert vio.stats.maps_started == 1 and vio.stats.bridged_back == 0


def test_a_frame_with_too_few_map_points_is_bridged_by_the_imu():
    """Most map points gone (as when sparse frames see new ground): the frame is made a
    keyframe at the IMU's prediction, its tracks that earlier keyframes saw triangulated, and
    tracking goes on in the same map; the bridged pose moved as the ground truth did."""
    seq = simulate(SimConfig(duration_s=5.0, seed=5))
    vio = VioManager(seq.camera, seq.imu)
    row = {int(t): i for i, t in enumerate(seq.gt_timestamps_ns)}
    results = []
    for i, (t, g, a, fr) in enumerate(seq.feed()):
        vio.feed_imu(t, g, a)
        if i == 61:
            vmap = vio.current_map
            assert vio.initialized and vmap is not None
            for point_id in list(vmap.points)[: int(0.97 * len(vmap.points))]:
                vmap.remove_point(point_id)
        results.append(vio.feed_frame(fr))
    bridged = results[61]
    assert bridged.status == TrackingStatus.TRACKING and bridged.map_id == 0
    assert bridged.reason.startswith("IMU-bridged") and bridged.is_new_keyframe
    assert vio.stats.frames_bridged == 1 and vio.stats.maps_started == 0
    assert all(r.status == TrackingStatus.TRACKING for r in results[61:])
    gt = seq.gt_T_world_body
    moved_gt = np.linalg.norm(
        gt[row[results[61].timestamp_ns], :3, 3] - gt[row[results[60].timestamp_ns], :3, 3]
    )
    moved = np.linalg.norm(results[61].T_world_body[:3, 3] - results[60].T_world_body[:3, 3])
    assert abs(moved - moved_gt) < 0.01  # m


def test_rejects_malformed_frames():
    with pytest.raises(VioError, match="keypoints_px"):
        FrameObservation(0, np.arange(3), np.zeros((3, 3)), np.zeros(3))
    with pytest.raises(VioError, match="duplicate"):
        FrameObservation(0, np.array([1, 1]), np.zeros((2, 2)), np.zeros(2))
    seq = simulate(SimConfig(duration_s=0.3))
    vio = VioManager(seq.camera, seq.imu)
    vio.feed_frame(seq.frames[1])
    with pytest.raises(VioError, match="not after"):
        vio.feed_frame(seq.frames[0])
    with pytest.raises(VioError, match="strictly increasing"):
        vio.feed_imu(np.array([5, 4]), np.zeros((2, 3)), np.zeros((2, 3)))


def test_a_visual_map_before_vi_initialisation_takes_no_pose_correction():
    """Corrections are metric; before VI initialisation (e.g. a restarted edge re-running a
    map from its journal) the map's scale is its own: they are ignored, nothing moves."""
    from common.geometry import make_T, so3_exp

    seq = simulate(SimConfig(duration_s=8.0, seed=6))
    vio = VioManager(seq.camera, seq.imu)
    for t, g, a, fr in seq.feed():
        vio.feed_imu(t, g, a)
        vio.feed_frame(fr)
        vmap = vio.current_map
        if vmap is not None and len(vmap.keyframe_list()) >= 2:
            break
    assert vmap is not None and not vio.initialized
    before = {k.id: k.T_world_body.copy() for k in vmap.keyframe_list()}
    D = make_T(so3_exp([0.0, 0.0, 0.2]), [0.5, -0.3, 0.0])
    assert vio.apply_pose_corrections(vmap.map_id, {k: D @ T for k, T in before.items()}) == 0
    assert all(np.array_equal(k.T_world_body, before[k.id]) for k in vmap.keyframe_list())
    assert vio.pop_point_moves() == []


def test_pose_corrections_move_map_rigidly_and_tracking_continues():
    from common.geometry import make_T, so3_exp
    from services.edge.vio.local_ba import reprojection_chi2

    seq = simulate(SimConfig(duration_s=8.0, seed=6))
    vio = VioManager(seq.camera, seq.imu)
    feed = list(seq.feed())
    for t, g, a, fr in feed[:130]:
        vio.feed_imu(t, g, a)
        vio.feed_frame(fr)
    assert vio.initialized
    vmap = vio.current_map
    ids = [k.id for k in vmap.keyframe_list()]
    chi2 = reprojection_chi2(vmap, ids[-5:], vio.camera)
    D = make_T(so3_exp([0.0, 0.0, 0.2]), [0.5, -0.3, 0.0])  # a yaw + shift "drift correction"
    corrected = {k: D @ vmap.keyframes[k].T_world_body for k in ids}
    assert vio.apply_pose_corrections(vmap.map_id + 1, corrected) == 0
    assert vio.apply_pose_corrections(vmap.map_id, corrected) == len(ids)
    assert np.allclose(vmap.keyframes[ids[-1]].T_world_body, corrected[ids[-1]])
    assert abs(reprojection_chi2(vmap, ids[-5:], vio.camera) - chi2) < 1e-6
    # The uplink is told how the points moved: the correction of every keyframe, once.
    ((moved_map, deltas),) = vio.pop_point_moves()
    assert moved_map == vmap.map_id and set(deltas) == set(ids)
    assert all(np.allclose(deltas[k], D, atol=1e-9) for k in ids)
    assert vio.pop_point_moves() == []
    results = []
    for t, g, a, fr in feed[130:]:
        vio.feed_imu(t, g, a)
        results.append(vio.feed_frame(fr))
    assert all(r.status == TrackingStatus.TRACKING for r in results)
    assert {r.map_id for r in results} == {vmap.map_id}


def test_a_map_goes_up_only_once_vi_initialised_and_then_whole():
    """No map updates before VI initialisation (no scale, no gravity yet); the first one after
    holds every keyframe of the map."""
    seq = simulate(SimConfig(duration_s=8.0, seed=6))
    vio = VioManager(seq.camera, seq.imu)
    before_init = []
    first = None
    for t, g, a, fr in seq.feed():
        vio.feed_imu(t, g, a)
        vio.feed_frame(fr)
        ups = vio.pop_map_updates()
        if not vio.initialized:
            before_init += ups
        elif ups:
            first = ups[0]
            break
    assert before_init == []
    vmap = vio.current_map
    assert first is not None and first.vi_initialized and vmap is not None
    assert {k.keyframe_id for k in first.keyframes} == {k.id for k in vmap.keyframe_list()}
