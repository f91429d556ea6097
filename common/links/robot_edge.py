"""The robot <-> edge link: its wire messages (type ids 0x02xx robot -> edge, 0x03xx edge ->
robot) and their encoders and decoders, used by both ends and by every test and benchmark.

A robot's stream starts with :class:`RobotSensors` (its calibrations, ``common.links.sensors``);
the edge builds that robot's decoders and VIO from it.

Edge -> robot feedback has two wire formats that decode into one :class:`FeedbackContent`
(:func:`decode_feedback`): :class:`InertialFeedback` (0x0301, the raw float64 baseline: every
message carries the whole landmark set) and :class:`InertialFeedbackCoded` (0x0302: float32
state; landmarks as a delta against what the robot already holds, each point as its depth
along the ray of the track's own keypoint in the frame of the state, which both ends have
from the feature stream (:class:`Anchors`); range-coded. ``services.edge.feedback`` keeps the
sender's bookkeeping).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from common.calibration import CameraCalibration
from common.camera import camera_model
from common.codec.entropy import BitReader, BitWriter, best_scale_index, signed_cost
from common.codec.errors import CodecError
from common.links import body
from common.links.sensors import Sensors, decode_sensors, encode_sensors
from common.links.wire import (
    WireFormat,
    pack_finite_pose,
    pack_pose,
    unpack_pose,
    unpack_sent_pose,
)
from common.protocol.arrays import pack_array, unpack_array
from common.protocol.errors import RemoteProtocolError
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


@message(0x0203)
class RobotSensors(Message):
    """The robot's sensors, its first message on every stream (before any ``RobotFrame``):
    ``sensors`` is :func:`common.links.sensors.encode_sensors` of its camera and IMU
    calibrations (versioned, CRC-checked, float64). Build and read it with
    :func:`sensors_message` and :func:`read_sensors`."""

    sensors: bytes


def sensors_message(sensors: Sensors) -> RobotSensors:
    """The join message of a robot with these sensors."""
    return RobotSensors(encode_sensors(sensors))


def read_sensors(msg: RobotSensors) -> Sensors:
    """The sensors a join message describes; SensorsDecodeError (RemoteProtocolError) if the
    description is damaged or describes sensors that cannot exist."""
    return decode_sensors(msg.sensors, "RobotSensors.sensors")


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


@message(0x0303)
class CameraImuOffset(Message):
    """The camera-IMU time offset the edge's VIO estimated for this robot (sent when it
    moves): at one instant the IMU clock reads ``t_imu = t_cam + offset_ns``; ``sigma_ns`` is
    the estimate's standard deviation. The robot reads its frame times on the IMU clock from
    then on: each frame's IMU batch reaches ``t + offset`` and its IMU-assisted prediction
    integrates between the frames' IMU-clock times."""

    offset_ns: int
    sigma_ns: int


POSE_STATUSES = ("tracking", "initializing", "lost")
"""The VIO's state at a frame (``services.edge.vio.TrackingStatus``); ``FramePose.status`` is
its index here (one byte on the wire where the name took nine: the pose goes at camera rate)."""


@message(0x0304)
class FramePose(Message):
    """The robot's pose at one of its frames, as the edge's VIO found it: sent for every
    frame the VIO finished, so that the robot (and whoever it serves) has its own pose.
    Build it with :func:`frame_pose_message`, read it with :func:`pose_status` and
    :func:`decode_pose`.

    ``timestamp_ns``: the frame's camera time; ``map_id``: the edge's map it is in;
    ``status``: the index of the VIO's state in :data:`POSE_STATUSES`; ``pose``: 28 bytes, 7
    little-endian float32, the unit quaternion (w, x, y, z), w >= 0, of ``R_map_body`` and
    ``p_map_body`` m (:func:`encode_pose`), in the frame of the robot's own map as the cloud's
    corrections have moved it; ``b""`` while the VIO has no metric pose (initialising, lost)."""

    timestamp_ns: int
    map_id: int
    status: int
    pose: bytes


