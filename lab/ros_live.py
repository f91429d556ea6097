"""Live ROS 1 runs for tests and benchmarks: a real ``roscore`` and a player of a recording.

:class:`RosMaster` starts ``roscore`` on a free port with its logs in a folder of the
caller's and always kills it (and its children) at exit. :class:`Player` publishes an
EuRoC-layout folder on ROS topics at its camera rate through the ROS bridge (mode ``player``,
:mod:`services.robot.ros1.bridge`: the IMU on ``sensor_msgs/Imu``, the images as ``mono8``
``sensor_msgs/Image``, each stamped with its sensor time) and collects the stamps of the
``nav_msgs/Odometry`` it sees, with when they arrived.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from common.data.euroc import EurocSequence
from services.robot.ros1 import wire
from services.robot.ros1.process import BridgeProcess, Ros1Config

logger = logging.getLogger(__name__)


def start_recslam(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    """``python -m recslam ARGS`` with ``env``, its output in ``log``."""
    with log.open("w") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "recslam", *args], env=env, stdout=out, stderr=subprocess.STDOUT
        )


def stop_process(proc: subprocess.Popen, timeout: float) -> int:
    """SIGINT, then SIGKILL after ``timeout`` s; its exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class RosMaster:
    """``roscore -p PORT`` in its own process group (killed as a group at :meth:`close`);
    :attr:`env` is the environment its clients need (``ROS_MASTER_URI``, ``ROS_HOME``)."""

    def __init__(self, log_dir: Path, port: int | None = None, timeout_s: float = 30.0) -> None:
        roscore = shutil.which("roscore")
        if roscore is None:
            raise FileNotFoundError("roscore is not installed (apt-get install ros-core)")
        self.port = port or free_port()
        log_dir.mkdir(parents=True, exist_ok=True)
        self.env = dict(os.environ)
        self.env.update(
            ROS_MASTER_URI=f"http://127.0.0.1:{self.port}",
            ROS_HOME=str(log_dir),
            ROS_LOG_DIR=str(log_dir),
            ROS_IP="127.0.0.1",
        )
        self._log = (log_dir / "roscore.log").open("w")
        self.proc = subprocess.Popen(
            [roscore, "-p", str(self.port)],
            env=self.env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                self.close()
                raise RuntimeError(f"roscore exited with {self.proc.returncode}: see {log_dir}")
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), 0.2),
            ):
                break
            time.sleep(0.1)
        else:
            self.close()
            raise RuntimeError(f"roscore did not listen on {self.port} within {timeout_s} s")
        time.sleep(0.5)  # the master answers before rosout is up

    def _descendants(self) -> list[int]:
        """roscore's children (rosmaster, rosout), which sit in process groups of their own."""
        found, todo = [], [self.proc.pid]
        while todo:
            pid = todo.pop()
            with contextlib.suppress(OSError):
                kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
                found += [int(k) for k in kids]
                todo += [int(k) for k in kids]
        return found

    def close(self) -> None:
        children = self._descendants()
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(10.0)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        for pid in children:  # rosmaster and rosout, if roslaunch left them behind
            with contextlib.suppress(OSError):  # gone (and the pid not reused for another)
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
                if f"{self.env['ROS_HOME']}".encode() in cmd or f"{self.port}".encode() in cmd:
                    os.kill(pid, signal.SIGKILL)
        self._log.close()

    def __enter__(self) -> RosMaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Player:
    """Publishes ``folder`` on ``config``'s topics and records the Odometry it sees."""

    def __init__(self, folder: Path, config: Ros1Config, env: dict[str, str]) -> None:
        self.sequence = EurocSequence(folder)
        self.bridge = BridgeProcess("player", config, env=env)
        self.odometry: dict[int, float] = {}  # stamp -> monotonic arrival
        self.published: dict[int, float] = {}  # image stamp -> monotonic publication
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for kind, payload in self.bridge.frames():
            if kind == wire.ODOM:
                self.odometry.setdefault(wire.read_odom(payload), time.monotonic())

    def play(self, realtime: bool = True, max_frames: int | None = None) -> None:
        """Publish every frame's IMU then its image, at the camera rate (``realtime``)."""
        stop = len(self.sequence) if max_frames is None else min(max_frames, len(self.sequence))
        t0_wall: float | None = None
        t0 = 0
        for fr in self.sequence.frames(0, stop):
            if realtime:
                if t0_wall is None:
                    t0_wall, t0 = time.monotonic(), fr.timestamp_ns
                delay = t0_wall + (fr.timestamp_ns - t0) * 1e-9 - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            out = bytearray()
            for t, g, a in zip(fr.imu.timestamps_ns, fr.imu.gyro, fr.imu.accel, strict=True):
                gx, gy, gz = (float(v) for v in g)
                ax, ay, az = (float(v) for v in a)
                out += wire.imu(int(t), (gx, gy, gz), (ax, ay, az))
            assert fr.image is not None
            h, w = fr.image.shape
            out += wire.image(fr.timestamp_ns, h, w, w, "mono8", fr.image.tobytes())
            self.bridge.send(bytes(out))
            self.published[fr.timestamp_ns] = time.monotonic()

    def wait_odometry(self, timeout_s: float, settle_s: float = 3.0) -> None:
        """Until every published frame has its Odometry, or none came for ``settle_s``, or
        ``timeout_s`` passed."""
        deadline = time.monotonic() + timeout_s
        last, n = time.monotonic(), -1
        while time.monotonic() < deadline:
            if len(self.odometry) != n:
                last, n = time.monotonic(), len(self.odometry)
            if set(self.published) <= set(self.odometry) or time.monotonic() - last > settle_s:
                return
            time.sleep(0.1)

    def close(self) -> None:
        self.bridge.close()
        self._reader.join(5.0)

    def __enter__(self) -> Player:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
