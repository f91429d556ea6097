"""The edge's application: reacts to delivered messages, never touches bytes or sockets.

Per robot (agent id) an :class:`_Robot` holds its sensors, a :class:`RobotSession` (decoders,
outputs), a worker running its VIO (``services.edge.worker``), an input queue and a task
draining it:

- ``RobotSensors`` (first message of every robot stream): the robot's own camera and IMU
  calibrations; the robot's decoders and VIO are built from them, and they go on to the
  cloud (``AgentSensors``) ahead of the robot's keyframes. It is journaled like every message,
  so a restarted edge rebuilds the robot from its journal. An invalid description, a frame
  before any description, or a robot that re-joins under the same agent id with a different
  calibration is refused (``RejectedMessageError``: the robot is told why with a ``Reject``
  and stops; the message is never redelivered); other robots are unaffected;
- ``RobotFrame``: decoded at once (in stream order; a frame that does not decode is refused
  likewise and leaves the decoders untouched), journaled (when a journal is configured) and
  queued; the handler returns, so the transport acknowledges, once the
  frame is in the journal. The queue is bounded (``EdgeConfig.max_queued_frames``): a full
  queue makes the handler wait, which back-pressures the robot through the protocol window;
- the robot's task feeds the worker frame by frame, one frame ahead (the worker computes the
  next frame while the loop turns the previous result into messages via the :class:`Sink`:
  feedback to the robot, uplink to the cloud);
- the robot's codec work (decoding its frames, turning its VIO results into messages) runs on
  the robot's own codec thread, one call at a time, never on the event loop: six robots'
  decoding on a loaded machine once held the loop for 12 s, longer than the peers' idle
  timeout, and every robot timed out (#20). The loop only moves messages, so heartbeats and
  acks keep flowing however busy the codecs are;
- ``PoseCorrection`` from the cloud is attached to that robot's next frame; the
  ``MapPlacement`` that comes with it (where the robot's map sits in the global map) goes on
  to the robot when it changed;
- on start, :meth:`EdgeApp.replay` re-decodes each journal and fast-forwards the VIO over it
  (no robot feedback during replay). The re-run is a new map (map ids of this run's
  generations, :data:`~services.edge.worker.GENERATIONS_PER_RUN`): the VIO is not
  deterministic, so its keyframes and points are not the first run's under the same ids, and
  the cloud merges the new map with the old one as with any other map of the robot.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from common.codec.errors import CodecError
from common.links.edge_cloud import (
    MapPlacement,
    PoseCorrection,
    PoseCorrectionCoded,
    agent_sensors_message,
    decode_map_placement,
    decode_pose_correction,
)
from common.links.robot_edge import MapPlacement as RobotMapPlacement
from common.links.robot_edge import RobotFrame, RobotSensors, RobotSequenceEnd, read_sensors
from common.links.sensors import Sensors
from common.protocol.errors import RejectedMessageError, RemoteProtocolError
from common.protocol.messages import Message, decode_payload, encode_payload
from common.transport import Delivery
from common.vocabulary import Vocabulary
from services.edge.journal import JournalRecord, JournalStore
from services.edge.robot_session import RobotSession, SessionOptions
from services.edge.vio.types import VioOptions
from services.edge.worker import (
    GENERATIONS_PER_RUN,
    Worker,
    WorkerFactory,
    WorkerSpec,
    WorkItem,
    make_worker,
)

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EdgeConfig:
    """Options of the edge application.

    worker: "process" (one spawned VIO process per robot, default) or "thread".
    max_queued_frames: decoded frames waiting for a robot's VIO before the handler waits
        (200 = 10 s at 20 Hz).
    max_vio_lag_s: fresh before complete at the edge (``recslam edge --max-vio-lag``): a
        non-keyframe whose camera time is more than this behind the robot's newest decoded
        frame is not given to the VIO (its IMU goes with the next frame, which the VIO
        integrates across the gap; counted per robot as ``frames_skipped_stale``); keyframes
        always go. 0 (default): every frame, however late (the lossless recorder).
    vio: the VIO's options; session: feedback / status / uplink options.
    """

    worker: str = "process"
    max_queued_frames: int = 200
    max_vio_lag_s: float = 0.0
    vio: VioOptions = field(default_factory=VioOptions)
    session: SessionOptions = field(default_factory=SessionOptions)


class Sink(Protocol):
    """Where the app's messages go (the server implements it with the transport)."""

    def to_robot(self, agent_id: str, message: Message) -> bool:
        """Queue ``message`` for the robot; False if it was dropped (no such peer, outbox
        full): the robot's next feedback must then replace its landmarks, not update them."""
        ...

    async def to_cloud(self, message: Message) -> None: ...

    def link_counters(self, agent_id: str) -> dict[str, int]: ...


