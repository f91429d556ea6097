"""The robot's application logic: frames in, coded messages out, edge feedback applied.

No sockets, no threads, no locks and no bytes on the wire here: the robot's core
(:mod:`services.robot.core`) decides what is tracked and when feedback is applied, and its
runner (:mod:`services.robot.engine`) calls this object from one worker thread at a time.
:meth:`RobotApp.process` is CPU work (tracking, ORB, coding); :meth:`RobotApp.receive` queues
the edge's feedback, which is applied to the front end between frames, never while one is
being tracked (:meth:`RobotApp.apply_pending`, and before every frame).

Inertial feedback: the edge sends :class:`InertialFeedback` (raw) or
:class:`InertialFeedbackCoded`; both decode into one ``FeedbackContent``
(``common.links.robot_edge.decode_feedback``) applied in arrival order. ``T_world_body``
gives ``R_world_imu``/``p_world_imu`` (EuRoC's body frame is the IMU frame), the other
vectors map one to one. Track numbers are stream track numbers (see
``services.robot.coding``: the edge numbers tracks from the decoded stream); they are mapped
to the tracker's ids, and points of tracks no longer active are dropped. Coded points are
rebuilt on the rays of the keypoints the robot coded in the frame of the state (the last
``anchor_frames`` frames are kept; points about an older frame are dropped and counted). A
*reset* replaces the landmark set, an update merges into it (new or moved points) and removes
the tracks it forgets; a raw message with points is a reset, one without keeps the set.
Points of another map are meaningless: a new ``map_id`` without a reset drops the old set.
The landmarks are applied even when the state is refused (too old for the IMU buffer): points
live in the world frame, and the next update builds on them. A refused message (does not
decode, not a rotation, too old) is logged and counted, never retried. Messages that arrive
while a frame is tracked wait, all of them, in order.

The edge's :class:`FramePose` (the robot's pose at each frame) is not for this object: the
core hands it to the pose consumers (``services.robot.poses``).

With ``record=True`` every frame's :class:`UsedFrame` (what the pipeline used and what was
coded) is kept in memory, for tests that compare it with what the edge decoded.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.codec import ImuChunk
from common.errors import RecslamError
from common.links import CodecTimer
from common.links.robot_edge import (
    Anchors,
    CameraImuOffset,
    FeedbackContent,
    InertialFeedback,
    InertialFeedbackCoded,
    RobotFrame,
    RobotSequenceEnd,
    decode_feedback,
)
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.robot.coding import (
    CodedFrame,
    FrameCoder,
    ImuCoder,
    codec_config_for,
    imu_used,
    install_codec_grid,
)
from services.robot.config import FrontEndConfig
from services.robot.imu_prediction import InertialState
from services.robot.tracker import FrontEnd, ImuSamples, TrackedFrame
from services.robot.uplink_budget import KeyframePlan

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class UsedFrame:
    """What the robot used for one frame: the tracker's output, the coded features (codec
    order, with the tracker's id per row) and the IMU samples fed to the front end."""

    tracked: TrackedFrame
    coded: CodedFrame
    imu: ImuChunk
    imu_payload: bytes


