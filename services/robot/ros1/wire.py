"""The framing between the ROS bridge process and the robot (stdlib only: both ends use it).

A frame is ``<kind: u8><length: u32 LE><payload>``; the payloads (little-endian):

- ``IMU``: ``t_ns: i64``, gyro x y z [rad/s], accel x y z [m/s²] (6 float64);
- ``IMAGE``: ``t_ns: i64``, height, width, step (u32), encoding (u8 length + ASCII), pixels;
- ``POSE``: ``t_ns: i64``, ``map_id: i32``, status (u8, index in :data:`STATUSES`), position
  x y z [m] and quaternion x y z w (7 float64) of ``T_map_body``;
- ``ODOM``: ``t_ns: i64`` of an Odometry message a player's subscriber saw (tests, benchmarks);
- ``READY``: empty, the bridge is connected to the master and its topics;
- ``PLACEMENT``: ``global_map: i32``, ``map_id: i32``, position x y z [m] and quaternion
  x y z w (7 float64) of ``T_global_map``: where the robot's map sits in the cloud's global
  map (sent when it changes).

:class:`FrameReader` is sans-I/O: bytes in, ``(kind, payload)`` out.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

IMU, IMAGE, POSE, ODOM, READY, PLACEMENT = 1, 2, 3, 4, 5, 6
KINDS = (IMU, IMAGE, POSE, ODOM, READY, PLACEMENT)
STATUSES = ("tracking", "initializing", "lost")
MAX_FRAME = 64 * 1024 * 1024
"""Largest payload (a 4K colour image is 25 MB)."""

_HEAD = struct.Struct("<BI")
_IMU = struct.Struct("<q6d")
_IMAGE = struct.Struct("<qIIIB")
_POSE = struct.Struct("<qiB7d")
_ODOM = struct.Struct("<q")
_PLACEMENT = struct.Struct("<ii7d")


class WireError(ValueError):
    """A frame that is not one of ours (the peer is not a bridge of this version)."""


def frame(kind: int, payload: bytes) -> bytes:
    return _HEAD.pack(kind, len(payload)) + payload


def imu(t_ns: int, gyro: tuple[float, float, float], accel: tuple[float, float, float]) -> bytes:
    return frame(IMU, _IMU.pack(int(t_ns), *gyro, *accel))


def image(t_ns: int, height: int, width: int, step: int, encoding: str, data: bytes) -> bytes:
    enc = encoding.encode("ascii")
    return frame(IMAGE, _IMAGE.pack(int(t_ns), height, width, step, len(enc)) + enc + data)


def pose(
    t_ns: int, map_id: int, status: str, p: tuple[float, ...], q_xyzw: tuple[float, ...]
) -> bytes:
    return frame(POSE, _POSE.pack(int(t_ns), map_id, STATUSES.index(status), *p, *q_xyzw))


def placement(
    global_map: int, map_id: int, p: tuple[float, ...], q_xyzw: tuple[float, ...]
) -> bytes:
    return frame(PLACEMENT, _PLACEMENT.pack(int(global_map), int(map_id), *p, *q_xyzw))


def read_placement(payload: bytes) -> tuple[int, int, tuple[float, ...], tuple[float, ...]]:
    """``(global_map, map_id, position, quaternion xyzw)`` of ``T_global_map``."""
    g, m, *v = _PLACEMENT.unpack(payload)
    return g, m, tuple(v[:3]), tuple(v[3:])


def odom(t_ns: int) -> bytes:
    return frame(ODOM, _ODOM.pack(int(t_ns)))


def read_imu(payload: bytes) -> tuple[int, tuple[float, ...], tuple[float, ...]]:
    t, *v = _IMU.unpack(payload)
    return t, tuple(v[:3]), tuple(v[3:])


def read_image(payload: bytes) -> tuple[int, int, int, int, str, bytes]:
    """``(t_ns, height, width, step, encoding, data)``."""
    t, h, w, step, n = _IMAGE.unpack_from(payload)
    start = _IMAGE.size
    enc = payload[start : start + n].decode("ascii", "replace")
    return t, h, w, step, enc, payload[start + n :]


def read_pose(payload: bytes) -> tuple[int, int, str, tuple[float, ...], tuple[float, ...]]:
    """``(t_ns, map_id, status, position, quaternion xyzw)``."""
    t, map_id, status, *v = _POSE.unpack(payload)
    if status >= len(STATUSES):
        raise WireError(f"pose status {status} unknown")
    return t, map_id, STATUSES[status], tuple(v[:3]), tuple(v[3:])


def read_odom(payload: bytes) -> int:
    return int(_ODOM.unpack(payload)[0])


class FrameReader:
    """Bytes in (:meth:`feed`), whole frames out (:meth:`frames`); WireError on a frame
    that cannot be ours."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> None:
        self._buf += data

    def frames(self) -> Iterator[tuple[int, bytes]]:
        while len(self._buf) >= _HEAD.size:
            kind, n = _HEAD.unpack_from(self._buf)
            if kind not in KINDS or n > MAX_FRAME:
                raise WireError(f"frame kind {kind} of {n} bytes is not a bridge frame")
            if len(self._buf) < _HEAD.size + n:
                return
            payload = bytes(self._buf[_HEAD.size : _HEAD.size + n])
            del self._buf[: _HEAD.size + n]
            yield kind, payload
