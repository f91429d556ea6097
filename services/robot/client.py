"""The robot as a library: feed it from your driver, get your poses back.

:class:`RobotClient` runs one robot (front end, codecs, the link to its edge) on a thread of
its own with its own event loop, over the same core and runner as ``recslam robot``
(:class:`~services.robot.engine.RobotEngine` over :class:`~services.robot.core.RobotCore`).
Every method is safe to call from any thread (a driver's callback thread, say): the sensor
calls only hand a value to the robot's loop and return at once.

- :meth:`RobotClient.add_imu` ``(t_ns, gyro, accel)``: one IMU sample, IMU frame, rad/s and
  m/s², on the camera's clock (or with the offset the calibration states).
- :meth:`RobotClient.add_image` ``(t_ns, image)``: a uint8 (H, W) grey image of the calibrated
  size (or raw bytes with a ROS encoding: :meth:`RobotClient.add_raw_image`). The image is
  copied: the driver may reuse its buffer.
- :meth:`RobotClient.poses`: an iterator of :class:`~services.robot.poses.ReceivedPose` as
  they arrive (``on_pose``: the same as a callback, called on the robot's thread; keep it
  short, it holds the robot's loop).
- :meth:`RobotClient.stats`: the core's counters (input, frames, faults, pose latency) and
  the link's.
- :meth:`RobotClient.close`: the end of the input; waits for the edge to take the rest.

Back-pressure: images that come faster than tracking wait in a queue of
``LiveInputConfig.max_pending_images``; beyond it the oldest untracked image is dropped and
counted (``stats()["faults"]["dropped_backpressure"]``). Live-input faults are warned and
counted as :mod:`services.robot.core` states.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import RecslamError
from common.links.robot_edge import RobotSequenceEnd, sensors_message
from common.links.sensors import Sensors
from common.protocol import SessionConfig
from common.protocol.auth import Keyring, as_keyring
from common.protocol.messages import Message
from common.transport import Client, TransportConfig, link_load
from common.transport.tls import TlsFiles
from common.vocabulary import DEFAULT_VOCABULARY_PATH, Vocabulary
from services.robot.app import RobotApp
from services.robot.config import FrontEndConfig
from services.robot.core import (
    Event,
    ImageInput,
    ImuInput,
    LiveInputConfig,
    RobotCore,
)
from services.robot.engine import RobotEngine, ack_delay_s
from services.robot.poses import ReceivedPose
from services.robot.uplink_budget import UplinkBudget, UplinkBudgetConfig

logger = logging.getLogger(__name__)


class RobotClosedError(RecslamError):
    """The robot was closed (or its loop failed): it takes no more input."""


@dataclass(frozen=True)
class RobotClientConfig:
    """One live robot (built once by the caller, handed down).

    Attributes:
        sensors: its camera and IMU calibrations (``common.data.calibration_files.
            load_calibration(path)`` reads Kalibr or EuRoC files: ``Sensors(c.cam0, c.imu)``).
        edge_host, edge_port: the edge's address.
        agent_id: this robot's id, unique per edge.
        secret: its keys (``common.protocol.credentials.load_keys``) or the operator secret.
        tls: TLS towards the edge (none: plain TCP, frames sealed anyway).
        time_shift_ns: added to every image time (Kalibr's ``timeshift_cam_imu``, ns).
        live: the live-input limits (queue, IMU wait, gaps, jumps, stalls).
        front_end: front-end options.
        vocabulary: ORB vocabulary file (the repository's default).
        camera_rate_hz: the camera's rate, to size the outbox and to acknowledge the edge's
            messages with the next frame (20 Hz).
        backlog_s: edge outage the outbox absorbs before back-pressure (1800 s).
        close_timeout_s: longest wait at :meth:`RobotClient.close` for the edge (30 s).
        uplink: the uplink budget: which non-keyframes go (default none: every frame).
    """

    sensors: Sensors
    edge_host: str
    edge_port: int
    agent_id: str
    secret: bytes | Keyring = field(repr=False)
    tls: TlsFiles = field(default_factory=TlsFiles)
    time_shift_ns: int = 0
    live: LiveInputConfig = field(default_factory=LiveInputConfig)
    front_end: FrontEndConfig = field(default_factory=FrontEndConfig)
    vocabulary: Path = DEFAULT_VOCABULARY_PATH
    camera_rate_hz: float = 20.0
    backlog_s: float = 1800.0
    close_timeout_s: float = 30.0
    uplink: UplinkBudgetConfig = field(default_factory=UplinkBudgetConfig)
    heartbeat_interval_s: float = 2.0
    idle_timeout_s: float = 10.0


_END = object()
POSE_QUEUE = 10_000
"""Poses kept for :meth:`RobotClient.poses` when nobody reads them (the oldest go first)."""


class RobotClient:
    """One robot fed live (see the module docstring). Use it as a context manager, or call
    :meth:`close`."""

    def __init__(
        self,
        config: RobotClientConfig,
        on_pose: Callable[[ReceivedPose], None] | None = None,
    ) -> None:
        self.config = config
        self._on_pose = on_pose
        self._poses: queue.Queue[Any] = queue.Queue(maxsize=POSE_QUEUE)
        self._closed = False
        self._engine: RobotEngine | None = None
        self._client: Client | None = None
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._failure: BaseException | None = None
        self._finished: asyncio.Event | None = None
        self._result: dict[str, Any] = {}
        self._thread = threading.Thread(
            target=self._run, name=f"recslam-robot-{config.agent_id}", daemon=True
        )
        self._thread.start()
        self._ready.wait()
        if self._failure is not None:
            self._thread.join()
            raise self._failure

    # ------------------------------------------------------------------ driver side
    def add_imu(self, t_ns: int, gyro: Any, accel: Any) -> None:
        """One IMU sample: time [ns], gyro (3,) rad/s, accel (3,) m/s² (IMU frame)."""
        ts = np.array([int(t_ns)], np.int64)
        g = np.array(gyro, np.float64).reshape(1, 3)
        a = np.array(accel, np.float64).reshape(1, 3)
        self._submit(ImuInput(ts, g, a))

    def add_image(self, t_ns: int, image: np.ndarray) -> None:
        """One camera image: time [ns] and a uint8 (H, W) grey array (copied)."""
        t = int(t_ns) + self.config.time_shift_ns
        self._submit(ImageInput(t, np.array(image, copy=True)))

    def add_raw_image(
        self, t_ns: int, data: bytes, encoding: str, height: int, width: int, step: int
    ) -> None:
        """One camera image as raw bytes with its ROS encoding (``mono8``, ``bgr8``, ...)."""
        t = int(t_ns) + self.config.time_shift_ns
        self._submit(ImageInput(t, bytes(data), encoding, height, width, step))

    def poses(self, timeout: float | None = None) -> Iterator[ReceivedPose]:
        """The poses as they arrive, until :meth:`close` (or ``timeout`` s without one)."""
        while True:
            try:
                item = self._poses.get(timeout=timeout)
            except queue.Empty:
                return
            if item is _END:
                self._put(_END)  # for any other reader
                return
            yield item

    def stats(self) -> dict[str, Any]:
        """The core's counters and the link's (after :meth:`close`: the final ones)."""
        if self._closed or not self._loop.is_running():
            return dict(self._result)
        if threading.current_thread() is self._thread:  # from on_pose: already on the loop
            assert self._engine is not None and self._client is not None
            return {**self._engine.stats(), "link": self._client.counters()}
        fut = asyncio.run_coroutine_threadsafe(self._stats(), self._loop)
        return fut.result(timeout=10.0)

    def close(self) -> dict[str, Any]:
        """End of input: the images queued are tracked, the sequence end is sent, and the
        edge is given ``close_timeout_s`` to take the rest; returns the final stats
        (RobotClosedError if the robot failed, e.g. the edge refused it)."""
        if not self._closed:
            self._closed = True
            if self._finished is not None and self._loop.is_running():
                self._loop.call_soon_threadsafe(self._finished.set)
            self._thread.join()
        if self._failure is not None:
            raise RobotClosedError(
                f"robot {self.config.agent_id} failed: {self._failure}"
            ) from self._failure
        return dict(self._result)

    def __enter__(self) -> RobotClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _submit(self, event: Event) -> None:
        if self._closed or self._engine is None or not self._loop.is_running():
            raise RobotClosedError(f"robot {self.config.agent_id} is closed")
        with contextlib.suppress(RuntimeError):  # the loop closed in between
            self._engine.submit(event)
            return
        raise RobotClosedError(f"robot {self.config.agent_id} is closed")

    # ------------------------------------------------------------------ robot thread
    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._main())
        except BaseException as exc:
            self._failure = exc
            logger.error("robot %s stopped: %s", self.config.agent_id, exc)
        finally:
            self._ready.set()
            self._put(_END)
            self._loop.close()

    def _put(self, item: object) -> None:
        """Queue for :meth:`poses`; when full, the oldest pose makes room."""
        while True:
            try:
                self._poses.put_nowait(item)
                return
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    self._poses.get_nowait()

    def _pose(self, pose: ReceivedPose) -> None:
        self._put(pose)
        if self._on_pose is not None:
            try:
                self._on_pose(pose)
            except Exception:
                logger.exception("robot %s: on_pose callback failed", self.config.agent_id)

    async def _send(self, msg: Message) -> bool:
        assert self._client is not None
        await self._client.send(msg)
        return True

    async def _stats(self) -> dict[str, Any]:
        assert self._engine is not None and self._client is not None
        return {**self._engine.stats(), "link": self._client.counters()}

    async def _main(self) -> None:
        cfg = self.config
        self._finished = asyncio.Event()
        cam = cfg.sensors.camera
        app = RobotApp(cfg.front_end, cam, cfg.sensors.imu, Vocabulary.load(cfg.vocabulary))
        core = RobotCore(cam.width, cam.height, cfg.live, uplink=UplinkBudget(cfg.uplink))
        session = SessionConfig(
            role="robot",
            agent_id=cfg.agent_id,
            keys=as_keyring(cfg.secret),
            heartbeat_interval=cfg.heartbeat_interval_s,
            idle_timeout=cfg.idle_timeout_s,
            max_outbox_messages=math.ceil(cfg.backlog_s * cfg.camera_rate_hz) + 16,
            ack_delay=ack_delay_s(cfg.camera_rate_hz),
        )
        executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="robot-worker")
        try:
            engine = RobotEngine(
                core, app, executor, self._send, self._pose, lambda: link_load(self._client)
            )
            self._client = Client(
                session,
                engine.on_delivery,
                cfg.edge_host,
                cfg.edge_port,
                transport=TransportConfig(),
                server_name="edge",
                ssl=cfg.tls.client_context(),
                server_hostname=cfg.edge_host,
            )
            await self._client.start()
            await self._client.send(sensors_message(cfg.sensors))
            self._engine = engine
            self._ready.set()
            await self._finished.wait()
            t0 = time.monotonic()
            await engine.drain()
            await self._client.send(RobotSequenceEnd(frames=app.frames))
            with contextlib.suppress(TimeoutError):
                left = max(0.1, cfg.close_timeout_s - (time.monotonic() - t0))
                await asyncio.wait_for(self._client.flush(), left)
            self._result = await self._stats()
            await engine.close()
        finally:
            if self._client is not None:
                await self._client.close()
            executor.shutdown(wait=True)
