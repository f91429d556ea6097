"""The edge service as a process: its arguments, its run config and its run loop.

``add_arguments`` defines the options once, for ``recslam edge`` and ``python -m
services.edge`` alike; ``config_from_args`` turns them into an :class:`EdgeRunConfig`;
``serve`` runs the service until SIGINT / SIGTERM:

- loads its keys (``--key-file``, else the operator secret of ``--secret-file`` or
  ``$RECSLAM_SECRET``), the TLS files if any, and the vocabulary; a bad one is logged and
  the exit code is 2 (each robot brings its own calibration when it joins: the edge takes
  none);
- starts the :class:`~services.edge.server.EdgeServer` (connects to the cloud, replays the
  journals of ``--state-dir``, then listens for robots) and announces ``edge listening on
  HOST:PORT, replayed N frames``;
- rewrites ``--stats-out`` every second; on a signal stops the server (robots' side closed,
  workers stopped, the cloud uplink flushed for at most ``--stop-flush-timeout`` seconds with
  what is queued and what was left unsent logged, journals fsynced) and returns 0;
- exits by itself when the cloud link is given up: 3 when the cloud refused the edge's
  credential, 4 after ``--give-up-after`` seconds without a session with the cloud (one line
  saying why: the address, the last failure, how long; 0 = keep trying, the default).

Heavy modules (the server, the VIO, gtsam) are imported inside ``serve`` so that parsing and
``--help`` stay fast.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from common.entry import (
    Announce,
    add_give_up_argument,
    add_security_arguments,
    listen_address,
    run_until_signal,
    stop_on_signals,
    tls_from_args,
)
from common.links import WireFormat, codec_cpu
from common.protocol import PeerUnreachableError
from common.protocol.auth import Keyring
from common.protocol.credentials import load_keys
from common.transport.tls import TlsFiles
from services.edge.cloud_budget import CloudBudgetConfig

if TYPE_CHECKING:
    from common.vocabulary import Vocabulary
    from services.edge.server import EdgeServer

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EdgeRunConfig:
    """What ``recslam edge`` / ``python -m services.edge`` were asked to run.

    Attributes:
        listen: address robots connect to.
        cloud: the cloud's address (None: no cloud, the uplink is dropped and counted).
        state_dir: journal directory for restarts without loss (None: none).
        secret_file: operator secret file (None: ``$RECSLAM_SECRET``), without key_file.
        key_file: this edge's key file (its credential and the robots' role key).
        tls: TLS files (none: plain TCP, frames still sealed).
        agent_id: this edge's agent id.
        worker: where each robot's VIO runs: "process" (one per robot) or "thread".
        vocabulary: vocabulary file (None: the repository's default).
        wire: encoding of the messages to the robots and the cloud.
        stats_out: JSON counters file rewritten every second and at exit (None: none).
        stop_flush_timeout_s: at SIGINT/SIGTERM, longest flush of the cloud uplink (s).
        give_up_after_s: exit after this long without a session with the cloud (0 = never).
        time_offset_ms: the robots' camera-IMU time offset (``t_imu = t_cam + offset``, ms,
            Kalibr's ``timeshift_cam_imu``), held fixed; None: each robot's VIO estimates it
            online from 0.
        offset_wait_s: while the offset is estimated (``time_offset_ms`` None), each map's
            first VI initialisation waits up to this long (s of map time) for a confident
            estimate (0: it does not wait).
        max_vio_lag_s: a robot's non-keyframes more than this behind its newest frame are
            not given to its VIO (``EdgeConfig.max_vio_lag_s``; 0: every frame).
        cloud_budget: which robot keyframes go up to the cloud (``EdgeConfig.cloud_budget``).
    """

    listen: tuple[str, int] = ("0.0.0.0", 7000)
    cloud: tuple[str, int] | None = None
    state_dir: Path | None = None
    secret_file: Path | None = None
    key_file: Path | None = None
    tls: TlsFiles = field(default_factory=TlsFiles)
    agent_id: str = "edge"
    worker: str = "process"
    vocabulary: Path | None = None
    wire: WireFormat = WireFormat.CODED
    stats_out: Path | None = None
    stop_flush_timeout_s: float = 10.0
    time_offset_ms: float | None = None
    offset_wait_s: float = 0.0
    give_up_after_s: float = 0.0
    max_vio_lag_s: float = 0.0
    cloud_budget: CloudBudgetConfig = field(default_factory=CloudBudgetConfig)


def add_wire_argument(p: argparse.ArgumentParser) -> None:
    """``--wire``: the edge's, and ``recslam demo``'s for the edge it starts."""
    p.add_argument(
        "--wire",
        choices=[w.value for w in WireFormat],
        default=WireFormat.CODED.value,
        help="encoding of the messages to the robots and the cloud: coded (default) or raw "
        "(the float64 schema-1 baseline; robots and cloud accept both)",
    )


def add_vio_lag_argument(p: argparse.ArgumentParser) -> None:
    """``--max-vio-lag`` (also the demo's, passed to its edges)."""
    p.add_argument(
        "--max-vio-lag",
        type=float,
        default=0.0,
        metavar="S",
        help="fresh before complete: a robot's non-keyframes more than S seconds behind its "
        "newest frame are not given to its VIO (their IMU goes with the next frame; keyframes "
        "always go; default 0: every frame, however late)",
    )


def add_cloud_budget_argument(p: argparse.ArgumentParser) -> None:
    """``--cloud-budget`` (also the demo's, passed to its edges)."""
    p.add_argument(
        "--cloud-budget",
        default=None,
        metavar="KBPS|auto",
        help="the edge->cloud link's rate in kbit/s, or 'auto' (measured from its "
        "acknowledgements): robot keyframes go up to the cloud only as far apart as it "
        "carries them, the others stay on the edge like the VIO's own (default: every one)",
    )


def add_time_offset_arguments(p: argparse.ArgumentParser) -> None:
    """``--time-offset-ms`` and ``--offset-wait`` (also the demo's, passed to its edges)."""
    p.add_argument(
        "--time-offset-ms",
        type=_time_offset,
        default=None,
        metavar="MS|auto",
        help="the robots' camera-IMU time offset, t_imu = t_cam + MS (Kalibr's "
        "timeshift_cam_imu), held fixed; auto (default): each robot's VIO estimates it online "
        "and tells the robot",
    )
    p.add_argument(
        "--offset-wait",
        type=float,
        default=0.0,
        metavar="S",
        help="with --time-offset-ms auto, each map's first VI initialisation waits up to S "
        "seconds for a confident offset estimate instead of initialising on IMU segments that "
        "may be out of step with the images (default 0: no wait; ~6 suits a sensor known to "
        "be unsynchronised)",
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The edge's options (their defaults are :class:`EdgeRunConfig`'s)."""
    p.add_argument(
        "--listen",
        type=listen_address,
        default=("0.0.0.0", 7000),
        metavar="HOST:PORT",
        help="address robots connect to (default 0.0.0.0:7000)",
    )
    p.add_argument(
        "--cloud",
        type=listen_address,
        default=None,
        metavar="HOST:PORT",
        help="cloud address (default: none, the uplink is dropped)",
    )
    p.add_argument(
        "--state-dir",
        type=Path,
        default=None,
        metavar="DIR",
        help="journal directory for restarts without loss (default: none)",
    )
    add_security_arguments(p)
    p.add_argument("--agent-id", default="edge", help="this edge's agent id (default edge)")
    p.add_argument(
        "--worker",
        choices=("process", "thread"),
        default="process",
        help="where each robot's VIO runs (default: one process per robot)",
    )
    p.add_argument(
        "--vocabulary",
        type=Path,
        default=None,
        metavar="NPZ",
        help="vocabulary file (default: common/assets/orb_vocabulary.npz)",
    )
    add_wire_argument(p)
    p.add_argument(
        "--stats-out",
        type=Path,
        default=None,
        metavar="FILE",
        help="rewrite service and per-link traffic counters as JSON here every second and at "
        "exit (default: none)",
    )
    add_time_offset_arguments(p)
    add_vio_lag_argument(p)
    add_cloud_budget_argument(p)
    p.add_argument(
        "--stop-flush-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="after SIGINT/SIGTERM, seconds to flush the uplink backlog to the cloud before "
        "giving up (logged: what is queued, what is left unsent; default 10)",
    )
    add_give_up_argument(p, "cloud")


def config_from_args(args: argparse.Namespace) -> EdgeRunConfig:
    """The run config of arguments parsed by a parser that :func:`add_arguments` filled."""
    return EdgeRunConfig(
        listen=args.listen,
        cloud=args.cloud,
        state_dir=args.state_dir,
        secret_file=args.secret_file,
        key_file=args.key_file,
        tls=tls_from_args(args),
        agent_id=args.agent_id,
        worker=args.worker,
        vocabulary=args.vocabulary,
        wire=WireFormat(args.wire),
        stats_out=args.stats_out,
        stop_flush_timeout_s=args.stop_flush_timeout,
        give_up_after_s=args.give_up_after,
        time_offset_ms=args.time_offset_ms,
        offset_wait_s=args.offset_wait,
        max_vio_lag_s=args.max_vio_lag,
        cloud_budget=_cloud_budget(args.cloud_budget),
    )


def _cloud_budget(text: str | None) -> CloudBudgetConfig:
    """``--cloud-budget`` as a config; a bad value is an argparse error naming it."""
    try:
        return CloudBudgetConfig.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _time_offset(text: str) -> float | None:
    """``--time-offset-ms``: a number of milliseconds (within the VIO's search range), or
    ``auto`` (None)."""
    from services.edge.vio.time_offset import TimeOffsetConfig

    if text.strip().lower() == "auto":
        return None
    try:
        ms = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected milliseconds or auto, got {text!r}") from None
    limit = TimeOffsetConfig().max_offset_ms
    if not abs(ms) <= limit:
        raise argparse.ArgumentTypeError(
            f"{ms} ms is beyond ±{limit:g} ms: check the calibration's sign"
        )
    return ms


def write_stats(path: Path, edge: EdgeServer) -> None:
    """Write the edge's counters and every robot link's traffic counters to ``path`` (JSON),
    with the codec CPU (``codec_cpu``: all robots' sessions merged, and per robot) once the
    sessions time their codecs."""
    stats: dict[str, Any] = edge.stats()
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


def serve(config: EdgeRunConfig, announce: Announce = logger.info) -> int:
    """Run the edge until SIGINT / SIGTERM (see the module docstring); the exit code: 0, or
    2 when the keys, the TLS files or the vocabulary cannot be loaded or a folder it writes
    (``--state-dir``, ``--stats-out``'s) is not writable or an option is out of range, or 3 /
    4 when the cloud link was given up (credential refused / no session for
    ``--give-up-after`` seconds)."""
    from common.errors import RecslamError
    from common.folders import writable_folder
    from common.transport import run
    from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary

    try:
        if not config.stop_flush_timeout_s >= 0:
            raise RecslamError(
                f"--stop-flush-timeout must be >= 0 seconds, got {config.stop_flush_timeout_s}"
            )
        identity = ("edge", config.agent_id) if config.cloud is not None else None
        secret = load_keys(config.key_file, config.secret_file, identity=identity)
        config.tls.server_context()  # a bad certificate fails here, with its name
        config.tls.client_context()
        if config.state_dir is not None:
            writable_folder(config.state_dir, "--state-dir")
        if config.stats_out is not None:
            writable_folder(config.stats_out.parent, "--stats-out folder")
        vocab = Vocabulary.load(config.vocabulary or DEFAULT_VOCABULARY_PATH)
    except RecslamError as exc:
        logger.error("%s", exc)
        return 2
    return run(_run(config, secret, vocab, announce))


def _server(config: EdgeRunConfig, secret: Keyring, vocab: Vocabulary) -> EdgeServer:
    from services.edge.config import EdgeConfig
    from services.edge.robot_session import EdgeSessionConfig
    from services.edge.server import EdgeServer, EdgeServiceConfig
    from services.edge.vio.types import ViInitConfig, VioConfig

    cloud_host, cloud_port = config.cloud if config.cloud is not None else (None, 0)
    service = EdgeServiceConfig(
        agent_id=config.agent_id,
        cloud_host=cloud_host,
        cloud_port=cloud_port,
        stop_flush_timeout_s=config.stop_flush_timeout_s,
        give_up_after_s=config.give_up_after_s,
    )
    vio = VioConfig(
        time_offset_ns=round((config.time_offset_ms or 0.0) * 1e6),
        estimate_time_offset=config.time_offset_ms is None,
        vi_init=ViInitConfig(wait_for_time_offset_s=config.offset_wait_s),
    )
    app = EdgeConfig(
        worker=config.worker,
        session=EdgeSessionConfig(wire=config.wire),
        vio=vio,
        max_vio_lag_s=config.max_vio_lag_s,
        cloud_budget=config.cloud_budget,
    )
    return EdgeServer(secret, vocab, app, service, state_dir=config.state_dir, tls=config.tls)


async def _run(
    config: EdgeRunConfig, secret: Keyring, vocab: Vocabulary, announce: Announce
) -> int:
    edge = _server(config, secret, vocab)
    # After the server is built (importing pycolmap installs glog's SIGTERM handler, which
    # would replace ours) and before the announcement a supervisor acts on.
    stop = stop_on_signals()
    host, port = await edge.start(*config.listen)
    announce(f"edge listening on {host}:{port}, replayed {edge.replayed_frames} frames")
    stats_out = config.stats_out

    async def tick() -> None:
        if stats_out is not None:
            write_stats(stats_out, edge)

    # the cloud link given up (the client logged the one line why) stops the edge too
    cloud_failed = asyncio.ensure_future(edge.wait_cloud_failed())
    cloud_failed.add_done_callback(lambda _: stop.set())
    try:
        await run_until_signal(stop, tick)
    finally:
        announce("edge stopping")
        await edge.stop()  # its last uplinks count in the stats
        if stats_out is not None:
            write_stats(stats_out, edge)
    if not cloud_failed.done():
        cloud_failed.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await cloud_failed
        return 0
    return 4 if isinstance(cloud_failed.result(), PeerUnreachableError) else 3