def frame_pose_message(timestamp_ns: int, map_id: int, status: str, pose: bytes) -> FramePose:
    """A :class:`FramePose` with ``status`` by name (one of :data:`POSE_STATUSES`;
    ValueError naming it otherwise)."""
    if status not in POSE_STATUSES:
        raise ValueError(f"pose status {status!r} is not one of {POSE_STATUSES}")
    return FramePose(int(timestamp_ns), int(map_id), POSE_STATUSES.index(status), pose)


def pose_status(msg: FramePose) -> str:
    """The name of a :class:`FramePose`'s status; RemoteProtocolError if it has none."""
    if not 0 <= msg.status < len(POSE_STATUSES):
        raise RemoteProtocolError(
            f"FramePose.status {msg.status!r} is not an index of {POSE_STATUSES}"
        )
    return POSE_STATUSES[msg.status]


def encode_pose(T_map_body: np.ndarray) -> bytes:
    """:attr:`FramePose.pose` of a (4, 4) pose (ValueError if it is not finite in float32)."""
    return pack_finite_pose(T_map_body)


def decode_pose(msg: FramePose) -> np.ndarray | None:
    """``T_map_body`` (4, 4) of a :class:`FramePose`, None if it carries none;
    RemoteProtocolError naming the field if the message is malformed."""
    pose_status(msg)
    if not msg.pose:
        return None
    return unpack_sent_pose(msg.pose, "FramePose.pose")


@message(0x0305)
class MapPlacement(Message):
    """Where the robot's map ``map_id`` sits in the cloud's global map ``global_map``: ``pose``
    (:func:`~common.links.wire.pack_pose`, 28 bytes) is ``T_global_map``, so that a
    :class:`FramePose` ``T_map_body`` of that map gives ``T_global_body = T_global_map
    T_map_body`` (ROS' ``map -> odom`` over ``odom -> base_link``). The edge forwards the
    cloud's placement (``edge_cloud.MapPlacement``) when it changes; a robot whose map was
    never placed has only its own map frame."""

    map_id: int
    global_map: int
    pose: bytes


def decode_map_placement(msg: MapPlacement) -> np.ndarray:
    """``T_global_map`` (4, 4) of a :class:`MapPlacement`; RemoteProtocolError if malformed."""
    return unpack_sent_pose(msg.pose, "MapPlacement.pose")


# ------------------------------------------------------------------- edge -> robot, coded
FEEDBACK_VERSION = 2
"""Version byte of the sealed ``InertialFeedbackCoded.landmarks`` payload."""
DEPTH_STEP = 0.005
"""Relative step of the coded depths: ``z = (1 + DEPTH_STEP) ** q`` m, error <= 0.25 %."""
MIN_DEPTH_M = 0.05
MAX_DEPTH_M = 1000.0
"""Camera-frame depths [m] a coded point may have (others are not sendable)."""
MAX_FEEDBACK_POINTS = 1 << 16
"""Most tracks (and most forgotten tracks) one message may carry."""
MAX_TRACK_NUMBER = 1 << 62
"""Largest stream track number a coded message may carry."""
_STATE = struct.Struct("<19f")
_MAX_GAP = (1 << 32) - 1  # track number gaps are geometric-coded with a 32-bit escape
_LOG_STEP = float(np.log1p(DEPTH_STEP))
_Q_MIN = int(np.floor(np.log(MIN_DEPTH_M) / _LOG_STEP))
_Q_MAX = int(np.ceil(np.log(MAX_DEPTH_M) / _LOG_STEP))
_MAX_SHIFT = 12  # low bits of depth offsets sent raw (2**12 > _Q_MAX - _Q_MIN)
_WIDE_LIMIT = 1000  # |high part| kept inside the Laplace tables (+-2047 at most)


