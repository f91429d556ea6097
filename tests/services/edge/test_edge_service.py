"""The edge service over real TCP on loopback: real robot in, real (or stub) cloud out."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from common.codec.imu import ImuDecoder
from common.data.euroc import read_camera_yaml
from common.links.edge_cloud import (
    AgentSensors,
    AgentStatus,
    KeyframeUpdate,
    KeyframeUpdateCoded,
    MapPointUpdate,
    MapPointUpdateCoded,
    read_agent_sensors,
)
from common.links.robot_edge import InertialFeedbackCoded, decode_feedback
from common.protocol import SessionConfig
from common.transport import Delivery, Server, TransportConfig
from common.vocabulary import Vocabulary
from services.edge.app import EdgeConfig
from services.edge.server import EdgeServer, EdgeServiceConfig
from services.edge.worker import (
    MAP_ID_STRIDE,
    VIO_COUNTS,
    ProcessWorker,
    WorkerSpec,
    WorkItem,
    WorkResult,
)
from sim.robot import code_sequence, play, sim_sensors
from sim.vio import SimConfig, simulate

SECRET = b"edge-test-secret-0123456789"
FAST = TransportConfig(reconnect_initial_delay=0.02, reconnect_max_delay=0.3)
ROOT = Path(__file__).resolve().parents[3]

pytestmark = pytest.mark.timeout(240)


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def sim_frames(vocab):
    """A 7 s simulated robot (enough motion for VI initialisation), coded as RobotFrames."""
    seq = simulate(SimConfig(duration_s=7.0, seed=1))
    return seq, code_sequence(seq, vocab)


class CloudStub:
    """The cloud's side of the uplink, recording every message (a common.transport.Server)."""

    def __init__(self) -> None:
        self.messages: list = []
        self.server: Server | None = None

    async def __call__(self, d: Delivery) -> None:
        self.messages.append(d.message)

    async def start(self, port: int = 0) -> int:
        cfg = SessionConfig("cloud", "cloud", SECRET, heartbeat_interval=0.2, idle_timeout=2.0)
        self.server = Server(cfg, self, transport=FAST)
        return (await self.server.start("127.0.0.1", port))[1]

    def of(self, kind: type, agent: str | None = None) -> list:
        return [
            m
            for m in self.messages
            if isinstance(m, kind) and (agent is None or m.agent_id == agent)
        ]


def _edge(vocab, cloud_port: int, worker: str, **kw) -> EdgeServer:
    service = EdgeServiceConfig(
        agent_id="edge-1",
        cloud_host="127.0.0.1",
        cloud_port=cloud_port,
        heartbeat_interval_s=0.2,
        idle_timeout_s=2.0,
    )
    return EdgeServer(
        SECRET,
        vocab,
        EdgeConfig(worker=worker),
        service,
        transport=TransportConfig(accept_roles=("robot",)),
        **kw,
    )


