"""The robot service's configuration (built once at the entry point, handed down): where to
play from, the edge, the keys, the pace, handovers, and what to write; checked on
construction (:class:`RobotConfigError` names the field at fault)."""

from __future__ import annotations

import enum
import itertools
from dataclasses import dataclass, field
from pathlib import Path

from common.data.sources import SequenceSource, open_source
from common.errors import RecslamError
from common.protocol.auth import MIN_SECRET_SIZE, Keyring
from common.transport.tls import TlsFiles
from common.vocabulary import DEFAULT_VOCABULARY_PATH
from services.robot.config import FrontEndConfig
from services.robot.uplink_budget import UplinkBudgetConfig

DEV_SECRET = b"recslam-development-secret-do-not-deploy"


class RobotConfigError(RecslamError):
    """The robot service was configured wrongly (dataset, address, secret, options)."""


class Rate(enum.Enum):
    """Playback pace."""

    REALTIME = "realtime"
    """Frames are handed to the front end at their camera timestamps."""
    MAX = "max"
    """As fast as the front end runs."""


@dataclass(frozen=True)
class Handover:
    """From sequence frame ``frame`` on, the robot plays to the edge at ``host:port``."""

    frame: int
    host: str
    port: int


@dataclass(frozen=True)
class RobotServiceConfig:
    """Everything the robot service needs (built once, handed down).

    Attributes:
        dataset: EuRoC-layout sequence folder (``mav0`` inside or the folder itself), or None
            with ``bag``.
        edge_host, edge_port: the edge's address.
        agent_id: this robot's id on the link (unique per edge).
        secret: the robot's keys (a Keyring from its ``--key-file``: its credential only), or
            the operator secret (>= 16 bytes); see :func:`common.protocol.credentials.load_keys`.
        tls: TLS towards the edge (its CA bundle; none: plain TCP, frames sealed anyway).
        rate: playback pace (realtime default).
        start_frame: first frame played (0).
        max_frames: frames played at most (None = to the end).
        backlog_s: outage the outbox absorbs at the camera rate before back-pressure (1800 s).
        max_backlog_bytes: byte bound of the outbox (256 MiB).
        flush_timeout_s: longest wait for the edge to take the rest at the end (None = wait).
        stop_flush_timeout_s: longest wait, after a first SIGINT/SIGTERM, for the edge to take
            the backlog (10 s; within compose's stop_grace_period).
        give_up_after_s: stop (exit code 4, one line saying why) when there has been no
            session with the edge for this long (s): unreachable, timing out, or closing the
            connection before the handshake; 0 = keep trying for ever (default). A refused
            credential stops the robot at once either way (exit code 3).
        heartbeat_interval_s, idle_timeout_s: protocol liveness (2 s, 10 s).
        front_end: front-end options.
        vocabulary: ORB vocabulary file (the repository's default).
        record: keep what the pipeline used per frame in memory (tests).
        bag: a ROS 1 ``.bag`` file or ROS 2 bag folder instead of ``dataset``.
        calibration: calibration file or folder (Kalibr camchain.yaml, EuRoC sensor.yaml);
            overrides the folder's, required with ``bag``.
        image_topic, imu_topic: the bag's topics (default: the calibration's ``rostopic``).
        pose_out: write the edge's pose of every frame here as it arrives (TUM, the robot's own
            map frame; ``recslam robot --pose-out``), or None.
        global_pose_out: the same in the cloud's global map, for the frames whose map the cloud
            has placed (``--global-pose-out``), or None.
        pose_wait_s: after the last frame, wait up to this long (s) for the edge's poses of the
            frames it has not finished yet (0: do not wait).
        stats_out: write the run's counters and the pose latency here (JSON) at the end, or None.
        handovers: moves to other edges (sites), in increasing frame order, each after
            ``start_frame`` (see the module docstring; default none).
        uplink: the uplink budget (``--uplink-budget``): which non-keyframes go
            (:mod:`services.robot.uplink_budget`; default none: every frame goes).
        live: play the recording as a live driver would (``--live``, realtime pace only): an
            image that comes while tracking is behind drops the oldest waiting one, instead
            of the playback waiting for room (the coded bytes then depend on the CPU).
    """

    dataset: Path | None
    edge_host: str
    edge_port: int
    agent_id: str
    secret: bytes | Keyring = field(repr=False)
    rate: Rate = Rate.REALTIME
    start_frame: int = 0
    max_frames: int | None = None
    backlog_s: float = 1800.0
    max_backlog_bytes: int = 256 * 1024 * 1024
    flush_timeout_s: float | None = None
    stop_flush_timeout_s: float = 10.0
    give_up_after_s: float = 0.0
    heartbeat_interval_s: float = 2.0
    idle_timeout_s: float = 10.0
    front_end: FrontEndConfig = field(default_factory=FrontEndConfig)
    vocabulary: Path = DEFAULT_VOCABULARY_PATH
    record: bool = False
    bag: Path | None = None
    calibration: Path | None = None
    image_topic: str | None = None
    imu_topic: str | None = None
    tls: TlsFiles = field(default_factory=TlsFiles)
    handovers: tuple[Handover, ...] = ()
    pose_out: Path | None = None
    global_pose_out: Path | None = None
    pose_wait_s: float = 0.0
    stats_out: Path | None = None
    uplink: UplinkBudgetConfig = field(default_factory=UplinkBudgetConfig)
    live: bool = False

    def __post_init__(self) -> None:
        if self.live and self.rate is not Rate.REALTIME:
            raise RobotConfigError("--live plays at the camera's pace: it needs --rate realtime")
        if self.dataset is None and self.bag is None:
            raise RobotConfigError("a recording is required: --dataset FOLDER or --bag PATH")
        if self.dataset is not None and self.bag is not None:
            raise RobotConfigError("give --dataset (a sequence folder) or --bag, not both")
        if self.bag is not None and self.calibration is None:
            raise RobotConfigError(
                f"--bag {self.bag} needs --calibration FILE: a bag holds no calibration "
                "(Kalibr camchain.yaml, EuRoC cam0/sensor.yaml, or a folder holding them)"
            )
        if self.bag is None and (self.image_topic or self.imu_topic):
            raise RobotConfigError("--image-topic and --imu-topic apply to --bag only")
        if not isinstance(self.rate, Rate):
            raise RobotConfigError(f"rate must be one of {[r.value for r in Rate]}")
        if not self.edge_host:
            raise RobotConfigError("edge host is empty")
        if not 0 < int(self.edge_port) < 65536:
            raise RobotConfigError(f"edge port {self.edge_port} outside 1..65535")
        if not self.agent_id or len(self.agent_id) > 64:
            raise RobotConfigError("agent id must be 1..64 characters")
        if isinstance(self.secret, Keyring):
            if self.secret.credential("robot", self.agent_id) is None:
                raise RobotConfigError(f"the keys hold no credential for robot {self.agent_id!r}")
        elif not isinstance(self.secret, bytes) or len(self.secret) < MIN_SECRET_SIZE:
            raise RobotConfigError(f"shared secret must be at least {MIN_SECRET_SIZE} bytes")
        if self.start_frame < 0 or (self.max_frames is not None and self.max_frames < 0):
            raise RobotConfigError("start_frame and max_frames must be >= 0")
        if self.backlog_s <= 0 or self.max_backlog_bytes <= 0:
            raise RobotConfigError("backlog_s and max_backlog_bytes must be positive")
        if self.flush_timeout_s is not None and self.flush_timeout_s <= 0:
            raise RobotConfigError("flush_timeout_s must be positive (or None to wait)")
        if not self.stop_flush_timeout_s > 0:
            raise RobotConfigError(
                f"stop_flush_timeout_s must be positive, got {self.stop_flush_timeout_s}"
            )
        if self.idle_timeout_s <= self.heartbeat_interval_s:
            raise RobotConfigError("idle_timeout_s must exceed heartbeat_interval_s")
        if not self.pose_wait_s >= 0:
            raise RobotConfigError(f"pose_wait_s must be >= 0, got {self.pose_wait_s}")
        if not self.give_up_after_s >= 0:
            raise RobotConfigError(
                f"give_up_after_s must be >= 0 (0 = never), got {self.give_up_after_s}"
            )
        frames = [self.start_frame, *(h.frame for h in self.handovers)]
        if any(b <= a for a, b in itertools.pairwise(frames)):
            raise RobotConfigError(
                f"handover frames must increase and follow the start frame, got {frames}"
            )
        for h in self.handovers:
            if not h.host or not 0 < int(h.port) < 65536:
                raise RobotConfigError(f"handover at frame {h.frame}: bad edge {h.host}:{h.port}")


def open_sequence(config: RobotServiceConfig) -> SequenceSource:
    """Open the dataset folder or bag with its calibration and check the first image against
    it (a RecslamError names the missing or malformed file, field or topic)."""
    if config.dataset is not None and not Path(config.dataset).exists():
        raise RobotConfigError(f"{config.dataset}: dataset folder does not exist")
    if config.bag is not None and not Path(config.bag).exists():
        raise RobotConfigError(f"{config.bag}: bag does not exist")
    if config.calibration is not None and not Path(config.calibration).exists():
        raise RobotConfigError(f"{config.calibration}: calibration does not exist")
    return open_source(
        config.dataset, config.bag, config.calibration, config.image_topic, config.imu_topic
    )
