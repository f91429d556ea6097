"""The edge's application: the asyncio driver of :class:`~services.edge.core.EdgeCore`. It
reacts to delivered messages and never touches bytes or sockets.

The policy (joins and refusals, journal de-duplication, the bounded frame queue and its
back-pressure, stale frames skipped, corrections and placements, sequence ends) is the
core's (:mod:`services.edge.core`); this module does the core's actions. Per robot (agent id)
a :class:`_Robot` holds what they need: its sensors, a :class:`RobotSession` (decoders,
outputs), a worker running its VIO (``services.edge.worker``), a codec thread and a runner
task:

- a robot's message goes to the core (:class:`RobotMessage`, with the robot's last journaled
  position); a :class:`Reject` becomes ``RejectedMessageError`` (the robot is told why and
  stops); a :class:`Hold` keeps the handler (so the transport's acknowledgement) waiting until
  the core's :class:`Release`, which back-pressures the robot through the protocol window;
  :class:`Journal` appends to the robot's journal before the handler returns;
- the robot's codec work (decoding its frames, :class:`Decode`; turning its VIO results into
  messages) runs on the robot's own codec thread, one call at a time, never on the event
  loop: six robots' decoding on a loaded machine once held the loop for 12 s, longer than the
  peers' idle timeout, and every robot timed out (#20). The loop only moves messages, so
  heartbeats and acks keep flowing however busy the codecs are;
- :class:`FeedWorker` hands a frame to the worker at once; the robot's runner task takes the
  results in order, turns each into messages on the codec thread (:class:`WorkerResult`: the
  core says where they go) and reports :class:`StepDone`; :class:`CloseSequence` (the robot's
  sequence end) sends the rest of its points, frame poses and a status to the cloud;
- on start, :meth:`EdgeApp.replay` re-decodes each journal and fast-forwards the VIO over it
  (no robot feedback during replay). The re-run is a new map (map ids of this run's
  generations, :data:`~services.edge.worker.GENERATIONS_PER_RUN`): the VIO is not
  deterministic, so its keyframes and points are not the first run's under the same ids, and
  the cloud merges the new map with the old one as with any other map of the robot.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Protocol

from common.codec.errors import CodecError
from common.links.edge_cloud import KeyframeUpdate, KeyframeUpdateCoded
from common.links.robot_edge import RobotFrame
from common.links.sensors import Sensors
from common.protocol.errors import RejectedMessageError
from common.protocol.messages import Message, decode_payload, encode_payload
from common.transport import Delivery
from common.vocabulary import Vocabulary
from services.edge.cloud_budget import CloudBudget
from services.edge.config import EdgeConfig
from services.edge.core import EdgeCore
from services.edge.core_events import (
    Action,
    CloseSequence,
    CloudMessage,
    Decode,
    Event,
    FeedbackLost,
    FeedWorker,
    FrameDecoded,
    FrameUndecodable,
    Hold,
    Journal,
    Reject,
    Release,
    RobotExpected,
    RobotMessage,
    RobotSendFailed,
    SendStatus,
    StartRobot,
    StepDone,
    ToCloud,
    ToRobot,
    WorkerResult,
)
from services.edge.journal import JournalRecord, JournalStore
from services.edge.robot_session import RobotSession
from services.edge.worker import (
    GENERATIONS_PER_RUN,
    Worker,
    WorkerFactory,
    WorkerSpec,
    WorkResult,
    make_worker,
)

logger = logging.getLogger(__name__)

__all__ = ["EdgeApp", "EdgeConfig", "Sink"]


class Sink(Protocol):
    """Where the app's messages go (the server implements it with the transport)."""

    def to_robot(self, agent_id: str, message: Message) -> bool:
        """Queue ``message`` for the robot; False if it was dropped (no such peer, outbox
        full): the robot's next feedback must then replace its landmarks, not update them."""
        ...

    async def to_cloud(self, message: Message) -> None: ...

    def link_counters(self, agent_id: str) -> dict[str, int]: ...

    def cloud_load(self) -> tuple[int, int]:
        """The cloud link: (bytes unacknowledged, bytes acknowledged so far)."""
        ...