# ------------------------------------------------------------------ EuRoC excerpt, real cloud
@pytest.mark.slow
def test_excerpt_robot_to_edge_to_real_cloud(tmp_path, vocab, euroc_micro) -> None:
    """The image-based robot plays the excerpt into the edge (VIO in a worker process), which
    reports to the real cloud service: every frame decoded, status received, no VIO failure,
    and the VIO says why it has not initialised (too little motion)."""
    from services.cloud.server import CloudServer
    from services.cloud.service_config import CloudServiceConfig, ProcessConfig, StoreConfig
    from services.robot.server import RobotService
    from services.robot.service_config import Rate, RobotServiceConfig

    camera = read_camera_yaml(euroc_micro / "mav0/cam0/sensor.yaml")

    async def main():
        cloud = CloudServer(
            SessionConfig("cloud", "cloud", SECRET, heartbeat_interval=0.2, idle_timeout=2.0),
            tmp_path / "cloud",
            camera,
            vocab,
            CloudServiceConfig(
                processes=ProcessConfig(optimizer_process=False),
                store=StoreConfig(output_every_s=0),
            ),
            transport=TransportConfig(accept_roles=("edge",)),
        )
        _, cport = await cloud.start()
        edge = _edge(vocab, cport, "process")
        _, port = await edge.start()
        try:
            robot = RobotService(
                RobotServiceConfig(
                    dataset=euroc_micro,
                    edge_host="127.0.0.1",
                    edge_port=port,
                    agent_id="robot-1",
                    secret=SECRET,
                    rate=Rate.MAX,
                    heartbeat_interval_s=0.2,
                    idle_timeout_s=2.0,
                ),
                transport=FAST,
            )
            result = await robot.run()
            await asyncio.wait_for(edge.flush(), 60)
            stats = edge.stats()
            counters = cloud.transport.counters()
        finally:
            await edge.stop()
            await cloud.stop(write_output=False)
        return result, stats, counters

    result, stats, counters = asyncio.run(main())
    r = stats["robots"]["robot-1"]
    assert result.frames == 95 and result.flushed
    assert r["frames_decoded"] == r["frames_processed"] == 95
    assert r["expected_frames"] == 95 and r["finished"]
    assert r["failures"] == []
    assert r["state"] in ("initializing", "tracking")
    if r["state"] == "initializing":
        assert "parallax" in r["reason"] or "keyframe" in r["reason"], r["reason"]
    rx = counters["edge-1"]["rx"]["by_type"]
    assert rx["AgentStatus"]["messages"] >= 95 // 20 + 1  # periodic + the final "finished"
    assert stats["dropped_uplink"] == 0


# ------------------------------------------------------------------ containment
RAISE_AT, CRASH_AT = 25, 60


class _FaultyWorker(ProcessWorker):
    """A real VIO process that gets a frame out of time order at RAISE_AT (the VIO raises)
    and is SIGKILLed just before it would receive frame CRASH_AT (the process dies)."""

    def _roundtrip(self, item: WorkItem) -> WorkResult:
        if item.frame_index == RAISE_AT and item.obs is not None:
            item = dataclasses.replace(item, obs=dataclasses.replace(item.obs, timestamp_ns=0))
        if item.frame_index == CRASH_AT and self._proc is not None:
            os.kill(self._proc.pid, signal.SIGKILL)
            self._proc.join(10.0)
        return super()._roundtrip(item)


def _faulty_for(name: str):
    def make(spec: WorkerSpec, kind: str):
        assert kind == "process"
        return _FaultyWorker(spec) if spec.agent_id == name else ProcessWorker(spec)

    return make


