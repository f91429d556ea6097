"""One robot as the edge sees it (sans-I/O): decoding, track naming, outputs of its VIO.

:class:`RobotSession` turns each :class:`~common.protocol.messages.RobotFrame` into a
:class:`~services.edge.worker.WorkItem` (feature and IMU decoders are stateful per robot and
live here, outside the VIO worker, so that a VIO failure never loses the stream state), and
turns each :class:`~services.edge.worker.WorkResult` into messages:

- to the robot, inertial feedback after VI initialisation (or a new map) and then whenever
  biases/velocity moved more than :class:`FeedbackPolicy`'s thresholds or every
  ``every_frames`` frames (``services.edge.feedback``: raw :class:`InertialFeedback` or
  coded ``InertialFeedbackCoded`` with landmark deltas, per ``EdgeSessionConfig.wire``); tracks
  are named by stream numbers (``common.codec.tracks``);
- to the cloud, :class:`KeyframeUpdate` (first time with the keyframe's features re-coded
  standalone; later pose-only), :class:`MapPointUpdate`, :class:`CullEvent` (the base class
  :class:`~services.edge.session_uplink.SessionUplink`), and every ``status_every_frames`` an
  :class:`AgentStatus`.

No sockets, no asyncio: ``services/edge/app.py`` drives it.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from common.calibration import CameraCalibration
from common.codec import CodecConfig, FeatureDecoder, ImuDecoder, KeyframeFeatures
from common.codec.keypoints import kf_track_q
from common.codec.tracks import next_stream_numbers
from common.geometry import inverse_T
from common.links import CodecTimer, WireFormat
from common.links.edge_cloud import AgentStatus
from common.links.robot_edge import Anchors, CameraImuOffset, RobotFrame
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.edge.cloud_budget import REASONS as CLOUD_BUDGET_REASONS
from services.edge.feedback import FeedbackPolicy as FeedbackPolicy  # re-exported
from services.edge.feedback import FeedbackSender
from services.edge.frame_poses import FramePoseBatcher, frame_pose
from services.edge.imu_uplink import ImuUplink
from services.edge.point_uplink import SentPoints
from services.edge.session_config import EdgeSessionConfig  # also imported from here
from services.edge.session_uplink import SessionUplink
from services.edge.vio.types import FrameObservation, FrameResult, TrackingStatus
from services.edge.worker import WorkItem, WorkResult

logger = logging.getLogger(__name__)

_ANCHOR_FRAMES = 1000
"""Safety cap of decoded frames kept for their VIO result (a frame's anchors go when its result
comes): above the edge's frame queue (``EdgeConfig.max_queued_frames``, 200) plus the frames in
flight. A cap of 64 dropped the anchors of every frame whose result came more than 3 s after it
was decoded, as it does whenever the edge runs behind the robots, and then the coded feedback
carried no points at all."""


@dataclass
class Outputs:
    """Messages produced by one step: for the robot and for the cloud."""

    robot: list[Message]
    cloud: list[Message]
    status_due: bool = False  # time for an AgentStatus (the app adds the link counters)


class RobotSession(SessionUplink):
    """Edge-side state of one robot (see the module docstring)."""

    def __init__(
        self,
        agent_id: str,
        camera: CameraCalibration,
        vocabulary: Vocabulary,
        options: EdgeSessionConfig | None = None,
    ) -> None:
        self.agent_id = agent_id
        self.vocabulary = vocabulary
        self.codec = CodecConfig(image_width=camera.width, image_height=camera.height)
        self.options = options or EdgeSessionConfig()
        self.frames = 0  # frames decoded (this stream)
        self.keyframes = 0  # robot keyframes decoded
        self.processed = 0  # frames the VIO finished
        self.vio_keyframes = 0  # keyframes uplinked (distinct)
        self.failures: list[str] = []
        self.state = "initializing"
        self.reason = ""
        # The VIO's camera-IMU offset (t_imu = t_cam + offset): the robot is told when it
        # moves, the cloud with each status (it reads the IMU of keyframes at t + offset).
        self.time_offset_ns = 0
        self.time_offset_sigma_ms = float("nan")
        self._offset_told = 0  # a robot starts at 0
        self.map_id = 0
        self.last_timestamp_ns = 0
        self.finished = False
        self.feedback_sent = 0
        self.poses_sent = 0
        self.codec_timer = CodecTimer()  # encode time of this robot's messages
        self.feedback = FeedbackSender(
            self.options.feedback, self.options.wire, self.codec_timer, camera
        )
        # frame index -> the frame's tracks and keypoints, until its VIO result (feedback
        # points are sent along these rays)
        self._anchors: OrderedDict[int, Anchors] = OrderedDict()
        self.frame_poses = FramePoseBatcher(agent_id, self.options.frame_poses_every)
        self.frame_s: list[float] = []
        self.track_s: list[float] = []
        self.local_ba_s: list[float] = []
        self.vio_counts: dict[str, int] = {}  # the VIO's running totals (``WorkResult``)
        self._reset_stream()
        self._kf_features: OrderedDict[int, KeyframeFeatures] = OrderedDict()
        self.imu_uplink = ImuUplink(self.options.imu_history_s)  # the keyframes' IMU
        self._kf_time: dict[tuple[int, int], int] = {}
        self._sent_kfs: set[tuple[int, int]] = set()
        # The VIO's own keyframes (no robot features) stay on the edge: uplinked keyframes
        # chain to the previous uplinked keyframe of their map, observations skip the others.
        self._own_kfs: dict[int, set[int]] = {}  # map id -> the VIO's own keyframe ids
        self.cloud_allowance = None  # set by the driver when a cloud budget applies
        self.kept_on_edge = dict.fromkeys(CLOUD_BUDGET_REASONS, 0)
        self._budget_n = {}
        self._feature_rows = {}
        self._sent_descriptors = {}
        self.features_uplinked = {}
        self._up_prev: dict[tuple[int, int], int | None] = {}
        self._last_up: dict[int, int] = {}
        self._own_sorted: dict[int, np.ndarray] = {}  # map id -> sorted(_own_kfs[map id])
        self._sent_points: dict[int, SentPoints] = {}  # map id -> the points the cloud has
        # (map id, keyframe id) -> (T_world_body, v, bg, ba) the cloud has (coded wire)
        self._sent_state = {}
        # map id -> {keyframe id: T_world_body} of the uplinked keyframes whose pose here is
        # the one the cloud was sent or sent back (not moved by local BA since): the
        # candidates for a message's FrameAnchor (coded wire)
        self._agreed: dict[int, dict[int, np.ndarray]] = {}

    def _new_decoders(self) -> tuple[FeatureDecoder, ImuDecoder]:
        return FeatureDecoder(self.vocabulary, self.codec), ImuDecoder()

    def _reset_stream(self, decoders: tuple[FeatureDecoder, ImuDecoder] | None = None) -> None:
        """A fresh stream: fresh (or the given) decoders, numbering and feedback."""
        self.features, self.imu = decoders or self._new_decoders()
        self.numbers = np.zeros(0, np.int64)
        self.next_number = 0
        self.frames = 0
        self.feedback.restart()  # the robot's landmarks are unknown: the next one replaces them
        self._anchors.clear()

    def feedback_lost(self) -> None:
        """A feedback message could not be queued for the robot: the next one is a reset."""
        self.feedback.restart()

    # ------------------------------------------------------------------ decoding
    def decode(self, msg: RobotFrame) -> WorkItem:
        """Decode one frame (in stream order) into the VIO's input; raises CodecError.

        All or nothing: a frame that fails leaves every decoder as it was, so the next frame
        still decodes (each decoder commits only a whole payload; the IMU decoder, which runs
        first, is put back when the features then fail)."""
        restart = msg.frame_index == 0 and self.frames > 0
        if restart:  # a fresh stream: decode with fresh decoders, adopted if it decodes
            features, imu_decoder = self._new_decoders()
        else:
            features, imu_decoder = self.features, self.imu
        imu_state = imu_decoder.state.copy()
        imu = imu_decoder.decode(msg.imu)
        try:
            feats = features.decode(msg.features)
        except BaseException:
            imu_decoder.state = imu_state
            raise
        if restart:
            logger.warning("robot %s restarted its stream: fresh decoders", self.agent_id)
            self._reset_stream((features, imu_decoder))
            # its clock starts again too: the IMU of the old stream goes
            self.imu_uplink = ImuUplink(self.options.imu_history_s)
        self.numbers, self.next_number = next_stream_numbers(self.numbers, self.next_number, feats)
        if isinstance(feats, KeyframeFeatures):
            kp = feats.keypoints
            uv = kf_track_q(kp, self.codec).astype(np.float64) / self.codec.subpixel
            levels = kp[:, 2].astype(np.uint8)
            desc = feats.descriptors
            self.keyframes += 1
            self._kf_features[msg.timestamp_ns] = feats
            while len(self._kf_features) > self.options.keyframes_kept:
                self._kf_features.popitem(last=False)
        else:
            uv = feats.keypoints[:, :2]
            levels = feats.keypoints[:, 2].astype(np.uint8)
            desc = None
        self._anchors[msg.frame_index] = Anchors(self.numbers, uv)
        while len(self._anchors) > _ANCHOR_FRAMES:
            self._anchors.popitem(last=False)
        obs = FrameObservation(
            timestamp_ns=msg.timestamp_ns,
            track_ids=self.numbers,
            keypoints_px=uv,
            levels=levels,
            is_keyframe=isinstance(feats, KeyframeFeatures),
            descriptors=desc,
        )
        self.imu_uplink.add(imu.timestamps_ns, imu.gyro, imu.accel)
        self.frames += 1
        self.last_timestamp_ns = msg.timestamp_ns
        return WorkItem(
            msg.frame_index, imu.timestamps_ns, imu.gyro, imu.accel, obs, new_stream=restart
        )

    # ------------------------------------------------------------------ outputs
    def on_result(self, res: WorkResult, *, replaying: bool = False) -> Outputs:
        """Messages for one VIO result (no robot feedback while replaying the journal)."""
        out = Outputs([], [])
        self.processed += 1
        if res.failed:
            self.failures.append(f"frame {res.frame_index}: {res.failed}")
            self.state, self.reason = "initializing", f"VIO re-initialised after: {res.failed}"
            self.feedback.restart()
        if res.result is not None:
            r = res.result
            self.state = r.status.value
            self.reason = r.reason
            self.map_id = r.map_id
            self.frame_s.append(res.frame_s)
            self.time_offset_ns = res.time_offset_ns
            self.time_offset_sigma_ms = res.time_offset_sigma_ms
            if not replaying and self._offset_told != res.time_offset_ns:
                sigma = res.time_offset_sigma_ms
                sigma_ns = int(sigma * 1e6) if np.isfinite(sigma) else -1
                out.robot.append(CameraImuOffset(res.time_offset_ns, sigma_ns))
                self._offset_told = res.time_offset_ns
        if not replaying:
            self.poses_sent += 1
            out.robot.append(frame_pose(res.result, res.timestamp_ns, self.map_id))
        self.track_s.extend(res.track_s)
        self.local_ba_s.extend(res.local_ba_s)
        if res.vio_counts is not None:
            self.vio_counts = dict(res.vio_counts)
        for map_id, deltas in res.point_moves:  # before this frame's (corrected) points
            book = self._sent_points.get(map_id)
            if book is not None:
                book.move_held(deltas)
            self._follow_correction(map_id, deltas)
        for upd in res.updates:
            out.cloud.extend(self._uplink(upd))
        if res.result is not None and not replaying:
            out.cloud.extend(self._frame_relative(res.result))
        if res.state is not None and not replaying:
            fb = self._feedback(res)
            if fb is not None:
                out.robot.append(fb)
        while self._anchors and next(iter(self._anchors)) <= res.frame_index:
            self._anchors.popitem(last=False)  # results come in frame order
        out.status_due = self.processed % self.options.status_every_frames == 0
        return out

    def _frame_relative(self, r: FrameResult) -> list[Message]:
        """A tracked frame's pose relative to the newest keyframe the cloud has (coded wire),
        batched (:class:`FramePoseBatcher`)."""
        if r.status is not TrackingStatus.TRACKING or self.options.wire is not WireFormat.CODED:
            return []
        kf = self._last_up.get(r.map_id)
        if kf is None or (sent := self._sent_state.get((r.map_id, kf))) is None:
            return []
        rel = inverse_T(sent[0]) @ r.T_world_body
        return list(
            self.frame_poses.add(r.map_id, r.timestamp_ns, self._kf_time[(r.map_id, kf)], rel)
        )

    def release_frame_poses(self) -> list[Message]:
        """The frames' relative poses not sent yet (at the robot's end)."""
        return list(self.frame_poses.release())

    def _feedback(self, res: WorkResult) -> Message | None:
        assert res.state is not None
        msg = self.feedback.on_state(
            res.frame_index,
            res.state,
            res.live_track_ids,
            res.live_p_world,
            self.numbers,
            self._anchors.get(res.frame_index),
        )
        self.feedback_sent += msg is not None
        return msg

    def status(self, link_counters: dict[str, int]) -> AgentStatus:
        """The robot's :class:`AgentStatus` now (``link_counters``: flat int counters)."""
        return AgentStatus(
            agent_id=self.agent_id,
            map_id=int(self.map_id),
            state="finished" if self.finished else self.state,
            frames=int(self.processed),
            keyframes=int(self.vio_keyframes),
            timestamp_ns=int(self.last_timestamp_ns),
            link_counters={k: int(v) for k, v in link_counters.items()},
            detail=self.detail(),
            time_offset_ns=int(self.time_offset_ns),
        )

    def detail(self) -> str:
        """Why the robot is in its state (the VIO's reason, with numbers) and the camera-IMU
        time offset in use, for the status and the dashboard."""
        parts = [self.reason] if self.reason else []
        if np.isfinite(self.time_offset_sigma_ms) or self.time_offset_ns:
            sigma = self.time_offset_sigma_ms
            spread = f" ± {sigma:.1f}" if np.isfinite(sigma) else ""
            parts.append(f"camera-IMU offset {self.time_offset_ns * 1e-6:+.1f}{spread} ms")
        return "; ".join(parts)