@message(0x0302)
class InertialFeedbackCoded(Message):
    """:class:`InertialFeedback` at stated precisions, landmarks as a delta (the coded wire).

    ``state``: 76 bytes, 19 little-endian float32: the unit quaternion (w, x, y, z), w >= 0,
    of ``R_world_body``; ``p_world_body`` m; ``velocity_world`` m/s; ``bias_gyro`` rad/s;
    ``bias_accel`` m/s^2; ``gravity_world`` m/s^2 (float32: relative error <= 6e-8, rotation
    ~1e-7 rad, position <= 4 µm within 64 m of the origin).

    ``landmarks``: ``b""`` when there is nothing to add or forget, else sealed
    (``common.links.body``: version :data:`FEEDBACK_VERSION`, range-coded body, CRC-32):
    ``count M``; the M stream track numbers ascending (the first as a count, then the gaps
    minus one, geometric of a sent scale); their points, each as the depth ``z`` (camera
    frame) of the point on the ray of the track's keypoint at ``timestamp_ns`` (the frame of
    the state; the keypoint both ends have from the feature stream, see :class:`Anchors`):
    ``q = round(ln z / ln(1 + DEPTH_STEP))``, depth error <= 0.25 %, coded as their median
    (Laplace) and the offsets from it (Laplace of a sent scale, or ``q >> k`` and ``k`` raw
    low bits when spread wide). The direction is the robot's own measurement: the VIO
    point's reprojection residual in that frame (typically < 1 px) is not sent. Then
    ``count K`` and the K track numbers the robot should forget, coded like the first list.

    ``reset``: True: the robot's landmark set becomes exactly these tracks (first message to
    the robot, a new map, after a restart of either end); False: the tracks are added or
    replace the robot's points of the same tracks, the forgotten ones are removed, the rest
    is kept.
    """

    timestamp_ns: int
    map_id: int
    reset: bool
    state: bytes
    landmarks: bytes


@dataclass(frozen=True, eq=False)
class Anchors:
    """The robot's tracks in one frame of its feature stream, as both ends have them:
    ``numbers`` (N,) int64 stream track numbers and ``keypoints_px`` (N, 2) their level-0
    distorted keypoints [px] (the robot: what it coded; the edge: what it decoded)."""

    numbers: np.ndarray
    keypoints_px: np.ndarray

    def of(self, numbers: np.ndarray) -> np.ndarray:
        """Keypoints (M, 2) [px] of tracks ``numbers`` (M,); NaN rows for tracks not here."""
        numbers = np.asarray(numbers, np.int64).reshape(-1)
        out = np.full((len(numbers), 2), np.nan)
        if len(self.numbers) and len(numbers):
            order = np.argsort(self.numbers, kind="stable")
            srt = self.numbers[order]
            at = np.searchsorted(srt, numbers).clip(max=len(srt) - 1)
            hit = srt[at] == numbers
            out[hit] = np.asarray(self.keypoints_px, np.float64)[order[at[hit]]]
        return out


@dataclass(frozen=True, eq=False)
class FeedbackContent:
    """What either feedback message says, decoded (:func:`decode_feedback`).

    ``T_world_body`` (4, 4) pose of the body (IMU) at ``timestamp_ns`` in the edge's map
    ``map_id``; ``velocity_world`` (3,) m/s; ``bias_gyro`` (3,) rad/s; ``bias_accel`` (3,)
    m/s^2; ``gravity_world`` (3,) m/s^2. ``track_numbers`` (M,) int64 stream track numbers
    and ``p_world`` (M, 3) m their map points (world frame; NaN rows: a coded point whose
    keypoint the decoder was not given); ``forget`` (K,) int64 tracks whose point the robot
    should drop. ``reset``: the tracks replace the robot's whole set (else they are merged
    into it). ``keypoints_px`` (M, 2) or None: each track's keypoint at ``timestamp_ns``, the
    anchor of its coded point (needed to encode points on the coded wire).
    """

    timestamp_ns: int
    map_id: int
    T_world_body: np.ndarray
    velocity_world: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    gravity_world: np.ndarray
    reset: bool = True
    track_numbers: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    p_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    forget: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    keypoints_px: np.ndarray | None = None


