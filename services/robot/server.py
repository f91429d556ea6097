"""The robot service's lifecycle: connect to the edge, play a sequence, flush, shut down.

:class:`RobotService` plays an EuRoC-layout sequence (real download, TUM-VI, synthetic robot
folder) or a ROS bag (:mod:`common.data.sources`) frame by frame, after announcing its sensors
(``RobotSensors``, the stream's first message: the sequence's camera and IMU calibrations):
each frame's IMU and image go through the same robot core as a live driver's
(:class:`~services.robot.engine.RobotEngine` over :class:`~services.robot.core.RobotCore`),
which tracks and codes them in one worker thread (OpenCV releases the GIL, so heartbeats and
acks keep flowing on the event loop); the :class:`~common.protocol.messages.RobotFrame` goes
to the protocol :class:`~common.transport.Client`, and the edge's ``InertialFeedback`` is
applied by :class:`~services.robot.app.RobotApp` between frames. A recording waits for the
core's room instead of letting it drop images, so the coded bytes are the same as a frame-by-
frame loop's. ``rate=realtime`` paces frames at their camera
timestamps (when the front end falls behind, frames are processed late, never skipped),
``rate=max`` plays as fast as the front end runs. At the end a
``RobotSequenceEnd`` is sent and the service waits until the edge's application has taken
every message (``Client.flush``). An edge that refuses the robot (e.g. a different calibration
under an agent id it already knows) closes the link with its reason: the run then stops with
:class:`~common.protocol.errors.PeerRejectedError`.

The robot's own pose: the edge sends a ``FramePose`` for every frame its VIO finished;
:class:`~services.robot.poses.PoseTrack` matches it with the moment the frame was taken (the
latency), ``pose_out`` gets a TUM line per metric pose as it arrives (``global_pose_out``: in
the cloud's global map, once the edge forwarded where the robot's map sits), ``stats_out`` the run's
counters and the latency at the end, and ``pose_wait_s`` lets the robot wait after its last
frame for the poses of the frames still queued at the edge.

Backlog while the edge is away: the client keeps reconnecting with backoff and queues in its
outbox, which is sized for ``backlog_s`` seconds of frames at the camera rate (default 30
minutes: ``max_outbox_messages = ceil(backlog_s * rate)``) and at most
``max_backlog_bytes`` bytes (default 256 MiB; the EuRoC excerpt streams ~26 KB/s, so 30
minutes take ~47 MB of memory: see ``benchmarks/results/link_rate.md``). Frames keep being
tracked and queued in real time while the edge is away; on reconnect the protocol replays the
backlog in order, exactly once. Beyond the bound the send waits (back-pressure, logged once
per outage): frames are delayed, never dropped. The backlog lives in memory, so it does not
survive a restart of the robot process.

Shared secret (:func:`common.protocol.credentials.load_secret`): ``--secret-file``
(contents, trailing newline stripped), else the environment variable ``RECSLAM_SECRET``, else
a development default with a logged warning. At least 16 bytes.

Moving between sites (``handovers``): the robot may end its session with one edge and
continue with another at a given frame. Up to that frame it plays to the first edge; then it
sends that edge its ``RobotSequenceEnd`` and waits until the edge's application has taken every
message (the same flush as at the end: what the first edge acknowledged stays with it, nothing
is left in between), closes that link, and opens a new stream with the next edge, starting with
its ``RobotSensors``, from a fresh front end (the next edge holds none of the first one's
tracks, keyframes or inertial state: its VIO starts a new map, which the cloud merges by place
recognition like any other). Each frame is sent to exactly one edge, so nothing is lost or
counted twice; the frame indices of each stream start at 0.

Signals: SIGINT/SIGTERM stop the playback after the current frame; the sequence end is still
sent and flushed, for at most ``stop_flush_timeout_s`` after the signal (logged: how many
messages and bytes are still queued, and how long the robot waits); then, or at a second
signal, the robot gives up waiting for the edge (a blocked send or the flush) and exits.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import signal
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from common.data.euroc import EurocFrame
from common.links.robot_edge import RobotFrame, sensors_message
from common.links.sensors import Sensors
from common.protocol import PeerRejectedError, PeerUnreachableError, SessionConfig
from common.protocol.auth import as_keyring
from common.protocol.messages import Message
from common.transport import Client, TransportConfig, link_load
from common.vocabulary import Vocabulary
from services.robot.app import RobotApp
from services.robot.core import ImageInput, ImuInput, RobotCore
from services.robot.engine import RobotEngine, ack_delay_s
from services.robot.poses import PoseTrack, ReceivedPose, open_tum, tum_line
from services.robot.service_config import (
    Rate,
    RobotConfigError,
    RobotServiceConfig,
    open_sequence,
)
from services.robot.uplink_budget import UplinkBudget

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RobotRunResult:
    """Outcome of one run: frames and keyframes sent, whether a signal stopped it, whether
    the edge took everything, wall time [s], link counters (``Client.counters()``) of the last
    edge session, and of every session in order (``sessions``: one per edge, see handovers)."""

    frames: int
    keyframes: int
    interrupted: bool
    flushed: bool
    wall_s: float
    feedback_applied: int
    counters: dict[str, Any]
    sessions: tuple[dict[str, Any], ...] = ()
    poses: dict[str, float | int] = field(default_factory=dict)
    cores: tuple[dict[str, Any], ...] = ()  # each session's core counters (RobotCore.stats)
    latency_series: tuple[tuple[int, float], ...] = ()  # (camera time ns, latency s), newest


class RobotService:
    """One robot: ``await run()`` plays the sequence; ``request_stop()`` ends it early."""

    def __init__(self, config: RobotServiceConfig, transport: TransportConfig | None = None):
        self.config = config
        self.transport = transport
        self.sequence = open_sequence(config)
        stop = len(self.sequence)
        if config.max_frames is not None:
            stop = min(stop, config.start_frame + config.max_frames)
        if config.start_frame >= stop:
            raise RobotConfigError(
                f"{self.sequence.root}: start frame {config.start_frame} leaves no frames "
                f"({len(self.sequence)} in the sequence)"
            )
        self._stop_index = stop
        self._vocabulary = Vocabulary.load(config.vocabulary)
        self.poses = PoseTrack()  # the edge's pose of each frame, over every edge session
        self._pose_file: TextIO | None = None
        self._global_pose_file: TextIO | None = None
        self._global_map_written: int | None = None  # "# global map N" before its poses
        self.app = self._new_app()
        self.apps = [self.app]  # one per edge session (a handover starts a fresh one)
        self.cores: list[dict[str, Any]] = []  # each finished session's core counters
        self.client: Client | None = None
        self.engine: RobotEngine | None = None  # the current edge session's
        self._backlog_full = False
        self._stop = asyncio.Event()
        self._abort = asyncio.Event()
        self._signals = 0
        self._give_up: asyncio.TimerHandle | None = None

    def _new_app(self) -> RobotApp:
        app = RobotApp(
            self.config.front_end,
            self.sequence.cam0,
            self.sequence.imu,
            self._vocabulary,
            record=self.config.record,
        )
        return app

    def _on_pose(self, pose: ReceivedPose) -> None:
        """The edge's pose of one frame (event loop): the TUM lines if asked (the global file
        names each global map before its poses: a merge moves the robot's map into another)."""
        if self._pose_file is not None and (line := tum_line(pose)) is not None:
            self._pose_file.write(line + "\n")
        if self._global_pose_file is not None and (line := tum_line(pose, True)) is not None:
            if pose.global_map != self._global_map_written:
                self._global_pose_file.write(f"# global map {pose.global_map}\n")
                self._global_map_written = pose.global_map
            self._global_pose_file.write(line + "\n")

    def segments(self) -> list[tuple[int, int, str, int]]:
        """``(first frame, end frame, edge host, edge port)`` of each edge session, in order
        (handovers at or past the end of the played frames are ignored)."""
        cfg = self.config
        edges = [(cfg.start_frame, cfg.edge_host, cfg.edge_port)]
        edges += [(h.frame, h.host, h.port) for h in cfg.handovers if h.frame < self._stop_index]
        ends = [e[0] for e in edges[1:]] + [self._stop_index]
        return [(a, end, host, port) for (a, host, port), end in zip(edges, ends, strict=True)]

    def session_config(self) -> SessionConfig:
        cfg = self.config
        summary = self.sequence.summary()
        rate = float(summary["camera_rate_hz"])
        rate = 20.0 if not math.isfinite(rate) or rate <= 0 else rate
        return SessionConfig(
            role="robot",
            agent_id=cfg.agent_id,
            keys=as_keyring(cfg.secret),
            heartbeat_interval=cfg.heartbeat_interval_s,
            idle_timeout=cfg.idle_timeout_s,
            max_outbox_messages=math.ceil(cfg.backlog_s * rate) + 16,
            max_outbox_bytes=cfg.max_backlog_bytes,
            ack_delay=ack_delay_s(rate),
        )

    def request_stop(self) -> None:
        """Stop after the current frame and flush for at most ``stop_flush_timeout_s`` (first
        call, on the running loop); cancel the final flush (second)."""
        self._signals += 1
        if self._stop.is_set():
            logger.warning("robot %s: second stop request: not waiting for the edge", self.name)
            self._abort.set()
            return
        self._stop.set()
        timeout = self.config.stop_flush_timeout_s
        c = self.client.counters() if self.client is not None else {}
        logger.warning(
            "robot %s: stop requested: %d messages (%d B) queued for the edge; flushing them "
            "for at most %.3g s (a second signal gives up at once)",
            self.name,
            c.get("outbox_messages", 0),
            c.get("outbox_bytes", 0),
            timeout,
        )
        with contextlib.suppress(RuntimeError):  # no running loop: nothing to bound
            self._give_up = asyncio.get_running_loop().call_later(timeout, self._stop_waiting)

    @property
    def name(self) -> str:
        return self.config.agent_id

    def _stop_waiting(self) -> None:
        """``stop_flush_timeout_s`` after the first stop request: give up on the edge."""
        c = self.client.counters() if self.client is not None else {}
        logger.warning(
            "robot %s: the edge did not take the backlog within %.3g s of the stop request: "
            "giving up with %d messages (%d B) unsent",
            self.name,
            self.config.stop_flush_timeout_s,
            c.get("outbox_messages", 0),
            c.get("outbox_bytes", 0),
        )
        self._abort.set()

    async def run(self) -> RobotRunResult:
        cfg = self.config
        t_start = time.monotonic()
        executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"robot-{cfg.agent_id}")
        sessions: list[dict[str, Any]] = []
        flushed = True
        self._pose_file = open_tum(cfg.pose_out)
        self._global_pose_file = open_tum(cfg.global_pose_out)
        try:
            for i, (first, end, host, port) in enumerate(self.segments()):
                if i > 0:
                    if self._stop.is_set():
                        break
                    offset = self.app.time_offset_ns
                    self.app = self._new_app()
                    self.app.set_time_offset(offset)
                    self.apps.append(self.app)
                    logger.info(
                        "robot %s: handover at frame %d to the edge at %s:%d",
                        self.name,
                        first,
                        host,
                        port,
                    )
                took, counters = await self._session(executor, first, end, host, port)
                sessions.append(counters)
                flushed = flushed and took
                if not took:
                    break
        finally:
            if self._give_up is not None:
                self._give_up.cancel()
            executor.shutdown(wait=True)
            for file in (self._pose_file, self._global_pose_file):
                if file is not None:
                    file.close()
            self._pose_file = self._global_pose_file = None
        wall = time.monotonic() - t_start
        frames = sum(a.frames for a in self.apps)
        keyframes = sum(a.keyframes for a in self.apps)
        logger.info(
            "robot %s: %d frames (%d keyframes) to %d edge(s) in %.1f s, %d B sent, flushed=%s",
            cfg.agent_id,
            frames,
            keyframes,
            len(sessions),
            wall,
            sum(c["tx"]["bytes"] for c in sessions),
            flushed,
        )
        poses = self.poses.summary()
        logger.info(
            "robot %s: %d of %d frames' poses back from the edge (%d with a metric pose), "
            "latency median %.3f s, p95 %.3f s, max %.3f s",
            cfg.agent_id,
            poses["received"],
            frames,
            poses["with_pose"],
            poses["median_s"],
            poses["p95_s"],
            poses["max_s"],
        )
        result = RobotRunResult(
            frames=frames,
            keyframes=keyframes,
            interrupted=self._signals > 0,
            flushed=flushed,
            wall_s=wall,
            feedback_applied=sum(a.feedback_applied for a in self.apps),
            counters=sessions[-1] if sessions else {},
            sessions=tuple(sessions),
            poses=poses,
            cores=tuple(self.cores),
            latency_series=tuple(self.poses.series),
        )
        if cfg.stats_out is not None:
            write_run_stats(cfg.stats_out, result)
        return result

    async def _session(
        self, executor: ThreadPoolExecutor, first: int, end: int, host: str, port: int
    ) -> tuple[bool, dict[str, Any]]:
        """Play frames ``first..end-1`` to the edge at ``host:port`` on a stream of their own
        (sensors first, sequence end last); returns whether that edge took everything and the
        link's counters."""
        cfg = self.config
        transport = dataclasses.replace(
            self.transport or TransportConfig(), give_up_after=cfg.give_up_after_s
        )
        core = RobotCore(
            self.sequence.cam0.width,
            self.sequence.cam0.height,
            poses=self.poses,
            uplink=UplinkBudget(cfg.uplink),
        )
        core.offset_ns = self.app.time_offset_ns  # carried over a handover
        self.engine = RobotEngine(
            core,
            self.app,
            executor,
            self._send_frame,
            self._on_pose,
            lambda: link_load(self.client),
        )
        self.client = Client(
            self.session_config(),
            self.engine.on_delivery,
            host,
            port,
            transport=transport,
            server_name="edge",
            ssl=cfg.tls.client_context(),
            server_hostname=host,
        )
        try:
            await self.client.start()
        except BaseException:
            await self.engine.close()
            raise
        try:
            # The stream's first message: this robot's calibrations (the edge builds its
            # decoders and VIO from them).
            await self.client.send(sensors_message(Sensors(self.sequence.cam0, self.sequence.imu)))
            logger.info(
                "robot %s: playing %s frames %d..%d to %s:%d (%s)",
                cfg.agent_id,
                self.sequence.name,
                first,
                end - 1,
                host,
                port,
                cfg.rate.value,
            )
            await self._play(self.engine, executor, first, end)
            flushed = await self._send(self.app.end_message()) and await self._flush()
            if flushed and self.config.pose_wait_s > 0:
                await self._wait_poses(self.config.pose_wait_s)
            await self.engine.close()
            await asyncio.get_running_loop().run_in_executor(executor, self.app.apply_pending)
        finally:
            await self.engine.close()
            self.cores.append(self.engine.stats())
            counters = self.client.counters()
            await self.client.close()
        return flushed, counters

    async def _play(
        self, engine: RobotEngine, executor: ThreadPoolExecutor, first: int, end: int
    ) -> None:
        """Feed frames ``first..end-1`` (their IMU, then the image) to the robot's core, at
        their camera times with ``rate=realtime``, never faster than it tracks (a recording
        waits for room: no frame is dropped), and until every one is tracked and sent."""
        loop = asyncio.get_running_loop()
        # Each frame's IMU reaches t + the camera-IMU offset the edge found (its VIO reads the
        # frame there on the IMU clock); asked at each frame, the offset may arrive any time.
        frames = self.sequence.frames(first, end, imu_lead_ns=lambda: engine.core.imu_lead_ns)
        t0_wall: float | None = None
        t0_ns = 0
        try:
            while not self._stop.is_set():
                frame = await loop.run_in_executor(executor, _next_frame, frames)
                if frame is None:
                    break
                if self.config.rate is Rate.REALTIME:
                    if t0_wall is None:
                        t0_wall, t0_ns = loop.time(), frame.timestamp_ns
                    due = t0_wall + (frame.timestamp_ns - t0_ns) * 1e-9
                    if due > loop.time():
                        with contextlib.suppress(TimeoutError):
                            await asyncio.wait_for(self._stop.wait(), due - loop.time())
                        if self._stop.is_set():
                            break
                if not self.config.live:
                    await engine.room()
                assert frame.image is not None
                imu = frame.imu
                engine.handle(ImuInput(imu.timestamps_ns, imu.gyro, imu.accel))
                engine.handle(ImageInput(frame.timestamp_ns, frame.image))
            await engine.drain()
        finally:
            # a bag's reader lives in the worker thread (SQLite): close it there
            await loop.run_in_executor(executor, _close_frames, frames)

    async def _send_frame(self, msg: Message) -> bool:
        """The engine's send: a frame, with a warning when the backlog is full."""
        assert self.client is not None and self.client.peer is not None  # run() started it
        size = len(msg.features) + len(msg.imu) + 64 if isinstance(msg, RobotFrame) else 64
        if not self.client.peer.link.has_room(size):
            if not self._backlog_full:
                c = self.client.counters()
                logger.warning(
                    "robot %s: backlog full (%d messages, %d B): waiting for the edge; "
                    "frames are delayed, not dropped",
                    self.config.agent_id,
                    c["outbox_messages"],
                    c["outbox_bytes"],
                )
            self._backlog_full = True
        else:
            self._backlog_full = False
        return await self._send(msg)

    async def _wait_poses(self, timeout_s: float) -> None:
        """After the last frame: until the edge's pose of every frame sent is back, the stop
        is requested, or ``timeout_s`` passed (the rest is counted as not received)."""
        deadline = time.monotonic() + timeout_s
        while self.poses.pending and time.monotonic() < deadline and not self._stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), 0.05)

    async def _send(self, msg: Message) -> bool:
        """Queue ``msg`` (waiting while the backlog is full); False if a second signal
        aborted the wait."""
        assert self.client is not None
        if self._abort.is_set():
            return False
        send = asyncio.ensure_future(self.client.send(msg))
        abort = asyncio.ensure_future(self._abort.wait())
        try:
            await asyncio.wait({send, abort}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for fut in (send, abort):
                if not fut.done():
                    fut.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await fut
        if send.done() and not send.cancelled():
            send.result()  # re-raise a send error
            return True
        return False

    async def _flush(self) -> bool:
        assert self.client is not None
        flush = asyncio.ensure_future(self.client.flush())
        stop_wait = asyncio.ensure_future(self._abort.wait())
        try:
            done, _ = await asyncio.wait(
                {flush, stop_wait},
                timeout=self.config.flush_timeout_s,
                return_when=asyncio.FIRST_COMPLETED,
            )
        finally:
            for fut in (flush, stop_wait):
                fut.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await fut
        if flush not in done:
            c = self.client.counters()
            logger.warning(
                "robot %s: the edge did not take %d queued messages before shutdown",
                self.config.agent_id,
                c["outbox_messages"],
            )
            return False
        flush.result()  # re-raise a flush error (the edge refused the robot)
        return True


def write_run_stats(path: Path, result: RobotRunResult) -> None:
    """The run's outcome as JSON (``recslam robot --stats-out``): frames, keyframes, whether
    the edge took everything, wall time, the poses back from the edge and their latency, and
    each edge session's link counters."""
    stats = dataclasses.asdict(result)
    stats["time"] = time.time()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(stats, default=str), encoding="utf-8")
    tmp.replace(path)


