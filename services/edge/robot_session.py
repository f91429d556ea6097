"""One robot as the edge sees it (sans-I/O): decoding, track naming, outputs of its VIO.

:class:`RobotSession` turns each :class:`~common.protocol.messages.RobotFrame` into a
:class:`~services.edge.worker.WorkItem` (feature and IMU decoders are stateful per robot and
live here, outside the VIO worker, so that a VIO failure never loses the stream state), and
turns each :class:`~services.edge.worker.WorkResult` into messages:

- to the robot, :class:`InertialFeedback` after VI initialisation (or a new map) and then
  whenever biases/velocity moved more than :class:`FeedbackPolicy`'s thresholds or every
  ``every_frames`` frames; tracks are named by stream numbers (``common.codec.tracks``);
- to the cloud, :class:`KeyframeUpdate` (first time with the keyframe's features re-coded
  standalone; later pose-only), :class:`MapPointUpdate`, :class:`CullEvent`, and every
  ``status_every_frames`` an :class:`AgentStatus`.

No sockets, no asyncio: ``services/edge/app.py`` drives it.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass

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
from common.geometry import orthonormalize_T
from common.links import WireFormat
from common.links.edge_cloud import AgentStatus, CullEvent, KeyframeUpdate, MapPointUpdate
from common.links.robot_edge import InertialFeedback, RobotFrame
from common.protocol.arrays import pack_array
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.edge.vio.types import (
    FrameObservation,
    InertialState,
    MapPointBatch,
    MapUpdate,
)
from services.edge.worker import WorkItem, WorkResult

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FeedbackPolicy:
    """When the edge sends :class:`InertialFeedback` to a robot (after VI initialisation).

    A message goes out on the first initialised frame of a map, then whenever the gyro bias
    moved by more than ``gyro_bias_rad_s`` (rad/s, norm), the accel bias by more than
    ``accel_bias_mps2`` (m/s², norm) or the velocity by more than ``velocity_mps`` (m/s, norm)
    since the last message, and at least every ``every_frames`` frames.
    """

    gyro_bias_rad_s: float = 2e-3
    accel_bias_mps2: float = 2e-2
    velocity_mps: float = 0.1
    every_frames: int = 20


@dataclass(frozen=True)
class SessionOptions:
    """Per-robot output options: feedback policy, status period (frames), features kept for
    the keyframe uplink (robot keyframes, newest), IMU history kept (s), and the map-point
    uplink threshold: a point already sent is sent again only when it moved more than
    ``point_resend_m`` (m) or gained observations in robot keyframes, and then with only the
    new observations (local BA nudges every window point a little, and resending all of them
    with every observation dominated the edge->cloud link)."""

    feedback: FeedbackPolicy = FeedbackPolicy()
    status_every_frames: int = 20
    keyframes_kept: int = 300
    imu_history_s: float = 120.0
    point_resend_m: float = 0.01
    wire: WireFormat = WireFormat.CODED
    """Encoding of the messages to the robot and to the cloud (``raw``: the schema-1 baseline)."""


@dataclass
class Outputs:
    """Messages produced by one step: for the robot and for the cloud."""

    robot: list[Message]
    cloud: list[Message]
    status_due: bool = False  # time for an AgentStatus (the app adds the link counters)


def _one_point_each(b: MapPointBatch) -> list[MapPointBatch]:
    """``b`` split into one batch per point (in order)."""
    ends = np.cumsum(b.counts)
    return [
        MapPointBatch(b.point_ids[i : i + 1], b.p_world[i : i + 1], b.counts[i : i + 1],
                      b.keyframe_ids[e - c : e], b.feature_indices[e - c : e])
        for i, (c, e) in enumerate(zip(b.counts.tolist(), ends.tolist(), strict=True))
    ]  # fmt: skip


def _isin_sorted(sorted_values: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``x`` (N,) in ``sorted_values`` (M,, ascending) as a bool mask (N,)."""
    if not len(sorted_values):
        return np.zeros(len(x), bool)
    i = np.searchsorted(sorted_values, x).clip(max=len(sorted_values) - 1)
    return sorted_values[i] == x


_KEY = np.int64(2**32)  # (point, keyframe) key: point id * 2**32 + keyframe id


