"""Starting the ROS 1 bridge process and talking to it (the project's side; no rospy here).

:class:`BridgeProcess` listens on a Unix socket in a private temporary folder, starts
``python3 -m services.robot.ros1.bridge`` under the Python that has ``rospy`` (Debian's
``/usr/bin/python3``; the project's folder on that process's ``PYTHONPATH`` so that it finds
the wire module, nothing else), accepts its connection and waits for its ``READY``. The ROS
master is the environment's (``ROS_MASTER_URI``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import subprocess
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from common.errors import RecslamError
from services.robot.ros1 import wire

logger = logging.getLogger(__name__)

PROJECT_ROOT = Path(__file__).resolve().parents[3]
ROS_PYTHON = Path("/usr/bin/python3")


class RosUnavailableError(RecslamError):
    """ROS 1 (rospy, roscore) is not installed here."""


@dataclass(frozen=True)
class Ros1Config:
    """The ROS side of a robot: topics in, topic and frames out, the Python with rospy.

    Attributes:
        image_topic: ``sensor_msgs/Image`` topic of the camera (mono8, bgr8, rgb8, mono16).
        imu_topic: ``sensor_msgs/Imu`` topic (gyro and accelerometer, IMU frame).
        odom_topic: ``nav_msgs/Odometry`` topic of the pose (``odom``).
        map_frame, base_frame: TF frames of the pose (``map -> base_link``).
        global_frame: TF parent of ``map_frame`` once the cloud has placed the robot's map in
            its global map (``world -> map``, from that placement; re-sent when it moves).
        python: the interpreter that imports rospy (Debian's ``/usr/bin/python3``).
        node_name: the bridge's node name (anonymous: a suffix is added).
        connect_timeout_s: longest wait for the bridge to reach the master (30 s).
    """

    image_topic: str
    imu_topic: str
    odom_topic: str = "odom"
    map_frame: str = "map"
    base_frame: str = "base_link"
    global_frame: str = "world"
    python: Path = ROS_PYTHON
    node_name: str = "recslam_robot"
    connect_timeout_s: float = 30.0


def check_ros(python: Path = ROS_PYTHON) -> None:
    """RosUnavailableError unless ``python`` imports rospy and the ROS messages we use."""
    if not python.is_file():
        raise RosUnavailableError(f"{python} missing: ROS 1 needs Debian's python3 with rospy")
    probe = "import rospy, tf2_ros, nav_msgs.msg, sensor_msgs.msg"
    done = subprocess.run([str(python), "-c", probe], capture_output=True, text=True)
    if done.returncode != 0:
        raise RosUnavailableError(
            f"{python} cannot import rospy/tf2_ros/nav_msgs/sensor_msgs (apt-get install "
            f"ros-core python3-rospy python3-sensor-msgs python3-nav-msgs python3-tf2-ros): "
            f"{done.stderr.strip().splitlines()[-1] if done.stderr.strip() else done.returncode}"
        )


class BridgeProcess:
    """One bridge process (``mode`` ``robot`` or ``player``) and its socket."""

    def __init__(self, mode: str, config: Ros1Config, env: dict[str, str] | None = None) -> None:
        self._dir = tempfile.TemporaryDirectory(prefix="recslam-ros1-")
        path = os.path.join(self._dir.name, "bridge.sock")
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(path)
        server.listen(1)
        server.settimeout(config.connect_timeout_s)
        child_env = dict(os.environ if env is None else env)
        child_env["PYTHONPATH"] = str(PROJECT_ROOT)
        cmd = [
            str(config.python),
            "-m",
            "services.robot.ros1.bridge",
            "--mode",
            mode,
            "--socket",
            path,
            "--image-topic",
            config.image_topic,
            "--imu-topic",
            config.imu_topic,
            "--odom-topic",
            config.odom_topic,
            "--map-frame",
            config.map_frame,
            "--base-frame",
            config.base_frame,
            "--global-frame",
            config.global_frame,
            "--node-name",
            config.node_name,
        ]
        self.proc = subprocess.Popen(cmd, env=child_env, cwd=self._dir.name)
        self._lock = threading.Lock()
        self._reader = wire.FrameReader()
        try:
            self.sock, _ = server.accept()
        except TimeoutError as exc:
            self.close()
            raise RosUnavailableError(
                f"the ROS bridge did not connect within {config.connect_timeout_s} s"
            ) from exc
        finally:
            server.close()
        self.sock.settimeout(config.connect_timeout_s)
        ready = next(self.frames(), None)
        self.sock.settimeout(None)
        if ready is None or ready[0] != wire.READY:
            self.close()
            raise RosUnavailableError("the ROS bridge did not reach the ROS master")
        logger.info("ROS bridge (%s) up: pid %d", mode, self.proc.pid)

    def send(self, data: bytes) -> None:
        """Send frames to the bridge (any thread)."""
        with self._lock:
            self.sock.sendall(data)

    def frames(self) -> Iterator[tuple[int, bytes]]:
        """The bridge's frames until its socket closes."""
        while True:
            try:
                data = self.sock.recv(1 << 20)
            except OSError:
                return
            if not data:
                return
            self._reader.feed(data)
            yield from self._reader.frames()

    def shutdown(self) -> None:
        """Stop reading (a blocked :meth:`frames` returns)."""
        with contextlib.suppress(OSError, AttributeError):
            self.sock.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        """Close the socket and end the bridge (terminate, then kill after 5 s)."""
        self.shutdown()
        with contextlib.suppress(AttributeError):
            self.sock.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._dir.cleanup()

    def __enter__(self) -> BridgeProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
