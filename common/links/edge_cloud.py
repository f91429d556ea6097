"""The edge <-> cloud link: its wire messages (type ids 0x04xx edge -> cloud, 0x05xx cloud ->
edge) and their encoders and decoders, used by both ends and by every test, benchmark and
replay."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from common.codec.entropy import BitReader, BitWriter
from common.codec.errors import CodecError
from common.geometry import R_to_quat_wxyz, quat_wxyz_to_R
from common.links.body import (
    LinkDecodeError,
    get_scaled_geometric,
    get_scaled_signed,
    open_sealed,
    put_scaled_geometric,
    put_scaled_signed,
    seal,
)
from common.links.sensors import Sensors, decode_sensors, encode_sensors
from common.links.wire import pack_finite_pose, unpack_sent_pose
from common.protocol.arrays import pack_array, unpack_array
from common.protocol.errors import RemoteProtocolError
from common.protocol.messages import Message, message


# ------------------------------------------------------------------------- edge -> cloud
@message(0x0401)
class KeyframeUpdate(Message):
    """A new or updated keyframe of one robot's local map.

    ``T_world_body`` "<f8 (4,4)", ``velocity_world``/``bias_gyro``/``bias_accel`` "<f8 (3)".
    ``features``: the keyframe's features coded *intra* by ``common.codec.frames`` (a fresh
    encoder state per keyframe, so the cloud decodes each keyframe on its own; the robot's
    stream is differential against frames the cloud never sees; frame kind 3,
    ``KIND_STANDALONE_KEYFRAME``; kind 1, which older edges sent, still decodes). Empty on a
    pose-only update.
    ``map_point_ids`` "<i8 (N)": map point of each feature (-1 if none), in the coded order.
    ``imu`` "<f8 (M,7)": [t_s, gyro xyz, accel xyz] since the previous keyframe.
    ``previous_keyframe_id``: the robot's previous keyframe in the same map (-1 if first).
    """

    agent_id: str
    map_id: int
    keyframe_id: int
    previous_keyframe_id: int
    timestamp_ns: int
    T_world_body: bytes
    velocity_world: bytes
    bias_gyro: bytes
    bias_accel: bytes
    features: bytes
    map_point_ids: bytes
    imu: bytes


@message(0x0402)
class MapPointUpdate(Message):
    """New or moved map points of one robot's local map.

    ``ids`` "<i8 (N)", ``p_world`` "<f8 (N,3)"; ``observations`` "<i8 (M,3)" rows of
    (map point id, keyframe id, feature index within that keyframe).
    """

    agent_id: str
    map_id: int
    ids: bytes
    p_world: bytes
    observations: bytes


def pack_keyframe_update(
    agent_id: str,
    map_id: int,
    keyframe_id: int,
    previous_keyframe_id: int,
    timestamp_ns: int,
    T_world_body: np.ndarray,
    velocity_world: np.ndarray,
    bias_gyro: np.ndarray,
    bias_accel: np.ndarray,
    features: bytes = b"",
    map_point_ids: np.ndarray | None = None,
    imu: np.ndarray | None = None,
) -> KeyframeUpdate:
    """The raw (schema-1) :class:`KeyframeUpdate` of these arrays, packed as its docstring
    states (``map_point_ids`` None: none, a pose-only update; ``imu`` (M, 7) or None)."""
    return KeyframeUpdate(
        agent_id=agent_id,
        map_id=map_id,
        keyframe_id=keyframe_id,
        previous_keyframe_id=previous_keyframe_id,
        timestamp_ns=timestamp_ns,
        T_world_body=pack_array(T_world_body, "<f8"),
        velocity_world=pack_array(velocity_world, "<f8"),
        bias_gyro=pack_array(bias_gyro, "<f8"),
        bias_accel=pack_array(bias_accel, "<f8"),
        features=features,
        map_point_ids=pack_array(
            np.zeros(0, np.int64) if map_point_ids is None else map_point_ids, "<i8"
        ),
        imu=pack_array(np.zeros((0, 7)) if imu is None else imu, "<f8"),
    )


def pack_map_point_update(
    agent_id: str, map_id: int, ids: np.ndarray, p_world: np.ndarray, observations: np.ndarray
) -> MapPointUpdate:
    """The raw (schema-1) :class:`MapPointUpdate`: ``ids`` (N,), ``p_world`` (N, 3) m,
    ``observations`` (M, 3) ``[point id, keyframe id, feature index]``."""
    return MapPointUpdate(
        agent_id,
        map_id,
        pack_array(ids, "<i8"),
        pack_array(np.asarray(p_world, np.float64).reshape(-1, 3), "<f8"),
        pack_array(np.asarray(observations, np.int64).reshape(-1, 3), "<i8"),
    )


@message(0x0403)
class CullEvent(Message):
    """Keyframes and map points the edge removed: ``keyframe_ids``/``map_point_ids`` "<i8 (N)"."""

    agent_id: str
    map_id: int
    keyframe_ids: bytes
    map_point_ids: bytes


@message(0x0404)
class AgentStatus(Message):
    """Status of one robot as the edge sees it (dashboard, reports).

    ``state``: "initializing" | "tracking" | "lost" | "finished". ``link_counters``: the
    robot->edge link's byte counters by direction and message type (``"rx.RobotFrame"`` ...).
    ``detail``: why the state is what it is, with numbers (a refused VI initialisation's
    keyframes, span, scale and biases), and the camera-IMU time offset in use; may be empty.
    ``time_offset_ns``: the robot's camera-IMU time offset (``t_imu = t_cam + offset``): the
    IMU samples the keyframe messages carry are stamped on the IMU clock, and the cloud reads
    the IMU between two keyframes at their times plus this offset.
    """

    agent_id: str
    map_id: int
    state: str
    frames: int
    keyframes: int
    timestamp_ns: int
    link_counters: dict[str, int]
    detail: str = ""
    time_offset_ns: int = 0


@message(0x0408)
class AgentSensors(Message):
    """The sensors of robot ``agent_id`` as it described them at join (``sensors``:
    :func:`common.links.sensors.encode_sensors`), sent before that robot's first keyframe
    (and again after an edge restart; the cloud ignores a repeat). The cloud projects that
    robot's keyframes with this camera."""

    agent_id: str
    sensors: bytes


