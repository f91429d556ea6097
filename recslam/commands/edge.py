"""``recslam edge``: run the edge tier (per-robot VIO, feedback to robots, uplink to the cloud).

    recslam edge --listen 0.0.0.0:7000 --cloud cloud-host:7100 --state-dir state/edge \\
        --secret-file secret.txt

Robots connect with role "robot" and their robot name as agent id; the edge connects to the
cloud with role "edge" and ``--agent-id``. With ``--state-dir`` every robot's frames are
journaled before they are acknowledged, and a restarted edge (same directory) replays the
journals and loses nothing; without it a restart loses every robot's state.

Each robot brings its own calibration: its stream starts with its camera and IMU description
(``RobotSensors``), from which the edge builds that robot's decoders and VIO, and which it
forwards to the cloud. A robot re-joining under the same agent id with another calibration is
refused with the reason.
The shared secret comes from ``--secret-file`` or ``$RECSLAM_SECRET`` (at least 16 bytes).
SIGINT / SIGTERM stop it cleanly (journals are fsynced).

The options and the run loop are the service's (``services/edge/runner.py``, also run by
``python -m services.edge``); this module only registers them.
"""

from __future__ import annotations

import argparse
import functools

from common.links import codec_cpu as codec_cpu  # its former home; tests import it from here
from services.edge.runner import add_arguments, config_from_args, serve


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "edge",
        help="run the edge service (per-robot VIO, feedback, uplink to the cloud)",
        description=__doc__.split("\n\n")[0],
    )
    add_arguments(p)
    p.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    return serve(config_from_args(args), announce=functools.partial(print, flush=True))