def encode_feedback(
    content: FeedbackContent, wire: WireFormat, camera: CameraCalibration | None = None
) -> InertialFeedback | InertialFeedbackCoded:
    """``content`` as the message of ``wire``.

    RAW: the schema-1 :class:`InertialFeedback`, float64 arrays as given (its receiver
    replaces its set when tracks are present, so ``content`` must carry all of them and
    forget nothing). CODED: :class:`InertialFeedbackCoded`; points need ``camera`` (the
    robot's cam0) and ``content.keypoints_px``, and must pass :func:`points_sendable`.
    Raises ValueError for content a wire cannot carry.
    """
    if wire is WireFormat.RAW:
        if len(content.forget) or not content.reset:
            raise ValueError("raw InertialFeedback carries only whole landmark sets")
        return InertialFeedback(
            timestamp_ns=int(content.timestamp_ns),
            map_id=int(content.map_id),
            T_world_body=pack_array(content.T_world_body, "<f8"),
            velocity_world=pack_array(content.velocity_world, "<f8"),
            bias_gyro=pack_array(content.bias_gyro, "<f8"),
            bias_accel=pack_array(content.bias_accel, "<f8"),
            gravity_world=pack_array(content.gravity_world, "<f8"),
            track_ids=pack_array(content.track_numbers, "<i8"),
            p_world=pack_array(content.p_world, "<f8"),
        )
    state = _pack_state(content)
    if content.reset and len(content.forget):
        raise ValueError("a reset forgets nothing: it replaces the whole set")
    numbers = np.asarray(content.track_numbers, np.int64).reshape(-1)
    order = np.argsort(numbers, kind="stable")
    numbers = numbers[order]
    forget = np.sort(np.asarray(content.forget, np.int64).reshape(-1))
    landmarks = b""
    if len(numbers) or len(forget):
        w = BitWriter()
        _put_numbers(w, numbers, "track_numbers")
        if len(numbers):
            if camera is None or content.keypoints_px is None:
                raise ValueError("coded points need the camera and each track's keypoint")
            p = np.asarray(content.p_world, np.float64).reshape(-1, 3)[order]
            uv = np.asarray(content.keypoints_px, np.float64).reshape(-1, 2)[order]
            q = _depth_index(p, state, camera)
            if not points_sendable(p, content.T_world_body, uv, camera).all():
                raise ValueError("a point is not sendable (see points_sendable)")
            mid = int(np.median(q))
            body.put_scaled_signed(w, np.array([mid]), "depth")
            _put_wide(w, q - mid, "depth")
        _put_numbers(w, forget, "forget")
        landmarks = body.seal(FEEDBACK_VERSION, w)
    return InertialFeedbackCoded(
        timestamp_ns=int(content.timestamp_ns),
        map_id=int(content.map_id),
        reset=bool(content.reset),
        state=state,
        landmarks=landmarks,
    )


def points_sendable(
    p_world: np.ndarray,
    T_world_body: np.ndarray,
    keypoints_px: np.ndarray,
    camera: CameraCalibration,
) -> np.ndarray:
    """Mask (M,) of the points (M, 3) [m] the coded message can carry at pose ``T_world_body``
    (4, 4): finite, with a finite keypoint (M, 2) [px], a camera-frame depth in
    [:data:`MIN_DEPTH_M`, :data:`MAX_DEPTH_M`]."""
    p = np.asarray(p_world, np.float64).reshape(-1, 3)
    uv = np.asarray(keypoints_px, np.float64).reshape(-1, 2)
    ok = np.isfinite(p).all(axis=1) & np.isfinite(uv).all(axis=1)
    z = np.full(len(p), np.nan)
    z[ok] = _depth(p[ok], pack_pose(T_world_body), camera)
    with np.errstate(invalid="ignore"):
        return ok & (z >= MIN_DEPTH_M * (1 + DEPTH_STEP)) & (z <= MAX_DEPTH_M / (1 + DEPTH_STEP))


