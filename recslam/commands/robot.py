"""``recslam robot``: play a sequence as one robot and stream coded frames to an edge.

Example::

    recslam robot --dataset datasets/V1_01_easy --edge 127.0.0.1:7000 --agent-id robot-1

The shared secret comes from ``--secret-file`` or the environment variable
``RECSLAM_SECRET`` (a development default is used with a warning otherwise). For containers,
``--dataset``, ``--edge`` and ``--agent-id`` default to ``$RECSLAM_DATASET``,
``$RECSLAM_EDGE`` and ``$RECSLAM_AGENT_ID``. Exit code 0 once
the edge has taken every frame, 130 when interrupted, 1 when ``--flush-timeout`` expired,
2 on a configuration error.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

ENV_DEFAULTS = {
    "dataset": "RECSLAM_DATASET",
    "edge": "RECSLAM_EDGE",
    "agent_id": "RECSLAM_AGENT_ID",
}


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "robot",
        help="play a sequence as a robot: track, code and send frames to an edge",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    env = {k: os.environ.get(v) for k, v in ENV_DEFAULTS.items()}
    p.add_argument(
        "--dataset",
        type=Path,
        default=env["dataset"],
        required=env["dataset"] is None,
        help="EuRoC-layout sequence folder ($RECSLAM_DATASET)",
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
    p.add_argument("--secret-file", type=Path, default=None, help="file holding the shared secret")
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
    p.set_defaults(func=run)


def build_config(args: argparse.Namespace):
    """RobotServiceConfig from parsed arguments (RobotConfigError on bad values)."""
    from common.protocol.credentials import load_secret, parse_address
    from services.robot.server import DEV_SECRET, Rate, RobotConfigError, RobotServiceConfig

    host, port = parse_address(args.edge)
    if args.backlog_minutes is None or args.backlog_minutes <= 0:
        raise RobotConfigError(f"--backlog-minutes must be positive, got {args.backlog_minutes}")
    return RobotServiceConfig(
        dataset=args.dataset,
        edge_host=host,
        edge_port=port,
        agent_id=args.agent_id,
        secret=load_secret(args.secret_file, dev_default=DEV_SECRET),
        rate=Rate(args.rate),
        start_frame=args.start,
        max_frames=args.max_frames,
        backlog_s=60.0 * args.backlog_minutes,
        flush_timeout_s=args.flush_timeout,
    )


def run(args: argparse.Namespace) -> int:
    from common.transport import run as run_loop
    from services.robot.server import serve

    config = build_config(args)
    return run_loop(serve(config))
