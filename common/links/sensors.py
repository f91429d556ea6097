"""A robot's sensor description as both links carry it (robot -> edge at join, edge -> cloud
before the robot's first keyframe): one encoder, one decoder, one equality.

Layout of :func:`encode_sensors` (little endian, float64 throughout: it is sent once, so it
is exact rather than small)::

    u8  version (SENSORS_VERSION)
    u8  n, then n bytes: the camera model name (ASCII, CameraCalibration.model)
    u32 width, u32 height                              [px]
    f8  fx, fy, cx, cy                                  [px]
    u8  k, then k f8: the model's distortion coefficients, in CAMERA_MODELS order
    f8  camera rate_hz
    16 f8 T_body_cam, row major
    f8  gyro_noise_density, gyro_random_walk, accel_noise_density, accel_random_walk, imu rate_hz
    16 f8 T_body_imu, row major
    u32 CRC-32 of everything before it

Decoding checks the length, the CRC, the version, that every number is finite, that the
calibration is one a camera can have (``CameraCalibration``'s own checks:
:class:`~common.calibration.CalibrationError`), that rates and noise densities are positive
and that both transforms are rigid. Every failure is a :class:`SensorsDecodeError`, a
:class:`~common.protocol.errors.RemoteProtocolError` blamed on the sender.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

import numpy as np

from common.calibration import CalibrationError, CameraCalibration, ImuCalibration
from common.geometry import rigid_problem
from common.protocol.errors import RemoteProtocolError

SENSORS_VERSION = 1
"""Version byte of an encoded sensor description."""
RIGID_TOLERANCE = 1e-6
"""Largest deviation of ``R.T @ R`` from the identity (and of ``det R`` from 1) accepted in a
transform, and of its last row from ``[0, 0, 0, 1]``."""

_U8 = struct.Struct("<B")
_SIZE = struct.Struct("<II")
_F8 = struct.Struct("<d")
_CRC = struct.Struct("<I")
_MAX_MODEL_NAME = 32


class SensorsDecodeError(RemoteProtocolError):
    """A sensor description that does not decode or cannot describe a real robot."""


@dataclass(frozen=True, eq=False)
class Sensors:
    """What a robot carries: its camera (cam0) and IMU calibrations (``common.calibration``)."""

    camera: CameraCalibration
    imu: ImuCalibration

    def same_as(self, other: Sensors) -> bool:
        """True when both describe the very same sensors (bit-exact numbers)."""
        return encode_sensors(self) == encode_sensors(other)

    def summary(self) -> str:
        """One line for logs and refusal reasons."""
        c = self.camera
        return (
            f"{c.model} {c.width}x{c.height} fx={c.fx:.6g} fy={c.fy:.6g} cx={c.cx:.6g} "
            f"cy={c.cy:.6g} @ {c.rate_hz:g} Hz, IMU @ {self.imu.rate_hz:g} Hz"
        )


def encode_sensors(sensors: Sensors) -> bytes:
    """The description of ``sensors`` (see the module docstring for the layout)."""
    c, imu = sensors.camera, sensors.imu
    name = c.model.encode("ascii")
    parts = [
        _U8.pack(SENSORS_VERSION),
        _U8.pack(len(name)),
        name,
        _SIZE.pack(int(c.width), int(c.height)),
        _f8s([c.fx, c.fy, c.cx, c.cy]),
        _U8.pack(len(c.distortion)),
        _f8s(c.distortion),
        _f8s([c.rate_hz]),
        _f8s(np.asarray(c.T_body_cam).ravel()),
        _f8s(
            [
                imu.gyro_noise_density,
                imu.gyro_random_walk,
                imu.accel_noise_density,
                imu.accel_random_walk,
                imu.rate_hz,
            ]
        ),
        _f8s(np.asarray(imu.T_body_imu).ravel()),
    ]
    payload = b"".join(parts)
    return payload + _CRC.pack(zlib.crc32(payload))


def decode_sensors(data: bytes, what: str = "sensors") -> Sensors:
    """Inverse of :func:`encode_sensors`; SensorsDecodeError naming ``what`` for a description
    that is short, damaged, of another version, or of sensors that cannot exist."""
    data = bytes(data)
    if len(data) < 1 + _CRC.size:
        raise SensorsDecodeError(f"{what}: {len(data)} bytes is too short")
    (crc,) = _CRC.unpack_from(data, len(data) - _CRC.size)
    body = data[: -_CRC.size]
    if zlib.crc32(body) != crc:
        raise SensorsDecodeError(f"{what}: checksum mismatch (corrupt or truncated)")
    if body[0] != SENSORS_VERSION:
        raise SensorsDecodeError(f"{what}: version {body[0]}, expected {SENSORS_VERSION}")
    r = _Reader(body, 1, what)
    n = r.u8()
    if not 0 < n <= _MAX_MODEL_NAME:
        raise SensorsDecodeError(f"{what}: camera model name of {n} bytes")
    try:
        model = r.take(n).decode("ascii")
    except UnicodeDecodeError:
        raise SensorsDecodeError(f"{what}: camera model name is not ASCII") from None
    width, height = _SIZE.unpack(r.take(_SIZE.size))
    fx, fy, cx, cy = r.f8(4)
    distortion = r.f8(r.u8())
    (cam_rate,) = r.f8(1)
    T_body_cam = np.array(r.f8(16)).reshape(4, 4)
    g_nd, g_rw, a_nd, a_rw, imu_rate = r.f8(5)
    T_body_imu = np.array(r.f8(16)).reshape(4, 4)
    if r.pos != len(body):
        raise SensorsDecodeError(f"{what}: {len(body) - r.pos} trailing bytes")
    numbers = np.array([fx, fy, cx, cy, *distortion, cam_rate, g_nd, g_rw, a_nd, a_rw, imu_rate])
    if not all(np.isfinite(x).all() for x in (numbers, T_body_cam, T_body_imu)):
        raise SensorsDecodeError(f"{what}: non-finite numbers")
    for name, T in (("T_body_cam", T_body_cam), ("T_body_imu", T_body_imu)):
        why = rigid_problem(T, RIGID_TOLERANCE)
        if why:
            raise SensorsDecodeError(f"{what}: {name} is not a rigid transform ({why})")
    if not (cam_rate > 0 and imu_rate > 0):
        raise SensorsDecodeError(f"{what}: rates must be positive ({cam_rate}, {imu_rate} Hz)")
    if min(g_nd, g_rw, a_nd, a_rw) <= 0:
        raise SensorsDecodeError(f"{what}: IMU noise densities and random walks must be > 0")
    try:
        camera = CameraCalibration(
            width=width,
            height=height,
            fx=fx,
            fy=fy,
            cx=cx,
            cy=cy,
            distortion=tuple(distortion),
            T_body_cam=T_body_cam,
            rate_hz=cam_rate,
            model=model,
        )
    except CalibrationError as exc:
        raise SensorsDecodeError(f"{what}: {exc}") from None
    imu = ImuCalibration(g_nd, g_rw, a_nd, a_rw, imu_rate, T_body_imu)
    return Sensors(camera, imu)


def _f8s(values: object) -> bytes:
    v = np.asarray(values, np.float64).ravel()
    return v.astype("<f8").tobytes()


class _Reader:
    def __init__(self, data: bytes, pos: int, what: str) -> None:
        self.data, self.pos, self.what = data, pos, what

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise SensorsDecodeError(f"{self.what}: truncated at byte {self.pos}")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def u8(self) -> int:
        return int(self.take(1)[0])

    def f8(self, n: int) -> list[float]:
        return [float(x) for x in np.frombuffer(self.take(n * _F8.size), "<f8")]
