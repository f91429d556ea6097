"""``recslam robot``: play a sequence as one robot and stream coded frames to an edge.

Example::

    recslam robot --dataset datasets/V1_01_easy --edge 127.0.0.1:7000 --agent-id robot-1
    recslam robot --bag run.bag --calibration camchain.yaml --edge 127.0.0.1:7000 --agent-id r2

The calibration is the folder's (``mav0/cam0/sensor.yaml`` + ``mav0/imu0/sensor.yaml``:
EuRoC, TUM-VI; else a Kalibr ``camchain*.yaml`` + ``imu*.yaml`` in the folder) unless
``--calibration`` names a file or folder; a bag holds none, so ``--bag`` needs it. The
topics default to the Kalibr files' ``rostopic``. A bad calibration (missing field, unknown
model, wrong coefficient count, non-rigid transform, resolution unlike the images) stops the
robot before it starts, naming the file and the field.

The shared secret comes from ``--secret-file`` or the environment variable
``RECSLAM_SECRET`` (a development default is used with a warning otherwise). For containers,
``--dataset``, ``--edge`` and ``--agent-id`` default to ``$RECSLAM_DATASET``,
``$RECSLAM_EDGE`` and ``$RECSLAM_AGENT_ID``. Exit code 0 once
the edge has taken every frame, 130 when interrupted, 1 when ``--flush-timeout`` expired,
2 on a configuration error.
"""

from __future__ import annotations

import argparse

from services.robot.runner import ENV_DEFAULTS as ENV_DEFAULTS
from services.robot.runner import add_arguments, serve
from services.robot.runner import config_from_args as build_config


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "robot",
        help="play a sequence as a robot: track, code and send frames to an edge",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    return serve(build_config(args))
