"""The cloud service as a process: its arguments, its run config and its run loop.

``add_arguments`` defines the options once, for ``recslam cloud`` and ``python -m
services.cloud`` alike; ``config_from_args`` turns them into a :class:`CloudRunConfig`, and
``service_config`` that into the service's nested options; ``serve`` runs the service until
SIGINT / SIGTERM:

- loads its keys (``--key-file``, else the operator secret of ``--secret-file`` or
  ``$RECSLAM_SECRET``) and the TLS files if any,
  the fallback camera (:func:`find_camera`; each robot's own calibration arrives from its
  edge, this one serves only robots whose calibration never does, as in old recordings) and
  the vocabulary; a bad one is logged and the exit code is 2;
- starts the :class:`~services.cloud.server.CloudServer` (edges connect with role "edge"),
  announces ``cloud listening on HOST:PORT, state DIR`` and, with a dashboard port, the
  dashboard's address;
- rewrites ``--stats-out`` every second; on a signal stops the dashboard and the server
  (connections closed, last optimisation, MBP, outputs written) and returns 0.

Heavy modules (the server, gtsam, viser) are imported inside ``serve`` so that parsing and
``--help`` stay fast.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from common.entry import (
    Announce,
    add_security_arguments,
    listen_address,
    run_until_signal,
    stop_on_signals,
    tls_from_args,
)
from common.links import WireFormat, codec_cpu
from common.protocol.auth import Keyring
from common.protocol.credentials import load_keys
from common.transport.tls import TlsFiles

if TYPE_CHECKING:
    from common.calibration import CameraCalibration
    from common.vocabulary import Vocabulary
    from services.cloud.server import CloudServer
    from services.cloud.service_config import CloudServiceConfig

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CloudRunConfig:
    """What ``recslam cloud`` / ``python -m services.cloud`` were asked to run.

    Attributes:
        state_dir: SQLite state directory (created; resumed when it exists).
        listen: address edges connect to.
        dashboard_port: viser dashboard port, 0 = no dashboard.
        results: result folder for ``trajectories/`` and ``eval/`` (None: none).
        groundtruth: ground truth for the ATE report (dataset folder or file).
        secret_file: operator secret file (None: ``$RECSLAM_SECRET``), without key_file.
        key_file: the cloud's key file (the edges' role key).
        tls: TLS files (none: plain TCP, frames still sealed).
        dashboard_host: the dashboard's address (None: the host of ``listen``).
        dashboard_open: serve the dashboard without its access token.
        camera: EuRoC cam0 ``sensor.yaml`` of the fallback camera, for robots whose edge
            sent no calibration (None: see :func:`find_camera`).
        vocabulary: vocabulary file (None: the repository's default).
        mbp: map backbone profiling on/off.
        mbp_every: MBP also every this many new keyframes of a map while running (0: only
            at shutdown).
        full_ba: full bundle adjustment after the pose graph on/off.
        incremental_ba: ... solved on the map's iSAM2 graph (``FullBAConfig.incremental``).
        optimizer_nice: niceness added to the optimizer process
            (``ProcessConfig.optimizer_nice``).
        decode_workers: keyframe decode processes (``ProcessConfig.decode_workers``).
        overload_busy: the worker's busy share from which the cloud sheds its optional work
            (``OverloadConfig.busy``; 0: never).
        early_loop_candidates: candidates verified before they are consistent over
            consecutive keyframes (``PlaceRecognitionConfig.early_candidates``).
        agent_id: this service's agent id.
        wire: encoding of the pose corrections to the edges.
        output_every_s: rewrite outputs every so many seconds, 0 = only at exit.
        stats_out: JSON counters file rewritten every second and at exit (None: none).
        record: uplink recording appended to (None: off).
        mission: the named mission to serve (None: the state directory's current one; see
            ``services.cloud.store.mission``).
        prior_frame: ``eval/ate.json`` of the mission whose map this one starts in (the ATE
            is also reported in its frame; None: not).
    """

    state_dir: Path
    listen: tuple[str, int] = ("0.0.0.0", 7100)
    dashboard_port: int = 8080
    results: Path | None = None
    groundtruth: Path | None = None
    secret_file: Path | None = None
    key_file: Path | None = None
    tls: TlsFiles = field(default_factory=TlsFiles)
    dashboard_host: str | None = None
    dashboard_open: bool = False
    camera: Path | None = None
    vocabulary: Path | None = None
    mbp: bool = True
    mbp_every: int = 0
    full_ba: bool = True
    incremental_ba: bool = True
    optimizer_nice: int = 0
    decode_workers: int = 0
    overload_busy: float = 0.9
    early_loop_candidates: int = 1
    agent_id: str = "cloud"
    wire: WireFormat = WireFormat.CODED
    output_every_s: float = 30.0
    stats_out: Path | None = None
    record: Path | None = None
    mission: str | None = None
    prior_frame: Path | None = None


def _share(text: str) -> float:
    """An argparse type: a share in [0, 1]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {value}")
    return value


def add_dashboard_argument(p: argparse.ArgumentParser) -> None:
    """``--dashboard-port``: the cloud's, and ``recslam demo``'s for the cloud it starts."""
    p.add_argument(
        "--dashboard-port",
        type=int,
        default=8080,
        metavar="PORT",
        help="viser dashboard port, 0 disables it (default 8080)",
    )


def add_map_arguments(p: argparse.ArgumentParser) -> None:
    """The options of the cloud's map work that ``recslam demo`` passes on to its cloud:
    ``--mbp``, ``--mbp-every``, ``--early-loop-candidates`` (one definition, one help)."""
    p.add_argument(
        "--mbp",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="map backbone profiling on/off (default on: one pass over every map at shutdown, "
        "after the last full BA; pruning while running cost accuracy, see "
        "benchmarks/results/table3.md)",
    )
    p.add_argument(
        "--mbp-every",
        type=int,
        default=0,
        metavar="N",
        help="with --mbp, also prune a map every N new keyframes while running, right after a "
        "full BA of it (with --full-ba), keeping each robot's 30 newest (default 0: only at "
        "shutdown; see benchmarks/results/mbp_midrun.md)",
    )
    p.add_argument(
        "--early-loop-candidates",
        type=int,
        default=1,
        choices=range(11),
        metavar="N",
        help="verify the N best place-recognition candidates of a keyframe at once and accept "
        "one when the keyframe's covisible keyframes agree with it (ORB-SLAM3), besides those "
        "consistent over 3 keyframes (default 1; 0: only those; "
        "benchmarks/results/loop_recall.md)",
    )


def add_record_argument(p: argparse.ArgumentParser, flag: str = "--record") -> None:
    """The uplink recording; ``recslam demo`` offers it as ``--record-uplink``."""
    p.add_argument(
        flag,
        type=Path,
        default=None,
        metavar="FILE",
        help="append every applied uplink message to this recording (replayed by "
        "'recslam experiment table3'; default: off)",
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The cloud's options (their defaults are :class:`CloudRunConfig`'s)."""
    p.add_argument(
        "--listen",
        type=listen_address,
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
        "--mission",
        default=None,
        metavar="NAME",
        help="serve mission NAME: resumed when it is the state directory's current mission "
        "(a restart), else started inside the saved map, whose agents become a read-only "
        "prior map that the new robots relocalise against and merge into (default: the "
        "current mission continues)",
    )
    p.add_argument(
        "--prior-frame",
        type=Path,
        default=None,
        metavar="ATE_JSON",
        help="eval/ate.json of the mission whose map this one starts in: the ATE is also "
        "reported under its alignment (eval/ate_prior_frame.json)",
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
    add_dashboard_argument(p)
    add_security_arguments(p)
    p.add_argument(
        "--dashboard-host",
        default=None,
        metavar="HOST",
        help="address the dashboard listens on (default: the host of --listen)",
    )
    p.add_argument(
        "--dashboard-open",
        action="store_true",
        help="serve the dashboard to anyone who reaches it, without the access token that "
        "is otherwise part of its announced URL",
    )
    p.add_argument(
        "--camera",
        type=Path,
        default=None,
        metavar="SENSOR_YAML",
        help="EuRoC cam0 sensor.yaml of the fallback camera, used only for robots whose "
        "calibration never arrived (each robot sends its own through its edge)",
    )
    p.add_argument(
        "--vocabulary",
        type=Path,
        default=None,
        metavar="NPZ",
        help="vocabulary file (default: common/assets/orb_vocabulary.npz)",
    )
    add_map_arguments(p)
    p.add_argument(
        "--optimizer-nice",
        type=int,
        default=0,
        choices=range(20),
        metavar="N",
        help="niceness (0-19) added to the optimizer process: a shared core goes to applying "
        "the edges' messages first and the solves run in what is left (default 0; 10 on an "
        "overloaded core: a smaller queue, fewer corrections; benchmarks/results/scale.md)",
    )
    p.add_argument(
        "--decode-workers",
        type=int,
        default=0,
        choices=range(33),
        metavar="N",
        help="decode the keyframes' features in N helper processes, beside the worker that "
        "applies the messages (default 0: on the worker; with spare cores, 1 takes ~25 ms "
        "of each keyframe off it; benchmarks/results/scale.md)",
    )
    p.add_argument(
        "--overload-busy",
        type=_share,
        default=0.9,
        metavar="F",
        help="when the worker applying the edges' messages was busy at least this share of the "
        "last 10 s, shed the optional work (no full BA while running, no early loop "
        "candidates) until it falls to 0.6; pose graphs and corrections go on (default 0.9; "
        "0: never; benchmarks/results/scale.md)",
    )
    p.add_argument(
        "--full-ba",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="full bundle adjustment after the pose graph when there is time, and at exit "
        "(default on; --no-full-ba: pose graph only)",
    )
    p.add_argument(
        "--incremental-ba",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="solve each full BA of a map of 500 keyframes or more incrementally on the "
        "map's iSAM2 graph, rebuilt by a batch solve after merges (default on; "
        "--no-incremental-ba: a batch solve each time, whose cost grows with the map; "
        "benchmarks/results/cloud_vi_ba_incremental.md)",
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
    add_record_argument(p)


def config_from_args(args: argparse.Namespace) -> CloudRunConfig:
    """The run config of arguments parsed by a parser that :func:`add_arguments` filled."""
    return CloudRunConfig(
        state_dir=args.state_dir,
        listen=args.listen,
        dashboard_port=args.dashboard_port,
        results=args.results,
        groundtruth=args.groundtruth,
        secret_file=args.secret_file,
        key_file=args.key_file,
        tls=tls_from_args(args),
        dashboard_host=args.dashboard_host,
        dashboard_open=args.dashboard_open,
        camera=args.camera,
        vocabulary=args.vocabulary,
        mbp=args.mbp,
        mbp_every=args.mbp_every,
        full_ba=args.full_ba,
        incremental_ba=args.incremental_ba,
        optimizer_nice=args.optimizer_nice,
        decode_workers=args.decode_workers,
        overload_busy=args.overload_busy,
        early_loop_candidates=args.early_loop_candidates,
        agent_id=args.agent_id,
        wire=WireFormat(args.wire),
        output_every_s=args.output_every,
        stats_out=args.stats_out,
        record=args.record,
        mission=args.mission,
        prior_frame=args.prior_frame,
    )


def find_camera(camera: Path | None, groundtruth: Path | None) -> CameraCalibration:
    """The fallback camera: ``camera`` (an EuRoC cam0 ``sensor.yaml``), else the first
    ``<robot>/mav0/cam0/sensor.yaml`` (or ``mav0/cam0/sensor.yaml``) under the ``groundtruth``
    folder, else the synthetic dataset's EuRoC camera (the ``euroc`` preset of
    :mod:`common.data.synth.cameras` at 20 Hz, logged)."""
    from common.data.euroc import read_camera_yaml
    from common.data.synth.cameras import camera_preset

    if camera is not None:
        return read_camera_yaml(camera)
    if groundtruth is not None and groundtruth.is_dir():
        for yaml in sorted(groundtruth.glob("*/mav0/cam0/sensor.yaml")) + sorted(
            groundtruth.glob("mav0/cam0/sensor.yaml")
        ):
            logger.info("camera calibration from %s", yaml)
            return read_camera_yaml(yaml)
    logger.info("fallback camera: the synthetic dataset's EuRoC-like camera")
    return camera_preset("euroc").calibration(20.0)


async def write_stats(path: Path, cloud: CloudServer, codec_owners: Sequence[object] = ()) -> None:
    """Write the cloud's counters and every edge link's traffic counters to ``path`` (JSON;
    also after ``cloud.stop()``: both keep their final values), with the codec CPU of the
    ``codec_owners`` that have a ``codec_timer`` (``codec_cpu``; the application's timer
    keeps its counts after ``stop()``)."""
    stats: dict[str, Any] = dataclasses.asdict(await cloud.stats())
    cpu = codec_cpu([cloud, *codec_owners])
    if cpu is not None:
        stats["codec_cpu"] = cpu
    stats["links"] = cloud.transport.counters()
    stats["time"] = time.time()
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(stats))
    tmp.replace(path)


def serve(config: CloudRunConfig, announce: Announce = logger.info) -> int:
    """Run the cloud until SIGINT / SIGTERM (see the module docstring); the exit code: 0, or
    2 when the keys, the TLS files, the camera or the vocabulary cannot be loaded or a folder
    it writes (``--state-dir``, ``--results``, ``--stats-out``'s) is not writable."""
    from common.errors import RecslamError
    from common.folders import writable_folder
    from common.transport import run
    from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary

    try:
        secret = load_keys(config.key_file, config.secret_file)
        config.tls.server_context()  # a bad certificate fails here, with its name
        writable_folder(config.state_dir, "--state-dir")
        if config.results is not None:
            writable_folder(config.results, "--results")
        if config.stats_out is not None:
            writable_folder(config.stats_out.parent, "--stats-out folder")
        camera = find_camera(config.camera, config.groundtruth)
        vocab = Vocabulary.load(config.vocabulary or DEFAULT_VOCABULARY_PATH)
    except RecslamError as exc:
        logger.error("%s", exc)
        return 2
    return run(_run(config, secret, camera, vocab, announce))


def service_config(config: CloudRunConfig) -> CloudServiceConfig:
    """The service's options for the run ``config``: the defaults but for what the command
    line sets (``--no-mbp``, ``--mbp-every``, ``--early-loop-candidates``, ``--no-full-ba``,
    ``--no-incremental-ba``, ``--overload-busy``, ``--dashboard-port 0``, ``--mission``,
    ``--output-every``, ``--optimizer-nice``, ``--decode-workers``, ``--wire``)."""
    from services.cloud.config import CloudConfig, FullBAConfig, MbpConfig, PlaceRecognitionConfig
    from services.cloud.service_config import (
        CloudServiceConfig,
        MapViewConfig,
        MbpScheduleConfig,
        OverloadConfig,
        ProcessConfig,
        StoreConfig,
    )

    domain = CloudConfig(
        mbp=MbpConfig(enabled=config.mbp),
        full_ba=FullBAConfig(enabled=config.full_ba, incremental=config.incremental_ba),
        place_recognition=PlaceRecognitionConfig(early_candidates=config.early_loop_candidates),
    )
    return CloudServiceConfig(
        domain=domain,
        wire=config.wire,
        mbp=MbpScheduleConfig(every_keyframes=config.mbp_every),
        overload=OverloadConfig(
            busy=config.overload_busy,
            clear=min(OverloadConfig.clear, config.overload_busy * 2 / 3),
        ),
        # no dashboard: no map view to refresh (its atlas snapshot costs the worker)
        map_view=MapViewConfig(
            publish_every_s=MapViewConfig.publish_every_s if config.dashboard_port else 0.0
        ),
        store=StoreConfig(mission=config.mission, output_every_s=config.output_every_s),
        processes=ProcessConfig(
            optimizer_nice=config.optimizer_nice, decode_workers=config.decode_workers
        ),
    )


def _server(
    config: CloudRunConfig, secret: Keyring, camera: CameraCalibration, vocab: Vocabulary
) -> CloudServer:
    from common.protocol import SessionConfig
    from common.transport import TransportConfig
    from services.cloud.server import CloudServer

    service = service_config(config)
    return CloudServer(
        SessionConfig("cloud", config.agent_id, keys=secret),
        config.state_dir,
        camera,
        vocab,
        service,
        results_dir=config.results,
        groundtruth=config.groundtruth,
        transport=TransportConfig(accept_roles=("edge",)),
        record=config.record,
        ssl=config.tls.server_context(),
        prior_frame=config.prior_frame,
    )


async def _run(
    config: CloudRunConfig,
    secret: Keyring,
    camera: CameraCalibration,
    vocab: Vocabulary,
    announce: Announce,
) -> int:
    cloud = _server(config, secret, camera, vocab)
    # After the server is built (importing pycolmap installs glog's SIGTERM handler, which
    # would replace ours) and before the announcement a supervisor acts on.
    stop = stop_on_signals()
    host, port = await cloud.start(*config.listen)
    # The application's codec_timer (if it has one) stays readable after stop().
    codec_owners = [await cloud.call(lambda app: app)]
    dashboard = None
    if config.dashboard_port:
        from dashboard.viewer import Dashboard, DashboardConfig, new_access_token

        dash_cfg = DashboardConfig(
            host=config.dashboard_host or config.listen[0],
            port=config.dashboard_port,
            access_token=None if config.dashboard_open else new_access_token(),
        )
        dashboard = Dashboard(cloud.map_source, dash_cfg)
        dashboard.start()
        announce(f"dashboard at {dashboard.url}")
    announce(f"cloud listening on {host}:{port}, state {config.state_dir}")
    stats_out = config.stats_out

    async def tick() -> None:
        if stats_out is not None:
            await write_stats(stats_out, cloud, codec_owners)

    try:
        await run_until_signal(stop, tick)
    finally:
        announce("cloud stopping")
        if dashboard is not None:
            dashboard.stop()
        if stats_out is not None:
            await write_stats(stats_out, cloud, codec_owners)
        await cloud.stop()
        if stats_out is not None:  # again: shutdown's optimisation and MBP counted
            await write_stats(stats_out, cloud, codec_owners)
    return 0
