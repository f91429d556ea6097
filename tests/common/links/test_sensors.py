"""The sensor description both links carry: exact round trip, every damage a protocol error."""

from __future__ import annotations

import dataclasses
import struct
import zlib

import numpy as np
import pytest

from common.calibration import EUROC_IMU, CameraCalibration, ImuCalibration
from common.geometry import make_T
from common.links.edge_cloud import AgentSensors, agent_sensors_message, read_agent_sensors
from common.links.robot_edge import RobotSensors, read_sensors, sensors_message
from common.links.sensors import (
    SENSORS_VERSION,
    Sensors,
    SensorsDecodeError,
    decode_sensors,
    encode_sensors,
)
from common.protocol import RemoteProtocolError
from common.protocol.messages import decode_payload, encode_payload
from sim.cloud import default_camera


def _rot(rx: float, rz: float) -> np.ndarray:
    cx, sx, cz, sz = np.cos(rx), np.sin(rx), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Rx


def _sensors() -> Sensors:
    cam = CameraCalibration(
        width=640,
        height=480,
        fx=401.123456789012,
        fy=399.98765432101,
        cx=319.3141592653589,
        cy=241.2718281828459,
        distortion=(-0.2834, 0.0739, 1.9e-4, 1.76e-5),
        T_body_cam=make_T(_rot(0.1, -1.2), np.array([0.0216, -0.0647, 0.0098])),
        rate_hz=30.0,
    )
    imu = ImuCalibration(1.7e-4, 1.9e-5, 2.0e-3, 3.0e-3, 400.0, make_T(_rot(0.01, 0.02), [0, 0, 1]))
    return Sensors(cam, imu)


def _same(a: Sensors, b: Sensors) -> None:
    for f in ("width", "height", "fx", "fy", "cx", "cy", "distortion", "rate_hz", "model"):
        assert getattr(a.camera, f) == getattr(b.camera, f), f
    assert np.array_equal(a.camera.T_body_cam, b.camera.T_body_cam)
    for f in ("gyro_noise_density", "gyro_random_walk", "accel_noise_density"):
        assert getattr(a.imu, f) == getattr(b.imu, f), f
    assert a.imu.accel_random_walk == b.imu.accel_random_walk
    assert a.imu.rate_hz == b.imu.rate_hz
    assert np.array_equal(a.imu.T_body_imu, b.imu.T_body_imu)


@pytest.mark.parametrize("sensors", [_sensors(), Sensors(default_camera(), EUROC_IMU)])
def test_round_trip_is_exact_through_both_links(sensors: Sensors) -> None:
    data = encode_sensors(sensors)
    _same(decode_sensors(data), sensors)
    assert decode_sensors(data).same_as(sensors)
    msg = sensors_message(sensors)
    wire = decode_payload(RobotSensors.TYPE_ID, encode_payload(msg))
    assert isinstance(wire, RobotSensors)
    _same(read_sensors(wire), sensors)
    up = agent_sensors_message("robot-7", sensors)
    wire2 = decode_payload(AgentSensors.TYPE_ID, encode_payload(up))
    assert isinstance(wire2, AgentSensors) and wire2.agent_id == "robot-7"
    _same(read_agent_sensors(wire2), sensors)


def test_equidistant_model_travels_by_name() -> None:
    s = _sensors()
    fish = Sensors(dataclasses.replace(s.camera, model="equidistant"), s.imu)
    back = decode_sensors(encode_sensors(fish))
    assert back.camera.model == "equidistant" and back.same_as(fish)
    assert not back.same_as(s)


def test_a_different_calibration_is_not_the_same() -> None:
    s = _sensors()
    nudged = Sensors(dataclasses.replace(s.camera, fx=np.nextafter(s.camera.fx, 1e9)), s.imu)
    assert not nudged.same_as(s)


def test_truncated_or_corrupt_descriptions_are_remote_protocol_errors() -> None:
    data = encode_sensors(_sensors())
    for n in (0, 1, 4, 5, len(data) // 2, len(data) - 1):
        with pytest.raises(SensorsDecodeError):
            decode_sensors(data[:n])
    for i in range(len(data)):
        bad = bytearray(data)
        bad[i] ^= 0x40
        with pytest.raises(RemoteProtocolError):
            decode_sensors(bytes(bad))
    with pytest.raises(SensorsDecodeError, match="trailing"):
        decode_sensors(_resealed(data[:-4] + b"\0"))
    with pytest.raises(SensorsDecodeError, match="version"):
        decode_sensors(_resealed(bytes([SENSORS_VERSION + 1]) + data[1:-4]))


def _resealed(body: bytes) -> bytes:
    """``body`` with a valid CRC (forged: only the content checks can catch it)."""
    return body + struct.pack("<I", zlib.crc32(body))


def _patched(sensors: Sensors, **camera: object) -> bytes:
    """The encoding of ``sensors`` with camera fields replaced *without* the dataclass'
    checks (what a broken or hostile robot could send)."""
    cam = object.__new__(CameraCalibration)
    for f in dataclasses.fields(CameraCalibration):
        object.__setattr__(cam, f.name, camera.get(f.name, getattr(sensors.camera, f.name)))
    return encode_sensors(Sensors(cam, sensors.imu))


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"model": "kannala"}, "unknown camera model"),
        ({"distortion": (0.1, 0.2, 0.0)}, "distortion coefficients"),
        ({"width": 0}, "image size"),
        ({"fx": -3.0}, "focal"),
        ({"fy": float("nan")}, "non-finite"),
        ({"rate_hz": 0.0}, "rates"),
        ({"T_body_cam": np.diag([1.0, 1.0, -1.0, 1.0])}, "reflection"),
        ({"T_body_cam": np.diag([1.0, 2.0, 1.0, 1.0])}, "orthonormal"),
        (
            {"T_body_cam": np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]])},
            "last row",
        ),
    ],
)
def test_impossible_sensors_are_refused_with_the_reason(change: dict, why: str) -> None:
    with pytest.raises(SensorsDecodeError, match=why):
        decode_sensors(_patched(_sensors(), **change))


def test_impossible_imu_is_refused() -> None:
    s = _sensors()
    imu = dataclasses.replace(s.imu, gyro_noise_density=0.0)
    with pytest.raises(SensorsDecodeError, match="IMU noise"):
        decode_sensors(encode_sensors(Sensors(s.camera, imu)))