class SentPoints:
    """The points of one map the cloud has, as sorted arrays: ``ids`` (n,) point ids,
    ``p_world`` (n, 3) m the position last sent, ``keys`` (m,) the observations sent as
    ``point id * 2**32 + keyframe id`` (keyframe ids < 2**32)."""

    def __init__(self) -> None:
        self.ids = np.zeros(0, np.int64)
        self.p_world = np.zeros((0, 3))
        self.keys = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self.ids)

    def select(
        self, b: MapPointBatch, own_sorted: np.ndarray, resend_m: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """What of ``b`` (distinct point ids) to send (see ``RobotSession._points_to_send``),
        recorded as sent; ``own_sorted``: the VIO's own keyframe ids, ascending."""
        ids, p_world, kf_ids = b.point_ids, b.p_world, b.keyframe_ids
        n = len(ids)
        owner = np.repeat(np.arange(n), b.counts)  # (O,) point index of each observation
        robot = ~_isin_sorted(own_sorted, kf_ids)  # (O,) observation in a robot kf
        slot = np.searchsorted(self.ids, ids)
        known = slot < len(self.ids)
        known[known] = self.ids[slot[known]] == ids[known]
        keys = ids[owner] * _KEY + kf_ids
        new = robot & (~known[owner] | ~_isin_sorted(self.keys, keys))
        d = p_world[known] - self.p_world[slot[known]]
        moved = np.zeros(n, bool)
        moved[known] = (d * d).sum(axis=1) > resend_m**2
        seen = np.bincount(owner[robot], minlength=n) > 0
        go = seen & (~known | moved | (np.bincount(owner[new], minlength=n) > 0))
        if not go.any():
            return None
        self.p_world[slot[go & known]] = p_world[go & known]
        fresh = go & ~known
        if fresh.any():  # inserted in id order (np.insert keeps the given order at one slot)
            i = np.flatnonzero(fresh)[np.argsort(ids[fresh], kind="stable")]
            self.ids = np.insert(self.ids, slot[i], ids[i])
            self.p_world = np.insert(self.p_world, slot[i], p_world[i], axis=0)
        if new.any():
            k = np.sort(keys[new])
            self.keys = np.insert(self.keys, np.searchsorted(self.keys, k), k)
        rows = np.stack([ids[owner[new]], kf_ids[new], b.feature_indices[new]], axis=1)
        return ids[go], p_world[go], rows

    def remove(self, point_ids: np.ndarray) -> np.ndarray:
        """Forget ``point_ids`` (R,); the ones that were sent, in order (each once)."""
        first = np.sort(np.unique(point_ids, return_index=True)[1])
        point_ids = point_ids[first]
        hit = _isin_sorted(self.ids, point_ids)
        gone = point_ids[hit]
        if len(gone):
            keep = ~_isin_sorted(np.sort(gone), self.ids)
            self.ids, self.p_world = self.ids[keep], self.p_world[keep]
            lo = np.searchsorted(self.keys, gone * _KEY)
            hi = np.searchsorted(self.keys, (gone + 1) * _KEY)
            drop = np.zeros(len(self.keys) + 1, np.int64)
            np.add.at(drop, lo, 1)
            np.add.at(drop, hi, -1)
            self.keys = self.keys[np.cumsum(drop[:-1]) == 0]
        return gone


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
        self.map_id = 0
        self.last_timestamp_ns = 0
        self.finished = False
        self.feedback_sent = 0
        self.frame_s: list[float] = []
        self.track_s: list[float] = []
        self.local_ba_s: list[float] = []
        self._reset_stream()
        self._kf_features: OrderedDict[int, KeyframeFeatures] = OrderedDict()
        self._imu_chunks: list[tuple[np.ndarray, np.ndarray]] = []  # (t_ns (K,), (K, 6))
        self._kf_time: dict[tuple[int, int], int] = {}
        self._sent_kfs: set[tuple[int, int]] = set()
        # The VIO's own keyframes (no robot features) stay on the edge: uplinked keyframes
        # chain to the previous uplinked keyframe of their map, observations skip the others.
        self._own_kfs: dict[int, set[int]] = {}  # map id -> the VIO's own keyframe ids
        self._up_prev: dict[tuple[int, int], int | None] = {}
        self._last_up: dict[int, int] = {}
        self._own_sorted: dict[int, np.ndarray] = {}  # map id -> sorted(_own_kfs[map id])
        self._sent_points: dict[int, SentPoints] = {}  # map id -> the points the cloud has
        self._last_fb: InertialState | None = None
        self._last_fb_frame = -(10**9)
        self._fb_map: int | None = None

    def _reset_stream(self) -> None:
        self.features = FeatureDecoder(self.vocabulary, self.codec)
        self.imu = ImuDecoder()
        self.numbers = np.zeros(0, np.int64)
        self.next_number = 0
        self.frames = 0

    # ------------------------------------------------------------------ decoding
    def decode(self, msg: RobotFrame) -> WorkItem:
        """Decode one frame (in stream order) into the VIO's input; raises CodecError."""
        if msg.frame_index == 0 and self.frames > 0:
            logger.warning("robot %s restarted its stream: fresh decoders", self.agent_id)
            self._reset_stream()
        feats = self.features.decode(msg.features)
        imu = self.imu.decode(msg.imu)
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
        obs = FrameObservation(
            timestamp_ns=msg.timestamp_ns,
            track_ids=self.numbers,
            keypoints_px=uv,
            levels=levels,
            is_keyframe=isinstance(feats, KeyframeFeatures),
            descriptors=desc,
        )
        if len(imu):
            self._imu_chunks.append(
                (imu.timestamps_ns, np.concatenate([imu.gyro, imu.accel], axis=1))
            )
            horizon = int(imu.timestamps_ns[-1]) - int(self.options.imu_history_s * 1e9)
            while self._imu_chunks and self._imu_chunks[0][0][-1] < horizon:
                self._imu_chunks.pop(0)
        self.frames += 1
        self.last_timestamp_ns = msg.timestamp_ns
        return WorkItem(msg.frame_index, imu.timestamps_ns, imu.gyro, imu.accel, obs)

    def _imu_between(self, t0_ns: int | None, t1_ns: int) -> np.ndarray:
        """IMU rows "<f8 (M,7)" [t_s, gyro, accel] with t0 < t <= t1 (all up to t1 if None)."""
        if not self._imu_chunks:
            return np.zeros((0, 7))
        t = np.concatenate([c[0] for c in self._imu_chunks])
        v = np.concatenate([c[1] for c in self._imu_chunks])
        keep = t <= t1_ns
        if t0_ns is not None:
            keep &= t > t0_ns
        return np.concatenate([t[keep, None] * 1e-9, v[keep]], axis=1)

    # ------------------------------------------------------------------ outputs
    def on_result(self, res: WorkResult, *, replaying: bool = False) -> Outputs:
        """Messages for one VIO result (no robot feedback while replaying the journal)."""
        out = Outputs([], [])
        self.processed += 1
        if res.failed:
            self.failures.append(f"frame {res.frame_index}: {res.failed}")
            self.state, self.reason = "initializing", f"VIO re-initialised after: {res.failed}"
            self._fb_map = None
        if res.result is not None:
            r = res.result
            self.state = r.status.value
            self.reason = r.reason
            self.map_id = r.map_id
            self.frame_s.append(res.frame_s)
        self.track_s.extend(res.track_s)
        self.local_ba_s.extend(res.local_ba_s)
        for upd in res.updates:
            out.cloud.extend(self._uplink(upd))
        if res.state is not None and not replaying:
            fb = self._feedback(res)
            if fb is not None:
                out.robot.append(fb)
        out.status_due = self.processed % self.options.status_every_frames == 0
        return out

    def _feedback(self, res: WorkResult) -> InertialFeedback | None:
        s = res.state
        assert s is not None
        pol = self.options.feedback
        last = self._last_fb
        due = (
            last is None
            or self._fb_map != s.map_id
            or res.frame_index - self._last_fb_frame >= pol.every_frames
            or np.linalg.norm(s.bias_gyro - last.bias_gyro) > pol.gyro_bias_rad_s
            or np.linalg.norm(s.bias_accel - last.bias_accel) > pol.accel_bias_mps2
            or np.linalg.norm(s.v_world - last.v_world) > pol.velocity_mps
        )
        if not due:
            return None
        self._last_fb, self._last_fb_frame, self._fb_map = s, res.frame_index, s.map_id
        self.feedback_sent += 1
        ids = res.live_track_ids if res.live_track_ids is not None else np.zeros(0, np.int64)
        pts = res.live_p_world if res.live_p_world is not None else np.zeros((0, 3))
        g_world = s.T_world_body[:3, :3] @ s.gravity_body
        return InertialFeedback(
            timestamp_ns=int(s.timestamp_ns),
            map_id=int(s.map_id),
            T_world_body=pack_array(s.T_world_body, "<f8"),
            velocity_world=pack_array(s.v_world, "<f8"),
            bias_gyro=pack_array(s.bias_gyro, "<f8"),
            bias_accel=pack_array(s.bias_accel, "<f8"),
            gravity_world=pack_array(g_world, "<f8"),
            track_ids=pack_array(ids, "<i8"),
            p_world=pack_array(pts, "<f8"),
        )

    def _uplink(self, upd: MapUpdate) -> list[Message]:
        msgs: list[Message] = []
        for kf in upd.keyframes:
            key = (upd.map_id, kf.keyframe_id)
            self._kf_time[key] = kf.timestamp_ns
            if not kf.robot_keyframe:
                self._own_kfs.setdefault(upd.map_id, set()).add(kf.keyframe_id)
                self._own_sorted.pop(upd.map_id, None)
                continue
            if key not in self._up_prev:
                self._up_prev[key] = self._last_up.get(upd.map_id)
                self._last_up[upd.map_id] = kf.keyframe_id
            prev = self._up_prev[key]
            features = b""
            imu = np.zeros((0, 7))
            if key not in self._sent_kfs:
                feats = self._kf_features.get(kf.timestamp_ns)
                if feats is not None:
                    features = encode_standalone_keyframe(self.vocabulary, feats, self.codec)
                else:
                    logger.warning("robot %s: features of keyframe %d no longer kept",
                                   self.agent_id, kf.keyframe_id)  # fmt: skip
                t0 = None if prev is None else self._kf_time.get((upd.map_id, prev))
                imu = self._imu_between(t0, kf.timestamp_ns)
                self._sent_kfs.add(key)
                self.vio_keyframes += 1
            msgs.append(
                KeyframeUpdate(
                    agent_id=self.agent_id,
                    map_id=upd.map_id,
                    keyframe_id=kf.keyframe_id,
                    previous_keyframe_id=-1 if prev is None else int(prev),
                    timestamp_ns=kf.timestamp_ns,
                    T_world_body=pack_array(orthonormalize_T(kf.T_world_body), "<f8"),
                    velocity_world=pack_array(kf.v_world, "<f8"),
                    bias_gyro=pack_array(kf.bias_gyro, "<f8"),
                    bias_accel=pack_array(kf.bias_accel, "<f8"),
                    features=features,
                    map_point_ids=pack_array(kf.point_ids if features else [], "<i8"),
                    imu=pack_array(imu, "<f8"),
                )
            )
        points = self._points_to_send(upd)
        if points is not None:
            ids, p_world, rows = points
            msgs.append(
                MapPointUpdate(
                    agent_id=self.agent_id,
                    map_id=upd.map_id,
                    ids=pack_array(ids, "<i8"),
                    p_world=pack_array(p_world, "<f8"),
                    observations=pack_array(rows, "<i8"),
                )
            )
        book = self._sent_points.get(upd.map_id)
        removed = np.zeros(0, np.int64)
        if book is not None and upd.removed_point_ids:
            removed = book.remove(np.asarray(upd.removed_point_ids, np.int64))
        if len(removed):  # points the cloud never heard of need no cull
            msgs.append(
                CullEvent(
                    agent_id=self.agent_id,
                    map_id=upd.map_id,
                    keyframe_ids=b"",
                    map_point_ids=pack_array(removed, "<i8"),
                )
            )
        return msgs

    def _points_to_send(self, upd: MapUpdate) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The changed points worth sending: ``ids`` (P,), ``p_world`` (P, 3) m and the new
        observation rows (R, 3) ``[point id, keyframe id, feature row]``, in ``upd`` order;
        None if nothing is due.

        The cloud only knows the robot keyframes (the VIO's own keyframes carry no features),
        so only observations in those count: a point is sent once a robot keyframe observes
        it, again when it gains such observations (only the new rows: the cloud adds them to
        what it has) or moved more than ``point_resend_m`` since it was last sent.
        """
        if not upd.points:
            return None
        own = self._own_sorted.get(upd.map_id)
        if own is None:
            own = np.array(sorted(self._own_kfs.get(upd.map_id, ())), np.int64)
            self._own_sorted[upd.map_id] = own
        book = self._sent_points.setdefault(upd.map_id, SentPoints())
        batch = upd.points
        if len(np.unique(batch.point_ids)) < len(batch):  # a point twice: one at a time
            parts = [
                book.select(b, own, self.options.point_resend_m) for b in _one_point_each(batch)
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
        )
