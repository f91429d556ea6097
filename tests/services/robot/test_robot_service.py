"""Robot service on real loopback TCP against a small edge built from the transport and the
codec decoders: bit-exact decoding of what the robot used, feedback, outages, CLI, signals."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import signal
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from common.codec import FeatureDecoder, ImuDecoder, KeyframeFeatures, angle_to_bin
from common.codec.keypoints import kf_track_q
from common.data.euroc import EurocSequence
from common.geometry import so3_exp
from common.links.robot_edge import InertialFeedback, RobotFrame, RobotSequenceEnd
from common.protocol import SessionConfig
from common.protocol.arrays import pack_array
from common.transport import Delivery, Server, TransportConfig, run
from common.vocabulary import Vocabulary
from services.robot.app import UsedFrame
from services.robot.coding import next_stream_numbers
from services.robot.server import RobotService
from services.robot.service_config import Rate, RobotServiceConfig
from sim.faultproxy import FaultConfig, FaultProxy

ROOT = Path(__file__).resolve().parents[3]
SECRET = b"robot-service-test-secret"
FAST = TransportConfig(reconnect_initial_delay=0.02, reconnect_max_delay=0.3)
N_FRAMES = 40


@pytest.fixture(scope="module")
def vocabulary() -> Vocabulary:
    return Vocabulary.load()


class EdgeStub:
    """Decodes every RobotFrame in order; optional hook per decoded frame."""

    def __init__(self, vocabulary: Vocabulary, hook=None) -> None:
        self.vocabulary = vocabulary
        self.features: FeatureDecoder | None = None
        self.imu = ImuDecoder()
        self.numbers, self.next_number = np.zeros(0, np.int64), 0  # stream track numbers
        self.frames: list[tuple[RobotFrame, object, object]] = []
        self.errors: list[str] = []
        self.end: RobotSequenceEnd | None = None
        self.ended = asyncio.Event()
        self.hook = hook
        self.server: Server | None = None

    async def __call__(self, d: Delivery) -> None:
        m = d.message
        if isinstance(m, RobotFrame):
            if self.features is None:
                from services.robot.coding import codec_config_for
                from services.robot.config import FrontEndConfig

                self.features = FeatureDecoder(
                    self.vocabulary, codec_config_for(FrontEndConfig(), 752, 480)
                )
            if m.frame_index != len(self.frames):
                self.errors.append(f"frame {m.frame_index} arrived as #{len(self.frames)}")
            feats = self.features.decode(m.features)
            self.numbers, self.next_number = next_stream_numbers(
                self.numbers, self.next_number, feats
            )
            imu = self.imu.decode(m.imu)
            self.frames.append((m, feats, imu))
            if self.hook is not None:
                try:
                    await self.hook(self, d, m)
                except Exception as exc:
                    self.errors.append(f"hook failed: {exc!r}")
        elif isinstance(m, RobotSequenceEnd):
            self.end = m
            self.ended.set()

    async def start(self) -> tuple[str, int]:
        cfg = SessionConfig("edge", "edge-test", SECRET, heartbeat_interval=0.2, idle_timeout=1.5)
        self.server = Server(cfg, self, transport=FAST)
        return await self.server.start()


def robot_config(dataset: Path, port: int, **kw) -> RobotServiceConfig:
    base = dict(
        dataset=dataset,
        edge_host="127.0.0.1",
        edge_port=port,
        agent_id="robot-1",
        secret=SECRET,
        rate=Rate.MAX,
        max_frames=N_FRAMES,
        heartbeat_interval_s=0.2,
        idle_timeout_s=1.5,
        flush_timeout_s=30.0,
        record=True,
    )
    base.update(kw)
    return RobotServiceConfig(**base)


def assert_decoded_equals_used(used: list[UsedFrame], edge: EdgeStub, seq: EurocSequence) -> None:
    """The edge's decoded data equals, bit for bit, what the robot's pipeline used."""
    cc = FeatureDecoder(edge.vocabulary).config
    assert len(edge.frames) == len(used) == N_FRAMES
    edge_ids = np.zeros(0, np.int64)  # track identities as the edge reconstructs them
    numbers, next_number = np.zeros(0, np.int64), 0  # stream track numbers, decoded data only
    n_kf = 0
    for k, (u, (msg, feats, imu)) in enumerate(zip(used, edge.frames, strict=True)):
        t = u.tracked
        assert msg.frame_index == k and msg.timestamp_ns == t.timestamp_ns
        assert msg.keyframe == t.is_keyframe == isinstance(feats, KeyframeFeatures)
        row_of = {int(i): r for r, i in enumerate(t.track_ids)}
        rows = np.array([row_of[int(i)] for i in u.coded.track_ids], np.int64)
        assert sorted(rows.tolist()) == list(range(len(t)))  # a permutation of the rows
        if t.is_keyframe:
            n_kf += 1
            # Positions the robot tracks from, levels, orientation bins, descriptors.
            assert np.array_equal(kf_track_q(feats.keypoints, cc) / cc.subpixel, t.keypoints[rows])
            assert np.array_equal(feats.keypoints[:, 2], t.levels[rows])
            assert np.array_equal(feats.keypoints[:, 3], angle_to_bin(t.angles[rows]))
            assert np.array_equal(feats.descriptors, t.descriptors[rows])
            linked = feats.links >= 0
            assert np.array_equal(u.coded.track_ids[linked], edge_ids[feats.links[linked]])
            assert not np.isin(u.coded.track_ids[~linked], edge_ids).any()
        else:
            n_surv = int(feats.survived.sum())
            assert n_surv == int(t.survived_mask_vs_previous.sum())
            assert np.array_equal(feats.keypoints[:, :2], t.keypoints[rows])
            assert np.array_equal(feats.keypoints[:, 2], t.levels[rows])
            assert np.array_equal(u.coded.track_ids[:n_surv], edge_ids[feats.survived])
        edge_ids = np.asarray(u.coded.track_ids)
        numbers, next_number = next_stream_numbers(numbers, next_number, feats)
        assert np.array_equal(numbers, u.coded.stream_ids)
        # IMU: what the front end was fed, decoded bit for bit, and EuRoC's own values.
        assert imu.equals(u.imu)
        raw = seq.imu_between(None if k == 0 else used[k - 1].tracked.timestamp_ns, t.timestamp_ns)
        assert np.array_equal(u.imu.timestamps_ns, raw.timestamps_ns[-len(u.imu) :])
        assert u.imu.gyro.tobytes() == raw.gyro[-len(u.imu) :].tobytes()
    assert 2 <= n_kf < N_FRAMES // 2


def feedback_for(
    seq: EurocSequence, timestamp_ns: int, numbers: np.ndarray | None = None
) -> InertialFeedback:
    """A plausible edge state at ``timestamp_ns``: gravity-aligned attitude from the mean
    accelerometer reading, at rest, with V1_01-like biases (the excerpt has no ground truth)."""
    imu = seq.imu_between(timestamp_ns - 200_000_000, timestamp_ns)
    up = imu.accel.mean(axis=0)
    up = up / np.linalg.norm(up)  # IMU-frame direction of world +z
    axis = np.cross(up, [0.0, 0.0, 1.0])
    angle = np.arccos(np.clip(up[2], -1.0, 1.0))
    T = np.eye(4)
    T[:3, :3] = so3_exp(axis / max(np.linalg.norm(axis), 1e-12) * angle)
    return InertialFeedback(
        timestamp_ns=int(timestamp_ns),
        map_id=0,
        T_world_body=pack_array(T, "<f8"),
        velocity_world=pack_array(np.zeros(3), "<f8"),
        bias_gyro=pack_array(np.array([-0.0023, 0.0249, 0.0817]), "<f8"),
        bias_accel=pack_array(np.array([-0.0236, 0.1210, 0.0748]), "<f8"),
        gravity_world=pack_array(np.array([0.0, 0.0, -9.81]), "<f8"),
        track_ids=b"" if numbers is None else pack_array(numbers, "<i8"),
        p_world=b"" if numbers is None else pack_array(np.ones((len(numbers), 3)), "<f8"),
    )


def test_frames_decode_to_what_the_robot_used_and_feedback_is_applied(vocabulary, euroc_micro):
    seq = EurocSequence(euroc_micro)
    fb_at = 10

    async def hook(edge: EdgeStub, d: Delivery, m: RobotFrame) -> None:
        if m.frame_index == fb_at:
            assert edge.server is not None
            msg = feedback_for(seq, m.timestamp_ns, edge.numbers[:5])
            edge.server.peer(d.peer).send_nowait(msg)

    async def main():
        edge = EdgeStub(vocabulary, hook)
        _, port = await edge.start()
        try:
            service = RobotService(robot_config(euroc_micro, port), FAST)
            before = service.app.front_end.vi_initialised
            result = await service.run()
            await asyncio.wait_for(edge.ended.wait(), 5)
        finally:
            await edge.server.close()
        return service, result, edge, before

    service, result, edge, before = run(main())
    assert not edge.errors
    assert result.flushed and not result.interrupted and result.frames == N_FRAMES
    assert edge.end is not None and edge.end.frames == N_FRAMES
    assert_decoded_equals_used(service.app.recorded, edge, seq)
    # Feedback: applied once, the front end switched from gyro-only to preintegration.
    fe = service.app.front_end
    assert not before and fe.vi_initialised and result.feedback_applied == 1
    sent = feedback_for(seq, edge.frames[fb_at][0].timestamp_ns)
    state = fe.predictor.state_at(service.app.recorded[-1].tracked.timestamp_ns)
    assert state is not None
    assert np.array_equal(state.bias_gyro, np.frombuffer(sent.bias_gyro, "<f8"))
    modes = [u.tracked.stats.prediction for u in service.app.recorded]
    assert "preintegration" not in modes[: fb_at + 1]
    assert modes[-1] == "preintegration"
    # The edge named 5 map points by stream numbers: they reached the tracker's tracks (those
    # still alive when the feedback was applied).
    named = set(service.app.recorded[fb_at].coded.track_ids[:5].tolist())
    assert len(fe.predictor._landmarks) > 0 and set(fe.predictor._landmarks) <= named
    # Protocol accounting saw the frames.
    by_type = result.counters["tx"]["by_type"]
    assert by_type["RobotFrame"]["messages"] >= N_FRAMES


@pytest.mark.slow
@pytest.mark.parametrize("rate,backlog_s", [(Rate.REALTIME, 1800.0), (Rate.MAX, 0.05)])
def test_edge_outage_loses_nothing(vocabulary, rate, backlog_s, caplog, euroc_micro):
    """The edge vanishes (black hole + cut) mid-run: the robot keeps tracking and queueing
    (realtime), or waits on a tiny backlog (back-pressure); it catches up; nothing is lost."""
    seq = EurocSequence(euroc_micro)
    marks: dict[str, int] = {}
    service_box: list[RobotService] = []

    async def hook(edge: EdgeStub, d: Delivery, m: RobotFrame) -> None:
        if m.frame_index == 8:
            proxy.freeze()
            proxy.cut_all()
            marks["frozen_at"] = service_box[0].app.frames

            async def thaw() -> None:
                app = service_box[0].app
                if rate is Rate.REALTIME:  # until 10 more frames were tracked (or 20 s)
                    for _ in range(400):
                        if app.frames >= marks["frozen_at"] + 10:
                            break
                        await asyncio.sleep(0.05)
                else:  # until the 17-message backlog is full, then a little longer
                    client = service_box[0].client
                    for _ in range(400):
                        if client.counters()["outbox_messages"] >= 17:
                            break
                        await asyncio.sleep(0.05)
                    marks["full_at"] = app.frames
                    await asyncio.sleep(0.5)
                marks["thawed_at"] = app.frames
                proxy.thaw()

            asyncio.get_running_loop().create_task(thaw())

    async def main():
        nonlocal proxy
        edge = EdgeStub(vocabulary, hook)
        host, port = await edge.start()
        proxy = FaultProxy(host, port, FaultConfig())
        _, pport = await proxy.start()
        try:
            service = RobotService(
                robot_config(euroc_micro, pport, rate=rate, backlog_s=backlog_s), FAST
            )
            service_box.append(service)
            result = await service.run()
            await asyncio.wait_for(edge.ended.wait(), 5)
        finally:
            await proxy.close()
            await edge.server.close()
        return service, result, edge

    proxy: FaultProxy
    service, result, edge = run(main())
    assert not edge.errors
    assert result.flushed and result.frames == N_FRAMES
    assert result.counters["connections"] >= 2
    assert_decoded_equals_used(service.app.recorded, edge, seq)
    kept_going = marks["thawed_at"] - marks["frozen_at"]
    if rate is Rate.REALTIME:
        assert kept_going >= 10  # tracked and queued while the edge was away
    else:
        assert kept_going <= 19  # blocked on the 17-message backlog (+1 sending, +1 tracking)
        assert marks["thawed_at"] - marks["full_at"] <= 2  # stalled while full
        assert "backlog full" in caplog.text


@pytest.mark.slow
def test_robot_process_runs_to_the_end_and_stops_on_sigterm(vocabulary, tmp_path, euroc_micro):
    """``python -m services.robot`` as a real process: secret file, --rate max to the end
    (exit 0, every frame); realtime with SIGTERM mid-run (exit 130, sequence end sent)."""
    secret_file = tmp_path / "secret"
    secret_file.write_bytes(SECRET + b"\n")

    async def play(extra: list[str], stop_after: int | None):
        async def hook(edge: EdgeStub, d: Delivery, m: RobotFrame) -> None:
            if stop_after is not None and m.frame_index == stop_after:
                proc.send_signal(signal.SIGTERM)

        edge = EdgeStub(vocabulary, hook)
        _, port = await edge.start()
        env = {k: v for k, v in os.environ.items() if k != "RECSLAM_SECRET"}
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "services.robot",
            "--dataset",
            str(euroc_micro),
            "--edge",
            f"127.0.0.1:{port}",
            "--agent-id",
            "robot-7",
            "--secret-file",
            str(secret_file),
            *extra,
            cwd=ROOT,
            env=env,
            stderr=asyncio.subprocess.PIPE,
        )
        try:
            _, err = await asyncio.wait_for(proc.communicate(), 60)
            await asyncio.wait_for(edge.ended.wait(), 5)
        finally:
            if proc.returncode is None:
                proc.kill()
            await edge.server.close()
        return proc.returncode, err.decode(), edge

    code, err, edge = run(play(["--rate", "max", "--max-frames", "12"], None))
    assert code == 0, err
    assert edge.end is not None and edge.end.frames == 12 == len(edge.frames)
    assert not edge.errors

    code, err, edge = run(play(["--rate", "realtime"], 4))
    assert code == 130, err
    assert edge.end is not None and 5 <= edge.end.frames == len(edge.frames) < 95


def test_config_dataclass_rejects_nonsense(tmp_path):
    from services.robot.service_config import RobotConfigError

    ok = robot_config(tmp_path, 7000)
    for change, what in [
        ({"edge_port": 0}, "port"),
        ({"agent_id": ""}, "agent id"),
        ({"secret": b"short"}, "secret"),
        ({"backlog_s": 0.0}, "backlog"),
        ({"idle_timeout_s": 0.1}, "idle_timeout"),
        ({"max_frames": -1}, "max_frames"),
    ]:
        with pytest.raises(RobotConfigError, match=what):
            dataclasses.replace(ok, **change)


def test_unreachable_edge_keeps_frames_until_a_second_stop(vocabulary, euroc_micro):
    """No edge at all: every frame is tracked and queued; a first stop request waits for the
    edge, a second gives up (interrupted, not flushed)."""
    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]

    async def main():
        service = RobotService(
            robot_config(euroc_micro, port, max_frames=6, flush_timeout_s=None), FAST
        )
        task = asyncio.ensure_future(service.run())
        while service.client is None or service.client.counters()["outbox_messages"] < 8:
            await asyncio.sleep(0.05)  # the sensors, 6 frames and the sequence end, queued
        service.request_stop()
        await asyncio.sleep(0.3)
        assert not task.done()  # still waiting for the edge to take the backlog
        service.request_stop()
        return await asyncio.wait_for(task, 10)

    result = run(main())
    assert result.interrupted and not result.flushed and result.frames == 6
    assert result.counters["outbox_messages"] == 8


def test_first_stop_flushes_for_a_bounded_time_and_says_so(vocabulary, euroc_micro, caplog):
    """No edge: one stop request alone ends the run after ``stop_flush_timeout_s``, with the
    backlog and the bound logged."""
    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]

    async def main():
        cfg = robot_config(
            euroc_micro, port, max_frames=6, flush_timeout_s=None, stop_flush_timeout_s=0.5
        )
        service = RobotService(cfg, FAST)
        task = asyncio.ensure_future(service.run())
        while service.client is None or service.client.counters()["outbox_messages"] < 8:
            await asyncio.sleep(0.05)
        t0 = time.monotonic()
        service.request_stop()
        result = await asyncio.wait_for(task, 10)
        return result, time.monotonic() - t0

    with caplog.at_level(logging.WARNING, logger="services.robot.server"):
        result, waited = run(main())
    assert result.interrupted and not result.flushed and result.frames == 6
    assert 0.4 < waited < 5.0
    text = caplog.text
    assert "stop requested: 8 messages" in text and "for at most 0.5 s" in text
    assert "giving up with 8 messages" in text


def test_handover_to_a_second_edge_sends_each_frame_exactly_once(vocabulary, euroc_micro):
    """A robot that moves between sites: frames 0..24 go to edge A, which takes them all (its
    stream ends with RobotSequenceEnd(25)) before the robot opens a new stream with edge B,
    starting with its sensors, frame indices from 0 and a fresh front end (a keyframe first).
    Each sequence frame reaches exactly one edge, decoded."""
    from common.links.robot_edge import RobotSensors
    from services.robot.service_config import Handover

    seq = EurocSequence(euroc_micro)
    at = 25

    class Site(EdgeStub):
        def __init__(self, vocabulary) -> None:
            super().__init__(vocabulary)
            self.kinds: list[str] = []

        async def __call__(self, d: Delivery) -> None:
            self.kinds.append(type(d.message).__name__)
            await super().__call__(d)

    async def main():
        a, b = Site(vocabulary), Site(vocabulary)
        _, port_a = await a.start()
        _, port_b = await b.start()
        try:
            cfg = robot_config(euroc_micro, port_a, handovers=(Handover(at, "127.0.0.1", port_b),))
            service = RobotService(cfg, FAST)
            result = await service.run()
            await asyncio.wait_for(b.ended.wait(), 5)
        finally:
            await a.server.close()
            await b.server.close()
        return service, result, a, b

    service, result, a, b = run(main())
    assert not a.errors and not b.errors
    assert result.flushed and result.frames == N_FRAMES and len(result.sessions) == 2
    assert a.end is not None and a.end.frames == at and len(a.frames) == at
    assert b.end is not None and b.end.frames == N_FRAMES - at and len(b.frames) == N_FRAMES - at
    for site in (a, b):
        assert site.kinds[0] == RobotSensors.__name__ and site.kinds[-1] == "RobotSequenceEnd"
        assert site.frames[0][0].keyframe  # a new stream starts with a keyframe
    stamps = [m.timestamp_ns for site in (a, b) for m, _, _ in site.frames]
    assert stamps == [int(t) for t in seq.frame_timestamps_ns[:N_FRAMES]]
    assert [m.frame_index for m, _, _ in b.frames] == list(range(N_FRAMES - at))
    assert [len(x.recorded) for x in service.apps] == [at, N_FRAMES - at]


def test_handover_frames_must_increase(tmp_path):
    from services.robot.service_config import Handover, RobotConfigError

    with pytest.raises(RobotConfigError, match="handover frames must increase"):
        robot_config(tmp_path, 7000, handovers=(Handover(10, "h", 1), Handover(5, "h", 2)))
    with pytest.raises(RobotConfigError, match="handover frames must increase"):
        robot_config(tmp_path, 7000, start_frame=10, handovers=(Handover(10, "h", 1),))