_Job = tuple[asyncio.Future[WorkResult] | None, bool]  # a step (None: the sequence end)


@dataclass
class _Robot:
    sensors: Sensors
    session: RobotSession
    worker: Worker
    codec: ThreadPoolExecutor  # decode and on_result, one at a time (they share state)
    jobs: asyncio.Queue[_Job] = field(default_factory=asyncio.Queue)  # for the runner, in order
    task: asyncio.Task[None] | None = None
    idle: asyncio.Event = field(default_factory=asyncio.Event)
    ended: asyncio.Event = field(default_factory=asyncio.Event)
    released: asyncio.Event = field(default_factory=asyncio.Event)  # a held message queued


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
        self.core = EdgeCore(self.config, journal=journal is not None)
        self.robots: dict[str, _Robot] = {}
        self.cloud_budget = CloudBudget(self.config.cloud_budget)

    # ------------------------------------------------------------------ the core
    async def _handle(self, event: Event) -> None:
        """Give ``event`` to the core and do its actions."""
        actions = self.core.handle(event, asyncio.get_running_loop().time())
        agent_id = getattr(event, "agent_id", "")
        rb = self.robots.get(agent_id)
        if rb is not None:
            if self.core.idle(agent_id):
                rb.idle.set()
            else:
                rb.idle.clear()
        await self._do(actions)

    async def _do(self, actions: list[Action]) -> None:
        """Do the core's ``actions`` in order. Those that hand out work (FeedWorker,
        CloseSequence, Journal, Release) are done at once, without yielding to the loop."""
        for a in actions:
            if isinstance(a, StartRobot):
                self._new_robot(a.agent_id, a.sensors)
            elif isinstance(a, Reject):
                raise RejectedMessageError(a.reason)
            elif isinstance(a, Decode):
                await self._decode(a)
            elif isinstance(a, Hold):
                rb = self.robots[a.agent_id]
                rb.released.clear()
                await rb.released.wait()
            elif isinstance(a, Release):
                self.robots[a.agent_id].released.set()
            elif isinstance(a, Journal):
                assert self.journal is not None
                m = a.message
                rec = JournalRecord(a.stream_id, a.seq, m.TYPE_ID, encode_payload(m))
                self.journal.journal(a.agent_id).append(rec)
            elif isinstance(a, FeedWorker):
                rb = self.robots[a.agent_id]
                rb.jobs.put_nowait((asyncio.ensure_future(rb.worker.step(a.item)), a.replaying))
            elif isinstance(a, CloseSequence):
                self.robots[a.agent_id].jobs.put_nowait((None, False))
            elif isinstance(a, ToRobot):
                if not self.sink.to_robot(a.agent_id, a.message):
                    await self._handle(RobotSendFailed(a.agent_id, a.message))
            elif isinstance(a, ToCloud):
                await self._to_cloud(a.message)
            elif isinstance(a, SendStatus):
                await self._send_status(self.robots[a.agent_id].session)
            elif isinstance(a, FeedbackLost):
                self.robots[a.agent_id].session.feedback_lost()

    async def _send_status(self, s: RobotSession) -> None:
        await self._to_cloud(s.status(self.sink.link_counters(s.agent_id)))

    async def _to_cloud(self, m: Message) -> None:
        """Send ``m`` to the cloud, counted by the cloud budget (when one applies)."""
        features = 0
        if isinstance(m, KeyframeUpdateCoded | KeyframeUpdate) and m.agent_id in self.robots:
            sent = self.robots[m.agent_id].session.features_uplinked
            features = sent.pop((m.map_id, m.keyframe_id), 0)
        if self.config.cloud_budget.active:
            now = asyncio.get_running_loop().time()
            self.cloud_budget.on_sent(now, len(encode_payload(m)), features)
        await self.sink.to_cloud(m)

    def _allowance(self, s: RobotSession) -> None:
        """Hand the session the cloud budget's allowance for its next results."""
        if not self.config.cloud_budget.active:
            return
        self.cloud_budget.on_link(asyncio.get_running_loop().time(), *self.sink.cloud_load())
        active = sum(not rb.session.finished for rb in self.robots.values())
        s.cloud_allowance = self.cloud_budget.allowance(active)

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
            ThreadPoolExecutor(1, thread_name_prefix=f"codec-{agent_id}"),
        )
        rb.idle.set()
        rb.task = asyncio.create_task(self._run(rb), name=f"edge-robot-{agent_id}")
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

    async def _decode(self, a: Decode) -> None:
        """Decode a frame on the robot's codec thread (in stream order)."""
        rb = self.robots[a.agent_id]
        loop = asyncio.get_running_loop()
        try:
            item = await loop.run_in_executor(rb.codec, rb.session.decode, a.frame)
        except CodecError as exc:  # the robot's fault: refused once, decoders untouched
            await self._handle(FrameUndecodable(a.agent_id, a.frame.frame_index, str(exc)))
        else:
            await self._handle(FrameDecoded(a.agent_id, item))

    async def _run(self, rb: _Robot) -> None:
        """The robot's runner: its worker's results in order, each turned into messages on
        the codec thread while the worker computes the next step; then the sequence end."""
        s = rb.session
        loop = asyncio.get_running_loop()
        try:
            while True:
                step, replaying = await rb.jobs.get()
                if step is None:  # the sequence end, every step before it done
                    s.finished = True
                    for m in [*s.release_points(), *s.release_frame_poses()]:  # the rest
                        await self._to_cloud(m)
                    await self._send_status(s)
                    rb.ended.set()
                else:
                    res = await step
                    self._allowance(s)
                    on_result = functools.partial(s.on_result, res, replaying=replaying)
                    out = await loop.run_in_executor(rb.codec, on_result)
                    await self._handle(
                        WorkerResult(
                            s.agent_id,
                            tuple(out.robot),
                            tuple(out.cloud),
                            out.status_due,
                            res.failed,
                        )
                    )
                await self._handle(StepDone(s.agent_id))
        except BaseException:  # cancelled (shutdown) or a worker error: drop the steps out
            while not rb.jobs.empty():
                pending, _ = rb.jobs.get_nowait()
                if pending is not None:
                    pending.cancel()
            raise

    # ------------------------------------------------------------------ messages
    async def on_robot_message(self, d: Delivery) -> None:
        """Handler of the robots' link (one call per message, in order per robot)."""
        last = None if self.journal is None else self.journal.journal(d.peer).last
        await self._handle(RobotMessage(d.peer, d.message, d.stream_id, d.seq, last))

    async def on_cloud_message(self, d: Delivery) -> None:
        """Handler of the cloud link: pose corrections for a robot's map, and where that map
        sits in the global map (forwarded to the robot when it changed)."""
        await self._handle(CloudMessage(d.message))

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
                    await self._handle(
                        RobotMessage(agent, msg, rec.stream_id, rec.seq, replaying=True)
                    )
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
            core = self.core.stats(name)
            out[name] = {
                "frames_decoded": s.frames,
                "frames_processed": s.processed,
                "frames_skipped_stale": core["frames_skipped_stale"],
                "keyframes_decoded": s.keyframes,
                "keyframes_uplinked": s.vio_keyframes,
                "keyframes_kept_on_edge": dict(s.kept_on_edge),
                "state": s.state,
                "reason": s.reason,
                "time_offset_ms": s.time_offset_ns * 1e-6,
                "time_offset_sigma_ms": s.time_offset_sigma_ms,
                "map_id": s.map_id,
                "vio": dict(s.vio_counts),
                "failures": list(s.failures),
                "feedback_sent": s.feedback_sent,
                "queued": core["queued"],
                "finished": s.finished,
                "expected_frames": core["expected_frames"],
                "frame_s": list(s.frame_s),
                "track_s": list(s.track_s),
                "local_ba_s": list(s.local_ba_s),
                "sensors": core["sensors"],
            }
        return out

    async def prepare(self, robots: dict[str, Sensors]) -> None:
        """Create the sessions of robots expected soon (agent id -> the sensors they will
        describe; one that joins with others is refused) and start their workers now."""
        for agent_id, sensors in robots.items():
            await self._handle(RobotExpected(agent_id, sensors))
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