@pytest.mark.slow
def test_failing_robot_vio_does_not_disturb_another(vocab, sim_frames) -> None:
    """Robot "bad" gets a VIO exception at frame 25 and its worker process dies at frame 60;
    each time it re-initialises (fresh VIO, new map id range, process respawned). Robot "good"
    on the same edge initialises, gets feedback with stream-numbered map points and uplinks
    keyframes, untouched."""
    seq, frames = sim_frames

    async def main():
        cloud = CloudStub()
        cport = await cloud.start()
        edge = _edge(vocab, cport, "process", worker_factory=_faulty_for("bad"))
        _, port = await edge.start()
        done = asyncio.Event()
        try:
            plays = [
                asyncio.create_task(
                    play(
                        frames,
                        "127.0.0.1",
                        port,
                        name,
                        SECRET,
                        sim_sensors(seq),
                        transport=FAST,
                        linger=done,
                    )
                )
                for name in ("good", "bad")
            ]
            while len(edge.app.robots) < 2 or not all(
                rb.ended.is_set() for rb in edge.app.robots.values()
            ):
                await asyncio.sleep(0.1)
            await asyncio.wait_for(edge.flush(), 60)
            done.set()
            good, bad = await asyncio.gather(*plays)
            stats = edge.stats()
        finally:
            await edge.stop()
            await cloud.server.close()
        return cloud, stats, good, bad

    cloud, stats, good, _ = asyncio.run(main())
    g, b = stats["robots"]["good"], stats["robots"]["bad"]
    assert g["failures"] == [] and g["frames_processed"] == len(frames)
    assert g["state"] == "tracking" and g["map_id"] == 0
    assert g["vio"] == dict.fromkeys(VIO_COUNTS, 0) and "frames_bridged" in g["vio"]
    assert len(b["failures"]) == 2, b["failures"]
    assert "frame 25" in b["failures"][0] and "timestamp 0 not after previous" in b["failures"][0]
    assert "frame 60: VIO process died (exit -9)" in b["failures"][1]
    assert b["frames_processed"] == len(frames)
    # Good robot: feedback after VI init, tracks named by stream numbers with map points.
    fbs = [decode_feedback(m) for m in good.feedback if isinstance(m, InertialFeedbackCoded)]
    assert fbs, "no InertialFeedbackCoded reached the good robot"
    assert fbs[0].reset
    held: set[int] = set()  # the robot's tracks with a point (before it drops ended ones)
    for c in fbs:
        held = (set() if c.reset else held - set(c.forget.tolist())) | set(c.track_numbers.tolist())
    last = fbs[-1]
    assert len(held) > 10
    assert np.allclose(last.gravity_world, [0, 0, -9.81], atol=1e-5)  # float32 on the wire
    assert np.linalg.norm(last.bias_gyro - np.array(SimConfig().bias_gyro)) < 5e-3
    # Uplink: keyframes with features and IMU, map points, status.
    first = cloud.of(KeyframeUpdateCoded, "good")
    assert len(first) == len({m.keyframe_id for m in first}) == g["keyframes_uplinked"] > 5
    assert all(len(ImuDecoder().decode(m.imu)) > 0 for m in first[1:])
    assert cloud.of(MapPointUpdateCoded, "good")
    assert not cloud.of(KeyframeUpdate, "good") and not cloud.of(MapPointUpdate, "good")
    statuses = cloud.of(AgentStatus, "good")
    assert statuses[-1].state == "finished" and statuses[-1].frames == len(frames)
    assert statuses[-1].link_counters["rx.RobotFrame"] > 0
    # Bad robot: nothing of its old map after the failure; any new map has a fresh id.
    assert all(
        m.map_id in (0,) or m.map_id >= MAP_ID_STRIDE for m in cloud.of(KeyframeUpdate, "bad")
    )
    assert not [
        m
        for m in cloud.of(KeyframeUpdate, "bad")
        if m.map_id == 0 and m.timestamp_ns > frames[25].timestamp_ns
    ]


# ------------------------------------------------------------------ restart without loss
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_edge(port: int, cloud_port: int, state: Path, log: Path) -> subprocess.Popen:
    env = dict(os.environ, RECSLAM_SECRET=SECRET.decode())
    cmd = [
        sys.executable,
        "-m",
        "services.edge",
        "--listen",
        f"127.0.0.1:{port}",
        "--cloud",
        f"127.0.0.1:{cloud_port}",
        "--state-dir",
        str(state),
        "--worker",
        "thread",
        "--agent-id",
        "edge-1",
    ]
    with log.open("ab") as out:
        return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)


