"""The edge's policy without I/O: which robot messages are taken, queued, given to the VIO,
refused or held back, and where the VIO's and the cloud's messages go.

No sockets, threads, locks, clock or files here (h11's rule): events come in through
:meth:`EdgeCore.handle` and every decision leaves as an action (both in
:mod:`services.edge.core_events`). The driver (:class:`services.edge.app.EdgeApp`) decodes
frames on each robot's codec thread, runs each robot's VIO worker, journals and sends; a test
or an experiment can drive this very core with fabricated events instead. The edge has no
timing policy of its own (frames are ordered by their camera times; the transport times the
links), so there is no ``on_timer``: ``now`` is taken for the drivers' uniformity only.

Per robot (agent id) a :class:`RobotState`:

- ``RobotSensors`` (first message of every robot stream): the robot's own camera and IMU
  calibrations; a new robot is started (:class:`StartRobot`) and its sensors go on to the cloud
  (``AgentSensors``) ahead of its keyframes. An invalid description, a frame before any
  description, or a robot that re-joins under the same agent id with a different calibration
  is refused (:class:`Reject`: the robot is told why and stops; the message is never
  redelivered); the same calibration again (a robot's restart) is taken. Other robots are
  unaffected;
- journal: with journaling on, every live message taken is journaled (:class:`Journal`) once
  it is queued, before the handler returns (so before the transport acknowledges it); a live
  message at or before the robot's last journaled position is a duplicate (delivered again
  after a restart) and is dropped. Replayed messages are never journaled again;
- ``RobotFrame``: decoded by the driver (:class:`Decode`, in stream order; a frame that does
  not decode is refused and leaves the decoders untouched) and queued. The queue is bounded
  (``EdgeConfig.max_queued_frames``): a live frame (or sequence end) that finds it full is held
  (:class:`Hold`) until the runner takes one (:class:`Release`), which back-pressures the robot
  through the protocol window. Replayed frames are never held;
- the runner gets the queued frames one ahead (:class:`FeedWorker`: at most
  :data:`PIPELINE` steps out, the next handed over while the previous result is turned into
  messages, so the VIO never waits for the loop); a frame that arrives while the runner
  finishes its only step waits for that step (:class:`StepDone`), as it always did;
- fresh before complete (``EdgeConfig.max_vio_lag_s`` > 0): when its turn comes, a
  non-keyframe whose camera time is more than that behind the robot's newest decoded frame is
  not given to the VIO (counted as ``frames_skipped_stale``) and its IMU goes with the next
  frame fed; keyframes, a stream's first frame and replayed frames are never skipped;
- ``RobotSequenceEnd``: queued like a frame; when its turn comes and every step before it is
  done, :class:`CloseSequence` (the rest of the robot's points, frame poses and a status go
  to the cloud);
- ``PoseCorrection`` from the cloud is attached to the robot's next frame fed; the
  ``MapPlacement`` that comes with it (where the robot's map sits in the global map) goes on
  to the robot when it changed from the last one the robot was sent;
- a step's result (:class:`WorkerResult`) goes out: feedback to the robot (a feedback that
  could not be queued makes the next one a reset, :class:`FeedbackLost`), uplink to the
  cloud, a status when due.

Call everything from one thread: the core is as thread-unsafe as any plain object.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

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
from common.protocol.errors import RemoteProtocolError
from common.protocol.link_state import InboundPosition
from common.protocol.messages import Message
from services.edge.config import EdgeConfig
from services.edge.core_events import (
    Action,
    CloseSequence,
    CloudMessage,
    Decode,
    EdgeCoreError,
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

if TYPE_CHECKING:
    from services.edge.worker import WorkItem

logger = logging.getLogger(__name__)

PIPELINE = 2
"""Steps a robot's runner has out at once: one the worker computes, one it has ready next."""

Corrections = list[tuple[int, dict[int, np.ndarray]]]
"""Pose corrections for a robot's next frame: (map id, {keyframe id: (4, 4) T_world_body})."""
Placement = tuple[int, int, bytes]
"""A map placement as sent to the robot: (map id, global map, packed T_global_map)."""


@dataclass(frozen=True, eq=False)
class _Queued:
    item: WorkItem | None  # None: the robot's sequence end
    replaying: bool


@dataclass(frozen=True, eq=False)
class _InHand:
    """The robot message being handled (decoded, or waiting for room in the queue)."""

    stream_id: bytes
    seq: int
    message: Message
    replaying: bool


