"""One robot as the edge sees it (sans-I/O): decoding, track naming, outputs of its VIO.

:class:`RobotSession` turns each :class:`~common.protocol.messages.RobotFrame` into a
:class:`~services.edge.worker.WorkItem` (feature and IMU decoders are stateful per robot and
live here, outside the VIO worker, so that a VIO failure never loses the stream state), and
turns each :class:`~services.edge.worker.WorkResult` into messages:

- to the robot, inertial feedback after VI initialisation (or a new map) and then whenever
  biases/velocity moved more than :class:`FeedbackPolicy`'s thresholds or every
  ``every_frames`` frames (``services.edge.feedback``: raw :class:`InertialFeedback` or
  coded ``InertialFeedbackCoded`` with landmark deltas, per ``SessionOptions.wire``); tracks
  are named by stream numbers (``common.codec.tracks``);
- to the cloud, :class:`KeyframeUpdate` (first time with the keyframe's features re-coded
  standalone; later pose-only), :class:`MapPointUpdate`, :class:`CullEvent`, and every
  ``status_every_frames`` an :class:`AgentStatus`.

No sockets, no asyncio: ``services/edge/app.py`` drives it.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from common.calibration import CameraCalibration
from common.codec import (
    CodecConfig,
    FeatureDecoder,
    ImuDecoder,
    KeyframeFeatures,
    encode_standalone_keyframe,
)
from common.codec.keypoints import kf_track_q
from common.codec.tracks import next_stream_numbers
from common.geometry import inverse_T, orthonormalize_T, so3_log
from common.links import CodecTimer, WireFormat
from common.links.edge_cloud import (
    AgentStatus,
    CullEvent,
    KeyframePoses,
    KeyframeUpdateCoded,
    MapPointUpdateCoded,
    pack_keyframe_update,
    pack_map_point_update,
)
from common.links.edge_cloud_payloads import (
    FrameAnchor,
    KeyframeStates,
    PointBatch,
    encode_point_ids,
    encode_points,
    encode_states,
)
from common.links.robot_edge import (
    Anchors,
    CameraImuOffset,
    RobotFrame,
)
from common.protocol.arrays import pack_array
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.edge.feedback import FeedbackPolicy, FeedbackSender
from services.edge.frame_poses import FramePoseBatcher, frame_pose
from services.edge.imu_uplink import ImuUplink
from services.edge.point_uplink import Selection, SentPoints, one_point_each
from services.edge.vio.types import (
    FrameObservation,
    FrameResult,
    KeyframeSnapshot,
    MapUpdate,
    TrackingStatus,
)
from services.edge.worker import WorkItem, WorkResult

logger = logging.getLogger(__name__)

_ANCHOR_FRAMES = 1000
"""Safety cap of decoded frames kept for their VIO result (a frame's anchors go when its result
comes): above the edge's frame queue (``EdgeConfig.max_queued_frames``, 200) plus the frames in
flight. A cap of 64 dropped the anchors of every frame whose result came more than 3 s after it
was decoded, as it does whenever the edge runs behind the robots, and then the coded feedback
carried no points at all."""


@dataclass(frozen=True)
class SessionOptions:
    """Per-robot output options: feedback policy, status period (frames), features kept for
    the keyframe uplink (robot keyframes, newest), IMU history kept (s), and the map-point
    uplink threshold: a point already sent is sent again only when it moved more than
    ``point_resend_m`` (m) or gained observations in robot keyframes, and then with only the
    new observations (local BA nudges every window point a little, and resending all of them
    with every observation dominated the edge->cloud link)."""

    feedback: FeedbackPolicy = field(default_factory=FeedbackPolicy)
    status_every_frames: int = 20
    keyframes_kept: int = 300
    imu_history_s: float = 120.0
    point_resend_m: float = 0.01
    wire: WireFormat = WireFormat.CODED
    """Encoding of the messages to the robot and to the cloud (``raw``: the schema-1 baseline)."""
    frame_poses_every: int = 20
    """Coded wire only: the tracked frames' poses relative to the newest uplinked keyframe go
    to the cloud (``FramePoses``, 44 B a frame) in batches of this many frames (and when the
    map changes, and at the end), so that it writes a trajectory of every frame."""
    pose_resend_m: float = 1e-3
    """Coded wire only: a keyframe the cloud has gets a new state (``KeyframePoses``) when its
    position moved more than this (m) since last sent, its rotation more than
    ``pose_resend_rad``, its velocity more than ``velocity_resend_mps`` or a bias more than
    ``bias_resend``; each point then follows its reference keyframe at both ends, and is
    re-sent when it moved more than ``point_resend_m`` from where it followed to."""
    pose_resend_rad: float = 1e-3
    velocity_resend_mps: float = 0.01
    bias_resend: float = 1e-3
    point_settle_keyframes: int = 0
    """Coded wire only: a new map point goes up once this many robot keyframes were uplinked
    after its first robot observer (``services.edge.point_uplink``; 0: at once, as the raw
    wire does). Off by default: 3 cut the map-point bytes by ~45 % (edge->cloud 1237 -> 1020
    / 1034 kbit/s at camera rate, default dataset) but joint ATE was 2.7 / 3.0 cm against 2.5
    at 0 (single runs; ``benchmarks/results/link_budget_sweep.md``). A likely cause: a held
    point kept the position it had before a cloud correction the edge applied meanwhile (the
    VIO moves its points without re-sending them), so it reached the cloud off its corrected
    keyframes; held points now move with those corrections (``SentPoints.move_held``), not
    yet measured on the whole job."""


@dataclass
class Outputs:
    """Messages produced by one step: for the robot and for the cloud."""

    robot: list[Message]
    cloud: list[Message]
    status_due: bool = False  # time for an AgentStatus (the app adds the link counters)


_State = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(T_world_body (4, 4), v (3,) m/s, bias gyro (3,), bias accel (3,)) of one keyframe"""
_StateRow = tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(keyframe id, *:data:`_State`)"""


def _states(rows: list[_StateRow], anchor: FrameAnchor | None = None) -> KeyframeStates:
    """Rows of :data:`_StateRow` as KeyframeStates in the frame of ``anchor``."""
    ids, T, v, bg, ba = zip(*rows, strict=True)
    T_, v_, bg_, ba_ = (np.stack(x) for x in (T, v, bg, ba))
    return KeyframeStates(np.array(ids, np.int64), T_, v_, bg_, ba_, anchor)


class RobotSession:
    """Edge-side state of one robot (see the module docstring)."""

    def __init__(
        self,
        agent_id: str,
        camera: CameraCalibration,
        vocabulary: Vocabulary,
        options: SessionOptions | None = None,
    ) -> None:
        self.agent_id = agent_id
        self.vocabulary = vocabulary
        self.codec = CodecConfig(image_width=camera.width, image_height=camera.height)
        self.options = options or SessionOptions()
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
        self._reset_stream()
        self._kf_features: OrderedDict[int, KeyframeFeatures] = OrderedDict()
        self.imu_uplink = ImuUplink(self.options.imu_history_s)  # the keyframes' IMU
        self._kf_time: dict[tuple[int, int], int] = {}
        self._sent_kfs: set[tuple[int, int]] = set()
        # The VIO's own keyframes (no robot features) stay on the edge: uplinked keyframes
        # chain to the previous uplinked keyframe of their map, observations skip the others.
        self._own_kfs: dict[int, set[int]] = {}  # map id -> the VIO's own keyframe ids
        self._up_prev: dict[tuple[int, int], int | None] = {}
        self._last_up: dict[int, int] = {}
        self._own_sorted: dict[int, np.ndarray] = {}  # map id -> sorted(_own_kfs[map id])
        self._sent_points: dict[int, SentPoints] = {}  # map id -> the points the cloud has
        # (map id, keyframe id) -> (T_world_body, v, bg, ba) the cloud has (coded wire)
        self._sent_state: dict[tuple[int, int], _State] = {}
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

    def _imu_args(
        self, prev: tuple[int, int] | None, key: tuple[int, int], t_ns: int
    ) -> tuple[tuple[int, int] | None, int | None, tuple[int, int], int, int]:
        """:class:`ImuUplink` arguments of keyframe ``key`` (at ``t_ns``) after ``prev``."""
        prev_time = None if prev is None else self._kf_time.get(prev)
        return prev, prev_time, key, t_ns, self.time_offset_ns

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

    def _uplink(self, upd: MapUpdate) -> list[Message]:
        if self.options.wire is WireFormat.CODED:
            return self._uplink_coded(upd)
        return self._uplink_raw(upd)

    def _uplink_coded(self, upd: MapUpdate) -> list[Message]:
        """The coded uplink: new keyframes as KeyframeUpdateCoded, changed states of known
        ones in one KeyframePoses, points as MapPointUpdateCoded (see ``common.links``)."""
        msgs: list[Message] = []
        timer = self.codec_timer
        book = self._book(upd.map_id)
        agreed = self._agreed.setdefault(upd.map_id, {})
        anchor = self._anchor(agreed, {kf.keyframe_id for kf in upd.keyframes})
        moved: list[_StateRow] = []
        fresh: list[tuple[KeyframeSnapshot, _State, KeyframeFeatures, np.ndarray]] = []
        for kf in upd.keyframes:
            key = (upd.map_id, kf.keyframe_id)
            if not self._register(key, kf.timestamp_ns, kf.robot_keyframe):
                continue
            T = orthonormalize_T(kf.T_world_body)
            state: _State = (
                T,
                np.asarray(kf.v_world, float),
                np.asarray(kf.bias_gyro, float),
                np.asarray(kf.bias_accel, float),
            )
            if key in self._sent_kfs:
                last = self._sent_state.get(key)
                if last is None or self._state_moved(last, state):
                    moved.append((kf.keyframe_id, *state))
                    agreed[kf.keyframe_id] = T
                else:  # nudged below the thresholds: no longer where the cloud has it
                    agreed.pop(kf.keyframe_id, None)
                continue
            feats = self._kf_features.get(kf.timestamp_ns)
            if feats is None:
                logger.warning(
                    "robot %s: features of keyframe %d no longer kept",
                    self.agent_id,
                    kf.keyframe_id,
                )
                continue
            point_ids = np.asarray(kf.point_ids, np.int64)
            book.add_keys(point_ids[point_ids >= 0], kf.keyframe_id)
            fresh.append((kf, state, feats, point_ids))
            self._sent_kfs.add(key)
            self._sent_state[key] = state
            agreed[kf.keyframe_id] = T
            self.vio_keyframes += 1
        if moved:
            t0 = time.perf_counter()
            states = _states(moved, anchor)
            msgs.append(KeyframePoses(self.agent_id, upd.map_id, encode_states(states)))
            timer.add("encode.KeyframePoses", time.perf_counter() - t0)
            for kf_id, *new_state in moved:
                key = (upd.map_id, kf_id)
                T_new, v, bg, ba = new_state
                book.follow(kf_id, self._sent_state[key][0], T_new)
                self._sent_state[key] = (T_new, v, bg, ba)
        points = self._points_to_send(upd)  # after the follows: compared where they moved to
        kf_msgs: list[Message] = []
        for kf, state, feats, point_ids in fresh:  # after the points: what they may name
            t0 = time.perf_counter()
            prev = self._up_prev[(upd.map_id, kf.keyframe_id)]
            kf_msgs.append(
                KeyframeUpdateCoded(
                    agent_id=self.agent_id,
                    map_id=upd.map_id,
                    keyframe_id=kf.keyframe_id,
                    previous_keyframe_id=-1 if prev is None else int(prev),
                    timestamp_ns=kf.timestamp_ns,
                    state=encode_states(_states([(kf.keyframe_id, *state)], anchor)),
                    features=encode_standalone_keyframe(self.vocabulary, feats, self.codec),
                    map_point_ids=encode_point_ids(book.carried(point_ids, kf.keyframe_id)),
                    imu=self.imu_uplink.coded(
                        *self._imu_args(
                            None if prev is None else (upd.map_id, prev),
                            (upd.map_id, kf.keyframe_id),
                            kf.timestamp_ns,
                        )
                    ),
                )
            )
            timer.add("encode.KeyframeUpdateCoded", time.perf_counter() - t0)
        msgs[:0] = kf_msgs
        msgs.extend(self.release_points(keep_map=upd.map_id))
        if points is not None:
            msgs.append(self._points_coded(upd.map_id, points, anchor))
        msgs.extend(self._culls(upd))
        return msgs

    @staticmethod
    def _anchor(agreed: dict[int, np.ndarray], changed: set[int]) -> FrameAnchor | None:
        """The newest keyframe the cloud has at the pose it has here and that this update
        leaves alone: the frame its messages are in (None: no such keyframe yet)."""
        best = max((k for k in agreed if k not in changed), default=None)
        return None if best is None else FrameAnchor(best, agreed[best])

    def _follow_correction(self, map_id: int, deltas: dict[int, np.ndarray]) -> None:
        """The VIO applied a cloud correction (``{keyframe id: (4, 4) T_new T_old^-1}``):
        the agreed poses move as its keyframes did (``VioManager.apply_pose_corrections``)."""
        agreed = self._agreed.get(map_id)
        if not agreed:
            return
        for kf_id, T in agreed.items():
            delta = deltas.get(kf_id)
            if delta is not None:
                agreed[kf_id] = orthonormalize_T(delta @ T)

    def _points_coded(
        self, map_id: int, points: Selection, anchor: FrameAnchor | None = None
    ) -> MapPointUpdateCoded:
        t0 = time.perf_counter()
        ids, p_world, rows = points
        last = len(ids) - 1 - np.unique(ids[::-1], return_index=True)[1]  # a point twice:
        ids, p_world = ids[last], p_world[last]  # its last position (rows are distinct)
        body = encode_points(PointBatch(ids, p_world, rows, anchor))
        self.codec_timer.add("encode.MapPointUpdateCoded", time.perf_counter() - t0)
        return MapPointUpdateCoded(self.agent_id, map_id, body)

    def _book(self, map_id: int) -> SentPoints:
        book = self._sent_points.get(map_id)
        if book is None:
            settle = self.options.point_settle_keyframes
            book = SentPoints(settle if self.options.wire is WireFormat.CODED else 0)
            self._sent_points[map_id] = book
        return book

    def _own(self, map_id: int) -> np.ndarray:
        """The VIO's own keyframe ids of a map, ascending."""
        own = self._own_sorted.get(map_id)
        if own is None:
            own = np.array(sorted(self._own_kfs.get(map_id, ())), np.int64)
            self._own_sorted[map_id] = own
        return own

    def release_points(self, keep_map: int | None = None) -> list[Message]:
        """The held points of every map but ``keep_map`` (all at the end of the robot's
        sequence; a map the robot left gets no keyframe that would settle them)."""
        msgs: list[Message] = []
        for map_id, book in self._sent_points.items():
            if map_id == keep_map or not book.n_held:
                continue
            points = book.release(self._own(map_id), self.options.point_resend_m)
            if points is not None:
                anchor = self._anchor(self._agreed.get(map_id, {}), set())
                msgs.append(self._points_coded(map_id, points, anchor))
        return msgs

    def _state_moved(
        self,
        last: _State,
        new: _State,
    ) -> bool:
        o = self.options
        dT = inverse_T(last[0]) @ new[0]
        return bool(
            np.linalg.norm(new[0][:3, 3] - last[0][:3, 3]) > o.pose_resend_m
            or np.linalg.norm(so3_log(dT[:3, :3])) > o.pose_resend_rad
            or np.linalg.norm(new[1] - last[1]) > o.velocity_resend_mps
            or np.abs(new[2] - last[2]).max() > o.bias_resend
            or np.abs(new[3] - last[3]).max() > o.bias_resend
        )

    def _culls(self, upd: MapUpdate) -> list[Message]:
        book = self._sent_points.get(upd.map_id)
        removed = np.zeros(0, np.int64)
        if book is not None and upd.removed_point_ids:
            removed = book.remove(np.asarray(upd.removed_point_ids, np.int64))
        if not len(removed):  # points the cloud never heard of need no cull
            return []
        return [CullEvent(self.agent_id, upd.map_id, b"", pack_array(removed, "<i8"))]

    def _register(self, key: tuple[int, int], timestamp_ns: int, robot_keyframe: bool) -> bool:
        """Note a keyframe ``(map id, keyframe id)`` of an update; False for the VIO's own
        keyframes, which stay on the edge (uplinked ones chain to the previous uplinked one)."""
        map_id, kf_id = key
        self._kf_time[key] = timestamp_ns
        if not robot_keyframe:
            self._own_kfs.setdefault(map_id, set()).add(kf_id)
            self._own_sorted.pop(map_id, None)
            return False
        if key not in self._up_prev:
            self._up_prev[key] = self._last_up.get(map_id)
            self._last_up[map_id] = kf_id
        return True

    def _uplink_raw(self, upd: MapUpdate) -> list[Message]:
        msgs: list[Message] = []
        for kf in upd.keyframes:
            key = (upd.map_id, kf.keyframe_id)
            if not self._register(key, kf.timestamp_ns, kf.robot_keyframe):
                continue
            prev = self._up_prev[key]
            features = b""
            imu = np.zeros((0, 7))
            if key not in self._sent_kfs:
                feats = self._kf_features.get(kf.timestamp_ns)
                if feats is not None:
                    features = encode_standalone_keyframe(self.vocabulary, feats, self.codec)
                else:
                    logger.warning(
                        "robot %s: features of keyframe %d no longer kept",
                        self.agent_id,
                        kf.keyframe_id,
                    )
                prev_key = None if prev is None else (upd.map_id, int(prev))
                imu = self.imu_uplink.raw(*self._imu_args(prev_key, key, kf.timestamp_ns))
                self._sent_kfs.add(key)
                self.vio_keyframes += 1
            msgs.append(
                pack_keyframe_update(
                    self.agent_id,
                    upd.map_id,
                    kf.keyframe_id,
                    -1 if prev is None else int(prev),
                    kf.timestamp_ns,
                    orthonormalize_T(kf.T_world_body),
                    kf.v_world,
                    kf.bias_gyro,
                    kf.bias_accel,
                    features,
                    kf.point_ids if features else None,
                    imu,
                )
            )
        points = self._points_to_send(upd)
        if points is not None:
            msgs.append(pack_map_point_update(self.agent_id, upd.map_id, *points))
        msgs.extend(self._culls(upd))
        return msgs

    def _points_to_send(self, upd: MapUpdate) -> Selection | None:
        """The changed points worth sending: ``ids`` (P,), ``p_world`` (P, 3) m and the new
        observation rows (R, 3) ``[point id, keyframe id, feature row]``, in ``upd`` order;
        None if nothing is due.

        The cloud only knows the robot keyframes (the VIO's own keyframes carry no features),
        so only observations in those count: a point is sent once a robot keyframe observes
        it, again when it gains such observations (only the new rows: the cloud adds them to
        what it has) or moved more than ``point_resend_m`` since it was last sent.
        """
        book = self._book(upd.map_id)
        if not upd.points and not book.n_held:
            return None
        own = self._own(upd.map_id)
        batch = upd.points
        if len(np.unique(batch.point_ids)) < len(batch):  # a point twice: one at a time
            parts = [
                book.select(b, own, self.options.point_resend_m) for b in one_point_each(batch)
            ]
            sent = [p for p in parts if p is not None]
            if not sent:
                return None
            ids, p_world, rows = zip(*sent, strict=True)
            return np.concatenate(ids), np.concatenate(p_world), np.concatenate(rows)
        return book.select(batch, own, self.options.point_resend_m)

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