@dataclass
class _Robot:
    sensors: Sensors
    session: RobotSession
    worker: Worker
    queue: asyncio.Queue[tuple[WorkItem | None, bool]]
    space: asyncio.Event
    codec: ThreadPoolExecutor  # decode and on_result, one at a time (they share state)
    corrections: list[tuple[int, dict[int, np.ndarray]]] = field(default_factory=list)
    placement: tuple[int, int, bytes] | None = None  # the last one the robot was sent
    task: asyncio.Task[None] | None = None
    idle: asyncio.Event = field(default_factory=asyncio.Event)
    ended: asyncio.Event = field(default_factory=asyncio.Event)
    expected_frames: int | None = None
    newest_ns: int = 0  # camera time of the newest frame decoded
    skipped_stale: int = 0  # non-keyframes not given to the VIO (EdgeConfig.max_vio_lag_s)
    carry: list[WorkItem] = field(default_factory=list)  # their IMU, for the next frame


class EdgeApp:
    """All robots of one edge (see the module docstring)."""

    def __init__(
        self,
        vocabulary: Vocabulary,
        sink: Sink,
        config: EdgeConfig | None = None,
        journal: JournalStore | None = None,
        worker_factory: WorkerFactory = make_worker,
    ) -> None:
        self.vocabulary = vocabulary
        self.sink = sink
        self.config = config or EdgeConfig()
        self.journal = journal
        self.worker_factory = worker_factory
        self.robots: dict[str, _Robot] = {}
        self.on_robot_added: Callable[[str], None] | None = None

    # ------------------------------------------------------------------ robots
    def _new_robot(self, agent_id: str, sensors: Sensors) -> _Robot:
        """The session and worker of a robot that joined with ``sensors``."""
        camera = sensors.camera
        session = RobotSession(agent_id, camera, self.vocabulary, self.config.session)
        run = 0 if self.journal is None else self.journal.next_run(agent_id)
        spec = WorkerSpec(agent_id, camera, sensors.imu, self.config.vio, run * GENERATIONS_PER_RUN)
        rb = _Robot(
            sensors,
            session,
            self.worker_factory(spec, self.config.worker),
            asyncio.Queue(),
            asyncio.Event(),
            ThreadPoolExecutor(1, thread_name_prefix=f"codec-{agent_id}"),
        )
        rb.idle.set()
        rb.task = asyncio.create_task(self._drain(rb), name=f"edge-robot-{agent_id}")
        self.robots[agent_id] = rb
        if self.journal is not None:
            self.journal.register(agent_id)
        logger.info(
            "robot %s: new session (%s worker): %s",
            agent_id,
            self.config.worker,
            sensors.summary(),
        )
        return rb

    async def _join(self, agent_id: str, msg: RobotSensors) -> None:
        """A robot described its sensors: a new robot's session, or the check that a known
        robot came back with the very same ones (RejectedMessageError otherwise)."""
        try:
            sensors = read_sensors(msg)
        except RemoteProtocolError as exc:
            why = f"robot {agent_id}: invalid sensor description: {exc}"
            raise RejectedMessageError(why) from exc
        rb = self.robots.get(agent_id)
        if rb is not None:
            if not rb.sensors.same_as(sensors):
                raise RejectedMessageError(
                    f"robot {agent_id} re-joined with other sensors ({sensors.summary()}) "
                    f"than its session has ({rb.sensors.summary()}); refused, maps are never "
                    "mixed: give a robot with a new calibration a new agent id"
                )
            return
        self._new_robot(agent_id, sensors)
        await self.sink.to_cloud(agent_sensors_message(agent_id, sensors))

    async def _drain(self, rb: _Robot) -> None:
        """Feed the robot's worker in order, one frame ahead: the next frame is handed over
        before the previous result is turned into messages, so the VIO never waits for this
        loop (the worker runs its steps one after another, in order)."""
        s = rb.session
        pending: tuple[asyncio.Future, bool] | None = None  # the step in flight
        while True:
            if pending is not None and rb.queue.empty():
                await self._finish(rb, *pending)  # nothing to overlap with
                pending = None
                if rb.queue.empty():
                    rb.idle.set()
                continue
            item, replaying = await rb.queue.get()
            rb.idle.clear()
            rb.space.set()
            if item is None:
                if pending is not None:
                    await self._finish(rb, *pending)
                    pending = None
                s.finished = True
                for m in [*s.release_points(), *s.release_frame_poses()]:  # the rest
                    await self.sink.to_cloud(m)
                await self.sink.to_cloud(s.status(self.sink.link_counters(s.agent_id)))
                rb.ended.set()
                if rb.queue.empty():
                    rb.idle.set()
                continue
            if self._stale(rb, item, replaying):
                rb.carry.append(item)
                rb.skipped_stale += 1
                continue
            if rb.carry:
                item = _with_imu_of(rb.carry, item)
                rb.carry.clear()
            if rb.corrections:
                item = dataclasses.replace(item, corrections=tuple(rb.corrections))
                rb.corrections.clear()
            step = asyncio.ensure_future(rb.worker.step(item))
            if pending is not None:
                try:
                    await self._finish(rb, *pending)
                except BaseException:  # cancelled (shutdown) or a worker error: drop the next
                    step.cancel()
                    raise
            pending = (step, replaying)

    def _stale(self, rb: _Robot, item: WorkItem, replaying: bool) -> bool:
        """A non-keyframe too far behind the robot's newest frame for the VIO to spend time
        on (``EdgeConfig.max_vio_lag_s``; never while replaying, never a keyframe)."""
        lag = self.config.max_vio_lag_s
        obs = item.obs
        if replaying or lag <= 0 or obs is None or obs.is_keyframe or item.new_stream:
            return False
        return rb.newest_ns - obs.timestamp_ns > lag * 1e9

    async def _finish(self, rb: _Robot, step: asyncio.Future, replaying: bool) -> None:
        """Turn one worker result into feedback and uplink messages."""
        s = rb.session
        res = await step
        if res.failed:
            logger.error("robot %s: %s (other robots unaffected)", s.agent_id, res.failed)
        on_result = functools.partial(s.on_result, res, replaying=replaying)
        out = await asyncio.get_running_loop().run_in_executor(rb.codec, on_result)
        for m in out.robot:
            if not self.sink.to_robot(s.agent_id, m):
                s.feedback_lost()
        for m in out.cloud:
            await self.sink.to_cloud(m)
        if out.status_due:
            await self.sink.to_cloud(s.status(self.sink.link_counters(s.agent_id)))

    async def _enqueue(self, rb: _Robot, item: WorkItem | None, replaying: bool) -> None:
        if not replaying:
            while rb.queue.qsize() >= self.config.max_queued_frames:
                rb.space.clear()
                await rb.space.wait()
        rb.idle.clear()
        if item is not None and item.obs is not None:
            rb.newest_ns = max(rb.newest_ns, item.obs.timestamp_ns)
        rb.queue.put_nowait((item, replaying))

    # ------------------------------------------------------------------ messages
    async def on_robot_message(self, d: Delivery) -> None:
        """Handler of the robots' link (one call per message, in order per robot)."""
        if self.journal is not None:
            last = self.journal.journal(d.peer).last
            if last is not None and last.stream_id == d.stream_id and d.seq <= last.last_delivered:
                return  # already journaled (and processed) before a restart
        await self._apply(d.peer, d.message, replaying=False)
        if self.journal is not None:
            rec = JournalRecord(d.stream_id, d.seq, d.message.TYPE_ID, encode_payload(d.message))
            self.journal.journal(d.peer).append(rec)

    async def _apply(self, agent_id: str, m: Message, replaying: bool) -> None:
        if isinstance(m, RobotSensors):
            await self._join(agent_id, m)
            return
        rb = self.robots.get(agent_id)
        if rb is None:
            raise RejectedMessageError(
                f"robot {agent_id}: {type(m).__name__} before its RobotSensors (a robot's "
                "stream starts with its sensor description; after an edge restart without "
                "--state-dir the robot must restart its stream)"
            )
        if isinstance(m, RobotFrame):
            loop = asyncio.get_running_loop()
            try:
                item = await loop.run_in_executor(rb.codec, rb.session.decode, m)
            except CodecError as exc:  # the robot's fault: refused once, decoders untouched
                raise RejectedMessageError(
                    f"robot {agent_id}: frame {m.frame_index} does not decode: {exc}"
                ) from exc
            await self._enqueue(rb, item, replaying)
        elif isinstance(m, RobotSequenceEnd):
            rb.expected_frames = m.frames
            logger.info(
                "robot %s: sequence end after %d frames (decoded %d)",
                rb.session.agent_id,
                m.frames,
                rb.session.frames,
            )
            await self._enqueue(rb, None, replaying)
        else:
            logger.warning(
                "robot %s sent an unexpected %s; ignored", rb.session.agent_id, type(m).__name__
            )

    async def on_cloud_message(self, d: Delivery) -> None:
        """Handler of the cloud link: pose corrections for a robot's map, and where that map
        sits in the global map (forwarded to the robot when it changed)."""
        m = d.message
        if not isinstance(m, PoseCorrection | PoseCorrectionCoded | MapPlacement):
            logger.warning("cloud sent an unexpected %s; ignored", type(m).__name__)
            return
        rb = self.robots.get(m.agent_id)
        if rb is None:
            logger.warning("%s for unknown robot %s; ignored", type(m).__name__, m.agent_id)
            return
        if isinstance(m, MapPlacement):
            self._forward_placement(rb, m)
            return
        try:
            ids, T = decode_pose_correction(m)
        except RemoteProtocolError as exc:
            logger.warning("pose correction for %s refused: %s", m.agent_id, exc)
            return
        poses = {int(k): np.array(t) for k, t in zip(ids, T, strict=True)}
        rb.corrections.append((m.map_id, poses))

    def _forward_placement(self, rb: _Robot, m: MapPlacement) -> None:
        try:
            decode_map_placement(m)
        except RemoteProtocolError as exc:
            logger.warning("map placement for %s refused: %s", m.agent_id, exc)
            return
        key = (m.map_id, m.global_map, m.pose)
        if rb.placement == key:
            return
        msg = RobotMapPlacement(m.map_id, m.global_map, m.pose)
        if self.sink.to_robot(m.agent_id, msg):
            rb.placement = key

    # ------------------------------------------------------------------ restart
    async def replay(self) -> int:
        """Re-decode every journal and queue its frames (VIO fast-forward); returns frames."""
        if self.journal is None:
            return 0
        n = 0
        for agent in self.journal.agents():
            records = self.journal.journal(agent).read()
            for rec in records:
                try:
                    msg = decode_payload(rec.type_id, rec.payload)
                    await self._apply(agent, msg, replaying=True)
                except RejectedMessageError as exc:  # a journal from before sensors travelled
                    logger.error("robot %s: journal not replayed: %s", agent, exc)
                    break
                n += rec.type_id == RobotFrame.TYPE_ID
            logger.info("robot %s: replaying %d journaled messages", agent, len(records))
        return n

    # ------------------------------------------------------------------ lifecycle
    async def wait_idle(self, agent_id: str | None = None) -> None:
        """Until the robot's (every robot's) queued frames are processed."""
        for name, rb in list(self.robots.items()):
            if agent_id is None or name == agent_id:
                await rb.idle.wait()

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per-robot plain-data counters."""
        out = {}
        for name, rb in self.robots.items():
            s = rb.session
            out[name] = {
                "frames_decoded": s.frames,
                "frames_processed": s.processed,
                "frames_skipped_stale": rb.skipped_stale,
                "keyframes_decoded": s.keyframes,
                "keyframes_uplinked": s.vio_keyframes,
                "state": s.state,
                "reason": s.reason,
                "time_offset_ms": s.time_offset_ns * 1e-6,
                "time_offset_sigma_ms": s.time_offset_sigma_ms,
                "map_id": s.map_id,
                "failures": list(s.failures),
                "feedback_sent": s.feedback_sent,
                "queued": rb.queue.qsize(),
                "finished": s.finished,
                "expected_frames": rb.expected_frames,
                "frame_s": list(s.frame_s),
                "track_s": list(s.track_s),
                "local_ba_s": list(s.local_ba_s),
                "sensors": rb.sensors.summary(),
            }
        return out

    async def prepare(self, robots: dict[str, Sensors]) -> None:
        """Create the sessions of robots expected soon (agent id -> the sensors they will
        describe; one that joins with others is refused) and start their workers now."""
        for agent_id, sensors in robots.items():
            if agent_id not in self.robots:
                self._new_robot(agent_id, sensors)
                await self.sink.to_cloud(agent_sensors_message(agent_id, sensors))
        await self.start_workers()

    async def start_workers(self) -> None:
        """Start process workers ahead of the first frame (spawn + imports take ~1-2 s)."""
        for rb in self.robots.values():
            start = getattr(rb.worker, "start", None)
            if start is not None:
                await start()

    async def close(self) -> None:
        for rb in self.robots.values():
            if rb.task is not None:
                rb.task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await rb.task
            await rb.worker.close()
            rb.codec.shutdown(wait=False)


def _with_imu_of(skipped: list[WorkItem], item: WorkItem) -> WorkItem:
    """``item`` with the IMU of the frames ``skipped`` before it, in time order."""
    parts = [*skipped, item]
    return dataclasses.replace(
        item,
        imu_t_ns=np.concatenate([p.imu_t_ns for p in parts]),
        gyro=np.concatenate([p.gyro for p in parts]),
        accel=np.concatenate([p.accel for p in parts]),
    )