@dataclass(eq=False)
class RobotState:
    """One robot's policy state (plain data)."""

    sensors: Sensors
    queue: deque[_Queued] = field(default_factory=deque)  # waiting for the runner
    busy: int = 0  # jobs handed to the runner (steps, a CloseSequence) not yet StepDone
    closing: bool = False  # the sequence end left the queue: nothing is fed until it is done
    close_out: bool = False  # its CloseSequence is out
    in_hand: _InHand | None = None
    held: _Queued | None = None  # decoded, waiting for room in the queue
    newest_ns: int = 0  # camera time of the newest frame queued
    frames: int = 0  # frames decoded in this stream
    skipped_stale: int = 0  # non-keyframes not given to the VIO (EdgeConfig.max_vio_lag_s)
    carry: list[WorkItem] = field(default_factory=list)  # their IMU, for the next frame
    corrections: Corrections = field(default_factory=list)  # for the next frame fed
    placement: Placement | None = None  # the last one the robot was sent
    placement_before: Placement | None = None  # the one before (if that send fails)
    expected_frames: int | None = None  # from the robot's sequence end


class EdgeCore:
    """All robots' policy of one edge (module docstring). ``journal``: whether live messages
    are journaled (the driver has a journal store)."""

    def __init__(self, config: EdgeConfig | None = None, journal: bool = False) -> None:
        self.config = config or EdgeConfig()
        self.journal = journal
        self.robots: dict[str, RobotState] = {}

    # ------------------------------------------------------------------ events
    def handle(self, event: Event, now: float) -> list[Action]:
        """Take one event at ``now``; the actions to do, in order."""
        if isinstance(event, RobotMessage):
            return self._on_robot(event)
        if isinstance(event, RobotExpected):
            if event.agent_id in self.robots:
                return []
            return self._start(event.agent_id, event.sensors)
        if isinstance(event, CloudMessage):
            return self._on_cloud(event.message)
        rb = self._robot(event.agent_id)
        if isinstance(event, FrameDecoded):
            return self._on_decoded(event.agent_id, rb, event.item)
        if isinstance(event, FrameUndecodable):
            self._take(event.agent_id, rb, RobotFrame)
            return [
                Reject(
                    event.agent_id,
                    f"robot {event.agent_id}: frame {event.frame_index} does not decode: "
                    f"{event.error}",
                )
            ]
        if isinstance(event, WorkerResult):
            return self._on_result(event)
        if isinstance(event, StepDone):
            if rb.busy <= 0:
                raise EdgeCoreError(f"robot {event.agent_id}: StepDone without a job out")
            rb.busy -= 1
            if rb.close_out:
                rb.close_out = rb.closing = False
            return self._advance(event.agent_id, rb)
        if isinstance(event, RobotSendFailed):
            return self._send_failed(rb, event.agent_id, event.message)
        raise EdgeCoreError(f"not an edge core event: {event!r}")

    # ------------------------------------------------------------------ queries
    def idle(self, agent_id: str) -> bool:
        """True when the robot has nothing queued and nothing out with its runner."""
        rb = self.robots.get(agent_id)
        return rb is None or (not rb.queue and rb.busy == 0 and not rb.closing)

    def stats(self, agent_id: str) -> dict[str, Any]:
        """The robot's policy counters (``EdgeApp.stats`` adds its session's)."""
        rb = self._robot(agent_id)
        return {
            "frames_skipped_stale": rb.skipped_stale,
            "queued": len(rb.queue),
            "expected_frames": rb.expected_frames,
            "sensors": rb.sensors.summary(),
        }

    # ------------------------------------------------------------------ robot messages
    def _robot(self, agent_id: str) -> RobotState:
        rb = self.robots.get(agent_id)
        if rb is None:
            raise EdgeCoreError(f"robot {agent_id} is not known to the core")
        return rb

    def _start(self, agent_id: str, sensors: Sensors) -> list[Action]:
        self.robots[agent_id] = RobotState(sensors)
        return [StartRobot(agent_id, sensors), ToCloud(agent_sensors_message(agent_id, sensors))]

    def _journal(self, agent_id: str, hand: _InHand) -> list[Action]:
        if hand.replaying or not self.journal:
            return []
        return [Journal(agent_id, hand.stream_id, hand.seq, hand.message)]

    def _on_robot(self, ev: RobotMessage) -> list[Action]:
        agent_id, m, last = ev.agent_id, ev.message, ev.journaled
        if _journaled(ev, last):
            return []  # already journaled (and processed) before a restart
        hand = _InHand(ev.stream_id, ev.seq, m, ev.replaying)
        rb = self.robots.get(agent_id)
        if rb is not None and rb.in_hand is not None:  # the driver gave the last one up
            logger.warning(
                "robot %s: %s seq %d was not taken (its handler failed or was cancelled)",
                agent_id,
                type(rb.in_hand.message).__name__,
                rb.in_hand.seq,
            )
            rb.in_hand = rb.held = None
        if isinstance(m, RobotSensors):
            out = self._join(agent_id, m)
            if any(isinstance(a, Reject) for a in out):
                return out
            return out + self._journal(agent_id, hand)
        if rb is None:
            why = (
                f"robot {agent_id}: {type(m).__name__} before its RobotSensors (a robot's "
                "stream starts with its sensor description; after an edge restart without "
                "--state-dir the robot must restart its stream)"
            )
            return [Reject(agent_id, why)]
        if isinstance(m, RobotFrame):
            rb.in_hand = hand
            return [Decode(agent_id, m)]
        if isinstance(m, RobotSequenceEnd):
            rb.expected_frames = m.frames
            logger.info(
                "robot %s: sequence end after %d frames (decoded %d)", agent_id, m.frames, rb.frames
            )
            rb.in_hand = hand
            return self._offer(agent_id, rb, None)
        logger.warning("robot %s sent an unexpected %s; ignored", agent_id, type(m).__name__)
        return self._journal(agent_id, hand)

    def _join(self, agent_id: str, msg: RobotSensors) -> list[Action]:
        """A robot described its sensors: a new robot, or the check that a known robot came
        back with the very same ones."""
        try:
            sensors = read_sensors(msg)
        except RemoteProtocolError as exc:
            return [Reject(agent_id, f"robot {agent_id}: invalid sensor description: {exc}")]
        rb = self.robots.get(agent_id)
        if rb is None:
            return self._start(agent_id, sensors)
        if not rb.sensors.same_as(sensors):
            why = (
                f"robot {agent_id} re-joined with other sensors ({sensors.summary()}) "
                f"than its session has ({rb.sensors.summary()}); refused, maps are never "
                "mixed: give a robot with a new calibration a new agent id"
            )
            return [Reject(agent_id, why)]
        return []

    def _take(self, agent_id: str, rb: RobotState, kind: type[Message]) -> _InHand:
        hand = rb.in_hand
        if hand is None or not isinstance(hand.message, kind):
            raise EdgeCoreError(f"robot {agent_id}: no {kind.__name__} is being handled")
        rb.in_hand = None
        return hand

    def _on_decoded(self, agent_id: str, rb: RobotState, item: WorkItem) -> list[Action]:
        if rb.in_hand is None or not isinstance(rb.in_hand.message, RobotFrame):
            raise EdgeCoreError(f"robot {agent_id}: a decoded frame nobody asked for")
        rb.frames = 1 if item.new_stream else rb.frames + 1
        return self._offer(agent_id, rb, item)

    # ------------------------------------------------------------------ the queue
    def _offer(self, agent_id: str, rb: RobotState, item: WorkItem | None) -> list[Action]:
        """Queue the message in hand (a decoded frame, or the sequence end), or hold it while
        the queue is full (live messages only)."""
        assert rb.in_hand is not None
        queued = _Queued(item, rb.in_hand.replaying)
        if not queued.replaying and len(rb.queue) >= self.config.max_queued_frames:
            rb.held = queued
            return [Hold(agent_id)]
        return self._admit(agent_id, rb, queued)

    def _admit(self, agent_id: str, rb: RobotState, queued: _Queued) -> list[Action]:
        hand = rb.in_hand
        assert hand is not None
        rb.in_hand = None
        if queued.item is not None and queued.item.obs is not None:
            t = queued.item.obs.timestamp_ns  # (a restarted stream's time starts again)
            rb.newest_ns = t if queued.item.new_stream else max(rb.newest_ns, t)
        rb.queue.append(queued)
        out = self._journal(agent_id, hand)
        if rb.busy == 0 and not rb.closing:  # the runner waits for a frame
            out += self._advance(agent_id, rb)
        return out

    def _advance(self, agent_id: str, rb: RobotState) -> list[Action]:
        """The runner's next jobs, then the held message into the room they made."""
        out = self._pump(agent_id, rb)
        if rb.held is not None and len(rb.queue) < self.config.max_queued_frames:
            queued, rb.held = rb.held, None
            out += self._admit(agent_id, rb, queued)
            out.append(Release(agent_id))
        return out

    def _pump(self, agent_id: str, rb: RobotState) -> list[Action]:
        """Hand the runner frames while it has room (:data:`PIPELINE`); the sequence end once
        every step before it is done."""
        out: list[Action] = []
        while not rb.closing and rb.queue and rb.busy < PIPELINE:
            q = rb.queue.popleft()
            if q.item is None:
                rb.closing = True
                break
            item = q.item
            if self._stale(rb, item, q.replaying):
                rb.carry.append(item)
                rb.skipped_stale += 1
                continue
            if rb.carry:
                item = _with_imu_of(rb.carry, item)
                rb.carry = []
            if rb.corrections:
                item = dataclasses.replace(item, corrections=tuple(rb.corrections))
                rb.corrections = []
            rb.busy += 1
            out.append(FeedWorker(agent_id, item, q.replaying))
        if rb.closing and rb.busy == 0 and not rb.close_out:
            rb.close_out = True
            rb.busy += 1
            out.append(CloseSequence(agent_id))
        return out

    def _stale(self, rb: RobotState, item: WorkItem, replaying: bool) -> bool:
        """A non-keyframe too far behind the robot's newest frame for the VIO to spend time
        on (``EdgeConfig.max_vio_lag_s``; never while replaying, never a keyframe)."""
        lag = self.config.max_vio_lag_s
        obs = item.obs
        if replaying or lag <= 0 or obs is None or obs.is_keyframe or item.new_stream:
            return False
        return rb.newest_ns - obs.timestamp_ns > lag * 1e9

    # ------------------------------------------------------------------ results
    def _on_result(self, ev: WorkerResult) -> list[Action]:
        if ev.failed:
            logger.error("robot %s: %s (other robots unaffected)", ev.agent_id, ev.failed)
        out: list[Action] = [ToRobot(ev.agent_id, m) for m in ev.robot]
        out += [ToCloud(m) for m in ev.cloud]
        if ev.status_due:
            out.append(SendStatus(ev.agent_id))
        return out

    def _send_failed(self, rb: RobotState, agent_id: str, m: Message) -> list[Action]:
        if isinstance(m, RobotMapPlacement):  # sent again when it comes again
            if rb.placement == (m.map_id, m.global_map, m.pose):
                rb.placement = rb.placement_before
            return []
        return [FeedbackLost(agent_id)]

    # ------------------------------------------------------------------ the cloud
    def _on_cloud(self, m: Message) -> list[Action]:
        """Pose corrections for a robot's map, and where that map sits in the global map
        (forwarded to the robot when it changed)."""
        if not isinstance(m, PoseCorrection | PoseCorrectionCoded | MapPlacement):
            logger.warning("cloud sent an unexpected %s; ignored", type(m).__name__)
            return []
        rb = self.robots.get(m.agent_id)
        if rb is None:
            logger.warning("%s for unknown robot %s; ignored", type(m).__name__, m.agent_id)
            return []
        if isinstance(m, MapPlacement):
            return self._forward_placement(rb, m)
        try:
            ids, T = decode_pose_correction(m)
        except RemoteProtocolError as exc:
            logger.warning("pose correction for %s refused: %s", m.agent_id, exc)
            return []
        poses = {int(k): np.array(t) for k, t in zip(ids, T, strict=True)}
        rb.corrections.append((m.map_id, poses))
        return []

    def _forward_placement(self, rb: RobotState, m: MapPlacement) -> list[Action]:
        try:
            decode_map_placement(m)
        except RemoteProtocolError as exc:
            logger.warning("map placement for %s refused: %s", m.agent_id, exc)
            return []
        key = (m.map_id, m.global_map, m.pose)
        if rb.placement == key:
            return []
        rb.placement_before, rb.placement = rb.placement, key
        return [ToRobot(m.agent_id, RobotMapPlacement(m.map_id, m.global_map, m.pose))]


def _journaled(ev: RobotMessage, last: InboundPosition | None) -> bool:
    """A live message at or before the robot's last journaled position (a duplicate)."""
    if ev.replaying or last is None:
        return False
    return last.stream_id == ev.stream_id and ev.seq <= last.last_delivered


def _with_imu_of(skipped: list[WorkItem], item: WorkItem) -> WorkItem:
    """``item`` with the IMU of the frames ``skipped`` before it, in time order."""
    parts = [*skipped, item]
    return dataclasses.replace(
        item,
        imu_t_ns=np.concatenate([p.imu_t_ns for p in parts]),
        gyro=np.concatenate([p.gyro for p in parts]),
        accel=np.concatenate([p.accel for p in parts]),
    )