@pytest.mark.slow
def test_edge_killed_and_restarted_loses_no_frame(tmp_path, vocab, sim_frames) -> None:
    """SIGKILL the edge process mid-stream, restart it on the same state directory: the
    journal replay plus the robot's replay give every frame exactly once, and the keyframes
    uplinked cover every keyframe id of the final map. The robot's sensors (its stream's
    first message, journaled) come back from the journal: the restarted edge builds the same
    VIO and sends the cloud the same calibration again."""
    seq, frames = sim_frames
    port = _free_port()
    log = tmp_path / "edge.log"

    async def main():
        cloud = CloudStub()
        cport = await cloud.start()
        proc = _start_edge(port, cport, tmp_path / "state", log)
        try:
            task = asyncio.create_task(
                play(
                    frames,
                    "127.0.0.1",
                    port,
                    "robot-1",
                    SECRET,
                    sim_sensors(seq),
                    rate_hz=20.0,
                    transport=FAST,
                )
            )
            while not any(m.frames >= 40 for m in cloud.of(AgentStatus)):
                assert proc.poll() is None, log.read_text()
                assert not task.done(), "robot finished before the kill"
                await asyncio.sleep(0.05)
            proc.send_signal(signal.SIGKILL)
            proc.wait(10)
            killed_at = max(m.frames for m in cloud.of(AgentStatus))
            proc = _start_edge(port, cport, tmp_path / "state", log)
            result = await asyncio.wait_for(task, 120)
            while not any(m.state == "finished" for m in cloud.of(AgentStatus)[-3:]):
                assert proc.poll() is None, log.read_text()
                await asyncio.sleep(0.1)
            await asyncio.sleep(0.5)
        finally:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            proc.wait(20)
            await cloud.server.close()
        return cloud, result, killed_at

    cloud, result, killed_at = asyncio.run(main())
    text = log.read_text()
    assert "Traceback" not in text, text[-3000:]
    replayed = [int(n) for n in re.findall(r"replayed (\d+) frames", text)]
    assert replayed[0] == 0 and replayed[-1] >= killed_at, replayed  # journal fast-forward
    assert result.frames == len(frames) and killed_at < len(frames)
    final = [m for m in cloud.of(AgentStatus) if m.state == "finished"][-1]
    assert final.frames == len(frames)  # journal replay + robot replay: each frame once
    kfs = cloud.of(KeyframeUpdateCoded, "robot-1")
    by_map: dict[int, set[int]] = {}
    prev_of: dict[tuple[int, int], int] = {}
    for m in kfs:
        by_map.setdefault(m.map_id, set()).add(m.keyframe_id)
        prev_of[(m.map_id, m.keyframe_id)] = m.previous_keyframe_id
    assert by_map, "no keyframes uplinked"
    for map_id, ids in by_map.items():
        # The VIO's own keyframes are not uplinked: the uplinked ones form one unbroken chain.
        chain = sorted(ids)
        assert prev_of[(map_id, chain[0])] == -1, (map_id, chain)
        for i in range(1, len(chain)):
            assert prev_of[(map_id, chain[i])] == chain[i - 1], (map_id, chain)
    # The restarted edge's re-run is a new map (the first run's maps are the cloud's): its
    # map ids are the second run's generations, and its chain is the final keyframe count.
    from services.edge.worker import GENERATIONS_PER_RUN, MAP_ID_STRIDE

    rerun = {m: ids for m, ids in by_map.items() if m >= GENERATIONS_PER_RUN * MAP_ID_STRIDE}
    assert rerun, sorted(by_map)  # (the first run's map, killed before its VI init, never went up)
    assert final.keyframes == sum(len(v) for v in rerun.values())
    sent = cloud.of(AgentSensors, "robot-1")
    assert len(sent) == 2  # once per edge run: the restarted edge had it from its journal
    assert all(read_agent_sensors(m).same_as(sim_sensors(seq)) for m in sent)


# ------------------------------------------------------------------ command line
def test_edge_command_parses_and_names_missing_inputs(tmp_path, monkeypatch, caplog) -> None:
    import argparse

    from recslam.commands import edge as edge_cmd

    parser = argparse.ArgumentParser()
    edge_cmd.register(parser.add_subparsers())
    args = parser.parse_args(
        [
            "edge",
            "--listen",
            "127.0.0.1:7001",
            "--cloud",
            "cloud:7100",
            "--state-dir",
            str(tmp_path),
        ]
    )
    assert args.listen == ("127.0.0.1", 7001) and args.cloud == ("cloud", 7100)
    assert args.worker == "process" and args.func is edge_cmd.handle
    monkeypatch.setenv("RECSLAM_SECRET", "short")
    args = parser.parse_args(["edge"])
    assert args.func(args) == 2
    assert "at least 16 bytes" in caplog.text
    with pytest.raises(SystemExit):
        parser.parse_args(["edge", "--listen", "nonsense"])
    with pytest.raises(SystemExit):  # the robots bring their calibrations
        parser.parse_args(["edge", "--camera", "x"])


