"""The edge <-> cloud link: its wire messages (type ids 0x04xx edge -> cloud, 0x05xx cloud ->
edge) and their encoders and decoders, used by both ends and by every test, benchmark and
replay."""

from __future__ import annotations

from common.protocol.messages import Message, message


# ------------------------------------------------------------------------- edge -> cloud
@message(0x0401)
class KeyframeUpdate(Message):
    """A new or updated keyframe of one robot's local map.

    ``T_world_body`` "<f8 (4,4)", ``velocity_world``/``bias_gyro``/``bias_accel`` "<f8 (3)".
    ``features``: the keyframe's features coded *intra* by ``common.codec.frames`` (a fresh
    encoder state per keyframe, so the cloud decodes each keyframe on its own; the robot's
    stream is differential against frames the cloud never sees). Empty on a pose-only update.
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
    """

    agent_id: str
    map_id: int
    state: str
    frames: int
    keyframes: int
    timestamp_ns: int
    link_counters: dict[str, int]


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
