"""``recslam cloud``: run the cloud tier (map fusion, global optimisation, MBP, dashboard).

    recslam cloud --listen 0.0.0.0:7100 --state-dir state/cloud --results out/ \\
        --groundtruth datasets/synthetic --secret-file secret.txt

Edges connect with role "edge" and their edge id as agent id. The state directory is a
SQLite database: a restarted cloud with the same ``--state-dir`` resumes with every keyframe
it had acknowledged. SIGINT / SIGTERM stop it cleanly: connections are closed, trajectories
(``RESULT_DIR/trajectories/<robot>.tum``) and, with ``--groundtruth``, the ATE report
(``RESULT_DIR/eval/``) are written.

The shared secret comes from ``--secret-file`` or the ``RECSLAM_SECRET`` environment
variable (at least 16 bytes). The camera calibration comes from ``--camera`` (an EuRoC
``sensor.yaml``), else from the first ``<robot>/mav0/cam0/sensor.yaml`` of
``--groundtruth``, else the synthetic dataset's EuRoC-like camera.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path

from common.protocol.credentials import SECRET_ENV, load_secret, parse_address

log = logging.getLogger(__name__)


def _address(text: str) -> tuple[str, int]:
    return parse_address(text, default_host="0.0.0.0")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "cloud",
        help="run the cloud service (map fusion, global optimisation, MBP, dashboard)",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument(
        "--listen",
        type=_address,
        default=("0.0.0.0", 7100),
        metavar="HOST:PORT",
        help="address edges connect to (default 0.0.0.0:7100)",
    )
    p.add_argument(
        "--state-dir",
        type=Path,
        required=True,
        metavar="DIR",
        help="SQLite state directory (created; resumed when it exists)",
    )
    p.add_argument(
        "--dashboard-port",
        type=int,
        default=8080,
        metavar="PORT",
        help="viser dashboard port, 0 disables it (default 8080)",
    )
    p.add_argument(
        "--results",
        type=Path,
        default=None,
        metavar="DIR",
        help="result folder for trajectories/ and eval/ (default: none)",
    )
    p.add_argument(
        "--groundtruth",
        type=Path,
        default=None,
        metavar="DATASET",
        help="ground truth for the ATE report (dataset folder or file)",
    )
    p.add_argument(
        "--secret-file",
        type=Path,
        default=None,
        metavar="F",
        help=f"shared secret file (default: ${SECRET_ENV})",
    )
    p.add_argument(
        "--camera",
        type=Path,
        default=None,
        metavar="SENSOR_YAML",
        help="EuRoC cam0 sensor.yaml of the robots' camera",
    )
    p.add_argument(
        "--vocabulary",
        type=Path,
        default=None,
        metavar="NPZ",
        help="vocabulary file (default: common/assets/orb_vocabulary.npz)",
    )
    p.add_argument(
        "--mbp",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="map backbone profiling on/off (default on: one pass over every map at shutdown, "
        "after the last full BA; pruning while running cost accuracy, see "
        "benchmarks/results/table3.md)",
    )
    p.add_argument(
        "--full-ba",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="full bundle adjustment after the pose graph when there is time, and at exit "
        "(default on; --no-full-ba: pose graph only)",
    )
    p.add_argument("--agent-id", default="cloud", help="this service's agent id (default cloud)")
    p.add_argument(
        "--wire",
        choices=("coded", "raw"),
        default="coded",
        help="encoding of the pose corrections to the edges: coded (default) or raw (the "
        "float64 schema-1 baseline; edges accept both)",
    )
    p.add_argument(
        "--output-every",
        type=float,
        default=30.0,
        metavar="S",
        help="rewrite outputs every S seconds, 0 = only at exit (default 30)",
    )
    p.add_argument(
        "--stats-out",
        type=Path,
        default=None,
        metavar="FILE",
        help="rewrite service counters and per-edge traffic counters as JSON here every "
        "second and at exit (default: none)",
    )
    p.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="FILE",
        help="append every applied uplink message to this recording (replayed by "
        "'recslam experiment table3'; default: off)",
    )
    p.set_defaults(func=handle)


async def write_stats(path: Path, cloud, codec_owners: Sequence[object] = ()) -> None:
    """Write the cloud's counters and every edge link's traffic counters to ``path`` (JSON;
    also after ``cloud.stop()``: both keep their final values), with the codec CPU of the
    ``codec_owners`` that have a ``codec_timer`` (``codec_cpu``; the application's timer
    keeps its counts after ``stop()``)."""
    import dataclasses
    import json
    import time

    from recslam.commands.edge import codec_cpu

    stats = dataclasses.asdict(await cloud.stats())
    cpu = codec_cpu([cloud, *codec_owners])
    if cpu is not None:
        stats["codec_cpu"] = cpu
    stats["links"] = cloud.transport.counters()
    stats["time"] = time.time()
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(stats))
    tmp.replace(path)


def find_camera(camera: Path | None, groundtruth: Path | None):
    """The robots' camera (see the module docstring)."""
    from common.data.euroc import read_camera_yaml
    from services.cloud.simulation import default_camera

    if camera is not None:
        return read_camera_yaml(camera)
    if groundtruth is not None and groundtruth.is_dir():
        for yaml in sorted(groundtruth.glob("*/mav0/cam0/sensor.yaml")) + sorted(
            groundtruth.glob("mav0/cam0/sensor.yaml")
        ):
            log.info("camera calibration from %s", yaml)
            return read_camera_yaml(yaml)
    log.warning("no --camera: using the synthetic dataset's EuRoC-like camera")
    return default_camera()


