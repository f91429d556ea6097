"""When and what the edge tells one robot for its IMU-assisted tracking (sans-I/O).

:class:`FeedbackSender` turns the VIO's inertial state and the map points of the robot's live
tracks into the feedback message of the session's wire format (``common.links.robot_edge``):

- **when** (:class:`FeedbackPolicy`, both wires): on the first initialised frame of a map, then
  whenever the gyro bias, the accel bias or the velocity moved more than a threshold since the
  last message, and at least every ``every_frames`` frames;
- **what**, RAW: :class:`~common.links.robot_edge.InertialFeedback` with every live track's
  point, exactly the schema-1 message;
- **what**, CODED: :class:`~common.links.robot_edge.InertialFeedbackCoded` with only what the
  robot does not hold yet: tracks whose point is new to it, or moved more than
  ``point_resend_m`` from the point it was sent, and the tracks it should forget (no point
  any more while the robot still tracks them). A point travels as its depth along the ray of
  the track's keypoint in the state's frame (``anchors``: the frame's tracks as the edge
  decoded them, the same the robot coded). The sender remembers, per robot, the point the
  robot decodes for each track (on that ray, depth quantised; not the VIO's float64 value),
  so quantisation never accumulates. A message *resets* the robot's set (sends all live
  points) when it is the first one, the map changed, or :meth:`FeedbackSender.restart` was
  called: after the robot restarted its stream, after the VIO re-initialised, and when a
  message could not be queued for the robot (the deltas after it would refer to a set the
  robot never got). Delivery is otherwise exactly-once and in order, so a robot that
  reconnects keeps a valid set.

Tracks the robot no longer tracks are dropped from the bookkeeping without a message: the
robot drops their points itself. No sockets, no clocks (``CodecTimer`` spans only).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from common.calibration import CameraCalibration
from common.links import CodecTimer, WireFormat
from common.links.robot_edge import (
    Anchors,
    FeedbackContent,
    InertialFeedback,
    InertialFeedbackCoded,
    coded_points,
    encode_feedback,
    points_sendable,
)
from services.edge.vio.types import VioState

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FeedbackPolicy:
    """When the edge sends feedback to a robot (after VI initialisation), and which points.

    A message goes out on the first initialised frame of a map, then whenever the gyro bias
    moved by more than ``gyro_bias_rad_s`` (rad/s, norm), the accel bias by more than
    ``accel_bias_mps2`` (m/s², norm) or the velocity by more than ``velocity_mps`` (m/s, norm)
    since the last message, and at least every ``every_frames`` frames. Coded wire only: a
    point the robot holds is sent again when the VIO moved it by more than ``point_resend_m``
    (m, norm) from what the robot decoded.
    """

    gyro_bias_rad_s: float = 2e-3
    accel_bias_mps2: float = 2e-2
    velocity_mps: float = 0.1
    every_frames: int = 20
    point_resend_m: float = 0.02


class FeedbackSender:
    """Feedback to one robot: the policy and the robot's landmark bookkeeping (see the module
    docstring). ``codec_timer`` gets the encode time under ``"encode.<message type>"``;
    ``camera``: the robot's cam0 (coded wire: points are sent along its rays)."""

    def __init__(
        self,
        policy: FeedbackPolicy | None = None,
        wire: WireFormat = WireFormat.CODED,
        codec_timer: CodecTimer | None = None,
        camera: CameraCalibration | None = None,
    ) -> None:
        self.policy = policy or FeedbackPolicy()
        self.wire = wire
        self.camera = camera
        self.codec_timer = codec_timer if codec_timer is not None else CodecTimer()
        self.sent = 0  # messages returned
        self.resets = 0  # of which replaced the robot's set (coded)
        self._last: VioState | None = None
        self._last_frame = -(10**9)
        self._map: int | None = None  # None: the next message is a reset
        self._numbers = np.zeros(0, np.int64)  # (n,) ascending: tracks the robot has a point of
        self._held = np.zeros((0, 3))  # (n, 3) m: the point the robot decoded for each
        self._sent = np.zeros((0, 3))  # (n, 3) m: the VIO's point when it was last sent

    @property
    def held(self) -> tuple[np.ndarray, np.ndarray]:
        """Tracks (n,) ascending and points (n, 3) [m, world] the robot was last sent."""
        return self._numbers.copy(), self._held.copy()

    def restart(self) -> None:
        """Make the next message due at once and a reset (the robot's set is unknown)."""
        self._map = None

    def on_state(
        self,
        frame_index: int,
        state: VioState,
        live_numbers: np.ndarray | None,
        live_p_world: np.ndarray | None,
        tracked_numbers: np.ndarray,
        anchors: Anchors | None = None,
    ) -> InertialFeedback | InertialFeedbackCoded | None:
        """The message for the VIO's ``state`` at frame ``frame_index``, or None if none is due.

        ``live_numbers`` (L,) stream track numbers of the frame's tracks with a map point and
        ``live_p_world`` (L, 3) m their points (None: no map); ``tracked_numbers`` (T,) the
        tracks of the newest frame decoded from the robot (tracks the robot still follows);
        ``anchors``: the tracks and keypoints of frame ``frame_index`` (coded wire: the rays
        the points are sent along; None or no ``camera``: no points are sent).
        """
        pol = self.policy
        last = self._last
        due = (
            last is None
            or self._map != state.map_id
            or frame_index - self._last_frame >= pol.every_frames
            or np.linalg.norm(state.bias_gyro - last.bias_gyro) > pol.gyro_bias_rad_s
            or np.linalg.norm(state.bias_accel - last.bias_accel) > pol.accel_bias_mps2
            or np.linalg.norm(state.v_world - last.v_world) > pol.velocity_mps
        )
        if not due:
            return None
        reset = self._map != state.map_id
        self._last, self._last_frame, self._map = state, frame_index, state.map_id
        ids = np.zeros(0, np.int64) if live_numbers is None else np.asarray(live_numbers, np.int64)
        pts = np.zeros((0, 3)) if live_p_world is None else np.asarray(live_p_world, np.float64)
        content = FeedbackContent(
            timestamp_ns=int(state.timestamp_ns),
            map_id=int(state.map_id),
            T_world_body=state.T_world_body,
            velocity_world=state.v_world,
            bias_gyro=state.bias_gyro,
            bias_accel=state.bias_accel,
            gravity_world=state.T_world_body[:3, :3] @ state.gravity_body,
            reset=True,
            track_numbers=ids,
            p_world=pts,
        )
        if self.wire is WireFormat.CODED:
            content = self._delta(content, reset, tracked_numbers, anchors)
        t0 = time.perf_counter()
        msg = encode_feedback(content, self.wire, self.camera)
        self.codec_timer.add(f"encode.{type(msg).__name__}", time.perf_counter() - t0)
        self.sent += 1
        self.resets += int(content.reset)
        return msg

    def _delta(
        self,
        full: FeedbackContent,
        reset: bool,
        tracked_numbers: np.ndarray,
        anchors: Anchors | None,
    ) -> FeedbackContent:
        """``full`` (every live point) reduced to what the robot lacks; bookkeeping updated."""
        uv = np.full((len(full.track_numbers), 2), np.nan)
        if anchors is not None and self.camera is not None:
            uv = anchors.of(full.track_numbers)
            ok = points_sendable(full.p_world, full.T_world_body, uv, self.camera)
        else:
            ok = np.zeros(len(uv), bool)
        if not ok.all():
            logger.debug("feedback: %d of %d points not sendable", (~ok).sum(), len(ok))
        order = np.argsort(full.track_numbers[ok], kind="stable")
        ids, pts, uv = full.track_numbers[ok][order], full.p_world[ok][order], uv[ok][order]
        if len(ids) > 1 and not (np.diff(ids) > 0).all():  # one point per track number
            ids, first = np.unique(ids, return_index=True)
            pts, uv = pts[first], uv[first]
        held = np.zeros((0, 3))
        if len(ids):
            assert self.camera is not None
            held = coded_points(pts, full.T_world_body, uv, self.camera)
        forget = np.zeros(0, np.int64)
        send = np.ones(len(ids), bool)
        if not reset:
            book = self._numbers
            slot = np.searchsorted(book, ids).clip(max=max(len(book) - 1, 0))
            known = np.zeros(len(ids), bool)
            if len(book):
                known = book[slot] == ids
            # against the VIO's point as sent, not the robot's copy: that one lies on the
            # keypoint's ray, off the VIO point by its reprojection residual, which a resend
            # would not remove
            d = pts[known] - self._sent[slot[known]]
            send[known] = (d * d).sum(axis=1) > self.policy.point_resend_m**2
            keep = known & ~send
            held[keep] = self._held[slot[keep]]
            pts_sent = pts.copy()
            pts_sent[keep] = self._sent[slot[keep]]
            gone = book[~np.isin(book, ids)]
            forget = gone[np.isin(gone, np.asarray(tracked_numbers, np.int64))]
        else:
            pts_sent = pts
        self._numbers, self._held, self._sent = ids, held, pts_sent
        return dataclasses.replace(
            full,
            reset=reset,
            track_numbers=ids[send],
            p_world=pts[send],
            forget=forget,
            keypoints_px=uv[send],
        )
