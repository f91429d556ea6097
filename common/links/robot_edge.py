"""The robot <-> edge link: its wire messages (type ids 0x02xx robot -> edge, 0x03xx edge ->
robot) and their encoders and decoders, used by both ends and by every test and benchmark.

Edge -> robot feedback has two wire formats that decode into one :class:`FeedbackContent`
(:func:`decode_feedback`): :class:`InertialFeedback` (0x0301, the raw float64 baseline: every
message carries the whole landmark set) and :class:`InertialFeedbackCoded` (0x0302: float32
state, landmarks quantised to :data:`POINT_STEP_M`, range-coded, and sent as a delta against
what the robot already holds; see ``services.edge.feedback`` for the sender's bookkeeping).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from common.codec.entropy import BitReader, BitWriter, best_scale_index, signed_cost
from common.codec.errors import CodecError
from common.geometry import R_to_quat_wxyz, quat_wxyz_to_R
from common.links import WireFormat, body
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


# ------------------------------------------------------------------- edge -> robot, coded
FEEDBACK_VERSION = 1
"""Version byte of the sealed ``InertialFeedbackCoded.landmarks`` payload."""
POINT_STEP_M = 0.002
"""Lattice step of coded map points [m] (relative to the body position): error <= 1 mm per
axis, <= 1.8 mm in norm."""
MAX_POINT_RANGE_M = 1000.0
"""Coded points lie within this distance [m] per axis of the body (farther: not sendable)."""
MAX_FEEDBACK_POINTS = 1 << 16
"""Most tracks (and most forgotten tracks) one message may carry."""
MAX_TRACK_NUMBER = 1 << 62
"""Largest stream track number a coded message may carry."""
_STATE = struct.Struct("<19f")
_MAX_GAP = (1 << 32) - 1  # track number gaps are geometric-coded with a 32-bit escape
_MAX_Q = int(MAX_POINT_RANGE_M / POINT_STEP_M)
_MAX_SHIFT = 20  # low bits of lattice indices sent raw (2**20 steps > 2 MAX_POINT_RANGE_M)
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
    minus one, geometric of a sent scale); their points as lattice indices
    ``round((p_world - p_ref) / POINT_STEP_M)`` per axis, ``p_ref`` the float32 body position
    of ``state``: error <= 1 mm per axis (per axis: a shift ``k``, ``index >> k`` Laplace of a
    sent scale, the ``k`` low bits raw; ``k`` > 0 only for points spread over metres); then
    ``count K`` and the K track numbers the robot should forget (their point was culled or
    replaced by none), coded like the first list.

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
class FeedbackContent:
    """What either feedback message says, decoded (:func:`decode_feedback`).

    ``T_world_body`` (4, 4) pose of the body (IMU) at ``timestamp_ns`` in the edge's map
    ``map_id``; ``velocity_world`` (3,) m/s; ``bias_gyro`` (3,) rad/s; ``bias_accel`` (3,)
    m/s^2; ``gravity_world`` (3,) m/s^2. ``track_numbers`` (M,) int64 stream track numbers
    and ``p_world`` (M, 3) m their map points (world frame); ``forget`` (K,) int64 tracks
    whose point the robot should drop. ``reset``: the tracks replace the robot's whole set
    (else they are merged into it).
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