def handle(args: argparse.Namespace) -> int:
    import asyncio
    import contextlib
    import dataclasses
    import signal

    from common.errors import RecslamError
    from common.links import WireFormat
    from common.protocol import SessionConfig
    from common.transport import TransportConfig, run
    from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
    from services.cloud.config import CloudConfig, CloudServiceConfig, FullBAConfig, MbpConfig
    from services.cloud.server import CloudServer

    try:
        secret = load_secret(args.secret_file)
        camera = find_camera(args.camera, args.groundtruth)
        vocab = Vocabulary.load(args.vocabulary or DEFAULT_VOCABULARY_PATH)
    except RecslamError as exc:
        log.error("%s", exc)
        return 2
    domain = CloudConfig(
        mbp=dataclasses.replace(MbpConfig(), enabled=args.mbp),
        full_ba=dataclasses.replace(FullBAConfig(), enabled=args.full_ba),
    )
    config = CloudServiceConfig(
        domain=domain, output_every_s=args.output_every, wire=WireFormat(args.wire)
    )
    session = SessionConfig("cloud", args.agent_id, secret)

    async def main() -> int:
        cloud = CloudServer(
            session,
            args.state_dir,
            camera,
            vocab,
            config,
            results_dir=args.results,
            groundtruth=args.groundtruth,
            transport=TransportConfig(accept_roles=("edge",)),
            record=args.record,
        )
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        host, port = await cloud.start(*args.listen)
        # The application's codec_timer (if it has one) stays readable after stop().
        codec_owners = [await cloud.call(lambda app: app)]
        print(f"cloud listening on {host}:{port}, state {args.state_dir}", flush=True)
        dashboard = None
        if args.dashboard_port:
            from dashboard.viewer import Dashboard, DashboardConfig

            dashboard = Dashboard(cloud.map_source, DashboardConfig(port=args.dashboard_port))
            dashboard.start()
            print(f"dashboard at {dashboard.url}", flush=True)
        try:
            while not stop.is_set():
                if args.stats_out is not None:
                    await write_stats(args.stats_out, cloud, codec_owners)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), 1.0)
        finally:
            print("cloud stopping", flush=True)
            if dashboard is not None:
                dashboard.stop()
            if args.stats_out is not None:
                await write_stats(args.stats_out, cloud, codec_owners)
            await cloud.stop()
            if args.stats_out is not None:  # again: shutdown's optimisation and MBP counted
                await write_stats(args.stats_out, cloud, codec_owners)
        return 0

    return run(main())
