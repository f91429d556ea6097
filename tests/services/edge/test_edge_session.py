"""One robot's edge session without the network: decoding, track naming, uplink, corrections."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from common.codec import decode_standalone_keyframe
from common.links import WireFormat
from common.links.edge_cloud import KeyframeUpdate, MapPointUpdate
from common.links.robot_edge import (
    Anchors,
    FramePose,
    InertialFeedback,
    InertialFeedbackCoded,
    decode_feedback,
    decode_pose,
    pose_status,
)
from common.protocol.arrays import unpack_array
from common.protocol.messages import encode_payload
from common.vocabulary import Vocabulary
from services.edge.feedback import FeedbackPolicy, FeedbackSender
from services.edge.imu_uplink import ImuUplink
from services.edge.robot_session import EdgeSessionConfig, RobotSession
from services.edge.worker import VioRunner, WorkerSpec
from sim.robot import code_sequence
from sim.vio import SimConfig, simulate

RAW = EdgeSessionConfig(wire=WireFormat.RAW)  # these tests pin the schema-1 uplink


@pytest.fixture(scope="module")
def run():
    """A 5 s simulated robot through RobotSession + VioRunner, frame by frame."""
    vocab = Vocabulary.load()
    seq = simulate(SimConfig(duration_s=5.0, seed=3))
    frames = code_sequence(seq, vocab)
    session = RobotSession("r", seq.camera, vocab, RAW)
    runner = VioRunner(WorkerSpec("r", seq.camera, seq.imu))
    items, results, robot_msgs, cloud_msgs = [], [], [], []
    for k, msg in enumerate(frames):
        item = session.decode(msg)
        if k == len(frames) - 1:  # the cloud moves every keyframe of map 0 by +1 m in x
            vmap = runner.vio.current_map
            shift = np.eye(4)
            shift[0, 3] = 1.0
            poses = {kf.id: shift @ kf.T_world_body for kf in vmap.keyframe_list()}
            item = dataclasses.replace(item, corrections=((0, poses),))
        res = runner.step(item)
        out = session.on_result(res)
        items.append(item)
        results.append(res)
        robot_msgs += out.robot
        cloud_msgs += out.cloud
    return seq, vocab, session, items, results, robot_msgs, cloud_msgs


def test_stream_numbers_name_each_simulated_track_consistently(run) -> None:
    seq, _, _, items, _, _, _ = run
    number_of: dict[int, int] = {}
    for fr, item in zip(seq.frames, items, strict=True):
        # Same features as the simulator's frame, in codec order: keyframes are matched by
        # descriptor (unique per simulated landmark), other frames by their 1/4 px position.
        assert len(item.obs.track_ids) == len(fr.track_ids)
        rows_of = {}
        if fr.is_keyframe:
            rows_of = {d.tobytes(): r for r, d in enumerate(item.obs.descriptors)}
        for r_sim, sim_id in enumerate(fr.track_ids.tolist()):
            if fr.is_keyframe:
                row = rows_of[fr.descriptors[r_sim].tobytes()]
            else:
                d = np.linalg.norm(item.obs.keypoints_px - fr.keypoints_px[r_sim], axis=1)
                row = int(np.argmin(d))
                assert d[row] <= 0.125 * np.sqrt(2) + 1e-9
            num = int(item.obs.track_ids[row])
            assert number_of.setdefault(sim_id, num) == num
    assert len(set(number_of.values())) == len(number_of)  # a bijection


def test_feedback_after_vi_init_names_live_tracks(run) -> None:
    _, _, session, items, results, robot_msgs, _ = run
    fbs = [m for m in robot_msgs if isinstance(m, InertialFeedback | InertialFeedbackCoded)]
    first_state = next(k for k, r in enumerate(results) if r.state is not None)
    assert fbs and fbs[0].timestamp_ns == items[first_state].obs.timestamp_ns
    assert len(fbs) < len(results) - first_state  # thresholds / period, not every frame
    assert decode_feedback(fbs[0]).reset and len(decode_feedback(fbs[0]).track_numbers) > 0
    for fb in fbs:
        c = decode_feedback(fb)
        frame = next(i for i in items if i.obs.timestamp_ns == fb.timestamp_ns)
        assert np.isin(c.track_numbers, frame.obs.track_ids).all()
        assert np.isin(c.forget, frame.obs.track_ids).all()
    assert session.feedback_sent == len(fbs)
    timed = session.codec_timer.snapshot()[f"encode.{type(fbs[0]).__name__}"]
    assert timed["messages"] == len(fbs)


def test_coded_feedback_gives_the_robot_the_raw_landmarks_in_deltas(run) -> None:
    """The same results through a RAW and a CODED sender: same messages due, and the robot's
    set rebuilt from the coded deltas holds the raw set's tracks, each point on the ray of
    its keypoint (the VIO point's reprojection residual is not sent), depth to 0.25 %, at
    most ``point_resend_m`` (2 cm) behind the VIO."""
    seq, _, _, items, results, _, _ = run
    raw = FeedbackSender(FeedbackPolicy(), WireFormat.RAW)
    coded = FeedbackSender(FeedbackPolicy(), WireFormat.CODED, camera=seq.camera)
    view: dict[int, np.ndarray] = {}
    raw_bytes = coded_bytes = n = 0
    errs = []
    for item, res in zip(items, results, strict=True):
        if res.state is None:
            continue
        frame = Anchors(item.obs.track_ids, item.obs.keypoints_px)
        args = (res.frame_index, res.state, res.live_track_ids, res.live_p_world)
        r = raw.on_state(*args, item.obs.track_ids)
        c = coded.on_state(*args, item.obs.track_ids, frame)
        assert (r is None) == (c is None)
        if r is None:
            continue
        full, delta = decode_feedback(r), decode_feedback(c, seq.camera, frame)
        raw_bytes += len(encode_payload(r))
        coded_bytes += len(encode_payload(c))
        n += 1
        if delta.reset:
            view = {}
        view.update(zip(delta.track_numbers.tolist(), delta.p_world, strict=True))
        for k in delta.forget.tolist():
            del view[k]
        tracked = set(item.obs.track_ids.tolist())
        view = {k: p for k, p in view.items() if k in tracked}  # the robot drops ended tracks
        assert sorted(view) == sorted(full.track_numbers.tolist())
        got = np.array([view[k] for k in full.track_numbers.tolist()]).reshape(-1, 3)
        errs.append(np.linalg.norm(got - full.p_world, axis=1))
        assert np.abs(delta.T_world_body - full.T_world_body).max() < 1e-5
    assert n > 3 and coded_bytes < raw_bytes / 20, (n, raw_bytes, coded_bytes)
    # the robot's copy lies on the ray of the track's keypoint: the VIO points' reprojection
    # residuals (large for a few just after initialisation) are not in it, hence the tail
    err = np.concatenate(errs)
    assert np.median(err) < 0.02 and np.percentile(err, 90) < 0.05


def test_keyframe_uplink_is_standalone_and_consistent(run) -> None:
    _, vocab, session, _, _, _, cloud_msgs = run
    kfs = [m for m in cloud_msgs if isinstance(m, KeyframeUpdate) and m.features]
    assert len(kfs) == session.vio_keyframes > 3
    seen_points: set[int] = set()
    for m in cloud_msgs:
        if isinstance(m, MapPointUpdate):
            seen_points |= set(unpack_array(m.ids, "<i8").tolist())
    for m in kfs:
        feats = decode_standalone_keyframe(vocab, m.features, session.codec)
        pids = unpack_array(m.map_point_ids, "<i8")
        assert len(pids) == len(feats)
        assert set(pids[pids >= 0].tolist()) <= seen_points  # points were uplinked
        imu = unpack_array(m.imu, "<f8", (7,))
        if m.previous_keyframe_id >= 0:
            assert len(imu) > 0 and imu[-1, 0] <= m.timestamp_ns * 1e-9 + 1e-9


def test_cloud_pose_correction_moves_the_tracking_state(run) -> None:
    _, _, _, _, results, _, cloud_msgs = run
    before, after = results[-2], results[-1]
    assert after.corrections_applied > 0
    dx = after.state.T_world_body[0, 3] - before.state.T_world_body[0, 3]
    assert 0.7 < dx < 1.3  # 1 m correction plus one frame of motion
    moved = [m for m in cloud_msgs if isinstance(m, KeyframeUpdate) and not m.features]
    assert moved  # corrected keyframes go back up as pose-only updates


def test_the_clouds_uplink_decoder_accepts_every_message(run) -> None:
    """Contract check against the cloud's own decoders (services.cloud.fusion.uplink)."""
    from common.links.edge_cloud import CullEvent
    from services.cloud.fusion.uplink import (
        decode_cull_event,
        decode_keyframe_update,
        decode_map_point_update,
    )

    _, vocab, session, _, _, _, cloud_msgs = run
    n = 0
    for m in cloud_msgs:
        if isinstance(m, KeyframeUpdate):
            kf = decode_keyframe_update(m, 0, vocab, session.codec)
            assert (kf.keyframe is None) == (not m.features)
            n += 1
        elif isinstance(m, MapPointUpdate):
            assert decode_map_point_update(m, 0)
        elif isinstance(m, CullEvent):
            decode_cull_event(m)
    assert n > 0


def test_map_points_are_resent_only_when_moved_or_reobserved() -> None:
    from common.data.synth import EUROC_CAM0
    from services.edge.vio.types import MapPointBatch, MapPointSnapshot, MapUpdate

    session = RobotSession("r", EUROC_CAM0, Vocabulary.load(), RAW)

    def point(pid: int, x: float, n_obs: int) -> MapPointSnapshot:
        return MapPointSnapshot(
            pid, 0, np.array([x, 0.0, 1.0]), np.arange(n_obs), np.zeros(n_obs, np.int64)
        )

    def sent_ids(*points: MapPointSnapshot) -> list[int]:
        msgs = session._uplink(MapUpdate(0, True, (), MapPointBatch.of(points), ()))
        ups = [m for m in msgs if isinstance(m, MapPointUpdate)]
        return [int(i) for m in ups for i in unpack_array(m.ids, "<i8")]

    assert sent_ids(point(1, 0.0, 2), point(2, 0.0, 2)) == [1, 2]
    # a BA nudge of 1 mm: nothing to send; 5 cm or a new observation: resend that point
    assert sent_ids(point(1, 0.001, 2), point(2, 0.001, 2)) == []
    assert sent_ids(point(1, 0.05, 2), point(2, 0.001, 3)) == [1, 2]


@pytest.mark.slow
def test_coded_feedback_keeps_its_points_when_the_vio_runs_far_behind() -> None:
    """Every frame decoded before the VIO sees the first (an edge far behind its robots, as
    when the queue fills): the feedback still finds each result's frame and sends points."""
    vocab = Vocabulary.load()
    seq = simulate(SimConfig(duration_s=8.0, seed=5))
    session = RobotSession("r", seq.camera, vocab)  # the coded wire
    items = [session.decode(msg) for msg in code_sequence(seq, vocab)]
    runner = VioRunner(WorkerSpec("r", seq.camera, seq.imu))
    fbs = []
    for item in items:
        fbs += [m for m in session.on_result(runner.step(item)).robot if type(m) is not FramePose]
    assert fbs and all(isinstance(m, InertialFeedbackCoded) for m in fbs)
    assert fbs[0].reset and fbs[0].landmarks, "the first feedback carries no points"
    with_points = sum(bool(m.landmarks) for m in fbs)
    assert with_points >= len(fbs) // 2, (with_points, len(fbs))


def test_a_restarted_robot_stream_starts_a_new_vio_map_without_a_failure() -> None:
    """A robot whose process was restarted (a swarm task killed and started again) sends its
    frame 0 again: the edge decodes it with fresh decoders and the VIO starts the next
    generation (a new map, new map ids) instead of failing on a timestamp that goes back."""
    from services.edge.worker import MAP_ID_STRIDE

    vocab = Vocabulary.load()
    seq = simulate(SimConfig(duration_s=3.0, seed=5))
    frames = code_sequence(seq, vocab)[:40]
    session = RobotSession("r", seq.camera, vocab)
    runner = VioRunner(WorkerSpec("r", seq.camera, seq.imu))
    first = [runner.step(session.decode(m)) for m in frames]
    held = len(session.imu_uplink.window(None, None, (0, 999), frames[-1].timestamp_ns, 0)[0])
    items = [session.decode(m) for m in frames[:1]]  # the same sequence from its start
    # its clock went back: only the new stream's IMU is held for its keyframes
    again = session.imu_uplink.window(None, None, (0, 1000), frames[-1].timestamp_ns, 0)[0]
    assert 0 < len(again) < held and np.all(np.diff(again) > 0)
    items += [session.decode(m) for m in frames[1:]]
    assert [item.new_stream for item in items] == [True] + [False] * (len(items) - 1)
    second = [runner.step(item) for item in items]
    assert not [r.failed for r in first + second if r.failed]
    assert runner.generation == 1
    first_maps = {r.result.map_id for r in first if r.result is not None}
    second_maps = {r.result.map_id for r in second if r.result is not None}
    assert first_maps and max(first_maps) < MAP_ID_STRIDE, first_maps
    assert second_maps and min(second_maps) >= MAP_ID_STRIDE, second_maps


def test_a_frame_that_fails_to_decode_leaves_the_decoders_as_they_were() -> None:
    """All or nothing: frame 1 with a corrupted feature part (its IMU part decodes first) is
    refused, and the intact frame 1 then decodes, as do the frames after it."""
    from common.codec.errors import CodecError

    vocab = Vocabulary.load()
    seq = simulate(SimConfig(duration_s=1.0, seed=5))
    frames = code_sequence(seq, vocab)
    session = RobotSession("r", seq.camera, vocab, RAW)
    session.decode(frames[0])
    bad = bytearray(frames[1].features)
    bad[len(bad) // 2] ^= 0xFF
    with pytest.raises(CodecError):
        session.decode(dataclasses.replace(frames[1], features=bytes(bad)))
    with pytest.raises(CodecError):  # a frame-0 copy that fails does not reset the stream
        session.decode(dataclasses.replace(frames[0], imu=frames[0].imu[:-1]))
    for msg in frames[1:6]:
        item = session.decode(msg)
        assert item.obs.timestamp_ns == msg.timestamp_ns
    assert session.frames == 6


def test_keyframe_imu_windows_neither_skip_nor_repeat_samples_when_the_offset_moves() -> None:
    """Keyframes at 0.5 s steps, the offset found late (0 -> 15 ms) and then refined down
    (-> 14 ms): each keyframe's IMU starts where its predecessor's ended, so the uplinked
    samples are every sample up to the last keyframe's time plus the offset, once each."""
    uplink = ImuUplink(history_s=65.0)
    t = np.arange(0, 3_000_000_000, 5_000_000, dtype=np.int64)  # 200 Hz IMU clock
    uplink.add(t, np.zeros((len(t), 3)), np.ones((len(t), 3)))
    sent = []
    prev, prev_t = None, None
    for k, offset_ms in enumerate([0.0, 0.0, 15.0, 15.0, 14.0]):
        t_kf = 500_000_000 * (k + 1)
        stamps, values = uplink.window(prev, prev_t, (0, k), t_kf, int(offset_ms * 1e6))
        assert values.shape == (len(stamps), 6) and np.all(values[:, 3:] == 1.0)
        sent.append(stamps)
        prev, prev_t = (0, k), t_kf
    everything = np.concatenate(sent)
    assert np.array_equal(everything, t[t <= 2_500_000_000 + 14_000_000])
    assert sent[2][0] == 1_000_000_000 + 5_000_000  # right after keyframe 1's end, no 15 ms gap
    assert sent[4][-1] == 2_510_000_000  # the last sample at or before 2.5 s + 14 ms
    # A keyframe whose predecessor's window is unknown (a restart) starts at its time.
    stamps, _ = uplink.window((0, 99), 2_000_000_000, (0, 100), 2_100_000_000, 0)
    assert stamps[0] == 2_005_000_000 and stamps[-1] == 2_100_000_000


def test_every_processed_frame_sends_the_robot_its_pose(run) -> None:
    """One FramePose per frame, in frame order: a metric pose (the VIO's) once it tracks,
    none while it initialises."""
    _, _, _, _, results, robot_msgs, _ = run
    poses = [m for m in robot_msgs if isinstance(m, FramePose)]
    assert [p.timestamp_ns for p in poses] == [r.result.timestamp_ns for r in results]
    for p, r in zip(poses, results, strict=True):
        assert pose_status(p) == r.result.status.value and p.map_id == r.result.map_id
        T = decode_pose(p)
        if r.result.status.value == "tracking":
            assert T is not None and np.allclose(T, r.result.T_world_body, atol=1e-5)
        else:
            assert T is None
    assert sum(pose_status(p) == "tracking" for p in poses) >= len(poses) // 3  # VI init ~2 s of 5
