"""The robot service as a process: its arguments, its run config and its run.

``add_arguments`` defines the options once, for ``recslam robot`` and ``python -m
services.robot`` alike (``--dataset``, ``--edge`` and ``--agent-id`` default to the
environment variables of :data:`ENV_DEFAULTS`, for containers; ``--bag`` with
``--calibration`` and the topics plays a ROS bag instead of a folder); ``config_from_args`` turns
them into a :class:`~services.robot.server.RobotServiceConfig` (its keys loaded: its
``--key-file``, else the operator secret of ``--secret-file``, else ``$RECSLAM_SECRET``,
else a development default with a warning);
``serve`` plays the sequence with SIGINT / SIGTERM handled
(:func:`services.robot.server.serve`). Exit code 0 once the edge has taken every frame, 130
when interrupted, 1 when ``--flush-timeout`` expired, 3 when the edge refused the robot (e.g.
another calibration under an agent id it knows) or its credential, 4 when there was no session
with the edge for ``--give-up-after`` seconds; a configuration error raises
:class:`~common.errors.RecslamError` (the entry points exit with 2).

The service modules (OpenCV, the front end) are imported inside the functions so that
parsing and ``--help`` stay fast.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import TYPE_CHECKING

from common.entry import add_give_up_argument, add_security_arguments
from services.robot.uplink_budget import UplinkBudgetConfig

if TYPE_CHECKING:
    from common.protocol.auth import Keyring
    from services.robot.ros1.source import Ros1RunConfig
    from services.robot.service_config import RobotServiceConfig

ENV_DEFAULTS = {
    "dataset": "RECSLAM_DATASET",
    "edge": "RECSLAM_EDGE",
    "agent_id": "RECSLAM_AGENT_ID",
}
"""Argument (``dest``) -> the environment variable that supplies it when it is not given."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The robot's options; the environment (:data:`ENV_DEFAULTS`) is read now."""
    env = {k: os.environ.get(v) for k, v in ENV_DEFAULTS.items()}
    p.add_argument(
        "--dataset",
        type=Path,
        default=env["dataset"],
        help="EuRoC-layout sequence folder: EuRoC, TUM-VI, synthetic ($RECSLAM_DATASET)",
    )
    p.add_argument(
        "--bag",
        type=Path,
        default=None,
        help="ROS 1 .bag file or ROS 2 bag folder instead of --dataset (needs --calibration)",
    )
    p.add_argument(
        "--calibration",
        type=Path,
        default=None,
        metavar="PATH",
        help="Kalibr camchain.yaml (imu.yaml beside it), EuRoC cam0/sensor.yaml, or a folder "
        "holding them; overrides the dataset folder's own",
    )
    p.add_argument(
        "--source",
        choices=("folder", "bag", "ros1"),
        default=None,
        help="where the frames come from: folder (--dataset, default), bag (--bag), or ros1: "
        "live ROS 1 topics (--image-topic, --imu-topic, --calibration; publishes "
        "nav_msgs/Odometry on --odom-topic and TF --map-frame -> --base-frame)",
    )
    p.add_argument(
        "--image-topic", default=None, help="the bag's or ROS's camera topic (sensor_msgs/Image)"
    )
    p.add_argument("--imu-topic", default=None, help="the bag's or ROS's IMU topic (Imu)")
    p.add_argument(
        "--max-pending-images",
        type=int,
        default=2,
        metavar="N",
        help="ros1: images waiting for tracking before the oldest is dropped (default 2: "
        "fresh poses; more: fewer drops when the CPU falls behind, later poses)",
    )
    p.add_argument("--odom-topic", default="odom", help="ros1: Odometry topic (default odom)")
    p.add_argument("--map-frame", default="map", help="ros1: TF parent frame (default map)")
    p.add_argument(
        "--global-frame",
        default="world",
        help="ros1: TF parent of --map-frame once the cloud has placed the robot's map in its "
        "global map (the frame all merged robots share; default world)",
    )
    p.add_argument(
        "--base-frame", default="base_link", help="ros1: TF child frame (default base_link)"
    )
    p.add_argument(
        "--edge",
        metavar="HOST:PORT",
        default=env["edge"],
        required=env["edge"] is None,
        help="the edge's address ($RECSLAM_EDGE)",
    )
    p.add_argument(
        "--agent-id",
        default=env["agent_id"],
        required=env["agent_id"] is None,
        help="this robot's id, unique per edge ($RECSLAM_AGENT_ID)",
    )
    p.add_argument(
        "--rate",
        choices=("realtime", "max"),
        default="realtime",
        help="realtime: camera rate (default); max: as fast as the front end runs",
    )
    add_security_arguments(p)
    p.add_argument("--start", type=int, default=0, help="first frame to play (default 0)")
    p.add_argument("--max-frames", type=int, default=None, help="play at most this many frames")
    p.add_argument(
        "--backlog-minutes",
        type=float,
        default=30.0,
        help="edge outage absorbed before back-pressure (default 30 min)",
    )
    p.add_argument(
        "--flush-timeout",
        type=float,
        default=None,
        help="seconds to wait at the end for the edge to take the rest (default: wait)",
    )
    p.add_argument(
        "--stop-flush-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="after SIGINT/SIGTERM, seconds to flush the backlog to the edge before giving up "
        "(default 10; a second signal gives up at once)",
    )
    p.add_argument(
        "--handover",
        action="append",
        default=[],
        metavar="FRAME=HOST:PORT",
        help="from sequence frame FRAME on, end the session with the current edge (after it "
        "took everything) and continue with the edge at HOST:PORT (repeat, in frame order)",
    )
    p.add_argument(
        "--pose-out",
        type=Path,
        default=None,
        metavar="FILE.tum",
        help="write the robot's pose at every frame, as the edge sends it back, to this TUM "
        "file as it arrives (the robot's own map frame; default: none)",
    )
    p.add_argument(
        "--global-pose-out",
        type=Path,
        default=None,
        metavar="FILE.tum",
        help="also write each pose in the cloud's global map (the robot's map placed where the "
        "cloud merged it; frames before the first placement are not written; a '# global map "
        "N' comment line precedes the poses of each global map; default: none)",
    )
    p.add_argument(
        "--pose-wait",
        type=float,
        default=0.0,
        metavar="S",
        help="after the last frame, wait up to S seconds for the edge's poses of the frames it "
        "is still working on (default 0: stop once the edge took the frames)",
    )
    p.add_argument(
        "--stats-out",
        type=Path,
        default=None,
        metavar="FILE.json",
        help="write the run's counters and the pose latency (camera frame -> its pose back on "
        "the robot: median, p95, max) to this JSON file at the end (default: none)",
    )
    p.add_argument(
        "--uplink-budget",
        default=None,
        metavar="KBPS|auto",
        help="the link's rate to the edge in kbit/s, or 'auto' (estimated from the link's "
        "acknowledgements): keyframes and the IMU always go, non-keyframes at the rate the "
        "budget leaves (20/10/5 Hz) and only when the link's backlog drains within 0.7 s "
        "(fresh before complete); default: none, every frame goes",
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="play the folder as a live driver would: at the camera's pace, an image that "
        "comes while tracking is behind drops the oldest waiting one (default: wait, so no "
        "frame is dropped)",
    )
    add_give_up_argument(p, "edge")