def _next_frame(frames: Iterator[EurocFrame]) -> EurocFrame | None:
    """Read (and decode) the next frame; runs in the worker thread."""
    return next(frames, None)


def _close_frames(frames: Iterator[EurocFrame]) -> None:
    """Close the frame iterator (and the files it reads); runs in the worker thread."""
    close = getattr(frames, "close", None)
    if close is not None:
        close()


async def serve(config: RobotServiceConfig, transport: TransportConfig | None = None) -> int:
    """Run the service with SIGINT/SIGTERM handlers; exit code 0, or 130 if interrupted, or
    1 if the edge did not take everything before ``flush_timeout_s``, or 3 if the edge refused
    the robot or its credential, or 4 if there was no session with the edge for
    ``give_up_after_s`` (the reason is logged, one line)."""
    service = RobotService(config, transport)
    loop = asyncio.get_running_loop()
    installed = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, service.request_stop)
            installed.append(sig)
    try:
        result = await service.run()
    except PeerRejectedError as exc:
        if service.client is None or service.client.failure is not exc:
            logger.error("robot %s: %s", config.agent_id, exc)  # else the client said it
        return 4 if isinstance(exc, PeerUnreachableError) else 3
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)
    if result.interrupted:
        return 130
    return 0 if result.flushed else 1
