"""Lossless IMU coding: every float64 and timestamp is reproduced bit for bit.

Sensor resolution assumed (defaults, :class:`ImuCodecConfig`): gyro 1/50 deg/s, accel
1/1200 g (g = 9.80665 m/s^2) — the lattices the EuRoC ADIS16448 values lie on. Each value
``x`` is split into a lattice index ``q = round(x / step)`` and an *ulp correction*
``c = ord(x) - ord(dequant(q))`` (``ord`` maps float64 bit patterns to integers
monotonically), so any float64 is recovered exactly. ``dequant`` is the float expression that
reproduces EuRoC's CSVs bit for bit (``q / 50 / 180 * pi`` rad/s, ``q / 1200 * 9.80665``
m/s^2: 100 % of the excerpt's values, so ``c`` is 0 and costs ~nothing); a robot that uses
:func:`dequantise_imu` values gets the same. Lattice indices are coded as differences to the
previous sample of the channel (discrete Laplace; its scale index per chunk and channel is
coded as a difference to the previous chunk's), corrections with their own Laplace model.
A channel whose values are off the lattice (ulp correction beyond 2**20, or non-finite
values) falls back to raw 64-bit patterns for that chunk.

Timestamps: the first of a stream raw (64 bits), then differences of consecutive time steps
(second differences) divided by their largest common power of two, coded with a Laplace
model. The encoder/decoder keep the last timestamp, step and lattice indices as state.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

from common.codec.entropy import N_SCALES, BitReader, BitWriter, best_scale_index
from common.codec.errors import CodecError, CodecUsageError
from common.codec.types import ImuChunk

MAGIC = 0xA7
VERSION = 1
MAX_SAMPLES = 1 << 16
MAX_CORR = 1 << 20
_SIGN = np.int64(-(1 << 63))
_MASK = np.int64((1 << 63) - 1)


@dataclass(frozen=True)
class ImuCodecConfig:
    """gyro_lsb_per_deg_s: gyro lattice steps per deg/s (50 -> 0.02 deg/s).
    accel_lsb_per_g: accel lattice steps per g (1200). gravity: m/s^2 per g (9.80665)."""

    gyro_lsb_per_deg_s: float = 50.0
    accel_lsb_per_g: float = 1200.0
    gravity: float = 9.80665

    @property
    def gyro_step(self) -> float:
        return float(np.pi / 180.0 / self.gyro_lsb_per_deg_s)

    @property
    def accel_step(self) -> float:
        return self.gravity / self.accel_lsb_per_g


def dequantise(q: np.ndarray, channel: int, config: ImuCodecConfig) -> np.ndarray:
    """float64 value of lattice indices ``q`` of channel 0-2 (gyro) or 3-5 (accel)."""
    q = np.asarray(q, dtype=np.float64)
    if channel < 3:
        return q / config.gyro_lsb_per_deg_s / 180.0 * np.pi
    return q / config.accel_lsb_per_g * config.gravity


def dequantise_imu(chunk: ImuChunk, config: ImuCodecConfig | None = None) -> ImuChunk:
    """Snap a chunk to the sensor lattice (what a robot should use to make IMU coding cheap)."""
    config = ImuCodecConfig() if config is None else config
    v = np.concatenate([chunk.gyro, chunk.accel], axis=1)
    steps = _steps(config)
    out = np.stack([dequantise(np.round(v[:, c] / steps[c]), c, config) for c in range(6)], 1)
    return ImuChunk(chunk.timestamps_ns, out[:, :3], out[:, 3:])


SCALE_DELTA_INDEX = 8  # Laplace scale 1 for chunk-to-chunk changes of scale indices


def _ord(x: np.ndarray) -> np.ndarray:
    i = np.ascontiguousarray(x, dtype=np.float64).view(np.int64)
    return np.where(i < 0, -1 - (i & _MASK), i)


def _unord(o: np.ndarray) -> np.ndarray:
    o = np.asarray(o, dtype=np.int64)
    i = np.where(o >= 0, o, (-1 - o) | _SIGN)
    return i.view(np.float64)


@dataclass
class ImuState:
    last_ts: int | None = None
    last_dt: int = 0
    last_q: np.ndarray = field(default_factory=lambda: np.zeros(6, dtype=np.int64))
    seq: int = 0
    last_si: np.ndarray = field(default_factory=lambda: np.full(12, 24, dtype=np.int64))

    def copy(self) -> ImuState:
        return ImuState(
            self.last_ts, self.last_dt, self.last_q.copy(), self.seq, self.last_si.copy()
        )


def _steps(config: ImuCodecConfig) -> np.ndarray:
    return np.array([config.gyro_step] * 3 + [config.accel_step] * 3)


def _trailing_zeros(v: np.ndarray) -> int:
    nz = v[v != 0]
    if nz.size == 0:
        return 0
    tz = 0
    while tz < 40 and np.all((nz >> tz) & 1 == 0):
        tz += 1
    return tz


class ImuEncoder:
    """Sans-I/O IMU encoder for one robot: ``encode(chunk) -> bytes``."""

    def __init__(self, config: ImuCodecConfig = ImuCodecConfig()) -> None:
        self.config = config
        self.state = ImuState()
        self.last_bits: dict[str, float] = {}

    def encode(self, chunk: ImuChunk) -> bytes:
        m = len(chunk)
        if m > MAX_SAMPLES:
            raise CodecUsageError(f"IMU chunk of {m} samples exceeds {MAX_SAMPLES}")
        st = self.state.copy()
        w = BitWriter()
        w.put_count(m, "imu_side")
        if m:
            ts = chunk.timestamps_ns
            if st.last_ts is None:
                w.put_raw(np.array([ts[0]]).view(np.uint64), 64, "imu_time")
                prev_ts, prev_dt = ts[0], 0
                body = ts[1:]
            else:
                prev_ts, prev_dt, body = st.last_ts, st.last_dt, ts
            if body.size:
                dts = np.diff(np.concatenate([[prev_ts], body]))
                dd = np.diff(np.concatenate([[prev_dt], dts]))
                tz = _trailing_zeros(dd)
                w.put_uniform(np.array([tz]), 41, "imu_time")
                si = best_scale_index(dd >> tz, signed=True)
                w.put_uniform(np.array([si]), N_SCALES, "imu_time")
                w.put_signed(dd >> tz, si, "imu_time", escape_bits=64)
                prev_dt = int(dts[-1])
            st.last_ts, st.last_dt = int(ts[-1]), int(prev_dt)
            values = np.concatenate([chunk.gyro, chunk.accel], axis=1)
            steps = _steps(self.config)
            for c in range(6):
                x = values[:, c]
                with np.errstate(over="ignore", invalid="ignore"):
                    ok = bool(np.all(np.abs(x / steps[c]) < 2.0**40))  # False for NaN / inf
                if ok:
                    q = np.round(x / steps[c]).astype(np.int64)
                    corr = _ord(x) - _ord(dequantise(q, c, self.config))
                    ok = bool(np.all(np.abs(corr) < MAX_CORR))
                w.put_bernoulli(np.array([int(ok)]), np.array([0.5]), "imu_side")
                if not ok:
                    w.put_raw(x.view(np.uint64), 64, "imu_value")
                    continue
                dq = np.diff(np.concatenate([[st.last_q[c]], q]))
                si = best_scale_index(dq, signed=True)
                w.put_signed(np.array([si - st.last_si[c]]), SCALE_DELTA_INDEX, "imu_side")
                w.put_signed(dq, si, "imu_value", escape_bits=64)
                st.last_si[c] = si
                si = best_scale_index(corr, signed=True)
                w.put_signed(np.array([si - st.last_si[6 + c]]), SCALE_DELTA_INDEX, "imu_side")
                w.put_signed(corr, si, "imu_ulp")
                st.last_si[6 + c] = si
                st.last_q[c] = q[-1]
        head = struct.pack("<BBH", MAGIC, VERSION, st.seq & 0xFFFF)
        payload = head + w.finish()
        payload += struct.pack("<I", zlib.crc32(payload))
        st.seq += 1
        self.state = st
        self.last_bits = dict(w.bits)
        return payload


class ImuDecoder:
    """Sans-I/O IMU decoder for one robot: ``decode(bytes) -> ImuChunk``."""

    def __init__(self, config: ImuCodecConfig = ImuCodecConfig()) -> None:
        self.config = config
        self.state = ImuState()

    def decode(self, payload: bytes) -> ImuChunk:
        if len(payload) < 8:
            raise CodecError(f"IMU payload of {len(payload)} bytes is too short")
        (crc,) = struct.unpack("<I", payload[-4:])
        if zlib.crc32(payload[:-4]) != crc:
            raise CodecError("IMU payload checksum mismatch (corrupted or truncated)")
        magic, version, seq = struct.unpack("<BBH", payload[:4])
        if magic != MAGIC or version != VERSION:
            raise CodecError(f"not an IMU payload (magic {magic:#x}, version {version})")
        st = self.state.copy()
        if seq != st.seq & 0xFFFF:
            raise CodecError(f"IMU payload {seq} out of order (expected {st.seq & 0xFFFF})")
        r = BitReader(payload[4:-4])
        m = r.get_count(MAX_SAMPLES)
        ts = np.zeros(m, dtype=np.int64)
        values = np.zeros((m, 6), dtype=np.float64)
        if m:
            if st.last_ts is None:
                ts[0] = int(r.get_raw(1, 64).view(np.int64)[0])
                prev_ts, prev_dt, start = int(ts[0]), 0, 1
            else:
                prev_ts, prev_dt, start = st.last_ts, st.last_dt, 0
            nb = m - start
            if nb:
                tz = int(r.get_uniform(1, 41)[0])
                si = int(r.get_uniform(1, N_SCALES)[0])
                dd = r.get_signed(nb, si, escape_bits=64) << tz
                with np.errstate(over="ignore"):
                    dts = prev_dt + np.cumsum(dd)
                    ts[start:] = prev_ts + np.cumsum(dts)
                prev_dt = int(dts[-1])
            st.last_ts, st.last_dt = int(ts[-1]), prev_dt
            for c in range(6):
                ok = bool(r.get_bernoulli(np.array([0.5]))[0])
                if not ok:
                    values[:, c] = r.get_raw(m, 64).view(np.float64)
                    continue
                si = int(st.last_si[c] + r.get_signed(1, SCALE_DELTA_INDEX)[0])
                if not 0 <= si < N_SCALES:
                    raise CodecError("IMU scale index out of range")
                st.last_si[c] = si
                dq = r.get_signed(m, si, escape_bits=64)
                with np.errstate(over="ignore"):
                    q = st.last_q[c] + np.cumsum(dq)
                if np.abs(q).max() >= 2**40:
                    raise CodecError("IMU lattice index out of range")
                si = int(st.last_si[6 + c] + r.get_signed(1, SCALE_DELTA_INDEX)[0])
                if not 0 <= si < N_SCALES:
                    raise CodecError("IMU scale index out of range")
                st.last_si[6 + c] = si
                corr = r.get_signed(m, si)
                with np.errstate(over="ignore", invalid="ignore"):
                    values[:, c] = _unord(_ord(dequantise(q, c, self.config)) + corr)
                st.last_q[c] = q[-1]
        st.seq += 1
        self.state = st
        return ImuChunk(ts, values[:, :3], values[:, 3:])
