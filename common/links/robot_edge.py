"""The robot <-> edge link: its wire messages (type ids 0x02xx robot -> edge, 0x03xx edge ->
robot) and their encoders and decoders, used by both ends and by every test and benchmark."""

from __future__ import annotations

from common.protocol.messages import Message, message

# ------------------------------------------------------------------------- robot -> edge
# Array fields are raw little-endian bytes (see ``common.protocol.arrays``); the dtype and
# row shape of each are stated in the docstring: "<f8 (N,3)" = float64 rows of 3.


@message(0x0201)
class RobotFrame(Message):
    """One camera frame of a robot, coded (the robot never sends images).

    ``features``: the feature codec's payload (``common.codec.frames``; keyframe or
    non-keyframe, stateful per robot, in frame order). ``imu``: the IMU samples since the
    previous frame, coded by ``common.codec.imu`` (stateful, in order). ``frame_index`` counts
    frames of this robot's sequence from 0; ``timestamp_ns`` is the camera time.
    """

    frame_index: int
    timestamp_ns: int
    keyframe: bool
    features: bytes
    imu: bytes


@message(0x0202)
class RobotSequenceEnd(Message):
    """The robot has sent its last frame (``frames`` frames in all)."""

    frames: int


# ------------------------------------------------------------------------- edge -> robot
@message(0x0301)
class InertialFeedback(Message):
    """Refined inertial state for the robot's IMU-assisted prediction (after VI init).

    ``T_world_body``: "<f8 (4,4)" pose of the body (IMU) at ``timestamp_ns`` in the edge's
    map; ``velocity_world`` "<f8 (3)" m/s; ``bias_gyro`` "<f8 (3)" rad/s; ``bias_accel``
    "<f8 (3)" m/s^2; ``gravity_world`` "<f8 (3)" m/s^2. ``track_ids`` "<i8 (N)" and
    ``p_world`` "<f8 (N,3)": map points of the robot's live tracks (may be empty).
    """

    timestamp_ns: int
    map_id: int
    T_world_body: bytes
    velocity_world: bytes
    bias_gyro: bytes
    bias_accel: bytes
    gravity_world: bytes
    track_ids: bytes
    p_world: bytes
