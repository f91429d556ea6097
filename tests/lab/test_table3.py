"""The Table 3 replay on a tiny recording made from the cloud's simulation."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from common.errors import RecslamError
from lab.replay_schedule import ReplayDivergedError
from lab.table3 import replay, service_config
from services.cloud.app import open_app
from services.cloud.core_actions import SolveRequest, SolveResult, solve
from services.cloud.service_config import (
    MbpScheduleConfig,
    OptimizationScheduleConfig,
    OverloadConfig,
    ProcessConfig,
    StoreConfig,
)
from services.cloud.store.recording import (
    Step,
    has_schedule,
    read_recording,
    read_schedule,
)
from sim.cloud import (
    circle_poses,
    default_camera,
    encode_session,
    make_session,
    make_world,
    yaw_T,
)


@pytest.mark.slow
def test_replay_with_and_without_mbp(recording, vocab, tmp_path):
    results = {}
    for mbp in (False, True):
        cfg = dataclasses.replace(
            service_config(mbp),
            schedule=OptimizationScheduleConfig(every_keyframes=5),
            mbp=MbpScheduleConfig(every_keyframes=10, keep_recent=2, settle_keyframes=2),
        )
        results[mbp] = replay(
            read_recording(recording), default_camera(), vocab, cfg, tmp_path / str(mbp), "x"
        )
    off, on = results[False], results[True]
    assert off.keyframes_received == on.keyframes_received == 42
    assert off.keyframes == 42 and off.mbp_passes == 0 and off.optimizations > 0
    assert on.mbp_passes > 0 and on.keyframes < off.keyframes
    assert on.map_points <= off.map_points
    assert set(on.trajectories) == {"r0", "r1"}
    assert on.backbone["keyframes"] == on.keyframes
    assert off.backbone["kept_by_one_more_pass"] <= off.keyframes
    # Every new keyframe was queried against what the cloud held; the second robot's map
    # was merged into the first through an accepted detection.
    assert len(on.queries) == 42 and on.queries[0].held_keys.size == 0
    assert off.merges >= 1 and off.maps == [0]
    assert any(d.kind == "merge" for d in off.detections)
    merge = next(d for d in off.detections if d.kind == "merge")
    assert off.info[merge.query_key].robot == "r1" and off.info[merge.match_key].robot == "r0"


def test_record_options_parse_and_reach_the_cloud_command(tmp_path):
    import argparse

    from lab.run.orchestration import Job, JobConfig
    from recslam.commands import cloud, demo, experiment

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    for mod in (cloud, demo, experiment):
        mod.register(sub)
    args = parser.parse_args(["experiment", "table3", "--recording", "r.rec", "--data", "d"])
    assert args.func is experiment.run_table3 and str(args.recording) == "r.rec"
    args = parser.parse_args(["cloud", "--state-dir", "s", "--record", "u.rec"])
    assert str(args.record) == "u.rec"
    assert parser.parse_args(["cloud", "--state-dir", "s"]).record is None
    assert str(parser.parse_args(["demo", "--record-uplink", "u.rec"]).record_uplink) == "u.rec"
    (tmp_path / "data" / "robot0" / "mav0").mkdir(parents=True)
    rec = tmp_path / "u.rec"
    job = Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "run", record_uplink=rec))
    argv = job.cloud_argv()
    assert argv[argv.index("--record") + 1] == str(rec) and argv.index("cloud") < argv.index(
        "--record"
    )
    plain = Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "run2"))
    assert "--record" not in plain.cloud_argv()


@pytest.mark.slow
def test_replay_of_a_recording_with_each_robots_calibration(tmp_path, vocab):
    """A recording the cloud service writes today holds each robot's ``AgentSensors`` ahead
    of its keyframes; the replay uses them: r1, seen through a 640x480 camera of its own
    (another size, intrinsics and mounting than the fallback camera), decodes and merges.
    It holds the service's schedule too: replayed through it, the core ends where the service
    ended (same solves, same poses), its load shedding included (a low ``OverloadConfig.busy``:
    the worker applying messages back to back is overloaded)."""
    import asyncio

    from common.calibration import EUROC_IMU, CameraCalibration
    from common.codec import CodecConfig
    from common.geometry import make_T
    from common.links.edge_cloud import AgentSensors, agent_sensors_message
    from common.links.sensors import Sensors
    from common.protocol import SessionConfig
    from common.transport import Delivery
    from services.cloud.server import CloudServer
    from sim.cloud import R_BODY_CAM

    mount = make_T(R_BODY_CAM, np.array([0.12, -0.03, 0.02]))
    cam_b = CameraCalibration(640, 480, 330.0, 331.5, 318.2, 243.7, (-0.21, 0.04, 5e-4, 0.0), mount)
    world = make_world(51)
    r0 = make_session(world, default_camera(), 0, circle_poses(24, turns=1.0), np.eye(4), seed=1)
    T_r1 = yaw_T(np.radians(-60.0), np.array([-1.5, 0.5, 0.0]))
    r1 = make_session(world, cam_b, 1, circle_poses(12, turns=0.5, phase=2.0), T_r1, seed=2)
    codec_b = CodecConfig(image_width=640, image_height=480)
    msgs = [agent_sensors_message("r0", Sensors(default_camera(), EUROC_IMU))]
    msgs += [m for g in encode_session(*r0, "r0", vocab, 7) for m in g]
    msgs += [agent_sensors_message("r1", Sensors(cam_b, EUROC_IMU))]
    msgs += [m for g in encode_session(*r1, "r1", vocab, 7, codec=codec_b) for m in g]
    rec = tmp_path / "uplink.rec"
    cfg = dataclasses.replace(
        service_config(False),
        store=StoreConfig(output_every_s=0),
        processes=ProcessConfig(optimizer_process=False),
        schedule=OptimizationScheduleConfig(debounce_s=0.05),
        overload=OverloadConfig(busy=0.2, clear=0.01),
    )
    stats = []

    async def record() -> None:
        session = SessionConfig("cloud", "cloud", b"0123456789abcdef0123")
        cloud = CloudServer(session, tmp_path / "state", default_camera(), vocab, cfg, record=rec)
        await cloud.start("127.0.0.1", 0)
        try:
            for seq, m in enumerate(msgs, 1):
                await cloud._on_message(Delivery("edge", "edge", m, seq, b"stream"))
                if seq % 7 == 0:
                    await asyncio.sleep(0.3)  # the timer's rounds run between messages
        finally:
            await cloud.stop(write_output=False)
            stats.append(await cloud.stats())

    asyncio.run(record())
    assert has_schedule(rec)
    recorded = list(read_recording(rec))
    assert sum(isinstance(r.message, AgentSensors) for r in recorded) == 2
    assert all(r.t_core is not None for r in recorded)
    res = replay(recorded, default_camera(), vocab, service_config(False), tmp_path / "replay")
    assert res.keyframes_received == 36 and res.merges >= 1 and res.maps == [0]
    assert set(res.trajectories) == {"r0", "r1"}

    steps = [e for e in read_schedule(rec) if isinstance(e, Step)]
    names = [s.name for s in steps]
    assert names.count("timer") >= 2 and names[-1] in ("solved", "shutdown")
    assert names.count("request") == names.count("solved") + names.count("failed")
    assert names.count("load") >= 1 and stats[0].overload["overloads"] >= 1
    same = replay(
        read_schedule(rec),
        default_camera(),
        vocab,
        cfg,
        tmp_path / "r2",
        "x",
        True,
        schedule="recorded",
    )
    (live,) = stats
    assert (same.optimizations, same.merges, same.loops) == (
        live.optimizations,
        live.merges,
        live.loops,
    )
    service = open_app(tmp_path / "state", default_camera(), vocab, cfg)
    try:
        live_trajs, _ = service.trajectories()
    finally:
        service.close()
    for name, traj in live_trajs.items():
        np.testing.assert_allclose(
            same.trajectories[name].T_world_body, traj.T_world_body, atol=1e-9
        )

    # A configuration that schedules otherwise does not fit the recorded steps.
    other = dataclasses.replace(
        cfg, schedule=OptimizationScheduleConfig(every_keyframes=1000, debounce_s=1e6)
    )
    with pytest.raises(ReplayDivergedError, match="schedules otherwise"):
        replay(
            read_schedule(rec), default_camera(), vocab, other, tmp_path / "r3", schedule="recorded"
        )


@pytest.mark.slow
def test_solves_that_take_time_let_records_arrive_before_their_result(recording, vocab, tmp_path):
    """With solve latency the replay handles the records received while a solve is out
    before its result applies, as the service does: one round spans many records, so fewer
    pose graphs run than when solves take no time; nothing is lost either way."""
    cfg = dataclasses.replace(
        service_config(False),
        schedule=OptimizationScheduleConfig(every_keyframes=2, debounce_s=0.1),
    )

    def slow_solve(request: SolveRequest) -> SolveResult:
        t0 = time.perf_counter()
        result = solve(request)
        while time.perf_counter() - t0 < 0.02:  # at least 20 ms here
            pass
        return result

    runs = {}
    for scale in (0.0, 300.0):  # 300 x >= 20 ms: a solve spans >= 6 s, 30 records
        runs[scale] = replay(
            read_recording(recording),
            default_camera(),
            vocab,
            cfg,
            tmp_path / str(scale),
            "x",
            solve_fn=slow_solve,
            latency_scale=scale,
        )
    instant, slow = runs[0.0], runs[300.0]
    assert instant.keyframes_received == slow.keyframes_received == 42
    assert instant.failed == slow.failed == 0
    assert instant.maps == slow.maps == [0]
    assert 0 < slow.optimizations < instant.optimizations / 2
    with pytest.raises(RecslamError, match="latency_scale"):
        replay(
            read_recording(recording),
            default_camera(),
            vocab,
            cfg,
            tmp_path / "n",
            "x",
            latency_scale=-1.0,
        )
