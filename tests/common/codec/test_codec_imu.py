"""Lossless IMU coding: bit-exact float64 and timestamps, cheap on the sensor lattice."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.codec import CodecError, ImuChunk, ImuDecoder, ImuEncoder
from common.codec.imu import dequantise_imu


def euroc_like(n: int, seed: int = 0) -> ImuChunk:
    rng = np.random.default_rng(seed)
    ts = 1403715273262142976 + np.cumsum(rng.choice([4999936, 5000192], n))
    g = np.round(rng.normal(0, 5, (n, 3))) * (np.pi / 180 * 0.02)
    a = np.round(rng.normal(400, 20, (n, 3))) * (9.80665 / 1200)
    return ImuChunk(ts, g, a)


def roundtrip_chunks(chunks):
    enc, dec = ImuEncoder(), ImuDecoder()
    sizes = []
    for c in chunks:
        p = enc.encode(c)
        out = dec.decode(p)
        assert out.equals(c)
        sizes.append(len(p))
    return sizes


def test_lattice_values_roundtrip_cheaply():
    sizes = roundtrip_chunks([euroc_like(10, s) for s in range(5)] + [euroc_like(0)])
    assert np.mean(sizes[1:5]) * 8 / 10 < 6 * 16  # well below 6 x 64-bit floats per sample


def test_real_euroc_imu_is_bit_exact(euroc_micro: Path):
    lines = (euroc_micro / "mav0/imu0/data.csv").read_text().splitlines()[1:401]
    ts = np.array([int(line.split(",")[0]) for line in lines], dtype=np.int64)
    d = np.array([[float(x) for x in line.split(",")] for line in lines])
    chunks = [
        ImuChunk(ts[i : i + 10], d[i : i + 10, 1:4], d[i : i + 10, 4:7]) for i in range(0, 400, 10)
    ]
    sizes = roundtrip_chunks(chunks)
    assert 8 * sum(sizes[1:]) / 390 < 90  # bits per sample (6 channels + time)
    # The excerpt lies exactly on the assumed lattice and dequantisation expression.
    assert all(dequantise_imu(c).equals(c) for c in chunks)


@settings(max_examples=40, deadline=None)
@given(
    values=st.lists(
        st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=6, max_size=60
    ),
    gaps=st.lists(st.integers(-(2**40), 2**40), min_size=1, max_size=10),
)
def test_arbitrary_floats_and_timestamps_roundtrip(values, gaps):
    n = len(values) // 6
    v = np.array(values[: 6 * n], dtype=np.float64).reshape(n, 6)
    ts = np.cumsum(np.resize(np.array(gaps, dtype=np.int64), n))
    chunk = ImuChunk(ts, v[:, :3], v[:, 3:])
    roundtrip_chunks([chunk, chunk])


def test_corruption_and_order():
    enc, dec = ImuEncoder(), ImuDecoder()
    p0, p1 = enc.encode(euroc_like(10)), enc.encode(euroc_like(10, 1))
    with pytest.raises(CodecError, match="out of order"):
        dec.decode(p1)
    for bad in (p0[:-1], p0[:3], bytes([p0[0] ^ 1]) + p0[1:], p0 + b"x"):
        with pytest.raises(CodecError):
            dec.decode(bad)
    assert dec.decode(p0).equals(euroc_like(10))
