"""Entropy-coding primitives: every writer call round-trips through the mirrored reader."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.codec.entropy import (
    BitReader,
    BitWriter,
    best_scale_index,
    signed_cost,
    unzigzag,
    zigzag,
)
from common.codec.errors import CodecError


@settings(max_examples=40, deadline=None)
@given(
    signed=st.lists(st.integers(-(2**31) + 1, 2**31 - 1), max_size=40),
    small=st.lists(st.integers(-20, 20), max_size=40),
    unsigned=st.lists(st.integers(0, 2**31), max_size=20),
    raw=st.lists(st.integers(0, 2**64 - 1), max_size=5),
    count=st.integers(0, 2**40),
)
def test_primitives_roundtrip(signed, small, unsigned, raw, count):
    w = BitWriter()
    si = best_scale_index(np.array(small), signed=True)
    w.put_signed(np.array(small), si, "a")
    w.put_signed(np.array(signed), 10, "a")
    w.put_geometric(np.array(unsigned), 20, "b")
    w.put_raw(np.array(raw, dtype=np.uint64), 64, "c")
    w.put_count(count, "c")
    bits = np.array([v & 1 for v in unsigned], dtype=np.int64)
    w.put_bernoulli(bits, np.full(bits.size, 0.9), "d")
    w.put_uniform(np.array([5, 0, 6]), 7, "d")
    r = BitReader(w.finish())
    assert r.get_signed(len(small), si).tolist() == small
    assert r.get_signed(len(signed), 10).tolist() == signed
    assert r.get_geometric(len(unsigned), 20).tolist() == unsigned
    assert r.get_raw(len(raw), 64).tolist() == raw
    assert r.get_count(2**41) == count
    assert r.get_bernoulli(np.full(bits.size, 0.9)).tolist() == bits.tolist()
    assert r.get_uniform(3, 7).tolist() == [5, 0, 6]


def test_tallies_match_payload_size():
    rng = np.random.default_rng(0)
    v = np.round(rng.laplace(0, 3, 5000)).astype(np.int64)
    w = BitWriter()
    si = best_scale_index(v, signed=True)
    w.put_signed(v, si, "x")
    size = 8 * len(w.finish())
    assert abs(size - w.bits["x"]) < 64
    assert w.bits["x"] == pytest.approx(signed_cost(v, si))
    assert w.bits["x"] / v.size < 4.15  # entropy of Laplace(b=3) is log2(2e * 3) = 4.03


def test_zigzag_inverse():
    v = np.array([0, -1, 1, -(2**40), 2**40])
    assert np.array_equal(unzigzag(zigzag(v)), v)


def test_count_limit_and_bad_length():
    w = BitWriter()
    w.put_count(1000, "x")
    with pytest.raises(CodecError, match="limit"):
        BitReader(w.finish()).get_count(999)
    with pytest.raises(CodecError, match="32-bit"):
        BitReader(b"abc")
