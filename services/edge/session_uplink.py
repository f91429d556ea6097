"""The cloud half of one robot's session on the edge (sans-I/O): its VIO's map updates as
messages to the cloud.

:class:`SessionUplink` is a base of :class:`~services.edge.robot_session.RobotSession`, which
sets the attributes declared here. Per :class:`~services.edge.vio.types.MapUpdate`
(``EdgeSessionConfig.wire``): on the coded wire, a new robot keyframe as
:class:`~common.links.edge_cloud.KeyframeUpdateCoded` (its features re-coded standalone, its
state, its IMU since the previous uplinked keyframe), the states of keyframes the cloud has
that moved past the thresholds in one :class:`~common.links.edge_cloud.KeyframePoses`, points
as :class:`~common.links.edge_cloud.MapPointUpdateCoded`, each in the frame of a
:class:`~common.links.edge_cloud_payloads.FrameAnchor`; on the raw wire,
:class:`~common.links.edge_cloud.KeyframeUpdate` and
:class:`~common.links.edge_cloud.MapPointUpdate`; on both, a
:class:`~common.links.edge_cloud.CullEvent` for the points the cloud has that the VIO culled.
The VIO's own keyframes (no robot features) stay on the edge.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict

import numpy as np

from common.codec import CodecConfig, KeyframeFeatures, encode_standalone_keyframe
from common.geometry import inverse_T, orthonormalize_T, so3_log
from common.links import CodecTimer, WireFormat
from common.links.edge_cloud import (
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
from common.protocol.arrays import pack_array
from common.protocol.messages import Message
from common.vocabulary import Vocabulary
from services.edge.cloud_budget import KeyframeAllowance
from services.edge.imu_uplink import ImuUplink
from services.edge.point_uplink import Selection, SentPoints, one_point_each
from services.edge.session_config import EdgeSessionConfig
from services.edge.vio.types import KeyframeSnapshot, MapPointBatch, MapUpdate

logger = logging.getLogger(__name__)

_State = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(T_world_body (4, 4), v (3,) m/s, bias gyro (3,), bias accel (3,)) of one keyframe"""
_StateRow = tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""(keyframe id, *:data:`_State`)"""


def _states(rows: list[_StateRow], anchor: FrameAnchor | None = None) -> KeyframeStates:
    """Rows of :data:`_StateRow` as KeyframeStates in the frame of ``anchor``."""
    ids, T, v, bg, ba = zip(*rows, strict=True)
    T_, v_, bg_, ba_ = (np.stack(x) for x in (T, v, bg, ba))
    return KeyframeStates(np.array(ids, np.int64), T_, v_, bg_, ba_, anchor)


class SessionUplink:
    """The cloud uplink of :class:`~services.edge.robot_session.RobotSession`."""

    agent_id: str
    vocabulary: Vocabulary
    codec: CodecConfig
    options: EdgeSessionConfig
    codec_timer: CodecTimer
    vio_keyframes: int  # keyframes uplinked (distinct)
    time_offset_ns: int  # the VIO's camera-IMU offset (t_imu = t_cam + offset)
    imu_uplink: ImuUplink  # the keyframes' IMU
    _kf_features: OrderedDict[int, KeyframeFeatures]  # robot keyframes by timestamp, newest
    _kf_time: dict[tuple[int, int], int]
    _sent_kfs: set[tuple[int, int]]
    # The VIO's own keyframes (no robot features) stay on the edge: uplinked keyframes chain
    # to the previous uplinked keyframe of their map, observations skip the others.
    _own_kfs: dict[int, set[int]]  # map id -> the VIO's own keyframe ids
    _up_prev: dict[tuple[int, int], int | None]
    _last_up: dict[int, int]
    _own_sorted: dict[int, np.ndarray]  # map id -> sorted(_own_kfs[map id])
    _sent_points: dict[int, SentPoints]  # map id -> the points the cloud has
    # (map id, keyframe id) -> (T_world_body, v, bg, ba) the cloud has (coded wire)
    _sent_state: dict[tuple[int, int], _State]
    # map id -> {keyframe id: T_world_body} of the uplinked keyframes whose pose here is the
    # one the cloud was sent or sent back (not moved by local BA since): the candidates for a
    # message's FrameAnchor (coded wire)
    _agreed: dict[int, dict[int, np.ndarray]]
    # The cloud budget's allowance for the next results (None: every robot keyframe goes up;
    # set by the driver, ``EdgeApp``) and the robot keyframes it kept on the edge, by reason.
    cloud_allowance: KeyframeAllowance | None
    kept_on_edge: dict[str, int]
    _budget_n: dict[tuple[int, int], int | None]  # features a registered keyframe may carry
    # (map id, keyframe id) -> for each of its robot features, its row in what the cloud was
    # sent, or -1 (only keyframes the budget cut down to a subset)
    _feature_rows: dict[tuple[int, int], np.ndarray]
    # map id -> (keyframe id, {descriptor bytes: row}) of the newest keyframe sent up: a new
    # keyframe's features with a descriptor of it carry its row instead (coded wire)
    _sent_descriptors: dict[int, tuple[int, dict[bytes, int]]]
    features_uplinked: dict[tuple[int, int], int]  # keyframe -> features sent (the driver's)

    def _imu_args(
        self, prev: tuple[int, int] | None, key: tuple[int, int], t_ns: int
    ) -> tuple[tuple[int, int] | None, int | None, tuple[int, int], int, int]:
        """:class:`ImuUplink` arguments of keyframe ``key`` (at ``t_ns``) after ``prev``."""
        prev_time = None if prev is None else self._kf_time.get(prev)
        return prev, prev_time, key, t_ns, self.time_offset_ns

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
            feats, point_ids = self._subset(key, feats, point_ids, self._budget_n.pop(key, None))
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
                    features=self._features_coded(upd.map_id, kf.keyframe_id, prev, feats),
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
            self.features_uplinked[(upd.map_id, kf.keyframe_id)] = len(feats)
        msgs[:0] = kf_msgs
        msgs.extend(self.release_points(keep_map=upd.map_id))
        if points is not None:
            msgs.append(self._points_coded(upd.map_id, points, anchor))
        msgs.extend(self._culls(upd))
        return msgs

    def _features_coded(
        self, map_id: int, keyframe_id: int, prev: int | None, feats: KeyframeFeatures
    ) -> bytes:
        """A keyframe's features for the cloud, standalone: a feature whose descriptor the
        previous keyframe sent up had (a continued track, ``carry_track_descriptors``)
        carries that row instead (~20 instead of ~200 bits)."""
        carried = None
        last = self._sent_descriptors.get(map_id)
        if prev is not None and last is not None and last[0] == prev:
            rows = last[1]
            carried = np.array([rows.get(d.tobytes(), -1) for d in feats.descriptors], np.int64)
        table: dict[bytes, int] = {}
        for row, d in enumerate(feats.descriptors):
            table.setdefault(d.tobytes(), row)
        self._sent_descriptors[map_id] = (keyframe_id, table)
        return encode_standalone_keyframe(self.vocabulary, feats, self.codec, carried)

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
        own = self._own_kfs.setdefault(map_id, set())
        if kf_id in own:
            return False
        if robot_keyframe and key not in self._up_prev:
            n = self._budget_features(map_id, timestamp_ns)  # (before it is the newest sent)
            if n == 0:  # the cloud budget keeps it on the edge, like the VIO's own
                hold = self.cloud_allowance is not None and self.cloud_allowance.hold
                self.kept_on_edge["backlog" if hold else "rate"] += 1
                robot_keyframe = False
            else:
                self._budget_n[key] = n
        if not robot_keyframe:
            own.add(kf_id)
            self._own_sorted.pop(map_id, None)
            return False
        if key not in self._up_prev:
            self._up_prev[key] = self._last_up.get(map_id)
            self._last_up[map_id] = kf_id
        return True

    def _budget_features(self, map_id: int, timestamp_ns: int) -> int | None:
        """How many features a new robot keyframe of ``map_id`` may carry up (None: all; 0:
        none, it stays on the edge: too little paid for, or the link is behind). A map's first
        keyframe always goes whole (the cloud must know the map)."""
        allowance = self.cloud_allowance
        last = self._last_up.get(map_id)
        if allowance is None or last is None:
            return None
        since_s = (timestamp_ns - self._kf_time[(map_id, last)]) * 1e-9
        return allowance.features(since_s)

    def _subset(
        self, key: tuple[int, int], feats: KeyframeFeatures, point_ids: np.ndarray, n: int | None
    ) -> tuple[KeyframeFeatures, np.ndarray]:
        """At most ``n`` of a keyframe's features for the cloud: those on map points first,
        then the others evenly over their canonical order (by level, then row: spread over
        the image). Remembers the rows kept (``_feature_rows``) so that the points'
        observations name the rows the cloud has, and drop those it has not."""
        if n is None or n >= len(feats):
            return feats, point_ids
        on_points = np.flatnonzero(point_ids >= 0)
        others = np.flatnonzero(point_ids < 0)
        k = max(0, n - len(on_points))
        pick = others[np.linspace(0, len(others) - 1, k).round().astype(int)] if k else others[:0]
        keep = np.sort(np.concatenate([on_points[:n], pick]))
        rows = np.full(len(feats), -1, np.int64)
        rows[keep] = np.arange(len(keep))
        self._feature_rows[key] = rows
        sub = KeyframeFeatures(feats.keypoints[keep], feats.descriptors[keep], feats.links[keep])
        return sub, point_ids[keep]

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
                    self.features_uplinked[key] = len(feats)
                else:
                    logger.warning(
                        "robot %s: features of keyframe %d no longer kept",
                        self.agent_id,
                        kf.keyframe_id,
                    )
                self._budget_n.pop(key, None)  # (the raw wire sends every feature)
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
        batch = self._on_rows_sent(upd.map_id, upd.points)
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

    def _on_rows_sent(self, map_id: int, batch: MapPointBatch) -> MapPointBatch:
        """``batch`` with the observations in keyframes the cloud budget cut down renamed to
        the rows the cloud has, and those in features it was not sent dropped (a point left
        with no observation in a robot keyframe is then not sent, as any such point)."""
        cut = [
            k for k in np.unique(batch.keyframe_ids).tolist() if (map_id, k) in self._feature_rows
        ]
        if not cut:
            return batch
        feat = batch.feature_indices.copy()
        keep = np.ones(len(feat), bool)
        for k in cut:
            at = np.flatnonzero(batch.keyframe_ids == k)
            rows = self._feature_rows[(map_id, k)]
            inside = feat[at] < len(rows)
            new = np.full(len(at), -1, np.int64)
            new[inside] = rows[feat[at][inside]]
            feat[at] = new
            keep[at] = new >= 0
        owner = np.repeat(np.arange(len(batch)), batch.counts)[keep]
        return MapPointBatch(
            batch.point_ids,
            batch.p_world,
            np.bincount(owner, minlength=len(batch)).astype(np.int64),
            batch.keyframe_ids[keep],
            feat[keep],
        )