def agent_sensors_message(agent_id: str, sensors: Sensors) -> AgentSensors:
    return AgentSensors(agent_id, encode_sensors(sensors))


def read_agent_sensors(msg: AgentSensors) -> Sensors:
    """The sensors of ``msg``; SensorsDecodeError (RemoteProtocolError) if damaged/invalid."""
    return decode_sensors(msg.sensors, f"AgentSensors({msg.agent_id!r}).sensors")


@message(0x0409)
class FramePoses(Message):
    """Where robot ``agent_id``'s frames were, relative to its uplinked keyframes, so that the
    cloud can write a trajectory of every frame (the VIO's motion since a keyframe, placed on
    the cloud's corrected pose of that keyframe).

    ``timestamps_ns`` "<i8 (N)": the frames' camera times; ``keyframe_timestamps_ns`` "<i8
    (N)": each one's reference keyframe (an uplinked keyframe of edge map ``map_id``), by its
    time; ``poses`` "<f4 (N, 7)": ``T_kf_frame`` of each, the unit quaternion (w, x, y, z) of
    its rotation then its translation [m]."""

    agent_id: str
    map_id: int
    timestamps_ns: bytes
    keyframe_timestamps_ns: bytes
    poses: bytes


def pack_frame_poses(
    agent_id: str, map_id: int, t_ns: np.ndarray, t_kf_ns: np.ndarray, T_kf_frame: np.ndarray
) -> FramePoses:
    """A :class:`FramePoses` of frames (N,) at ``t_ns`` relative to the keyframes at
    ``t_kf_ns`` (N,), ``T_kf_frame`` (N, 4, 4)."""
    T = np.asarray(T_kf_frame, np.float64).reshape(-1, 4, 4)
    rows = np.concatenate([R_to_quat_wxyz(T[:, :3, :3]).reshape(-1, 4), T[:, :3, 3]], axis=1)
    return FramePoses(
        agent_id,
        int(map_id),
        pack_array(np.asarray(t_ns, np.int64), "<i8"),
        pack_array(np.asarray(t_kf_ns, np.int64), "<i8"),
        pack_array(rows, "<f4"),
    )


