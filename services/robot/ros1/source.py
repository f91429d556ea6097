"""``recslam robot --source ros1``: a live robot fed from ROS 1 topics, its pose published back.

The bridge process (:mod:`services.robot.ros1.bridge`) subscribes to the camera and IMU
topics; this process reads what it forwards on the main thread (a driver's thread for the
:class:`~services.robot.client.RobotClient`) and hands it to the robot; every metric pose the
edge sends back goes to the bridge, which publishes ``nav_msgs/Odometry`` and TF, and to the
TUM file of ``--pose-out``. SIGINT/SIGTERM end the input; the robot then gives the edge its
last frames, writes ``--stats-out`` and exits 0.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.geometry import R_to_quat_wxyz
from services.robot.client import RobotClient, RobotClientConfig, RobotClosedError
from services.robot.poses import ReceivedPose, open_tum, tum_line
from services.robot.ros1 import wire
from services.robot.ros1.process import BridgeProcess, Ros1Config, check_ros

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Ros1RunConfig:
    """A ROS 1 robot: the robot, its topics, and what it writes (``pose_out`` TUM,
    ``stats_out`` JSON, or None)."""

    robot: RobotClientConfig
    ros: Ros1Config
    pose_out: Path | None = None
    stats_out: Path | None = None


def pose_frame(pose: ReceivedPose) -> bytes | None:
    """The bridge's POSE frame of a metric pose (None without one)."""
    T = pose.T_map_body
    if T is None:
        return None
    w, x, y, z = (float(v) for v in R_to_quat_wxyz(T[:3, :3]))
    p = tuple(float(v) for v in T[:3, 3])
    return wire.pose(pose.timestamp_ns, pose.map_id, pose.status, p, (x, y, z, w))


def placement_of(pose: ReceivedPose) -> tuple[int, int, np.ndarray] | None:
    """``(global map, map id, T_global_map (4, 4))`` of a pose placed in the global map (None if
    it is not): ``T_global_map = T_global_body T_map_body^-1``."""
    if pose.T_global_body is None or pose.T_map_body is None or pose.global_map is None:
        return None
    return pose.global_map, pose.map_id, pose.T_global_body @ np.linalg.inv(pose.T_map_body)


def placement_frame(global_map: int, map_id: int, T_global_map: np.ndarray) -> bytes:
    """The bridge's PLACEMENT frame (the TF from the global map to the robot's map)."""
    w, x, y, z = (float(v) for v in R_to_quat_wxyz(T_global_map[:3, :3]))
    p = tuple(float(v) for v in T_global_map[:3, 3])
    return wire.placement(global_map, map_id, p, (x, y, z, w))


def placement_moved(
    last: tuple[int, int, np.ndarray] | None, new: tuple[int, int, np.ndarray]
) -> bool:
    """Whether ``new`` is worth a TF update: another map, or moved by 1 mm / ~0.01°."""
    if last is None or last[:2] != new[:2]:
        return True
    return not np.allclose(last[2], new[2], atol=1e-4)


def serve(config: Ros1RunConfig) -> int:
    """Run until SIGINT/SIGTERM or until the bridge ends; exit code 0 (1 if the robot failed)."""
    check_ros(config.ros.python)
    stop = threading.Event()
    pose_file = open_tum(config.pose_out)
    counts = {"imu": 0, "images": 0, "odometry": 0}
    with BridgeProcess("robot", config.ros) as bridge:
        placed: list[tuple[int, int, np.ndarray] | None] = [None]  # the last one sent

        def on_pose(pose: ReceivedPose) -> None:
            data = pose_frame(pose)
            if data is None:
                return
            where = placement_of(pose)
            with contextlib.suppress(OSError):
                if where is not None and placement_moved(placed[0], where):
                    bridge.send(placement_frame(*where))  # TF global frame -> map frame
                    placed[0] = where
                bridge.send(data)
                counts["odometry"] += 1
            if pose_file is not None and (line := tum_line(pose)) is not None:
                pose_file.write(f"{line}\n")

        def on_signal(signum: int, _frame: object) -> None:
            logger.warning("robot: %s: ending the input", signal.Signals(signum).name)
            stop.set()
            bridge.shutdown()

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        t0 = time.monotonic()
        try:
            with RobotClient(config.robot, on_pose=on_pose) as robot:
                logger.info(
                    "robot %s: live from ROS topics %s and %s to the edge at %s:%d",
                    config.robot.agent_id,
                    config.ros.image_topic,
                    config.ros.imu_topic,
                    config.robot.edge_host,
                    config.robot.edge_port,
                )
                for kind, payload in bridge.frames():
                    if stop.is_set():
                        break
                    if kind == wire.IMU:
                        t, g, a = wire.read_imu(payload)
                        robot.add_imu(t, g, a)
                        counts["imu"] += 1
                    elif kind == wire.IMAGE:
                        t, h, w, step, enc, data = wire.read_image(payload)
                        robot.add_raw_image(t, data, enc, h, w, step)
                        counts["images"] += 1
                stats = robot.close()
        except RobotClosedError as exc:
            logger.error("robot %s: %s", config.robot.agent_id, exc)
            return 1
        finally:
            for s, handler in old.items():
                signal.signal(s, handler)
            if pose_file is not None:
                pose_file.close()
    stats = {**stats, "ros": counts, "wall_s": time.monotonic() - t0, "time": time.time()}
    poses = stats.get("poses", {})
    logger.info(
        "robot %s: %d images and %d IMU samples from ROS, %d frames sent, %d odometry "
        "published, pose latency median %.3f s, p95 %.3f s",
        config.robot.agent_id,
        counts["images"],
        counts["imu"],
        stats.get("frames_sent", 0),
        counts["odometry"],
        poses.get("median_s", float("nan")),
        poses.get("p95_s", float("nan")),
    )
    if config.stats_out is not None:
        write_stats(config.stats_out, stats)
    return 0


def write_stats(path: Path, stats: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(stats, default=str), encoding="utf-8")
    tmp.replace(path)