def encode_feedback(
    content: FeedbackContent, wire: WireFormat
) -> InertialFeedback | InertialFeedbackCoded:
    """``content`` as the message of ``wire``.

    RAW: the schema-1 :class:`InertialFeedback`, float64 arrays as given (its receiver
    replaces its set when tracks are present, so ``content`` must carry all of them and
    forget nothing). CODED: :class:`InertialFeedbackCoded` (tracks sorted by number; points
    must pass :func:`points_sendable`). Raises ValueError for content a wire cannot carry.
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
    p = np.asarray(content.p_world, np.float64).reshape(-1, 3)[order]
    forget = np.sort(np.asarray(content.forget, np.int64).reshape(-1))
    landmarks = b""
    if len(numbers) or len(forget):
        w = BitWriter()
        _put_numbers(w, numbers, "track_numbers")
        if len(numbers):
            q = _lattice(p, _reference(state))
            for axis in range(3):
                _put_lattice(w, q[:, axis], "points")
        _put_numbers(w, forget, "forget")
        landmarks = body.seal(FEEDBACK_VERSION, w)
    return InertialFeedbackCoded(
        timestamp_ns=int(content.timestamp_ns),
        map_id=int(content.map_id),
        reset=bool(content.reset),
        state=state,
        landmarks=landmarks,
    )


def points_sendable(p_world: np.ndarray, T_world_body: np.ndarray) -> np.ndarray:
    """Mask (M,) of the points (M, 3) the coded message can carry: finite and within
    :data:`MAX_POINT_RANGE_M` per axis of the body position of ``T_world_body`` (4, 4)."""
    p = np.asarray(p_world, np.float64).reshape(-1, 3)
    d = p - _reference_of(T_world_body)
    with np.errstate(invalid="ignore"):
        return np.isfinite(p).all(axis=1) & (np.abs(d) < MAX_POINT_RANGE_M - 1.0).all(axis=1)


def coded_points(p_world: np.ndarray, T_world_body: np.ndarray) -> np.ndarray:
    """The points (M, 3) [m] the robot decodes from a coded message at pose ``T_world_body``
    (4, 4) for the sendable points ``p_world`` (M, 3): what the edge should remember as sent."""
    ref = _reference_of(T_world_body)
    return ref + _lattice(np.asarray(p_world, np.float64).reshape(-1, 3), ref) * POINT_STEP_M


def decode_feedback(msg: InertialFeedback | InertialFeedbackCoded) -> FeedbackContent:
    """The content of either feedback message (raw: a reset with all its tracks, or, without
    tracks, an update that changes none). Raises RemoteProtocolError (the peer's fault)
    naming the field when a message does not decode."""
    if isinstance(msg, InertialFeedbackCoded):
        return _decode_coded(msg)
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


def _pack_state_pose(T_world_body: np.ndarray) -> bytes:
    T = np.asarray(T_world_body, np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_world_body must be (4, 4), got {T.shape}")
    q = R_to_quat_wxyz(T[:3, :3])
    return np.concatenate([q, T[:3, 3]]).astype("<f4").tobytes()


def _pack_state(c: FeedbackContent) -> bytes:
    vecs = (c.velocity_world, c.bias_gyro, c.bias_accel, c.gravity_world)
    vec = np.concatenate([np.asarray(v, np.float64).reshape(3) for v in vecs])
    out = _pack_state_pose(c.T_world_body) + vec.astype("<f4").tobytes()
    if not np.isfinite(np.frombuffer(out, "<f4")).all():
        raise ValueError("feedback state must be finite (and fit float32)")
    return out


def _reference(state: bytes) -> np.ndarray:
    """``p_ref`` (3,) [m]: the float32 body position of a packed state, as float64."""
    return np.frombuffer(state[16:28], "<f4").astype(np.float64)


def _reference_of(T_world_body: np.ndarray) -> np.ndarray:
    """``p_ref`` (3,) of a pose (4, 4): what :func:`_reference` reads from its packed state."""
    return np.asarray(T_world_body, np.float64)[:3, 3].astype("<f4").astype(np.float64)


def _lattice(p: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.round((p - ref) / POINT_STEP_M).astype(np.int64)


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
    if (gaps < 0).any() or (gaps > MAX_TRACK_NUMBER).any():
        raise FeedbackDecodeError(f"{field_name}: track numbers out of order or beyond 2**62")
    numbers = first + np.concatenate([[0], np.cumsum(gaps + 1)]).astype(np.int64)
    if (numbers > MAX_TRACK_NUMBER).any():
        raise FeedbackDecodeError(f"{field_name}: track number beyond 2**62")
    return numbers


def _put_lattice(w: BitWriter, q: np.ndarray, part: str) -> None:
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


def _get_lattice(r: BitReader, n: int) -> np.ndarray:
    k = int(r.get_uniform(1, _MAX_SHIFT + 1)[0])
    hi = body.get_scaled_signed(r, n)
    if (np.abs(hi) > _MAX_Q).any():  # (keeps the shift below from overflowing)
        raise CodecError(f"a point beyond {MAX_POINT_RANGE_M:.0f} m")
    lo = r.get_raw(n, k).astype(np.int64) if k else 0
    return (hi << k) + lo


def _decode_coded(msg: InertialFeedbackCoded) -> FeedbackContent:
    name = "InertialFeedbackCoded"
    if len(msg.state) != _STATE.size:
        raise FeedbackDecodeError(f"{name}.state: {len(msg.state)} bytes, expected {_STATE.size}")
    s32 = np.frombuffer(msg.state, "<f4")
    if not np.isfinite(s32).all():
        raise FeedbackDecodeError(f"{name}.state: non-finite values")
    s = s32.astype(np.float64)
    if abs(np.linalg.norm(s[:4]) - 1.0) > 1e-3:
        raise FeedbackDecodeError(f"{name}.state: the rotation is not a unit quaternion")
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_R(s[:4])
    T[:3, 3] = s[4:7]
    numbers = forget = np.zeros(0, np.int64)
    p = np.zeros((0, 3))
    if msg.landmarks:
        field_name = f"{name}.landmarks"
        r = body.open_sealed(msg.landmarks, FEEDBACK_VERSION, field_name)
        try:
            numbers = _get_numbers(r, f"{field_name} track numbers")
            q = np.zeros((len(numbers), 3), np.int64)
            if len(numbers):
                for axis in range(3):
                    q[:, axis] = _get_lattice(r, len(numbers))
            forget = _get_numbers(r, f"{field_name} forget")
        except CodecError as exc:
            raise FeedbackDecodeError(f"{field_name}: {exc}") from exc
        if (np.abs(q) > _MAX_Q).any():
            raise FeedbackDecodeError(f"{field_name}: a point beyond {MAX_POINT_RANGE_M:.0f} m")
        if msg.reset and len(forget):
            raise FeedbackDecodeError(f"{field_name}: a reset that forgets tracks")
        if len(np.intersect1d(numbers, forget)):
            raise FeedbackDecodeError(f"{field_name}: a track both sent and forgotten")
        p = _reference(msg.state) + q * POINT_STEP_M
    return FeedbackContent(
        timestamp_ns=msg.timestamp_ns,
        map_id=msg.map_id,
        T_world_body=T,
        velocity_world=s[7:10],
        bias_gyro=s[10:13],
        bias_accel=s[13:16],
        gravity_world=s[16:19],
        reset=msg.reset,
        track_numbers=numbers,
        p_world=p,
        forget=forget,
    )