def read_frame_poses(msg: FramePoses) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t_ns (N,), t_kf_ns (N,), T_kf_frame (N, 4, 4))`` of a :class:`FramePoses`;
    RemoteProtocolError naming the field when the arrays disagree or are not finite."""
    t = unpack_array(msg.timestamps_ns, "<i8", (), "FramePoses.timestamps_ns")
    t_kf = unpack_array(msg.keyframe_timestamps_ns, "<i8", (), "FramePoses.keyframe_timestamps_ns")
    rows = unpack_array(msg.poses, "<f4", (7,), "FramePoses.poses").astype(np.float64)
    if not len(t) == len(t_kf) == len(rows):
        raise RemoteProtocolError(
            f"FramePoses: {len(t)} frames, {len(t_kf)} keyframe times, {len(rows)} poses"
        )
    if not np.isfinite(rows).all() or np.any(np.linalg.norm(rows[:, :4], axis=1) < 0.5):
        raise RemoteProtocolError("FramePoses.poses: not finite unit quaternions and positions")
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :3] = quat_wxyz_to_R(rows[:, :4])
    T[:, :3, 3] = rows[:, 4:]
    return t.astype(np.int64), t_kf.astype(np.int64), T


# ------------------------------------------------------------------------- cloud -> edge
@message(0x0501)
class PoseCorrection(Message):
    """Corrected keyframe poses after a merge or global optimisation.

    ``keyframe_ids`` "<i8 (N)", ``T_world_body`` "<f8 (N,4,4)" in the frame of the robot's
    own map ``map_id`` (the cloud maps corrections back into each robot's frame).
    """

    agent_id: str
    map_id: int
    keyframe_ids: bytes
    T_world_body: bytes


@message(0x0503)
class MapPlacement(Message):
    """Where robot ``agent_id``'s own map ``map_id`` (the edge's map id) sits in the cloud's
    global map ``global_map`` (the atlas map it is part of): ``pose`` (28 bytes,
    :func:`~common.links.wire.pack_pose`) is ``T_global_map``. Sent with every correction of
    that robot; the edge forwards it to the robot (``robot_edge.MapPlacement``)."""

    agent_id: str
    map_id: int
    global_map: int
    pose: bytes


def encode_map_placement(
    agent_id: str, map_id: int, global_map: int, T_global_map: np.ndarray
) -> MapPlacement:
    """A :class:`MapPlacement` (ValueError if the transform is not finite in float32)."""
    return MapPlacement(agent_id, int(map_id), int(global_map), pack_finite_pose(T_global_map))


def decode_map_placement(msg: MapPlacement) -> np.ndarray:
    """``T_global_map`` (4, 4) of a :class:`MapPlacement`; RemoteProtocolError if malformed."""
    return unpack_sent_pose(msg.pose, f"MapPlacement.pose of {msg.agent_id}")


# ------------------------------------------------------------------ coded (schema 2) messages
# The coded forms of KeyframeUpdate, pose-only updates and MapPointUpdate. Each payload
# decodes on its own (no decoder state across messages, so a cloud restored from its database
# decodes the next message as it would have), behind the version byte and CRC of
# ``common.links.body``. The schema-1 messages above stay: they are the ``raw`` baseline of
# ``recslam experiment links`` and what older recordings hold.


@message(0x0405)
class KeyframeUpdateCoded(Message):
    """A new keyframe of one robot's local map (the coded form of a first KeyframeUpdate).

    ``state``: :func:`encode_states` of this one keyframe (pose, velocity, biases).
    ``features``: the keyframe coded *intra* by ``common.codec.frames`` (as KeyframeUpdate).
    ``map_point_ids``: :func:`encode_point_ids`, the map point of each feature, coded order.
    ``imu``: ``common.codec.imu`` of the samples since the previous keyframe with a fresh
    encoder (bit-exact: the robot's own lossless IMU coding; empty if none).
    """

    agent_id: str
    map_id: int
    keyframe_id: int
    previous_keyframe_id: int
    timestamp_ns: int
    state: bytes
    features: bytes
    map_point_ids: bytes
    imu: bytes


@message(0x0406)
class KeyframePoses(Message):
    """New states of keyframes the cloud already has (one robot map): :func:`encode_states`.

    The cloud moves each map point whose reference keyframe moved with it
    (``p' = T'_ref T_ref^-1 p``), so the edge re-sends a point only when it moved more than
    its threshold relative to that prediction. The states name their frame
    (:class:`FrameAnchor`), as do a new keyframe's state and the points of
    :class:`MapPointUpdateCoded`."""

    agent_id: str
    map_id: int
    states: bytes


@message(0x0407)
class MapPointUpdateCoded(Message):
    """New or moved map points and new observations of one robot map: :func:`encode_points`."""

    agent_id: str
    map_id: int
    points: bytes


STATE_VERSION = 2
"""2: an optional :class:`FrameAnchor` follows the rows (1, without one, still decodes)."""
POINTS_VERSION = 2
"""2: an optional :class:`FrameAnchor` follows the observation rows (1 still decodes)."""
POINT_IDS_VERSION = 1
POSITION_STEP_M = 1e-3
"""Map point positions travel on a 1 mm grid in the robot map's frame (error <= 0.5 mm per
axis); the keyframe states as float32."""
MAX_ITEMS = 1 << 22
"""Largest count of keyframes, points, features or rows one coded payload may declare."""
_STATE_COLS = 16


@dataclass(frozen=True, eq=False)
class FrameAnchor:
    """The frame of a payload's poses and positions, named by a keyframe the cloud has:
    ``T_world_body`` (4, 4) is the edge's pose of ``keyframe_id`` in it. A message may be in
    the frame before a correction the edge has not applied yet; the cloud places it through
    its own pose of the anchor (``services.cloud.fusion.rebase``; COVINS' ``pos_ref`` idea)."""

    keyframe_id: int
    T_world_body: np.ndarray


@dataclass(frozen=True, eq=False)
class KeyframeStates:
    """States of K keyframes: ``keyframe_ids`` (K,) int64, ``T_world_body`` (K, 4, 4),
    ``velocity_world`` (K, 3) m/s, ``bias_gyro`` (K, 3) rad/s, ``bias_accel`` (K, 3) m/s²;
    ``anchor``: their frame (None: the agent's map frame as the cloud has it)."""

    keyframe_ids: np.ndarray
    T_world_body: np.ndarray
    velocity_world: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    anchor: FrameAnchor | None = None

    def __len__(self) -> int:
        return int(self.keyframe_ids.shape[0])


@dataclass(frozen=True, eq=False)
class PointBatch:
    """Map points of one message: ``ids`` (P,) int64 ascending, ``p_world`` (P, 3) m and the
    observation rows ``observations`` (R, 3) int64 ``[point id, keyframe id, feature index]``
    sorted by keyframe id and feature index (every row's point is in ``ids``); ``anchor``:
    the frame of ``p_world`` (see :class:`KeyframeStates`)."""

    ids: np.ndarray
    p_world: np.ndarray
    observations: np.ndarray
    anchor: FrameAnchor | None = None


@contextlib.contextmanager
def _decoding(what: str) -> Iterator[None]:
    """Entropy-decoder failures and impossible values as LinkDecodeError naming ``what``."""
    try:
        yield
    except (CodecError, ValueError, OverflowError) as exc:
        raise LinkDecodeError(f"{what}: {exc}") from exc


def _put_ids(w: BitWriter, ids: np.ndarray) -> None:
    """Distinct ascending non-negative ids: count, first, gaps - 1 (geometric)."""
    w.put_count(len(ids), "id")
    if len(ids):
        w.put_count(int(ids[0]), "id")
        put_scaled_geometric(w, np.diff(ids) - 1, "id")


def _get_ids(r: BitReader, what: str) -> np.ndarray:
    n = r.get_count(MAX_ITEMS)
    if n == 0:
        return np.zeros(0, np.int64)
    first = r.get_count(2**62)
    ids = first + np.concatenate([[0], np.cumsum(get_scaled_geometric(r, n - 1) + 1)])
    if ids[-1] >= 2**62:
        raise LinkDecodeError(f"{what}: id out of range")
    return ids.astype(np.int64)


def _put_anchor(w: BitWriter, anchor: FrameAnchor | None) -> None:
    """A flag, then the anchor's keyframe id and its pose as 7 float32 (position, wxyz)."""
    w.put_count(0 if anchor is None else 1, "anchor")
    if anchor is not None:
        if anchor.keyframe_id < 0:
            raise ValueError("anchor keyframe id must be >= 0")
        T = np.asarray(anchor.T_world_body, np.float64).reshape(4, 4)
        if not np.all(np.isfinite(T)):
            raise ValueError("anchor pose is not finite")
        row = np.concatenate([T[:3, 3], R_to_quat_wxyz(T[None, :3, :3]).reshape(4)])
        w.put_count(int(anchor.keyframe_id), "anchor")
        w.put_raw(np.ascontiguousarray(row, "<f4").view("<u4").astype(np.uint64), 32, "anchor")


def _get_anchor(r: BitReader, what: str) -> FrameAnchor | None:
    flag = r.get_count(1)
    if not flag:
        return None
    kf_id = r.get_count(2**62)
    row = r.get_raw(7, 32).astype("<u4").view("<f4").astype(np.float64)
    if not np.all(np.isfinite(row)):
        raise LinkDecodeError(f"{what}: non-finite anchor pose")
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_R(row[None, 3:7])[0]
    T[:3, 3] = row[:3]
    return FrameAnchor(int(kf_id), T)


def encode_states(states: KeyframeStates) -> bytes:
    """Keyframe ids (ascending gaps, geometric), then per keyframe 16 float32: position (3),
    rotation as a unit quaternion wxyz (4), velocity (3), gyro bias (3), accel bias (3).

    Precision: float32 (position ~1 µm at 10 m, rotation ~1e-7 rad, velocity and biases 7
    significant digits); the decoder re-normalises the quaternion, so rotations stay exact
    rotations."""
    ids = np.asarray(states.keyframe_ids, np.int64).reshape(-1)
    order = np.argsort(ids, kind="stable")
    ids = ids[order]
    if len(ids) and (ids[0] < 0 or np.any(np.diff(ids) <= 0)):
        raise ValueError("keyframe ids must be distinct and >= 0")
    T = np.asarray(states.T_world_body, np.float64).reshape(-1, 4, 4)[order]
    cols = [
        T[:, :3, 3],
        R_to_quat_wxyz(T[:, :3, :3]).reshape(-1, 4),
        np.asarray(states.velocity_world, np.float64).reshape(-1, 3)[order],
        np.asarray(states.bias_gyro, np.float64).reshape(-1, 3)[order],
        np.asarray(states.bias_accel, np.float64).reshape(-1, 3)[order],
    ]
    rows = np.ascontiguousarray(np.concatenate(cols, axis=1), "<f4")
    w = BitWriter()
    _put_ids(w, ids)
    w.put_raw(rows.view("<u4").astype(np.uint64), 32, "state")
    _put_anchor(w, states.anchor)
    return seal(STATE_VERSION, w)


def decode_states(data: bytes, what: str = "keyframe states") -> KeyframeStates:
    """Inverse of :func:`encode_states`; LinkDecodeError on bad input."""
    r = open_sealed(data, (1, STATE_VERSION), what)
    with _decoding(what):
        ids = _get_ids(r, what)
        raw = r.get_raw(len(ids) * _STATE_COLS, 32).astype("<u4")
        anchor = _get_anchor(r, what) if data[0] >= 2 else None
    rows = raw.view("<f4").astype(np.float64).reshape(-1, _STATE_COLS)
    if not np.all(np.isfinite(rows)):
        raise LinkDecodeError(f"{what}: non-finite values")
    with _decoding(what):
        R = quat_wxyz_to_R(rows[:, 3:7]) if len(rows) else np.zeros((0, 3, 3))
    T = np.zeros((len(ids), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = rows[:, :3]
    T[:, 3, 3] = 1.0
    return KeyframeStates(ids, T, rows[:, 7:10], rows[:, 10:13], rows[:, 13:16], anchor)


def encode_point_ids(map_point_ids: np.ndarray) -> bytes:
    """The map point of each of N features (-1: none): N, a has-point flag per feature
    (adaptive binary), then the ids of the features that have one, as signed differences to
    the previous such id (Laplace of a chosen scale)."""
    ids = np.asarray(map_point_ids, np.int64).reshape(-1)
    if np.any(ids < -1):
        raise ValueError("map point ids must be >= -1")
    has = ids >= 0
    w = BitWriter()
    w.put_count(len(ids), "side")
    _put_flags(w, has)
    v = ids[has]
    if len(v):
        w.put_count(int(v[0]), "id")
        put_scaled_signed(w, np.diff(v), "id")
    return seal(POINT_IDS_VERSION, w)


def decode_point_ids(data: bytes, what: str = "map point ids") -> np.ndarray:
    """Inverse of :func:`encode_point_ids`: (N,) int64, -1 where a feature has no point."""
    r = open_sealed(data, POINT_IDS_VERSION, what)
    with _decoding(what):
        n = r.get_count(MAX_ITEMS)
        has = _get_flags(r, n)
        out = np.full(n, -1, np.int64)
        k = int(has.sum())
        if k:
            first = r.get_count(2**62)
            out[has] = first + np.concatenate([[0], np.cumsum(get_scaled_signed(r, k - 1))])
    if np.any(out < -1):
        raise LinkDecodeError(f"{what}: negative map point id")
    return out


def _put_flags(w: BitWriter, flags: np.ndarray) -> None:
    """Binary flags with one probability (its count of ones sent first)."""
    ones = int(flags.sum())
    w.put_count(ones, "side")
    if 0 < ones < len(flags):
        p = np.full(len(flags), ones / len(flags))
        w.put_bernoulli(flags.astype(np.int32), np.clip(p, 1e-6, 1 - 1e-6), "flags")


def _get_flags(r: BitReader, n: int) -> np.ndarray:
    ones = r.get_count(n)
    if ones in (0, n):
        return np.full(n, ones == n, bool)
    p = np.clip(np.full(n, ones / n), 1e-6, 1 - 1e-6)
    flags = r.get_bernoulli(p).astype(bool)
    if int(flags.sum()) != ones:
        raise ValueError(f"{int(flags.sum())} flags set, {ones} declared")
    return flags


def encode_points(batch: PointBatch) -> bytes:
    """Points and observation rows (see :class:`PointBatch`; the arrays are sorted here).

    Layout: point ids (count, first, gaps); positions on the :data:`POSITION_STEP_M` grid, per
    axis as differences to the axis median (Laplace of a chosen scale); rows grouped by
    keyframe: the distinct keyframe ids (as point ids), rows per keyframe (geometric), feature
    index gaps within a keyframe (geometric) and each row's point as an index into the ids
    (uniform)."""
    ids = np.asarray(batch.ids, np.int64).reshape(-1)
    p = np.asarray(batch.p_world, np.float64).reshape(-1, 3)
    obs = np.asarray(batch.observations, np.int64).reshape(-1, 3)
    if len(ids) != len(p) or not np.all(np.isfinite(p)):
        raise ValueError(f"{len(ids)} point ids but {len(p)} positions (or non-finite)")
    order = np.argsort(ids, kind="stable")
    ids, p = ids[order], p[order]
    if len(ids) and (ids[0] < 0 or np.any(np.diff(ids) <= 0)):
        raise ValueError("point ids must be distinct and >= 0")
    obs = obs[np.lexsort((obs[:, 2], obs[:, 1]))]
    point_index = np.searchsorted(ids, obs[:, 0])
    named = point_index < len(ids)
    named[named] = ids[point_index[named]] == obs[named, 0]
    if len(obs) and (not named.all() or obs[:, 1:].min() < 0):
        raise ValueError("observation rows must name points of the batch and indices >= 0")
    w = BitWriter()
    _put_ids(w, ids)
    q = np.floor(p / POSITION_STEP_M + 0.5).astype(np.int64)
    for axis in range(3):
        centre = int(np.median(q[:, axis])) if len(q) else 0
        put_scaled_signed(w, np.array([centre]), "position")
        put_scaled_signed(w, q[:, axis] - centre, "position")
    kf_ids, per_kf = np.unique(obs[:, 1], return_counts=True)
    _put_ids(w, kf_ids)
    put_scaled_geometric(w, per_kf - 1, "rows")
    starts = (np.cumsum(per_kf) - per_kf).astype(np.int64)
    gaps = np.diff(obs[:, 2], prepend=0)
    gaps[starts] = obs[starts, 2]
    if np.any(gaps < 0):
        raise ValueError("duplicate observation rows")
    put_scaled_geometric(w, gaps, "feature")
    w.put_uniform(point_index, max(len(ids), 1), "point")
    _put_anchor(w, batch.anchor)
    return seal(POINTS_VERSION, w)


def decode_points(data: bytes, what: str = "map points") -> PointBatch:
    """Inverse of :func:`encode_points` (positions on the 1 mm grid); LinkDecodeError."""
    r = open_sealed(data, (1, POINTS_VERSION), what)
    with _decoding(what):
        ids = _get_ids(r, what)
        q = np.zeros((len(ids), 3), np.int64)
        for axis in range(3):
            centre = int(get_scaled_signed(r, 1)[0])
            q[:, axis] = centre + get_scaled_signed(r, len(ids))
        kf_ids = _get_ids(r, what)
        per_kf = get_scaled_geometric(r, len(kf_ids)) + 1
        n_rows = int(per_kf.sum())
        if n_rows > MAX_ITEMS:
            raise LinkDecodeError(f"{what}: {n_rows} observation rows exceed {MAX_ITEMS}")
        gaps = get_scaled_geometric(r, n_rows)
        point_index = r.get_uniform(n_rows, max(len(ids), 1))
        anchor = _get_anchor(r, what) if data[0] >= 2 else None
    if n_rows and (len(ids) == 0 or point_index.max() >= len(ids)):
        raise LinkDecodeError(f"{what}: observation names a point outside the batch")
    starts = (np.cumsum(per_kf) - per_kf).astype(np.int64)
    group = np.repeat(np.arange(len(kf_ids)), per_kf)
    feat = np.cumsum(gaps)
    feat -= np.repeat(feat[starts] - gaps[starts], per_kf) if n_rows else 0
    point_ids = ids[point_index] if n_rows else np.zeros(0, np.int64)
    obs = np.stack([point_ids, kf_ids[group], feat], axis=1).astype(np.int64).reshape(-1, 3)
    return PointBatch(ids, q * POSITION_STEP_M, obs, anchor)


@message(0x0502)
class PoseCorrectionCoded(Message):
    """The coded form of :class:`PoseCorrection`: :func:`encode_poses` of the corrected
    keyframes, in the frame of the robot's own map ``map_id``."""

    agent_id: str
    map_id: int
    poses: bytes


POSES_VERSION = 1


def encode_poses(keyframe_ids: np.ndarray, T_world_body: np.ndarray) -> bytes:
    """Keyframe ids (ascending gaps) and per keyframe 7 float32: position (3) and rotation as a
    unit quaternion wxyz (4) (precision as :func:`encode_states`)."""
    ids = np.asarray(keyframe_ids, np.int64).reshape(-1)
    T = np.asarray(T_world_body, np.float64).reshape(-1, 4, 4)
    if len(ids) != len(T):
        raise ValueError(f"{len(ids)} keyframe ids but {len(T)} poses")
    order = np.argsort(ids, kind="stable")
    ids, T = ids[order], T[order]
    if len(ids) and (ids[0] < 0 or np.any(np.diff(ids) <= 0)):
        raise ValueError("keyframe ids must be distinct and >= 0")
    rows = np.concatenate([T[:, :3, 3], R_to_quat_wxyz(T[:, :3, :3]).reshape(-1, 4)], axis=1)
    w = BitWriter()
    _put_ids(w, ids)
    w.put_raw(np.ascontiguousarray(rows, "<f4").view("<u4").astype(np.uint64), 32, "pose")
    return seal(POSES_VERSION, w)


def decode_poses(data: bytes, what: str = "poses") -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`encode_poses`: (ids (N,) ascending, T_world_body (N, 4, 4))."""
    r = open_sealed(data, POSES_VERSION, what)
    with _decoding(what):
        ids = _get_ids(r, what)
        rows = r.get_raw(len(ids) * 7, 32).astype("<u4").view("<f4").astype(np.float64)
    rows = rows.reshape(-1, 7)
    if not np.all(np.isfinite(rows)):
        raise LinkDecodeError(f"{what}: non-finite values")
    T = np.tile(np.eye(4), (len(ids), 1, 1))
    with _decoding(what):
        if len(ids):
            T[:, :3, :3] = quat_wxyz_to_R(rows[:, 3:7])
    T[:, :3, 3] = rows[:, :3]
    return ids, T


def encode_pose_correction(
    agent_id: str,
    map_id: int,
    keyframe_ids: np.ndarray,
    T_world_body: np.ndarray,
    coded: bool = True,
) -> PoseCorrection | PoseCorrectionCoded:
    """Corrected poses ``T_world_body`` (N, 4, 4) (robot's own map frame) of ``keyframe_ids``
    (N,): coded, or the schema-1 float64 message (``coded=False``, the raw wire)."""
    ids = np.asarray(keyframe_ids, np.int64).reshape(-1)
    T = np.asarray(T_world_body, np.float64).reshape(ids.shape[0], 4, 4)
    if coded:
        return PoseCorrectionCoded(agent_id, int(map_id), encode_poses(ids, T))
    return PoseCorrection(agent_id, int(map_id), pack_array(ids, "<i8"), pack_array(T, "<f8"))


def decode_pose_correction(
    msg: PoseCorrection | PoseCorrectionCoded,
) -> tuple[np.ndarray, np.ndarray]:
    """(keyframe ids (N,), T_world_body (N, 4, 4)) of either form; RemoteProtocolError."""
    what = f"{type(msg).__name__} of {msg.agent_id}"
    if isinstance(msg, PoseCorrectionCoded):
        return decode_poses(msg.poses, what)
    ids = unpack_array(msg.keyframe_ids, "<i8", (), f"{what}: keyframe_ids")
    T = unpack_array(msg.T_world_body, "<f8", (4, 4), f"{what}: T_world_body")
    if T.shape[0] != ids.shape[0]:
        raise LinkDecodeError(f"{what}: {ids.shape[0]} ids but {T.shape[0]} poses")
    if not np.all(np.isfinite(T)):
        raise LinkDecodeError(f"{what}: non-finite poses")
    return ids, T
