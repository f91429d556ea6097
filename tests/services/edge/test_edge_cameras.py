"""A team of robots with different cameras through one real edge: each robot's stream starts
with its own calibration, the edge decodes and tracks it with that one, forwards it to the
cloud ahead of the robot's keyframes, and refuses a robot that re-joins under a known agent
id with another calibration."""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path

import pytest

from common.camera import PinholeRadtan
from common.data.euroc import EurocSequence
from common.data.synth import SynthConfig, generate_dataset
from common.links.edge_cloud import AgentSensors, KeyframeUpdateCoded, read_agent_sensors
from common.links.sensors import Sensors
from common.protocol import PeerRejectedError, SessionConfig
from common.transport import Delivery, Server, TransportConfig
from common.vocabulary import Vocabulary
from services.edge.app import EdgeConfig
from services.edge.server import EdgeServer, EdgeServiceConfig
from services.robot.server import RobotService
from services.robot.service_config import Rate, RobotServiceConfig

SECRET = b"edge-cameras-test-secret-0123"
FAST = TransportConfig(reconnect_initial_delay=0.02, reconnect_max_delay=0.3)
SECONDS = 6.0
OTHER_CAMERA = PinholeRadtan(640, 480, 380.0, 378.5, 315.5, 242.25, -0.22, 0.05, 2e-4, -1e-4)
"""A camera of other intrinsics and distortion than EuRoC's 752x480 cam0 (the sans-network
refusal test's second calibration)."""

pytestmark = pytest.mark.timeout(400)


@pytest.fixture(scope="module")
def team(tmp_path_factory) -> dict[str, Path]:
    """Two rendered robots: "euroc" with the generator's EuRoC-like 752x480 camera and
    "other" with its ``wide`` preset (640x480, other intrinsics and distortion, pitched
    mount)."""
    root = tmp_path_factory.mktemp("team")
    cfg = SynthConfig(robots=1, seconds=SECONDS, seed=3, contact_sheet=False, progress=False)
    generate_dataset(root / "euroc", cfg)
    generate_dataset(root / "other", dataclasses.replace(cfg, seed=4, cameras=("wide",)))
    return {"euroc": root / "euroc" / "robot0", "other": root / "other" / "robot0"}


class CloudStub:
    def __init__(self) -> None:
        self.messages: list = []
        self.server: Server | None = None

    async def __call__(self, d: Delivery) -> None:
        self.messages.append(d.message)

    async def start(self) -> int:
        cfg = SessionConfig("cloud", "cloud", SECRET, heartbeat_interval=0.2, idle_timeout=2.0)
        self.server = Server(cfg, self, transport=FAST)
        return (await self.server.start("127.0.0.1", 0))[1]


def _robot(dataset: Path, port: int, agent_id: str, **kw) -> RobotService:
    cfg = RobotServiceConfig(
        dataset=dataset,
        edge_host="127.0.0.1",
        edge_port=port,
        agent_id=agent_id,
        secret=SECRET,
        rate=Rate.MAX,
        heartbeat_interval_s=0.2,
        idle_timeout_s=2.0,
        **kw,
    )
    return RobotService(cfg, transport=FAST)


