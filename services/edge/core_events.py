"""What the edge's core takes in and hands out (plain data, no I/O).

Events go into :meth:`services.edge.core.EdgeCore.handle`; the actions it returns are for the
driver (:class:`services.edge.app.EdgeApp`) to do, in order. Frames and results travel as the
worker's own types (:class:`~services.edge.worker.WorkItem`); the core never runs a decoder,
a VIO step or a send itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from common.errors import RecslamError
from common.links.robot_edge import RobotFrame
from common.links.sensors import Sensors
from common.protocol.link_state import InboundPosition
from common.protocol.messages import Message

if TYPE_CHECKING:
    from services.edge.worker import WorkItem


class EdgeCoreError(RecslamError):
    """Local misuse of the core (an event for a robot it does not know, a decoded frame it
    did not ask for)."""


# ----------------------------------------------------------------------------- events in
@dataclass(frozen=True, eq=False)
class RobotMessage:
    """One message of a robot's link, in stream order: live from the transport, or from the
    robot's journal (``replaying``: never journaled again, never back-pressured, no robot
    feedback). ``stream_id``, ``seq``: its link position; ``journaled``: the position of the
    robot's last journaled message (live messages at or before it are duplicates)."""

    agent_id: str
    message: Message
    stream_id: bytes = b""
    seq: int = 0
    journaled: InboundPosition | None = None
    replaying: bool = False


@dataclass(frozen=True)
class RobotExpected:
    """A robot expected soon, with the sensors it will describe (``EdgeApp.prepare``)."""

    agent_id: str
    sensors: Sensors


@dataclass(frozen=True, eq=False)
class FrameDecoded:
    """The :class:`Decode` asked for is done: the frame as the VIO's input."""

    agent_id: str
    item: WorkItem


@dataclass(frozen=True)
class FrameUndecodable:
    """The :class:`Decode` asked for failed (the robot's fault; its decoders are untouched)."""

    agent_id: str
    frame_index: int
    error: str


@dataclass(frozen=True, eq=False)
class CloudMessage:
    """One message from the cloud (pose corrections, map placements)."""

    message: Message


@dataclass(frozen=True, eq=False)
class WorkerResult:
    """A :class:`FeedWorker` step's result, turned into messages by the robot's session:
    ``robot`` (feedback, poses, offset), ``cloud`` (uplink), ``status_due`` (time for an
    ``AgentStatus``), ``failed`` (the VIO's exception text when it threw and re-initialised)."""

    agent_id: str
    robot: tuple[Message, ...] = ()
    cloud: tuple[Message, ...] = ()
    status_due: bool = False
    failed: str = ""


@dataclass(frozen=True)
class StepDone:
    """The driver finished the robot's oldest job (a :class:`FeedWorker` step whose result's
    actions are done, or a :class:`CloseSequence`): the core may hand out the next."""

    agent_id: str


@dataclass(frozen=True, eq=False)
class RobotSendFailed:
    """A :class:`ToRobot` was not queued (no such peer, outbox full)."""

    agent_id: str
    message: Message


Event = (
    RobotMessage
    | RobotExpected
    | FrameDecoded
    | FrameUndecodable
    | CloudMessage
    | WorkerResult
    | StepDone
    | RobotSendFailed
)


# ----------------------------------------------------------------------------- actions out
@dataclass(frozen=True)
class StartRobot:
    """A new robot: build its session (decoders, outputs) and VIO worker from ``sensors``."""

    agent_id: str
    sensors: Sensors


@dataclass(frozen=True)
class Reject:
    """Refuse the robot's message being handled (``RejectedMessageError(reason)``: the robot
    is told why and stops; the message is never redelivered)."""

    agent_id: str
    reason: str


@dataclass(frozen=True, eq=False)
class Decode:
    """Decode ``frame`` with the robot's session (on its codec thread) and answer with
    :class:`FrameDecoded` or :class:`FrameUndecodable`."""

    agent_id: str
    frame: RobotFrame


@dataclass(frozen=True)
class Hold:
    """The robot's queue is full: keep the message being handled (do not return from the
    handler, so the transport does not acknowledge it and the robot's window closes) until
    :class:`Release`."""

    agent_id: str


@dataclass(frozen=True)
class Release:
    """The held message is queued (and journaled): the handler may return."""

    agent_id: str


@dataclass(frozen=True, eq=False)
class Journal:
    """Append the robot's message to its journal now (before the handler returns)."""

    agent_id: str
    stream_id: bytes
    seq: int
    message: Message


@dataclass(frozen=True, eq=False)
class FeedWorker:
    """Hand ``item`` to the robot's VIO worker now (its steps run in order) and, once its
    result is in, turn it into messages (``RobotSession.on_result(replaying=...)``) and answer
    with :class:`WorkerResult`, then :class:`StepDone`."""

    agent_id: str
    item: WorkItem
    replaying: bool = False


@dataclass(frozen=True)
class CloseSequence:
    """The robot's sequence ended and every step before it is done: mark its session
    finished, send the rest of its points and frame poses and a status to the cloud, and
    answer with :class:`StepDone`."""

    agent_id: str


@dataclass(frozen=True, eq=False)
class ToRobot:
    """Queue ``message`` for the robot (:class:`RobotSendFailed` if that fails)."""

    agent_id: str
    message: Message


@dataclass(frozen=True, eq=False)
class ToCloud:
    """Send ``message`` to the cloud (in order; the driver waits while the link is full)."""

    message: Message


@dataclass(frozen=True)
class SendStatus:
    """Send the robot's ``AgentStatus`` (its session's, with its link counters) to the cloud."""

    agent_id: str


@dataclass(frozen=True)
class FeedbackLost:
    """A feedback message did not reach the robot's outbox: its next one must be a reset
    (``RobotSession.feedback_lost``)."""

    agent_id: str


Action = (
    StartRobot
    | Reject
    | Decode
    | Hold
    | Release
    | Journal
    | FeedWorker
    | CloseSequence
    | ToRobot
    | ToCloud
    | SendStatus
    | FeedbackLost
)