# ------------------------------------------------------------------ rendered synthetic robot
@pytest.mark.slow
def test_synthetic_robot_initialises_and_receives_feedback(tmp_path) -> None:
    """The image-based robot plays a rendered synthetic sequence (15 s, enough keyframes for
    the default VI initialisation) in real time into the edge: the VIO initialises, the edge
    sends InertialFeedback and the robot applies it. Slowest test here (~70 s: rendering)."""
    from common.data.synth import SynthConfig, generate_dataset
    from services.robot.server import RobotService
    from services.robot.service_config import Rate, RobotServiceConfig

    generate_dataset(
        tmp_path / "synth",
        SynthConfig(robots=1, seconds=15.0, seed=2, contact_sheet=False, progress=False),
    )
    dataset = next(p for p in (tmp_path / "synth").iterdir() if p.is_dir())

    async def main():
        cloud = CloudStub()
        cport = await cloud.start()
        edge = _edge(Vocabulary.load(), cport, "thread")
        _, port = await edge.start()
        try:
            robot = RobotService(
                RobotServiceConfig(
                    dataset=dataset,
                    edge_host="127.0.0.1",
                    edge_port=port,
                    agent_id="synth-0",
                    secret=SECRET,
                    rate=Rate.REALTIME,
                    heartbeat_interval_s=0.2,
                    idle_timeout_s=2.0,
                ),
                transport=FAST,
            )
            result = await robot.run()
            await asyncio.wait_for(edge.flush(), 60)
            stats = edge.stats()
        finally:
            await edge.stop()
            await cloud.server.close()
        return cloud, result, stats

    cloud, result, stats = asyncio.run(main())
    s = stats["robots"]["synth-0"]
    assert s["failures"] == [] and s["frames_decoded"] == s["frames_processed"] == result.frames
    assert s["feedback_sent"] >= 1, s["reason"]
    assert result.feedback_applied >= 1
    kfs = cloud.of(KeyframeUpdateCoded, "synth-0")
    assert len(kfs) == s["keyframes_uplinked"] >= 5


@pytest.mark.slow
def test_a_late_vio_skips_stale_non_keyframes_and_keeps_their_imu(vocab, sim_frames) -> None:
    """Fresh before complete at the edge: a robot's frames arrive far faster than its VIO runs
    (played at link speed); with ``max_vio_lag_s`` the non-keyframes more than that behind the
    newest are not given to the VIO, keyframes always are, and the skipped frames' IMU goes
    with the next frame: the VIO still initialises, tracks, and finds the gyro bias."""
    seq, frames = sim_frames

    async def main():
        cloud = CloudStub()
        cport = await cloud.start()
        service = EdgeServiceConfig(
            agent_id="edge-1",
            cloud_host="127.0.0.1",
            cloud_port=cport,
            heartbeat_interval_s=0.2,
            idle_timeout_s=2.0,
        )
        edge = EdgeServer(
            SECRET,
            vocab,
            EdgeConfig(worker="thread", max_vio_lag_s=0.2),
            service,
            transport=TransportConfig(accept_roles=("robot",)),
        )
        _, port = await edge.start()
        done = asyncio.Event()
        try:
            task = asyncio.create_task(
                play(
                    frames,
                    "127.0.0.1",
                    port,
                    "r",
                    SECRET,
                    sim_sensors(seq),
                    transport=FAST,
                    linger=done,
                )
            )
            while not edge.app.robots or not all(
                rb.ended.is_set() for rb in edge.app.robots.values()
            ):
                await asyncio.sleep(0.1)
            await asyncio.wait_for(edge.flush(), 60)
            done.set()
            robot = await task
            stats = edge.stats()
        finally:
            await edge.stop()
            await cloud.server.close()
        return cloud, stats, robot

    cloud, stats, robot = asyncio.run(main())
    r = stats["robots"]["r"]
    keyframes = sum(f.keyframe for f in frames)
    assert r["frames_skipped_stale"] > 10, r
    assert r["frames_processed"] + r["frames_skipped_stale"] == len(frames)
    assert r["frames_processed"] >= keyframes and r["state"] == "tracking"
    fbs = [decode_feedback(m) for m in robot.feedback if isinstance(m, InertialFeedbackCoded)]
    assert fbs and np.linalg.norm(fbs[-1].bias_gyro - np.array(SimConfig().bias_gyro)) < 5e-3
    assert len(cloud.of(KeyframeUpdateCoded, "r")) > 5
