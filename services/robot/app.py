"""The robot's application logic: frames in, coded messages out, edge feedback applied.

No sockets and no bytes on the wire here (``services.robot.server`` does the lifecycle and
the transport). :meth:`RobotApp.process` is CPU work (tracking, ORB, coding) meant to run in
one worker thread; :meth:`RobotApp.on_message` runs on the event loop. Feedback from the
edge is applied to the front end between frames, never while one is being tracked: what
arrives while a frame is in progress waits and is applied before the next frame.

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

The edge's :class:`FramePose` (the robot's pose at each frame) and :class:`MapPlacement` (where
its map sits in the global map) go to ``pose_sink`` as they arrive (``services.robot.poses``),
nothing else is done with them here.

With ``record=True`` every frame's :class:`UsedFrame` (what the pipeline used and what was
coded) is kept in memory, for tests that compare it with what the edge decoded.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
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
    FramePose,
    InertialFeedback,
    InertialFeedbackCoded,
    MapPlacement,
    RobotFrame,
    RobotSequenceEnd,
    decode_feedback,
)
from common.transport import Delivery
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
        self.frames = 0
        self.keyframes = 0
        self.feedback_received = 0
        self.feedback_applied = 0
        self.feedback_rejected = 0
        self.codec_timer = CodecTimer()  # decode time of the edge's feedback
        self._map_id: int | None = None
        self._pending: list[InertialFeedback | InertialFeedbackCoded] = []
        self.anchor_frames = anchor_frames
        self._anchors: OrderedDict[int, Anchors] = OrderedDict()  # guarded by _lock
        self.feedback_points_unanchored = 0  # coded points of frames no longer kept
        self.time_offset_ns = 0  # the edge's camera-IMU offset estimate (t_imu = t_cam + it)
        self._offset_pending: int | None = None  # guarded by _pending_lock
        self._pending_lock = threading.Lock()  # guards _pending (loop vs worker thread)
        self._lock = threading.Lock()  # held while the front end is in use
        # Where the edge's FramePose messages go (on the event loop), e.g. a PoseTrack
        self.pose_sink: Callable[[FramePose | MapPlacement], None] | None = None

    # ------------------------------------------------------------------ worker thread
    def process(self, timestamp_ns: int, image: np.ndarray, imu: ImuSamples) -> RobotFrame:
        """Track and code one frame (CPU work, one thread at a time) -> the message to send.

        ``image`` uint8 (H, W); ``imu`` the samples since the previous frame (IMU frame).
        """
        with self._lock:
            self._apply_pending_locked()
            ts, gyro, accel = imu.timestamps_ns, imu.gyro, imu.accel
            if self.frames == 0 and len(ts):
                keep = ts > int(timestamp_ns) - int(self.preroll_imu_s * 1e9)
                ts, gyro, accel = ts[keep], gyro[keep], accel[keep]
            chunk = imu_used(ts, gyro, accel)
            tracked = self.front_end.process(image, timestamp_ns, chunk)
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

    # ------------------------------------------------------------------ event loop
    async def on_message(self, delivery: Delivery) -> None:
        """Handler for the edge's messages (never raises: a refused message is not retried)."""
        msg = delivery.message
        if isinstance(msg, FramePose | MapPlacement):
            if self.pose_sink is not None:
                self.pose_sink(msg)
            return
        if isinstance(msg, CameraImuOffset):
            with self._pending_lock:
                self._offset_pending = msg.offset_ns
        elif isinstance(msg, InertialFeedback | InertialFeedbackCoded):
            self.feedback_received += 1
            with self._pending_lock:
                self._pending.append(msg)
        else:
            logger.warning("robot ignores %s from %s", type(msg).__name__, delivery.peer)
            return
        if self._lock.acquire(blocking=False):  # no frame in progress: apply now
            try:
                self._apply_pending_locked()
            finally:
                self._lock.release()

    def set_time_offset(self, offset_ns: int) -> None:
        """Use this camera-IMU time offset (``t_imu = t_cam + offset``, ns) from the next frame
        (a robot carries its offset to the next edge at a handover)."""
        with self._pending_lock:
            self._offset_pending = int(offset_ns)
        self.apply_pending()

    def apply_pending(self) -> None:
        """Apply feedback that arrived during the last frame (e.g. after the sequence end)."""
        with self._lock:
            self._apply_pending_locked()

    def _apply_pending_locked(self) -> None:
        with self._pending_lock:
            msgs, self._pending = self._pending, []
            offset, self._offset_pending = self._offset_pending, None
        if offset is not None and offset != self.time_offset_ns:
            # Before the states: they are about camera times read with the new offset.
            self.front_end.set_time_offset(offset)
            self.time_offset_ns = offset
            logger.info("camera-IMU time offset from the edge: %+.2f ms", offset * 1e-6)
        for msg in msgs:
            self._apply_locked(msg)

    def _apply_locked(self, msg: InertialFeedback | InertialFeedbackCoded) -> None:
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