def uplink_from_args(args: argparse.Namespace) -> UplinkBudgetConfig:
    """``--uplink-budget`` (RobotConfigError when it is not kbit/s, auto or unlimited)."""
    from services.robot.service_config import RobotConfigError

    try:
        return UplinkBudgetConfig.parse(args.uplink_budget)
    except ValueError as exc:
        raise RobotConfigError(f"--uplink-budget: {exc}") from None


def config_from_args(args: argparse.Namespace) -> RobotServiceConfig | Ros1RunConfig:
    """RobotServiceConfig (a folder or a bag) or Ros1RunConfig (``--source ros1``) from parsed
    arguments (RobotConfigError on bad values, CredentialsError on a bad address or secret)."""
    if args.source == "ros1":
        return ros1_config_from_args(args)
    if args.source == "bag" and args.bag is None:
        from services.robot.service_config import RobotConfigError

        raise RobotConfigError("--source bag needs --bag PATH")
    from common.entry import tls_from_args
    from common.protocol.credentials import parse_address
    from services.robot.service_config import (
        Handover,
        Rate,
        RobotConfigError,
        RobotServiceConfig,
    )

    host, port = parse_address(args.edge)
    if args.backlog_minutes is None or args.backlog_minutes <= 0:
        raise RobotConfigError(f"--backlog-minutes must be positive, got {args.backlog_minutes}")
    dataset = args.dataset
    if args.bag is not None and dataset is not None:
        from_env = os.environ.get(ENV_DEFAULTS["dataset"])
        if from_env is None or Path(from_env) != dataset:
            raise RobotConfigError("give --dataset or --bag, not both")
        dataset = None  # $RECSLAM_DATASET gives way to an explicit --bag
    handovers = []
    for text in args.handover:
        frame, sep, address = text.partition("=")
        if not sep or not frame.strip().isdigit():
            raise RobotConfigError(f"--handover {text!r} is not FRAME=HOST:PORT")
        handovers.append(Handover(int(frame), *parse_address(address)))
    return RobotServiceConfig(
        handovers=tuple(handovers),
        dataset=dataset,
        bag=args.bag,
        calibration=args.calibration,
        image_topic=args.image_topic,
        imu_topic=args.imu_topic,
        edge_host=host,
        edge_port=port,
        agent_id=args.agent_id,
        secret=_robot_keys(args),
        tls=tls_from_args(args),
        rate=Rate(args.rate),
        start_frame=args.start,
        max_frames=args.max_frames,
        backlog_s=60.0 * args.backlog_minutes,
        flush_timeout_s=args.flush_timeout,
        stop_flush_timeout_s=args.stop_flush_timeout,
        give_up_after_s=args.give_up_after,
        pose_out=args.pose_out,
        global_pose_out=args.global_pose_out,
        pose_wait_s=args.pose_wait,
        stats_out=args.stats_out,
        uplink=uplink_from_args(args),
        live=args.live,
    )