class RobotApp:
    """Front end + codecs of one robot, and the reaction to the edge's messages.

    Args:
        config: front-end options.
        camera, imu: calibrations of the sequence.
        vocabulary: the ORB vocabulary both ends agreed on.
        record: keep every :class:`UsedFrame` in :attr:`recorded`.
        preroll_imu_s: IMU samples older than this before the first frame are not used or
            sent (EuRoC's first frame carries the whole pre-roll).
        code_links: code keyframe continuation links (False: the intra-only baseline).
        anchor_frames: frames whose coded keypoints are kept (timestamp -> tracks and
            keypoints) to rebuild the coded feedback's points, which are sent along them;
            feedback about an older frame gets no points.
    """

    def __init__(
        self,
        config: FrontEndConfig,
        camera: CameraCalibration,
        imu: ImuCalibration,
        vocabulary: Vocabulary,
        *,
        record: bool = False,
        preroll_imu_s: float = 1.0,
        code_links: bool = True,
        anchor_frames: int = 600,
    ) -> None:
        self.camera = camera
        self.front_end = FrontEnd(config, camera, imu)
        self.codec_config = codec_config_for(config, camera.width, camera.height)
        install_codec_grid(self.front_end, self.codec_config)
        self.frame_coder = FrameCoder(vocabulary, self.codec_config, links=code_links)
        self.imu_coder = ImuCoder()
        self.record = record
        self.recorded: list[UsedFrame] = []
        self.preroll_imu_s = preroll_imu_s
        self.frames = 0  # frames sent (coded)
        self.skipped = 0  # non-keyframes tracked but left out (process(send=False))
        self._carry: list[ImuChunk] = []  # IMU of the frames left out since the last sent
        self.keyframes = 0
        self.keyframe_plan: KeyframePlan | None = None  # the uplink budget's, in force
        self.feedback_received = 0
        self.feedback_applied = 0
        self.feedback_rejected = 0
        self.codec_timer = CodecTimer()  # decode time of the edge's feedback
        self._map_id: int | None = None
        self._pending: list[InertialFeedback | InertialFeedbackCoded] = []
        self.anchor_frames = anchor_frames
        self._anchors: OrderedDict[int, Anchors] = OrderedDict()
        self.feedback_points_unanchored = 0  # coded points of frames no longer kept
        self.time_offset_ns = 0  # the edge's camera-IMU offset estimate (t_imu = t_cam + it)
        self._offset_pending: int | None = None

    def set_keyframe_plan(self, plan: KeyframePlan | None) -> None:
        """Keyframes within the uplink budget from the next frame on (None: as configured)."""
        if plan != self.keyframe_plan:
            self.front_end.set_keyframe_plan(plan)
            self.keyframe_plan = plan
            if plan is not None:
                logger.debug(
                    "uplink budget: keyframes of at most %d features, at least %.1f s apart",
                    plan.n_features,
                    plan.min_interval_s,
                )

    def predicted_pose(self, timestamp_ns: int) -> tuple[int, np.ndarray] | None:
        """(map id, (4, 4) T_map_body): the front end's IMU propagation of the edge's last
        state to this frame's time, in the edge's map (None before the edge's first state)."""
        state = self.front_end.predictor.state_at(timestamp_ns)
        if state is None or self._map_id is None:
            return None
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = state.R_world_imu, state.p_world_imu
        return self._map_id, T

    def process(self, timestamp_ns: int, image: np.ndarray, imu: ImuSamples) -> RobotFrame:
        """Track and code one frame (CPU work, one thread at a time) -> the message to send.

        ``image`` uint8 (H, W); ``imu`` the samples since the previous frame (IMU frame).
        """
        msg = self.process_if(timestamp_ns, image, imu, send=True)
        assert msg is not None  # (send=True always codes)
        return msg

    def process_if(
        self,
        timestamp_ns: int,
        image: np.ndarray,
        imu: ImuSamples,
        send: bool,
        send_keyframe: bool = True,
    ) -> RobotFrame | None:
        """:meth:`process`, except that with ``send=False`` the frame is tracked but, unless
        the front end makes it a keyframe (and ``send_keyframe``: not during an outage), not
        coded (None: the uplink budget left it out); its IMU then goes with the next frame
        sent, so the edge integrates across the gap."""
        self.apply_pending()
        ts, gyro, accel = imu.timestamps_ns, imu.gyro, imu.accel
        if self.frames == 0 and not self._carry and len(ts):
            keep = ts > int(timestamp_ns) - int(self.preroll_imu_s * 1e9)
            ts, gyro, accel = ts[keep], gyro[keep], accel[keep]
        chunk = imu_used(ts, gyro, accel)
        tracked = self.front_end.process(image, timestamp_ns, chunk)
        if not send and (not tracked.is_keyframe or not send_keyframe):
            self._carry.append(chunk)
            self.skipped += 1
            return None
        if self._carry:
            parts = [*self._carry, chunk]
            self._carry = []
            chunk = ImuChunk(
                np.concatenate([c.timestamps_ns for c in parts]),
                np.concatenate([c.gyro for c in parts]),
                np.concatenate([c.accel for c in parts]),
            )
        coded = self.frame_coder.encode(tracked)
        self._keep_anchors(int(timestamp_ns), tracked, coded)
        imu_payload = self.imu_coder.encode(chunk)
        if self.record:
            self.recorded.append(UsedFrame(tracked, coded, chunk, imu_payload))
        msg = RobotFrame(
            frame_index=self.frames,
            timestamp_ns=int(timestamp_ns),
            keyframe=tracked.is_keyframe,
            features=coded.payload,
            imu=imu_payload,
        )
        self.frames += 1
        self.keyframes += int(tracked.is_keyframe)
        return msg

    def _keep_anchors(self, timestamp_ns: int, tracked: TrackedFrame, coded: CodedFrame) -> None:
        """Keep the frame's stream numbers and keypoints (codec order, the edge's decoding)."""
        order = np.argsort(tracked.track_ids, kind="stable")
        rows = order[np.searchsorted(tracked.track_ids[order], coded.track_ids)]
        self._anchors[timestamp_ns] = Anchors(coded.stream_ids, tracked.keypoints[rows])
        while len(self._anchors) > self.anchor_frames:
            self._anchors.popitem(last=False)

    def end_message(self) -> RobotSequenceEnd:
        return RobotSequenceEnd(frames=self.frames)

    def receive(self, msg: Message) -> bool:
        """Queue one of the edge's messages for the front end (applied by
        :meth:`apply_pending`, or before the next frame); False (logged) if it is not for the
        front end."""
        if isinstance(msg, CameraImuOffset):
            self._offset_pending = msg.offset_ns
        elif isinstance(msg, InertialFeedback | InertialFeedbackCoded):
            self.feedback_received += 1
            self._pending.append(msg)
        else:
            logger.warning("robot front end ignores %s", type(msg).__name__)
            return False
        return True

    def set_time_offset(self, offset_ns: int) -> None:
        """Use this camera-IMU time offset (``t_imu = t_cam + offset``, ns) from the next frame
        (a robot carries its offset to the next edge at a handover)."""
        self._offset_pending = int(offset_ns)
        self.apply_pending()

    def apply_pending(self) -> None:
        """Apply the feedback queued by :meth:`receive`, in arrival order (never raises: a
        refused message is logged and counted, not retried)."""
        msgs, self._pending = self._pending, []
        offset, self._offset_pending = self._offset_pending, None
        if offset is not None and offset != self.time_offset_ns:
            # Before the states: they are about camera times read with the new offset.
            self.front_end.set_time_offset(offset)
            self.time_offset_ns = offset
            logger.info("camera-IMU time offset from the edge: %+.2f ms", offset * 1e-6)
        for msg in msgs:
            self._apply(msg)

    def _apply(self, msg: InertialFeedback | InertialFeedbackCoded) -> None:
        try:
            t0 = time.perf_counter()
            content = decode_feedback(msg, self.camera, self._anchors.get(msg.timestamp_ns))
            self.codec_timer.add(f"decode.{type(msg).__name__}", time.perf_counter() - t0)
            state = content_to_state(content)
            self._apply_landmarks(content)
            self.front_end.set_inertial_state(state)
        except RecslamError as exc:
            self.feedback_rejected += 1
            logger.warning("inertial feedback at %d ns refused: %s", msg.timestamp_ns, exc)
            return
        self.feedback_applied += 1
        logger.debug("inertial feedback at %d ns applied (map %d)", msg.timestamp_ns, msg.map_id)

    def _apply_landmarks(self, c: FeedbackContent) -> None:
        """Reset or update the front end's landmarks (tracker ids of the numbers still active)."""
        coder = self.frame_coder
        ids = coder.tracker_ids_of(c.track_numbers)
        anchored = np.isfinite(c.p_world).all(axis=1)
        if not anchored.all():
            n = int((~anchored).sum())
            self.feedback_points_unanchored += n
            logger.debug("feedback at %d ns: %d points of an unkept frame", c.timestamp_ns, n)
        live = (ids >= 0) & anchored  # tracks that ended since the edge's frame have no use
        forget = coder.tracker_ids_of(c.forget)
        other_map = self._map_id is not None and c.map_id != self._map_id
        self.front_end.update_landmarks(
            ids[live],
            c.p_world[live],
            replace=c.reset or other_map,
            forget=forget[forget >= 0],
            active=coder.track_ids,
        )
        self._map_id = c.map_id


def content_to_state(c: FeedbackContent) -> InertialState:
    """The front end's :class:`InertialState` of decoded feedback (ImuPredictionError if the
    pose is not a rotation or a vector is not finite)."""
    return InertialState(
        timestamp_ns=c.timestamp_ns,
        R_world_imu=c.T_world_body[:3, :3],
        p_world_imu=c.T_world_body[:3, 3],
        v_world_imu=c.velocity_world,
        bias_gyro=c.bias_gyro,
        bias_accel=c.bias_accel,
        gravity_world=c.gravity_world,
    )
