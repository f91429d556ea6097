"""Services fail loudly (issue 19, item 3), as real processes over real sockets: an upstream
peer that is unreachable for ``--give-up-after`` seconds or refuses the credential ends the
process with a non-zero exit and one ERROR line saying why; an edge stopped with a backlog for
a cloud that is down says what is queued, flushes for at most ``--stop-flush-timeout`` and
says what it left unsent.

The subprocess timeouts are bounds (a process that never gives up fails the test), not timing
goals."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from common.protocol import SessionConfig
from common.protocol.auth import Keyring
from common.transport import Delivery, Server

ROOT = Path(__file__).resolve().parents[2]
SECRET = "loud-failures-test-secret-0123"
BOUND_S = 90.0  # far above the give-up times below: only a process that hangs reaches it


def closed_port() -> int:
    with socket.socket() as sock:  # bound, never listening: connections are refused
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def env(secret: str = SECRET) -> dict[str, str]:
    e = dict(os.environ, PYTHONPATH=str(ROOT), RECSLAM_SECRET=secret, PYTHONUNBUFFERED="1")
    e.pop("RECSLAM_GIVE_UP_AFTER", None)
    return e


def errors(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if " ERROR " in line]


def robot(dataset: Path, port: int, *extra: str, secret: str = SECRET):
    argv = [sys.executable, "-m", "services.robot", "--dataset", str(dataset)]
    argv += ["--edge", f"127.0.0.1:{port}", "--agent-id", "robot0", "--rate", "max", *extra]
    return subprocess.run(
        argv, cwd=ROOT, env=env(secret), capture_output=True, text=True, timeout=BOUND_S
    )


@pytest.mark.slow
def test_robot_gives_up_on_a_closed_port_with_one_line(euroc_micro) -> None:
    port = closed_port()
    t0 = time.monotonic()
    proc = robot(euroc_micro, port, "--give-up-after", "2")
    took = time.monotonic() - t0
    assert proc.returncode == 4, proc.stderr[-3000:]
    lines = errors(proc.stderr)
    assert len(lines) == 1, proc.stderr[-3000:]
    line = lines[0]
    assert f"giving up on 127.0.0.1:{port}: no session for 2." in line
    assert "give-up time 2 s" in line and "last failure: cannot connect" in line
    assert "Connection refused" in line or "Errno 111" in line
    # the warnings came before, from the first failure, with the address
    assert f"no session with 127.0.0.1:{port} (1 attempts" in proc.stderr
    assert took < BOUND_S


class _WrongKeyServer:
    """A real protocol server (``role``'s identity, another operator secret) on a thread."""

    def __init__(self, role: str = "edge") -> None:
        self.role = role
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.server: Server | None = None

    def start(self) -> int:
        async def go() -> int:
            keys = Keyring.from_secret(b"another-operator-secret-entirely")
            self.server = Server(SessionConfig(self.role, self.role, keys=keys), self._handle)
            _, port = await self.server.start("127.0.0.1", 0)
            return port

        return asyncio.run_coroutine_threadsafe(go(), self.loop).result(10)

    async def _handle(self, d: Delivery) -> None:
        raise AssertionError("nothing should be delivered")

    def close(self) -> None:
        if self.server is not None:
            asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


def test_robot_with_a_wrong_key_exits_with_the_authentication_reason(euroc_micro) -> None:
    edge = _WrongKeyServer("edge")
    try:
        port = edge.start()
        proc = robot(euroc_micro, port)  # no --give-up-after: a refused key stops at once
    finally:
        edge.close()
    assert proc.returncode == 3, proc.stderr[-3000:]
    lines = errors(proc.stderr)
    assert len(lines) == 1, proc.stderr[-3000:]
    assert "authentication failed, not reconnecting" in lines[0]
    assert "robot robot0" in lines[0] and "--key-file" in lines[0]


def _edge(tmp_path: Path, cloud_port: int, *extra: str) -> subprocess.Popen:
    argv = [sys.executable, "-m", "services.edge", "-v", "--listen", f"127.0.0.1:{closed_port()}"]
    argv += ["--cloud", f"127.0.0.1:{cloud_port}", "--worker", "thread", *extra]
    with (tmp_path / "edge.log").open("w") as log:
        return subprocess.Popen(
            argv, cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=log, text=True
        )


@pytest.mark.slow
def test_edge_gives_up_on_an_unreachable_cloud_with_one_line(tmp_path) -> None:
    port = closed_port()
    edge = _edge(tmp_path, port, "--give-up-after", "2")
    try:
        code = edge.wait(BOUND_S)
    finally:
        edge.kill()
        edge.communicate()
    log = (tmp_path / "edge.log").read_text()
    assert code == 4, log[-3000:]
    lines = errors(log)
    assert len(lines) == 1, log[-3000:]
    assert f"edge edge: giving up on 127.0.0.1:{port}: no session for 2." in lines[0]
    assert "last failure: cannot connect" in lines[0]


@pytest.mark.slow
def test_edge_stopped_with_a_backlog_for_a_down_cloud_flushes_for_a_bound(
    tmp_path, euroc_micro
) -> None:
    state = tmp_path / "state"
    edge = _edge(tmp_path, closed_port(), "--stop-flush-timeout", "1", "--state-dir", str(state))
    try:
        assert edge.stdout is not None
        line = edge.stdout.readline()  # the edge announces its address once it listens
        assert "edge listening on" in line, (tmp_path / "edge.log").read_text()[-3000:]
        port = int(line.split()[3].rstrip(",").rsplit(":", 1)[1])
        sent = robot(euroc_micro, port, "--max-frames", "10")
        assert sent.returncode == 0, sent.stderr[-3000:]  # the edge took every frame
        edge.send_signal(signal.SIGTERM)
        code = edge.wait(BOUND_S)
    finally:
        edge.kill()
        edge.communicate()
    log = (tmp_path / "edge.log").read_text()
    assert code == 0, log[-3000:]
    queued = [ln for ln in log.splitlines() if "queued for the cloud at 127.0.0.1:" in ln]
    assert len(queued) == 1 and "flushing them for at most 1 s" in queued[0], log[-3000:]
    left = [ln for ln in log.splitlines() if "did not take the backlog within 1 s" in ln]
    assert len(left) == 1, log[-3000:]
    assert "giving up with" in left[0] and f"journaled in {state}" in left[0]
    n_queued = int(queued[0].split("edge stopping: ")[1].split()[0])
    n_left = int(left[0].split("giving up with ")[1].split()[0])
    assert n_queued >= 1 and n_left == n_queued  # nothing could go: the cloud is down


def test_edge_whose_key_the_cloud_refuses_exits_with_the_reason(tmp_path) -> None:
    cloud = _WrongKeyServer("cloud")
    try:
        edge = _edge(tmp_path, cloud.start())  # no --give-up-after: a refused key stops at once
        try:
            code = edge.wait(BOUND_S)
        finally:
            edge.kill()
            edge.communicate()
    finally:
        cloud.close()
    log = (tmp_path / "edge.log").read_text()
    assert code == 3, log[-3000:]
    lines = errors(log)
    assert len(lines) == 1, log[-3000:]
    assert "edge edge: authentication failed, not reconnecting" in lines[0]


@pytest.mark.parametrize("value", ["-1", "soon"])
def test_give_up_after_must_be_seconds(value) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "services.edge", "--give-up-after", value],
        cwd=ROOT,
        env=env(),
        capture_output=True,
        text=True,
        timeout=BOUND_S,
    )
    assert proc.returncode == 2 and "--give-up-after" in proc.stderr
