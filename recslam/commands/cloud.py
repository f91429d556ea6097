"""``recslam cloud``: run the cloud tier (map fusion, global optimisation, MBP, dashboard).

    recslam cloud --listen 0.0.0.0:7100 --state-dir state/cloud --results out/ \\
        --groundtruth datasets/synthetic --secret-file secret.txt

Edges connect with role "edge" and their edge id as agent id. The state directory is a
SQLite database: a restarted cloud with the same ``--state-dir`` resumes with every keyframe
it had acknowledged. SIGINT / SIGTERM stop it cleanly: connections are closed, trajectories
(``RESULT_DIR/trajectories/<robot>.tum``) and, with ``--groundtruth``, the ATE report
(``RESULT_DIR/eval/``) are written.

The shared secret comes from ``--secret-file`` or the ``RECSLAM_SECRET`` environment
variable (at least 16 bytes). Each robot's camera calibration arrives from its edge
(``AgentSensors``) and is persisted with the state. ``--camera`` (an EuRoC ``sensor.yaml``)
is only a fallback for robots whose calibration never arrives (recordings made before
calibrations travelled); without it the fallback is the first
``<robot>/mav0/cam0/sensor.yaml`` of ``--groundtruth``, else the synthetic dataset's
EuRoC-like camera.

The options and the run loop are the service's (``services/cloud/runner.py``, also run by
``python -m services.cloud``); this module only registers them.
"""

from __future__ import annotations

import argparse
import functools

from services.cloud.runner import add_arguments, config_from_args, serve
from services.cloud.runner import find_camera as find_camera  # used by `experiment table3`


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "cloud",
        help="run the cloud service (map fusion, global optimisation, MBP, dashboard)",
        description=__doc__.split("\n\n")[0],
    )
    add_arguments(p)
    p.set_defaults(func=handle)


def handle(args: argparse.Namespace) -> int:
    return serve(config_from_args(args), announce=functools.partial(print, flush=True))