def _robot_keys(args: argparse.Namespace) -> Keyring:
    """The robot's credentials from ``--key-file`` / ``--secret-file`` (the dev secret without)."""
    from common.protocol.credentials import load_keys
    from services.robot.service_config import DEV_SECRET

    return load_keys(
        args.key_file, args.secret_file, dev_default=DEV_SECRET, identity=("robot", args.agent_id)
    )


def ros1_config_from_args(args: argparse.Namespace) -> Ros1RunConfig:
    """The live ROS 1 robot's config: the calibration file (required), the topics, the edge."""
    from common.data.calibration_files import load_calibration
    from common.entry import tls_from_args
    from common.links.sensors import Sensors
    from common.protocol.credentials import parse_address
    from services.robot.client import RobotClientConfig
    from services.robot.core import LiveInputConfig
    from services.robot.ros1.process import Ros1Config
    from services.robot.ros1.source import Ros1RunConfig
    from services.robot.service_config import RobotConfigError

    if args.bag is not None:
        raise RobotConfigError("--source ros1 reads live topics: --bag does not apply")
    if args.calibration is None:
        raise RobotConfigError(
            "--source ros1 needs --calibration (Kalibr camchain.yaml, EuRoC sensor.yaml, or a "
            "folder holding them): topics carry no calibration"
        )
    if args.max_pending_images < 1:
        raise RobotConfigError(f"--max-pending-images must be >= 1, got {args.max_pending_images}")
    calibration = load_calibration(args.calibration)
    image_topic = args.image_topic or calibration.image_topic
    imu_topic = args.imu_topic or calibration.imu_topic
    if not image_topic or not imu_topic:
        raise RobotConfigError("--source ros1 needs --image-topic and --imu-topic")
    host, port = parse_address(args.edge)
    robot = RobotClientConfig(
        sensors=Sensors(calibration.cam0, calibration.imu),
        edge_host=host,
        edge_port=port,
        agent_id=args.agent_id,
        secret=_robot_keys(args),
        tls=tls_from_args(args),
        time_shift_ns=round(calibration.timeshift_cam_imu_s * 1e9),
        backlog_s=60.0 * args.backlog_minutes,
        close_timeout_s=args.flush_timeout if args.flush_timeout is not None else 30.0,
        live=LiveInputConfig(max_pending_images=args.max_pending_images),
        uplink=uplink_from_args(args),
    )
    ros = Ros1Config(
        image_topic=image_topic,
        imu_topic=imu_topic,
        odom_topic=args.odom_topic,
        map_frame=args.map_frame,
        global_frame=args.global_frame,
        base_frame=args.base_frame,
    )
    return Ros1RunConfig(robot, ros, pose_out=args.pose_out, stats_out=args.stats_out)


def serve(config: RobotServiceConfig | Ros1RunConfig) -> int:
    """Play the sequence on a fresh event loop, or run live from ROS (see the module docstring
    for the exit code)."""
    from services.robot.ros1.source import Ros1RunConfig

    if isinstance(config, Ros1RunConfig):
        from services.robot.ros1.source import serve as serve_ros1

        return serve_ros1(config)
    from common.transport import run
    from services.robot.server import serve as serve_async

    return run(serve_async(config))