def coded_points(
    p_world: np.ndarray,
    T_world_body: np.ndarray,
    keypoints_px: np.ndarray,
    camera: CameraCalibration,
) -> np.ndarray:
    """The points (M, 3) [m] the robot decodes for the sendable points ``p_world`` (M, 3) with
    keypoints (M, 2) [px] at pose ``T_world_body`` (4, 4): what the edge remembers as sent."""
    pose = pack_pose(T_world_body)
    q = _depth_index(np.asarray(p_world, np.float64).reshape(-1, 3), pose, camera)
    return _anchored(pose, np.asarray(keypoints_px, np.float64).reshape(-1, 2), q, camera)


def decode_feedback(
    msg: InertialFeedback | InertialFeedbackCoded,
    camera: CameraCalibration | None = None,
    anchors: Anchors | None = None,
) -> FeedbackContent:
    """The content of either feedback message (raw: a reset with all its tracks, or, without
    tracks, an update that changes none). Coded points are rebuilt from ``anchors``, the
    robot's tracks in the frame at ``msg.timestamp_ns``, and ``camera`` (its cam0); without
    them, or for tracks the anchors lack, their rows of ``p_world`` are NaN. Raises
    RemoteProtocolError (the peer's fault) naming the field when a message does not decode."""
    if isinstance(msg, InertialFeedbackCoded):
        return _decode_coded(msg, camera, anchors)
    if not isinstance(msg, InertialFeedback):
        raise TypeError(f"not a feedback message: {type(msg).__name__}")
    T = unpack_array(msg.T_world_body, "<f8", (4, 4), "InertialFeedback.T_world_body")
    vecs = {}
    for name in ("velocity_world", "bias_gyro", "bias_accel", "gravity_world"):
        vecs[name] = unpack_array(getattr(msg, name), "<f8", (3,), f"InertialFeedback.{name}")
    if len(T) != 1:
        raise FeedbackDecodeError(f"InertialFeedback.T_world_body: {len(T)} poses, expected 1")
    for name, v in vecs.items():
        if len(v) != 1:
            raise FeedbackDecodeError(f"InertialFeedback.{name}: {len(v)} rows, expected 1")
    ids = np.zeros(0, np.int64)
    points = np.zeros((0, 3))
    if msg.track_ids or msg.p_world:
        ids = unpack_array(msg.track_ids, "<i8", (), "InertialFeedback.track_ids")
        points = unpack_array(msg.p_world, "<f8", (3,), "InertialFeedback.p_world")
        if len(ids) != len(points):
            raise FeedbackDecodeError(
                f"InertialFeedback.p_world: {len(points)} points for {len(ids)} track ids"
            )
    return FeedbackContent(
        timestamp_ns=msg.timestamp_ns,
        map_id=msg.map_id,
        T_world_body=T[0],
        velocity_world=vecs["velocity_world"][0],
        bias_gyro=vecs["bias_gyro"][0],
        bias_accel=vecs["bias_accel"][0],
        gravity_world=vecs["gravity_world"][0],
        reset=len(ids) > 0,
        track_numbers=ids,
        p_world=points,
    )


class FeedbackDecodeError(RemoteProtocolError):
    """A feedback message from the edge that does not decode (names the field at fault)."""


def _pack_state(c: FeedbackContent) -> bytes:
    vecs = (c.velocity_world, c.bias_gyro, c.bias_accel, c.gravity_world)
    vec = np.concatenate([np.asarray(v, np.float64).reshape(3) for v in vecs])
    out = pack_pose(c.T_world_body) + vec.astype("<f4").tobytes()
    if not np.isfinite(np.frombuffer(out, "<f4")).all():
        raise ValueError("feedback state must be finite (and fit float32)")
    return out