@pytest.mark.slow
def test_two_cameras_through_one_edge_and_a_rejoin_with_another_is_refused(team) -> None:
    sensors = {}
    for name, path in team.items():
        seq = EurocSequence(path)
        sensors[name] = Sensors(seq.cam0, seq.imu)
    assert sensors["euroc"].camera.width == 752 and sensors["other"].camera.width == 640

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
        edge = EdgeServer(SECRET, Vocabulary.load(), EdgeConfig(worker="thread"), service)
        _, port = await edge.start()
        try:
            robots = [_robot(path, port, name) for name, path in team.items()]
            results = await asyncio.gather(*(r.run() for r in robots))
            await asyncio.wait_for(edge.flush(), 120)
            before = edge.stats()
            # "euroc" comes back with the other robot's camera: refused, with the reason.
            with pytest.raises(PeerRejectedError) as refused:
                await _robot(team["other"], port, "euroc", max_frames=5).run()
            await asyncio.wait_for(edge.flush(), 30)
            after = edge.stats()
        finally:
            await edge.stop()
            assert cloud.server is not None
            await cloud.server.close()
        return dict(zip(team, results, strict=True)), before, after, cloud, str(refused.value)

    results, before, after, cloud, refusal = asyncio.run(main())
    for name, result in results.items():
        n = len(EurocSequence(team[name]))
        s = before["robots"][name]
        assert result.frames == n and result.flushed, name
        # Every frame decoded exactly once, with this robot's own codec and VIO.
        assert s["frames_decoded"] == s["frames_processed"] == s["expected_frames"] == n, s
        assert s["keyframes_decoded"] == result.keyframes and s["failures"] == [], s
        assert s["sensors"] == sensors[name].summary()
        # The VIO initialised on both cameras (a map, keyframes uplinked).
        assert s["state"] == "tracking", (name, s["reason"])
        assert s["keyframes_uplinked"] > 0, name
        # The cloud got this robot's calibration before its first keyframe.
        kinds = [
            type(m)
            for m in cloud.messages
            if isinstance(m, AgentSensors | KeyframeUpdateCoded) and m.agent_id == name
        ]
        assert kinds[0] is AgentSensors and kinds.count(AgentSensors) == 1, name
        up = next(m for m in cloud.messages if isinstance(m, AgentSensors) and m.agent_id == name)
        assert read_agent_sensors(up).same_as(sensors[name])
    # The re-join with another camera: refused with the reason, the session untouched.
    assert "re-joined with other sensors" in refusal and "640x480" in refusal, refusal
    assert after["robots"]["euroc"]["frames_decoded"] == before["robots"]["euroc"]["frames_decoded"]
    assert after["robots"]["euroc"]["sensors"] == sensors["euroc"].summary()


class _Sink:
    def __init__(self) -> None:
        self.cloud: list = []

    def to_robot(self, agent_id: str, message) -> bool:
        return True

    async def to_cloud(self, message) -> None:
        self.cloud.append(message)

    def link_counters(self, agent_id: str) -> dict[str, int]:
        return {}


def test_the_edge_refuses_bad_descriptions_and_frames_before_one() -> None:
    """Sans network: a damaged description, a frame before any description and a conflicting
    re-join are each a RejectedMessageError naming the robot (the transport then closes that
    robot's connection with the reason); a repeat of the same sensors is accepted."""
    from common.calibration import EUROC_IMU
    from common.links.robot_edge import RobotFrame, RobotSensors, sensors_message
    from common.protocol import RejectedMessageError
    from common.transport import Delivery
    from services.edge.app import EdgeApp
    from sim.cloud import default_camera

    good = Sensors(default_camera(), EUROC_IMU)
    other = Sensors(OTHER_CAMERA.to_calibration(default_camera().T_body_cam, 20.0), EUROC_IMU)

    def deliver(agent: str, msg, seq: int = 1) -> Delivery:
        return Delivery(agent, "robot", msg, seq, b"stream")

    async def main() -> None:
        sink = _Sink()
        app = EdgeApp(Vocabulary.load(), sink, EdgeConfig(worker="thread"))
        try:
            damaged = bytearray(sensors_message(good).sensors)
            damaged[10] ^= 1
            with pytest.raises(RejectedMessageError, match="robot a: invalid sensor description"):
                await app.on_robot_message(deliver("a", RobotSensors(bytes(damaged))))
            with pytest.raises(RejectedMessageError, match="before its RobotSensors"):
                await app.on_robot_message(deliver("a", RobotFrame(0, 0, True, b"", b"")))
            assert app.robots == {} and sink.cloud == []
            await app.on_robot_message(deliver("a", sensors_message(good)))
            await app.on_robot_message(deliver("a", sensors_message(good), 2))  # a restart
            with pytest.raises(RejectedMessageError, match="re-joined with other sensors"):
                await app.on_robot_message(deliver("a", sensors_message(other), 3))
            assert list(app.robots) == ["a"] and app.robots["a"].sensors.same_as(good)
            assert [type(m) for m in sink.cloud] == [AgentSensors]
        finally:
            await app.close()

    asyncio.run(main())
