"""What goes into and comes out of the robot's core (:mod:`services.robot.core`): sensor
input and the edge's messages in (events), CPU work out to the worker (jobs) and back, and
sends and poses out (actions). Plain frozen dataclasses, no behaviour."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.data.euroc import ImuBatch
from common.links.robot_edge import RobotFrame
from common.protocol.messages import Message
from services.robot.poses import ReceivedPose
from services.robot.uplink_budget import KeyframePlan


# ----------------------------------------------------------------------------- events in
@dataclass(frozen=True, eq=False)
class ImuInput:
    """IMU samples: ``timestamps_ns`` (K,) int64, ``gyro`` (K, 3) rad/s, ``accel`` (K, 3) m/s²,
    IMU frame, in time order (one sample: K = 1)."""

    timestamps_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray


@dataclass(frozen=True, eq=False)
class ImageInput:
    """One camera image at ``timestamp_ns``: a uint8 (H, W) array, or raw bytes with their
    ``encoding`` (one of :data:`ENCODINGS`), ``height``, ``width`` and row ``step`` [bytes]."""

    timestamp_ns: int
    image: np.ndarray | bytes
    encoding: str = "mono8"
    height: int = 0
    width: int = 0
    step: int = 0


@dataclass(frozen=True, eq=False)
class EdgeInput:
    """One message from the edge."""

    message: Message


@dataclass(frozen=True)
class EndOfInput:
    """No more sensor data: images waiting for IMU are tracked with what has come."""


@dataclass(frozen=True, eq=False)
class FrameDone:
    """The worker finished a :class:`TrackFrame`: the message to send, or None (the uplink
    budget left the non-keyframe at ``timestamp_ns`` out, for ``left_out``; ``predicted``:
    the robot's own pose of it, from the IMU, once the edge's state came; ``features``: a
    keyframe's feature count)."""

    message: RobotFrame | None
    timestamp_ns: int = 0
    left_out: str = ""
    predicted: tuple[int, np.ndarray] | None = None  # (map id, (4, 4) T_map_body) of it
    features: int = 0


@dataclass(frozen=True)
class LinkLoad:
    """The link to the edge at the moment: bytes waiting unacknowledged, and the bytes
    acknowledged so far (a running total)."""

    outbox_bytes: int
    acked_bytes: int


Event = ImuInput | ImageInput | EdgeInput | EndOfInput | FrameDone | LinkLoad


# ----------------------------------------------------------------------------- work out
@dataclass(frozen=True, eq=False)
class TrackFrame:
    """Apply ``feedback`` (in order), then track and code the image with its IMU
    (``RobotApp.receive`` each, then ``RobotApp.process``); answer with :class:`FrameDone`.
    ``hold_back``: unless the tracker makes it a keyframe (``"outage"``: even then), the
    frame is left out for this reason (:mod:`services.robot.uplink_budget`; ``""``: it
    goes); ``plan``: the keyframes the budget affords (``RobotApp.set_keyframe_plan``; None:
    the configured ones)."""

    timestamp_ns: int
    image: np.ndarray
    imu: ImuBatch
    feedback: tuple[Message, ...] = ()
    hold_back: str = ""
    plan: KeyframePlan | None = None


@dataclass(frozen=True, eq=False)
class ApplyFeedback:
    """Apply the edge's ``feedback`` to the front end now (no frame is waiting)."""

    feedback: tuple[Message, ...]


Job = TrackFrame | ApplyFeedback


# ----------------------------------------------------------------------------- actions
@dataclass(frozen=True, eq=False)
class Send:
    """Send ``message`` to the edge (in order; the runner waits while the link is full)."""

    message: Message


@dataclass(frozen=True, eq=False)
class PoseOut:
    """The robot's pose at one frame, for the user (``RobotClient.poses``, ROS, TUM file)."""

    pose: ReceivedPose


Action = Send | PoseOut