def _depth(p_world: np.ndarray, pose: bytes, camera: CameraCalibration) -> np.ndarray:
    """Camera-frame depths (M,) [m] of points (M, 3) seen from the packed pose."""
    T_wc = unpack_pose(pose) @ camera.T_body_cam
    return (p_world - T_wc[:3, 3]) @ T_wc[:3, 2]


def _depth_index(p_world: np.ndarray, pose: bytes, camera: CameraCalibration) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.round(np.log(_depth(p_world, pose, camera)) / _LOG_STEP).astype(np.int64)


def _anchored(pose: bytes, uv: np.ndarray, q: np.ndarray, camera: CameraCalibration) -> np.ndarray:
    """World points (M, 3) [m] at depth index ``q`` (M,) on the rays of keypoints ``uv``
    (M, 2) [px] from the packed pose (the decoder's reconstruction, shared by the edge)."""
    if not len(q):
        return np.zeros((0, 3))
    xy = camera_model(camera).pixels_to_normalized(uv)
    z = np.exp(np.asarray(q, np.float64) * _LOG_STEP)
    p_cam = np.concatenate([xy * z[:, None], z[:, None]], axis=1)
    T_wc = unpack_pose(pose) @ camera.T_body_cam
    return p_cam @ T_wc[:3, :3].T + T_wc[:3, 3]


def _put_numbers(w: BitWriter, numbers: np.ndarray, part: str) -> None:
    """Strictly increasing numbers (N,) in [0, 2**62]: count, first, gaps minus one (geometric;
    a flag switches to a Laplace model with 64-bit escapes for gaps of 2**32 and more)."""
    if len(numbers) > MAX_FEEDBACK_POINTS:
        raise ValueError(f"{part}: {len(numbers)} tracks, at most {MAX_FEEDBACK_POINTS}")
    w.put_count(len(numbers), part)
    if not len(numbers):
        return
    gaps = np.diff(numbers) - 1
    if numbers[0] < 0 or numbers[-1] > MAX_TRACK_NUMBER or (gaps < 0).any():
        raise ValueError(f"{part}: track numbers must be distinct, in [0, 2**62]")
    w.put_count(int(numbers[0]), part)
    wide = bool((gaps > _MAX_GAP).any())
    w.put_uniform(np.array([int(wide)]), 2, part)
    if wide:
        body.put_scaled_signed(w, gaps, part)
    else:
        body.put_scaled_geometric(w, gaps, part)


def _get_numbers(r: BitReader, field_name: str) -> np.ndarray:
    n = r.get_count(MAX_FEEDBACK_POINTS)
    if not n:
        return np.zeros(0, np.int64)
    first = r.get_count(MAX_TRACK_NUMBER)
    wide = int(r.get_uniform(1, 2)[0])
    gaps = (body.get_scaled_signed if wide else body.get_scaled_geometric)(r, n - 1)
    if (gaps < 0).any() or first + float(gaps.sum(dtype=np.float64)) + n > MAX_TRACK_NUMBER:
        raise FeedbackDecodeError(f"{field_name}: track numbers out of order or beyond 2**62")
    numbers = first + np.concatenate([[0], np.cumsum(gaps + 1)]).astype(np.int64)
    if (numbers > MAX_TRACK_NUMBER).any():
        raise FeedbackDecodeError(f"{field_name}: track number beyond 2**62")
    return numbers


