"""The robot's application logic: frames in, coded messages out, edge feedback applied.

No sockets and no bytes on the wire here (``services.robot.server`` does the lifecycle and
the transport). :meth:`RobotApp.process` is CPU work (tracking, ORB, coding) meant to run in
one worker thread; :meth:`RobotApp.on_message` runs on the event loop. Feedback from the
edge is applied to the front end between frames, never while one is being tracked: if a
frame is in progress the newest feedback waits and is applied before the next frame.

Inertial feedback conversion (``InertialFeedback`` -> ``FrontEnd.set_inertial_state``):
``T_world_body`` "<f8 (4,4)" gives ``R_world_imu``/``p_world_imu`` (EuRoC's body frame is the
IMU frame), the other arrays map one to one. ``track_ids`` are stream track numbers (see
``services.robot.coding``: the edge numbers tracks from the decoded stream); they are mapped
to the tracker's ids and points of tracks no longer active are dropped. Map points replace
the previous set; an empty set keeps the previous one unless ``map_id`` changed (points of
another map are meaningless, so they are dropped). Feedback the front end refuses (too old
for the IMU buffer, malformed arrays) is logged and counted, never retried.

With ``record=True`` every frame's :class:`UsedFrame` (what the pipeline used and what was
coded) is kept in memory, for tests that compare it with what the edge decoded.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from common.calibration import CameraCalibration, ImuCalibration
from common.codec import ImuChunk
from common.errors import RecslamError
from common.links.robot_edge import InertialFeedback, RobotFrame, RobotSequenceEnd
from common.protocol.arrays import unpack_array
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
    ) -> None:
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
        self._map_id: int | None = None
        self._pending: InertialFeedback | None = None
        self._pending_lock = threading.Lock()  # guards _pending (loop vs worker thread)
        self._lock = threading.Lock()  # held while the front end is in use

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

    def end_message(self) -> RobotSequenceEnd:
        return RobotSequenceEnd(frames=self.frames)

    # ------------------------------------------------------------------ event loop
    async def on_message(self, delivery: Delivery) -> None:
        """Handler for the edge's messages (never raises: a refused message is not retried)."""
        msg = delivery.message
        if isinstance(msg, InertialFeedback):
            self.feedback_received += 1
            with self._pending_lock:
                self._pending = msg
            if self._lock.acquire(blocking=False):  # no frame in progress: apply now
                try:
                    self._apply_pending_locked()
                finally:
                    self._lock.release()
        else:
            logger.warning("robot ignores %s from %s", type(msg).__name__, delivery.peer)

    def apply_pending(self) -> None:
        """Apply feedback that arrived during the last frame (e.g. after the sequence end)."""
        with self._lock:
            self._apply_pending_locked()

    def _apply_pending_locked(self) -> None:
        with self._pending_lock:
            msg, self._pending = self._pending, None
        if msg is None:
            return
        try:
            state, numbers, points = feedback_to_state(msg)
            ids = None
            if numbers is not None and points is not None:
                ids = self.frame_coder.tracker_ids_of(numbers)
                live = ids >= 0  # tracks that ended since the edge's frame have no use
                ids, points = ids[live], points[live]
            if self._map_id is not None and msg.map_id != self._map_id and ids is None:
                ids, points = np.zeros(0, np.int64), np.zeros((0, 3))  # drop the old map's
            self.front_end.set_inertial_state(state, ids, points)
        except RecslamError as exc:
            self.feedback_rejected += 1
            logger.warning("inertial feedback at %d ns refused: %s", msg.timestamp_ns, exc)
            return
        self._map_id = msg.map_id
        self.feedback_applied += 1
        logger.debug("inertial feedback at %d ns applied (map %d)", msg.timestamp_ns, msg.map_id)


def feedback_to_state(
    msg: InertialFeedback,
) -> tuple[InertialState, np.ndarray | None, np.ndarray | None]:
    """Convert the edge's message: (state, stream track numbers (M,) or None, points (M, 3)
    or None).

    Raises RemoteProtocolError (malformed arrays) or ImuPredictionError (not a rotation).
    """
    T = unpack_array(msg.T_world_body, "<f8", (4, 4), "InertialFeedback.T_world_body")
    vecs = {}
    for name in ("velocity_world", "bias_gyro", "bias_accel", "gravity_world"):
        vecs[name] = unpack_array(getattr(msg, name), "<f8", (3,), f"InertialFeedback.{name}")
    if len(T) != 1 or any(len(v) != 1 for v in vecs.values()):
        raise FeedbackError("InertialFeedback: expected one pose and one row per vector")
    ids = points = None
    if msg.track_ids or msg.p_world:
        ids = unpack_array(msg.track_ids, "<i8", (), "InertialFeedback.track_ids")
        points = unpack_array(msg.p_world, "<f8", (3,), "InertialFeedback.p_world")
        if len(ids) != len(points):
            raise FeedbackError(f"InertialFeedback: {len(ids)} track ids but {len(points)} points")
    state = InertialState(
        timestamp_ns=msg.timestamp_ns,
        R_world_imu=T[0, :3, :3],
        p_world_imu=T[0, :3, 3],
        v_world_imu=vecs["velocity_world"][0],
        bias_gyro=vecs["bias_gyro"][0],
        bias_accel=vecs["bias_accel"][0],
        gravity_world=vecs["gravity_world"][0],
    )
    return state, ids, points


class FeedbackError(RecslamError):
    """An InertialFeedback message whose arrays do not fit together."""
