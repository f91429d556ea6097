"""The edge <-> cloud link: its wire messages (type ids 0x04xx edge -> cloud, 0x05xx cloud ->
edge) and their encoders and decoders, used by both ends and by every test, benchmark and
replay. The coded messages' payloads (keyframe states, map point ids, map points, poses) are
coded by :mod:`common.links.edge_cloud_payloads`."""

from __future__ import annotations

import numpy as np

from common.geometry import R_to_quat_wxyz, quat_wxyz_to_R
from common.links.body import LinkDecodeError
from common.links.edge_cloud_payloads import decode_poses, encode_poses
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

    ``state``: :func:`~.edge_cloud_payloads.encode_states` of this one keyframe (pose,
    velocity, biases).
    ``features``: the keyframe coded *intra* by ``common.codec.frames`` (as KeyframeUpdate).
    ``map_point_ids``: :func:`~.edge_cloud_payloads.encode_point_ids`, the map point of each
    feature, coded order.
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
    """New states of keyframes the cloud already has (one robot map):
    :func:`~.edge_cloud_payloads.encode_states`.

    The cloud moves each map point whose reference keyframe moved with it
    (``p' = T'_ref T_ref^-1 p``), so the edge re-sends a point only when it moved more than
    its threshold relative to that prediction. The states name their frame
    (:class:`~.edge_cloud_payloads.FrameAnchor`), as do a new keyframe's state and the points
    of :class:`MapPointUpdateCoded`."""

    agent_id: str
    map_id: int
    states: bytes


@message(0x0407)
class MapPointUpdateCoded(Message):
    """New or moved map points and new observations of one robot map:
    :func:`~.edge_cloud_payloads.encode_points`."""

    agent_id: str
    map_id: int
    points: bytes


@message(0x0502)
class PoseCorrectionCoded(Message):
    """The coded form of :class:`PoseCorrection`: :func:`~.edge_cloud_payloads.encode_poses` of
    the corrected keyframes, in the frame of the robot's own map ``map_id``."""

    agent_id: str
    map_id: int
    poses: bytes


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