def _put_wide(w: BitWriter, q: np.ndarray, part: str) -> None:
    """Integers (N,) of any spread: ``q >> k`` Laplace-coded (scale sent), the ``k`` low bits
    raw; ``k`` (sent first) is the cheapest that keeps the high part in the Laplace tables."""
    q = np.asarray(q, np.int64)
    best, best_k = np.inf, 0
    mean = float(np.abs(q).mean()) if len(q) else 0.0
    k_lo = int(np.clip(np.floor(np.log2(max(mean, 1.0))) - 7, 0, _MAX_SHIFT))
    for k in range(k_lo, _MAX_SHIFT + 1):  # below k_lo (mean |q >> k| > 128): low bits ~raw
        hi = q >> k
        cost = signed_cost(hi, best_scale_index(hi, signed=True)) + k * len(q)
        if cost < best:
            best, best_k = cost, k
        if np.abs(hi).max(initial=0) < _WIDE_LIMIT:  # more shift only adds raw bits
            break
    w.put_uniform(np.array([best_k]), _MAX_SHIFT + 1, part)
    body.put_scaled_signed(w, q >> best_k, part)
    if best_k:
        w.put_raw((q & ((1 << best_k) - 1)).astype(np.uint64), best_k, part)


def _get_wide(r: BitReader, n: int) -> np.ndarray:
    k = int(r.get_uniform(1, _MAX_SHIFT + 1)[0])
    hi = body.get_scaled_signed(r, n)
    if (np.abs(hi) > _Q_MAX - _Q_MIN).any():  # (keeps the shift below from overflowing)
        raise CodecError(f"a depth beyond [{MIN_DEPTH_M}, {MAX_DEPTH_M:.0f}] m")
    lo = r.get_raw(n, k).astype(np.int64) if k else 0
    return (hi << k) + lo


def _decode_coded(
    msg: InertialFeedbackCoded, camera: CameraCalibration | None, anchors: Anchors | None
) -> FeedbackContent:
    name = "InertialFeedbackCoded"
    if len(msg.state) != _STATE.size:
        raise FeedbackDecodeError(f"{name}.state: {len(msg.state)} bytes, expected {_STATE.size}")
    s32 = np.frombuffer(msg.state, "<f4")
    if not np.isfinite(s32).all():
        raise FeedbackDecodeError(f"{name}.state: non-finite values")
    s = s32.astype(np.float64)
    if abs(np.linalg.norm(s[:4]) - 1.0) > 1e-3:
        raise FeedbackDecodeError(f"{name}.state: the rotation is not a unit quaternion")
    numbers = forget = np.zeros(0, np.int64)
    p = np.zeros((0, 3))
    uv = None
    if msg.landmarks:
        field_name = f"{name}.landmarks"
        r = body.open_sealed(msg.landmarks, FEEDBACK_VERSION, field_name)
        try:
            numbers = _get_numbers(r, f"{field_name} track numbers")
            q = np.zeros(0, np.int64)
            if len(numbers):
                mid = int(body.get_scaled_signed(r, 1)[0])
                q = mid + _get_wide(r, len(numbers))
            forget = _get_numbers(r, f"{field_name} forget")
        except CodecError as exc:
            raise FeedbackDecodeError(f"{field_name}: {exc}") from exc
        if ((q < _Q_MIN) | (q > _Q_MAX)).any():
            raise FeedbackDecodeError(
                f"{field_name}: a depth beyond [{MIN_DEPTH_M}, {MAX_DEPTH_M:.0f}] m"
            )
        if msg.reset and len(forget):
            raise FeedbackDecodeError(f"{field_name}: a reset that forgets tracks")
        if len(np.intersect1d(numbers, forget)):
            raise FeedbackDecodeError(f"{field_name}: a track both sent and forgotten")
        p = np.full((len(numbers), 3), np.nan)
        if camera is not None and anchors is not None and len(numbers):
            uv = anchors.of(numbers)
            ok = np.isfinite(uv).all(axis=1)
            p[ok] = _anchored(msg.state, uv[ok], q[ok], camera)
    return FeedbackContent(
        timestamp_ns=msg.timestamp_ns,
        map_id=msg.map_id,
        T_world_body=unpack_pose(msg.state),
        velocity_world=s[7:10],
        bias_gyro=s[10:13],
        bias_accel=s[13:16],
        gravity_world=s[16:19],
        reset=msg.reset,
        track_numbers=numbers,
        p_world=p,
        forget=forget,
        keypoints_px=uv,
    )
