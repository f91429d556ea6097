"""``recslam edge``: run the edge tier (per-robot VIO, feedback to robots, uplink to the cloud).

    recslam edge --listen 0.0.0.0:7000 --cloud cloud-host:7100 --state-dir state/edge \\
        --camera datasets/euroc-micro-V1_01 --secret-file secret.txt

Robots connect with role "robot" and their robot name as agent id; the edge connects to the
cloud with role "edge" and ``--agent-id``. With ``--state-dir`` every robot's frames are
journaled before they are acknowledged, and a restarted edge (same directory) replays the
journals and loses nothing; without it a restart loses every robot's state.

The robots' calibration comes from ``--camera``: an EuRoC dataset folder (``mav0/cam0`` and
``mav0/imu0`` sensor.yaml files) or a cam0 ``sensor.yaml`` (the IMU is then EuRoC's ADIS16448).
The shared secret comes from ``--secret-file`` or ``$RECSLAM_SECRET`` (at least 16 bytes).
SIGINT / SIGTERM stop it cleanly (journals are fsynced).
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from common.links import WireFormat
from common.protocol.credentials import SECRET_ENV, load_secret, parse_address

log = logging.getLogger(__name__)


def _address(text: str) -> tuple[str, int]:
    return parse_address(text, default_host="0.0.0.0")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "edge",
        help="run the edge service (per-robot VIO, feedback, uplink to the cloud)",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("--listen", type=_address, default=("0.0.0.0", 7000), metavar="HOST:PORT",
                   help="address robots connect to (default 0.0.0.0:7000)")  # fmt: skip
    p.add_argument("--cloud", type=_address, default=None, metavar="HOST:PORT",
                   help="cloud address (default: none, the uplink is dropped)")  # fmt: skip
    p.add_argument("--state-dir", type=Path, default=None, metavar="DIR",
                   help="journal directory for restarts without loss (default: none)")  # fmt: skip
    p.add_argument("--secret-file", type=Path, default=None, metavar="F",
                   help=f"shared secret file (default: ${SECRET_ENV})")  # fmt: skip
    p.add_argument("--camera", type=Path, default=None, metavar="PATH",
                   help="EuRoC dataset folder or cam0 sensor.yaml (required)")  # fmt: skip
    p.add_argument("--agent-id", default="edge", help="this edge's agent id (default edge)")
    p.add_argument("--worker", choices=("process", "thread"), default="process",
                   help="where each robot's VIO runs (default: one process per robot)")  # fmt: skip
    p.add_argument("--vocabulary", type=Path, default=None, metavar="NPZ",
                   help="vocabulary file (default: common/assets/orb_vocabulary.npz)")  # fmt: skip
    p.add_argument(
        "--wire",
        choices=[w.value for w in WireFormat],
        default=WireFormat.CODED.value,
        help="encoding of the messages to the robots and the cloud: coded (default) or raw "
        "(the float64 schema-1 baseline; robots and cloud accept both)",
    )
    p.add_argument("--stats-out", type=Path, default=None, metavar="FILE",
                   help="rewrite service and per-link traffic counters as JSON here every "
                   "second and at exit (default: none)")  # fmt: skip
    p.set_defaults(func=handle)


def codec_cpu(owners: Iterable[object]) -> dict[str, dict[str, float]] | None:
    """The merged ``codec_timer.snapshot()`` of those ``owners`` that have a ``codec_timer``
    (``common.links.CodecTimer``; a timer shared by two owners counts once): ``{"encode.Type":
    {"seconds": s, "messages": n}, ...}``; None when no owner has one."""
    timers: dict[int, Any] = {}
    for owner in owners:
        timer = getattr(owner, "codec_timer", None)
        if timer is not None:
            timers.setdefault(id(timer), timer)
    if not timers:
        return None
    out: dict[str, dict[str, float]] = {}
    for timer in timers.values():
        for key, entry in timer.snapshot().items():
            acc = out.setdefault(key, {"seconds": 0.0, "messages": 0})
            acc["seconds"] += float(entry["seconds"])
            acc["messages"] += int(entry["messages"])
    return dict(sorted(out.items()))


def write_stats(path: Path, edge) -> None:
    """Write the edge's counters and every robot link's traffic counters to ``path`` (JSON),
    with the codec CPU (``codec_cpu``: all robots' sessions merged, and per robot) once the
    sessions time their codecs."""
    import json
    import time

    stats = edge.stats()
    for robot in stats["robots"].values():
        for key in ("frame_s", "track_s", "local_ba_s"):
            values = robot.pop(key)
            robot[key.removesuffix("_s") + "_mean_s"] = (
                sum(values) / len(values) if values else None
            )
    sessions = {name: rb.session for name, rb in edge.app.robots.items()}
    for name, session in sessions.items():
        cpu = codec_cpu([session])
        if cpu is not None and name in stats["robots"]:
            stats["robots"][name]["codec_cpu"] = cpu
    cpu = codec_cpu([edge, edge.app, getattr(edge, "cloud", None), *sessions.values()])
    if cpu is not None:
        stats["codec_cpu"] = cpu
    stats["links"] = edge.server.counters()
    stats["time"] = time.time()
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(stats))
    tmp.replace(path)


def read_calibration(path: Path | None):
    """(CameraCalibration, ImuCalibration) from a dataset folder or a cam0 sensor.yaml."""
    from common.calibration import EUROC_IMU
    from common.data.euroc import find_mav0, read_camera_yaml, read_imu_yaml
    from common.errors import RecslamError

    if path is None:
        raise RecslamError("--camera is required (EuRoC dataset folder or cam0 sensor.yaml)")
    if path.is_dir():
        mav0 = find_mav0(path)
        imu_yaml = mav0 / "imu0" / "sensor.yaml"
        imu = read_imu_yaml(imu_yaml) if imu_yaml.exists() else EUROC_IMU
        return read_camera_yaml(mav0 / "cam0" / "sensor.yaml"), imu
    return read_camera_yaml(path), EUROC_IMU


def handle(args: argparse.Namespace) -> int:
    import asyncio
    import contextlib
    import signal

    from common.errors import RecslamError
    from common.transport import run
    from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
    from services.edge.app import EdgeConfig
    from services.edge.robot_session import SessionOptions
    from services.edge.server import EdgeServer, EdgeServiceConfig

    try:
        secret = load_secret(args.secret_file)
        camera, imu = read_calibration(args.camera)
        vocab = Vocabulary.load(args.vocabulary or DEFAULT_VOCABULARY_PATH)
    except RecslamError as exc:
        log.error("%s", exc)
        return 2
    cloud_host, cloud_port = args.cloud if args.cloud is not None else (None, 0)
    service = EdgeServiceConfig(agent_id=args.agent_id, cloud_host=cloud_host,
                                cloud_port=cloud_port)  # fmt: skip

    async def main() -> int:
        config = EdgeConfig(worker=args.worker, session=SessionOptions(wire=WireFormat(args.wire)))
        edge = EdgeServer(secret, camera, imu, vocab, config, service, state_dir=args.state_dir)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        host, port = await edge.start(*args.listen)
        print(f"edge listening on {host}:{port}, replayed {edge.replayed_frames} frames",
              flush=True)  # fmt: skip
        try:
            while not stop.is_set():
                if args.stats_out is not None:
                    write_stats(args.stats_out, edge)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), 1.0)
        finally:
            print("edge stopping", flush=True)
            await edge.stop()  # drains the workers: their last uplinks count in the stats
            if args.stats_out is not None:
                write_stats(args.stats_out, edge)
        return 0

    return run(main())
