"""The robot library API: the example of ``docs/robot.md`` runs as written against a real edge,
and a driver feeding ``RobotClient`` codes the very bytes the folder playback codes."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from common.data.euroc import EurocSequence
from common.links.robot_edge import RobotFrame
from common.links.sensors import Sensors
from common.protocol import SessionConfig
from common.transport import Delivery, Server, TransportConfig
from services.robot.client import RobotClient, RobotClientConfig, RobotClosedError
from services.robot.server import RobotService
from services.robot.service_config import Rate, RobotServiceConfig

ROOT = Path(__file__).resolve().parents[3]
SECRET = "robot-client-test-secret-0123456789"

pytestmark = pytest.mark.timeout(300)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def docs_example() -> str:
    text = (ROOT / "docs" / "robot.md").read_text()
    after = text.split("<!-- example: robot-api -->", 1)[1]
    block = re.search(r"```python\n(.*?)```", after, re.S)
    assert block, "docs/robot.md: no python block after the example marker"
    return block.group(1)


@pytest.mark.slow
def test_the_docs_example_runs_as_written_against_a_real_edge(
    tmp_path: Path, euroc_micro: Path
) -> None:
    code = docs_example()
    assert 15 <= len(code.strip().splitlines()) <= 35
    script = tmp_path / "example.py"
    script.write_text(code)
    port = _free_port()
    env = {
        **os.environ,
        "RECSLAM_SECRET": SECRET,
        "RECSLAM_EDGE": f"127.0.0.1:{port}",
        "RECSLAM_DATASET": str(euroc_micro),
        "PYTHONPATH": str(ROOT),
    }
    with (tmp_path / "edge.log").open("w") as log:
        edge = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "recslam",
                "edge",
                "--listen",
                f"127.0.0.1:{port}",
                "--worker",
                "thread",
            ],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    try:
        done = subprocess.run(
            [sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=240
        )
    finally:
        edge.send_signal(signal.SIGINT)
        edge.wait(60)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.strip().splitlines()
    found = re.fullmatch(r"(\d+) sent, (\d+) dropped, (\d+) poses", lines[-1])
    assert found, lines[-1]
    sent, dropped, back = map(int, found.groups())
    # a 20 Hz driver: every frame tracked, or dropped and counted when the (shared) CPU falls
    # behind; each pose printed by the callback
    assert sent + dropped == 95 and sent >= 40
    assert back == len(lines) - 1 >= 0.5 * sent


class Recorder:
    """A stand-in edge that keeps the RobotFrames and sends nothing back (no feedback: the
    coded bytes depend on the input alone)."""

    def __init__(self) -> None:
        self.frames: list[RobotFrame] = []

    async def __call__(self, d: Delivery) -> None:
        if isinstance(d.message, RobotFrame):
            self.frames.append(d.message)


async def _serve(recorder: Recorder) -> tuple[Server, int]:
    server = Server(
        SessionConfig("edge", "edge", SECRET.encode(), heartbeat_interval=0.2, idle_timeout=2.0),
        recorder,
        transport=TransportConfig(),
    )
    _, port = await server.start("127.0.0.1", 0)
    return server, port


def test_a_driver_feeding_the_api_codes_the_folder_playbacks_bytes(euroc_micro: Path) -> None:
    n = 30
    seq = EurocSequence(euroc_micro)

    async def folder() -> list[RobotFrame]:
        rec = Recorder()
        server, port = await _serve(rec)
        try:
            cfg = RobotServiceConfig(
                dataset=euroc_micro,
                edge_host="127.0.0.1",
                edge_port=port,
                agent_id="r0",
                secret=SECRET.encode(),
                rate=Rate.MAX,
                max_frames=n,
                heartbeat_interval_s=0.2,
                idle_timeout_s=2.0,
            )
            await RobotService(cfg).run()
        finally:
            await server.close()
        return rec.frames

    loop = asyncio.new_event_loop()
    rec = Recorder()
    server, port = loop.run_until_complete(_serve(rec))
    ticker = threading.Thread(target=loop.run_forever, daemon=True)
    ticker.start()
    try:
        config = RobotClientConfig(
            Sensors(seq.cam0, seq.imu), "127.0.0.1", port, "r0", SECRET.encode()
        )
        robot = RobotClient(config)
        for fr in seq.frames(0, n):  # a driver: each IMU sample, then the image
            for t, g, a in zip(fr.imu.timestamps_ns, fr.imu.gyro, fr.imu.accel, strict=True):
                robot.add_imu(int(t), g, a)
            robot.add_image(fr.timestamp_ns, fr.image)
            while robot.stats()["pending_images"] > 1:  # keep under the drop limit
                threading.Event().wait(0.01)
        stats = robot.close()
        with pytest.raises(RobotClosedError):
            robot.add_imu(0, (0, 0, 0), (0, 0, 0))
    finally:
        asyncio.run_coroutine_threadsafe(server.close(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        ticker.join(10)
        loop.close()
    live = rec.frames
    assert stats["frames_sent"] == n and stats["faults"]["dropped_backpressure"] == 0
    played = asyncio.run(folder())
    assert len(live) == len(played) == n
    for a, b in zip(live, played, strict=True):
        assert (a.timestamp_ns, a.keyframe) == (b.timestamp_ns, b.keyframe)
        assert a.features == b.features and a.imu == b.imu  # byte-identical
