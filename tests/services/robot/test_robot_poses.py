"""The robot's own pose back from the edge: the FramePose wire form, the latency bookkeeping,
the TUM file, and a robot playing a rendered sequence through a real edge (every frame's pose
back, the tracked ones close to the ground truth)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest

from common.data.euroc import EurocSequence
from common.data.synth import SynthConfig, generate_dataset
from common.evaluation import AteConfig, compute_ate, load_groundtruth, read_tum
from common.geometry import make_T, so3_exp
from common.links.robot_edge import (
    FramePose,
    MapPlacement,
    decode_map_placement,
    decode_pose,
    encode_pose,
    frame_pose_message,
    pose_status,
)
from common.protocol import SessionConfig
from common.protocol.errors import RemoteProtocolError
from common.protocol.messages import decode_payload, encode_payload
from common.transport import TransportConfig
from common.vocabulary import Vocabulary
from services.cloud.server import CloudServer
from services.cloud.service_config import CloudServiceConfig, ProcessConfig, StoreConfig
from services.edge.app import EdgeConfig
from services.edge.server import EdgeServer, EdgeServiceConfig
from services.robot.poses import PoseTrack, tum_line
from services.robot.server import RobotService
from services.robot.service_config import Rate, RobotServiceConfig

SECRET = b"robot-poses-test-secret-0123456"
FAST = TransportConfig(reconnect_initial_delay=0.02, reconnect_max_delay=0.3)

pytestmark = pytest.mark.timeout(400)


def test_a_frame_pose_round_trips_at_float32_precision_and_bad_ones_are_named() -> None:
    T = make_T(so3_exp(np.array([0.3, -1.2, 2.0])), np.array([12.5, -3.25, 1.0]))
    msg = frame_pose_message(1_600_000_000_050_000_000, 3, "tracking", encode_pose(T))
    back = decode_payload(FramePose.TYPE_ID, encode_payload(msg))
    assert isinstance(back, FramePose) and len(back.pose) == 28
    T_back = decode_pose(back)
    assert T_back is not None
    assert np.abs(T_back[:3, 3] - T[:3, 3]).max() < 2e-6  # float32 within 16 m
    assert np.abs(T_back[:3, :3] - T[:3, :3]).max() < 1e-6
    assert decode_pose(frame_pose_message(1, 0, "initializing", b"")) is None
    assert pose_status(back) == "tracking" and len(encode_payload(msg)) <= 48
    with pytest.raises(ValueError, match="flying"):
        frame_pose_message(1, 0, "flying", b"")
    with pytest.raises(RemoteProtocolError, match="status 3 is not an index"):
        decode_pose(FramePose(1, 0, 3, b""))
    with pytest.raises(RemoteProtocolError, match="27 bytes"):
        decode_pose(frame_pose_message(1, 0, "tracking", bytes(27)))
    with pytest.raises(ValueError, match="finite"):
        encode_pose(np.full((4, 4), np.nan))


def test_pose_track_measures_capture_to_pose_latency_and_writes_tum() -> None:
    track = PoseTrack(keep=3)
    T = make_T(np.eye(3), np.array([1.0, 2.0, 3.0]))
    for k in range(5):  # frames taken 0.05 s apart; only the newest 3 are remembered
        track.captured(1_000_000_000 + 50_000_000 * k, 10.0 + 0.05 * k)
    assert track.pending == 3
    first = track.on_pose(frame_pose_message(1_000_000_000, 0, "tracking", encode_pose(T)), 11.0)
    assert first is not None and first.latency_s is None  # forgotten: no latency
    late = track.on_pose(frame_pose_message(1_150_000_000, 0, "tracking", encode_pose(T)), 10.4)
    assert late is not None and late.latency_s == pytest.approx(0.25)
    lost = track.on_pose(frame_pose_message(1_200_000_000, 1, "lost", b""), 10.5)
    assert lost is not None and lost.T_map_body is None and lost.latency_s == pytest.approx(0.3)
    assert track.on_pose(frame_pose_message(1_100_000_000, 0, "tracking", b"\x00"), 10.6) is None
    s = track.summary()
    assert (s["received"], s["with_pose"], s["rejected"]) == (3, 2, 1)
    assert s["median_s"] == pytest.approx(0.275) and s["max_s"] == pytest.approx(0.3)
    assert track.pending == 1  # 1.1 s: its message was malformed
    assert (
        tum_line(late) == "1.150000000 1.000000 2.000000 3.000000 0.000000000 0.000000000 "
        "0.000000000 1.000000000"
    )
    assert tum_line(lost) is None


def test_a_placed_map_gives_global_poses_and_a_bad_placement_is_refused() -> None:
    track = PoseTrack()
    T_map_body = make_T(so3_exp(np.array([0.0, 0.0, 0.4])), np.array([1.0, 0.0, 0.5]))
    before = track.on_pose(frame_pose_message(1_000, 7, "tracking", encode_pose(T_map_body)), 1.0)
    assert before is not None and before.T_global_body is None and tum_line(before, True) is None
    T_global_map = make_T(so3_exp(np.array([0.0, 0.0, -1.1])), np.array([-4.0, 2.5, 0.0]))
    place = MapPlacement(7, 2, encode_pose(T_global_map))
    back = decode_payload(MapPlacement.TYPE_ID, encode_payload(place))
    assert isinstance(back, MapPlacement) and track.on_placement(back)
    after = track.on_pose(frame_pose_message(2_000, 7, "tracking", encode_pose(T_map_body)), 2.0)
    assert after is not None and after.global_map == 2 and after.T_global_body is not None
    np.testing.assert_allclose(after.T_global_body, T_global_map @ T_map_body, atol=1e-5)
    assert after.T_map_body is not None
    np.testing.assert_allclose(after.T_map_body, T_map_body, atol=1e-6)  # own frame unchanged
    other = track.on_pose(frame_pose_message(3_000, 8, "tracking", encode_pose(T_map_body)), 3.0)
    assert other is not None and other.T_global_body is None  # map 8 was never placed
    assert not track.on_placement(MapPlacement(8, 2, bytes(20)))
    with pytest.raises(RemoteProtocolError, match=r"MapPlacement\.pose has 20 bytes"):
        decode_map_placement(MapPlacement(8, 2, bytes(20)))
    s = track.summary()
    assert (s["received"], s["with_global"], s["rejected"]) == (3, 1, 1)


@pytest.mark.slow
def test_every_frame_gets_its_pose_back_and_the_tracked_ones_follow_the_truth(
    tmp_path: Path,
) -> None:
    """A 6 s rendered flight through a real edge (VIO in a thread) and the real cloud: the
    robot waits for the poses of the frames still in flight at the end, so every frame's pose
    comes back; the tracked ones (after VI initialisation) are metric and within a few cm of
    the truth; the cloud writes (and measures) the trajectory of every frame."""
    data = tmp_path / "data"
    generate_dataset(
        data, SynthConfig(robots=1, seconds=6.0, seed=3, contact_sheet=False, progress=False)
    )
    seq_dir = data / "robot0"
    pose_file = tmp_path / "poses.tum"
    global_file = tmp_path / "poses_global.tum"
    stats_file = tmp_path / "robot.json"
    results = tmp_path / "results"

    async def main():
        cloud = CloudServer(
            SessionConfig("cloud", "cloud", SECRET, heartbeat_interval=0.2, idle_timeout=2.0),
            tmp_path / "cloud",
            None,
            Vocabulary.load(),
            CloudServiceConfig(
                processes=ProcessConfig(optimizer_process=False),
                store=StoreConfig(output_every_s=0),
            ),
            results_dir=results,
            groundtruth=data,
            transport=TransportConfig(accept_roles=("edge",)),
        )
        _, cport = await cloud.start()
        service = EdgeServiceConfig(
            agent_id="edge-1",
            cloud_host="127.0.0.1",
            cloud_port=cport,
            heartbeat_interval_s=0.2,
            idle_timeout_s=2.0,
        )
        edge = EdgeServer(SECRET, Vocabulary.load(), EdgeConfig(worker="thread"), service)
        _, port = await edge.start()
        try:
            robot = RobotService(
                RobotServiceConfig(
                    dataset=seq_dir,
                    edge_host="127.0.0.1",
                    edge_port=port,
                    agent_id="robot0",
                    secret=SECRET,
                    rate=Rate.MAX,
                    heartbeat_interval_s=0.2,
                    idle_timeout_s=2.0,
                    pose_out=pose_file,
                    global_pose_out=global_file,
                    pose_wait_s=120.0,
                    stats_out=stats_file,
                ),
                transport=FAST,
            )
            result = await robot.run()
            await asyncio.wait_for(edge.flush(), 120)
            counters = edge.stats()
        finally:
            await edge.stop()
            await cloud.stop()
        return result, robot, counters

    result, robot, counters = asyncio.run(main())
    n = len(EurocSequence(seq_dir))
    assert result.frames == n and result.flushed
    # One pose per frame, every one back (the robot waited for the last ones).
    assert result.poses["received"] == n and robot.poses.pending == 0, result.poses
    assert 0 < result.poses["with_pose"] <= n
    assert 0 < result.poses["median_s"] <= result.poses["p95_s"] <= result.poses["max_s"]
    assert result.counters["rx"]["by_type"]["FramePose"]["messages"] == n
    assert counters["robots"]["robot0"]["frames_processed"] == n
    # The TUM file: the metric poses, in time order, near the ground truth.
    rows = np.loadtxt(pose_file)
    assert rows.shape == (result.poses["with_pose"], 8)
    assert np.all(np.diff(rows[:, 0]) > 0)
    refs, _ = load_groundtruth(["robot0"], data)
    err = compute_ate(refs["robot0"], read_tum(pose_file), AteConfig())
    assert err.stats.rmse < 0.05, err.stats
    assert stats_file.is_file() and '"received":' in stats_file.read_text()
    # The cloud's trajectory of every frame (the edge's frame poses on its final keyframes):
    # many more poses than keyframes, as accurate.
    per_frame = read_tum(results / "frames" / "trajectories" / "robot0.tum")
    keyframes = read_tum(results / "trajectories" / "robot0.tum")
    assert len(per_frame) >= 0.8 * result.poses["with_pose"] > 3 * len(keyframes)
    report = json.loads((results / "frames" / "eval" / "ate.json").read_text())
    assert report["agents"]["robot0"]["individual"]["stats_m"]["rmse"] < 0.05
