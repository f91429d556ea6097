"""Thin wrapper over constriction's range coder with the models the feature codec uses.

:class:`BitWriter` and :class:`BitReader` mirror each other call for call: every ``put_*``
on the writer has a ``get_*`` on the reader taking the same model arguments. Probability
tables are computed by the same numpy code on both sides, so they are bit-identical.
The writer also tallies the information content (``-log2 p``) of every symbol per *part*
label, which the benchmarks use to split a payload's size into keypoint / word / residual
/ side-information bits (the tallies sum to the payload size up to the coder's few bits of
termination overhead).

Models:

- ``bernoulli``: binary symbols with a per-symbol probability of 1.
- ``categorical``: a table shared by all symbols, or one row per symbol.
- ``uniform``: integers in ``[0, size)``; ``size`` up to 2**24.
- ``raw``: unsigned integers of up to 64 bits (16-bit uniform chunks).
- ``signed``: discrete Laplace (two-sided geometric) of scale ``2**(scale_index/4 - 3)``
  over ``[-R, R]`` plus an escape symbol followed by a raw zig-zag value (32 or 64 bits).
- ``geometric``: one-sided geometric of the given mean over ``[0, R)`` plus escape.
- ``count``: an unsigned integer of unknown size (6-bit length, then the bits).
"""

from __future__ import annotations

import functools

import constriction
import numpy as np

from common.codec.errors import CodecError

_MODEL = constriction.stream.model
_BERNOULLI = _MODEL.Bernoulli(perfect=False)
_CATEGORICAL = _MODEL.Categorical(perfect=False)
_UNIFORM = _MODEL.Uniform()
MAX_TABLE = 4096  # largest categorical table built for signed/geometric models
N_SCALES = 72  # scale_index in [0, N_SCALES): scale = 2 ** (i / 4 - 3), 0.125 .. ~3000
P_MIN = 1.0 / 4096  # probabilities of adaptive binary models are clipped to [P_MIN, 1-P_MIN]


def scale_of(index: int) -> float:
    return 2.0 ** (index / 4.0 - 3.0)


@functools.lru_cache(maxsize=256)
def signed_table(scale_index: int) -> tuple[np.ndarray, int]:
    """(probabilities over [-R..R] + escape, R) of the discrete Laplace model."""
    b = scale_of(scale_index)
    r = int(min(MAX_TABLE // 2 - 1, max(4, np.ceil(12.0 * b))))
    x = np.arange(-r, r + 1, dtype=np.float64)
    p = np.exp(-np.abs(x) / b)
    p = np.append(p / p.sum() * (1.0 - 1e-4), 1e-4)
    p.setflags(write=False)
    return p, r


@functools.lru_cache(maxsize=256)
def geometric_table(scale_index: int) -> tuple[np.ndarray, int]:
    """(probabilities over [0..R) + escape, R) of a geometric model of mean ~scale."""
    m = scale_of(scale_index)
    r = int(min(MAX_TABLE - 1, max(4, np.ceil(12.0 * m))))
    q = m / (1.0 + m)
    p = q ** np.arange(r, dtype=np.float64)
    p = np.append(p / p.sum() * (1.0 - 1e-4), 1e-4)
    p.setflags(write=False)
    return p, r


def best_scale_index(values: np.ndarray, signed: bool) -> int:
    """Scale index minimising the coded size of ``values`` (tries all, cheap tables)."""
    v = np.asarray(values, dtype=np.int64)
    if v.size == 0:
        return 0
    mean = float(np.mean(np.abs(v)))
    centre = int(np.clip(np.round(4 * (np.log2(max(mean, 0.125)) + 3)), 0, N_SCALES - 1))
    lo, hi = max(0, centre - 6), min(N_SCALES, centre + 7)
    # all candidates at once: the same floats as signed_cost / geometric_cost (each row of
    # the gathered matrix is summed like the 1-D array), first minimum as in a scan
    tables, r = _cost_tables(signed, lo, hi)
    r = r[:, None]
    if signed:
        esc = (v < -r) | (v > r)
        sym = np.where(esc, 2 * r + 1, v + r)
    else:
        esc = v >= r
        sym = np.where(esc, r, v)
    costs = tables[np.arange(hi - lo)[:, None], sym].sum(axis=1) + 32 * esc.sum(axis=1)
    return lo + int(np.argmin(costs))


@functools.lru_cache(maxsize=4 * N_SCALES)
def _cost_tables(signed: bool, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """``-log2`` tables of scales ``lo..hi-1`` zero-padded into one ``(hi - lo, L)`` array,
    and their ``R`` values ``(hi - lo,)``."""
    table = signed_table if signed else geometric_table
    rows = [_info_table(signed, i) for i in range(lo, hi)]
    out = np.zeros((hi - lo, max(t.size for t in rows)))
    for k, t in enumerate(rows):
        out[k, : t.size] = t
    r = np.array([table(i)[1] for i in range(lo, hi)], dtype=np.int64)
    out.setflags(write=False)
    r.setflags(write=False)
    return out, r


def _escape_split(v: np.ndarray, lo: int, hi: int) -> np.ndarray:
    return (v < lo) | (v > hi)


@functools.lru_cache(maxsize=256)
def _info_table(signed: bool, scale_index: int) -> np.ndarray:
    """``-log2`` of :func:`signed_table` / :func:`geometric_table` (bits per symbol)."""
    p = (signed_table if signed else geometric_table)(scale_index)[0]
    bits = -np.log2(p)
    bits.setflags(write=False)
    return bits


def signed_cost(values: np.ndarray, scale_index: int) -> float:
    r = signed_table(scale_index)[1]
    v = np.asarray(values, dtype=np.int64)
    esc = _escape_split(v, -r, r)
    sym = np.where(esc, 2 * r + 1, v + r)
    return float(_info_table(True, scale_index)[sym].sum() + 32 * esc.sum())


def geometric_cost(values: np.ndarray, scale_index: int) -> float:
    r = geometric_table(scale_index)[1]
    v = np.asarray(values, dtype=np.int64)
    esc = v >= r
    sym = np.where(esc, r, v)
    return float(_info_table(False, scale_index)[sym].sum() + 32 * esc.sum())


_POS = np.int64((1 << 63) - 1)


def zigzag(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.int64)
    return np.where(v >= 0, 2 * v, -2 * v - 1)


def unzigzag(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z, dtype=np.int64)
    return np.where(z % 2 == 0, z // 2, -(z + 1) // 2)


class BitWriter:
    """Encoder side: ``put_*`` symbols, then :meth:`finish` for the bytes."""

    def __init__(self) -> None:
        self._enc = constriction.stream.queue.RangeEncoder()
        self.bits: dict[str, float] = {}

    def _tally(self, part: str, bits: float) -> None:
        self.bits[part] = self.bits.get(part, 0.0) + float(bits)

    def put_bernoulli(
        self, symbols: np.ndarray, p1: np.ndarray, part: str, info: float | None = None
    ) -> None:
        """``info``: the symbols' information content in bits if the caller already has it
        (saves the ``log2`` pass)."""
        s = np.ascontiguousarray(symbols, dtype=np.int32).ravel()
        if s.size == 0:
            return
        p = np.ascontiguousarray(p1, dtype=np.float64).ravel()
        self._enc.encode(s, _BERNOULLI, p)
        if info is None:
            info = -np.log2(np.where(s == 1, p, 1.0 - p)).sum()
        self._tally(part, info)

    def put_categorical(self, symbols: np.ndarray, probs: np.ndarray, part: str) -> None:
        s = np.ascontiguousarray(symbols, dtype=np.int32).ravel()
        if s.size == 0:
            return
        probs = np.asarray(probs, dtype=np.float64)
        if probs.ndim == 1:
            self._enc.encode(s, _MODEL.Categorical(probs, perfect=False))
            sel = probs[s] / probs.sum()
        else:
            probs = np.ascontiguousarray(probs)
            self._enc.encode(s, _CATEGORICAL, probs)
            sel = probs[np.arange(s.size), s] / probs.sum(axis=1)
        self._tally(part, -np.log2(np.maximum(sel, 2.0**-24)).sum())

    def put_uniform(self, values: np.ndarray, size: int, part: str) -> None:
        v = np.ascontiguousarray(values, dtype=np.int32).ravel()
        if v.size == 0 or size <= 1:
            return
        self._enc.encode(v, _MODEL.Uniform(int(size)))
        self._tally(part, v.size * np.log2(size))

    def put_raw(self, values: np.ndarray, nbits: int, part: str) -> None:
        v = np.asarray(values, dtype=np.uint64).ravel()
        for shift in range(0, nbits, 16):
            width = min(16, nbits - shift)
            chunk = (v >> np.uint64(shift)) & np.uint64((1 << width) - 1)
            if width == 1:
                self.put_bernoulli(chunk.astype(np.int32), np.full(v.size, 0.5), part)
            else:
                self.put_uniform(chunk.astype(np.int32), 1 << width, part)

    def put_count(self, value: int, part: str) -> None:
        value = int(value)
        n = value.bit_length()
        self.put_uniform(np.array([n]), 64, part)
        if n > 1:
            self.put_raw(np.array([value - (1 << (n - 1))], dtype=np.uint64), n - 1, part)

    def put_flags(self, flags: np.ndarray, part: str, count_part: str | None = None) -> None:
        """Binary flags with one probability: their count of ones (tallied as ``count_part``,
        default ``part``), then the flags unless all or none are set."""
        ones = int(np.count_nonzero(flags))
        self.put_count(ones, count_part or part)
        if 0 < ones < len(flags):
            p = np.clip(np.full(len(flags), ones / len(flags)), 1e-6, 1 - 1e-6)
            self.put_bernoulli(np.asarray(flags).astype(np.int32), p, part)

    def put_signed(
        self, values: np.ndarray, scale_index: int, part: str, escape_bits: int = 32
    ) -> None:
        v = np.asarray(values, dtype=np.int64).ravel()
        if v.size == 0:
            return
        p, r = signed_table(scale_index)
        esc = _escape_split(v, -r, r)
        self.put_categorical(np.where(esc, 2 * r + 1, v + r), p, part)
        if esc.any():
            z = zigzag(v[esc]).astype(np.uint64)
            if escape_bits < 64 and np.any(z >> np.uint64(escape_bits)):
                raise ValueError(f"value too large for a {escape_bits}-bit escape")
            self.put_raw(z, escape_bits, part)

    def put_geometric(self, values: np.ndarray, scale_index: int, part: str) -> None:
        v = np.asarray(values, dtype=np.int64).ravel()
        if v.size == 0:
            return
        p, r = geometric_table(scale_index)
        esc = v >= r
        self.put_categorical(np.where(esc, r, v), p, part)
        if esc.any():
            self.put_raw(v[esc].astype(np.uint64), 32, part)

    def finish(self) -> bytes:
        return self._enc.get_compressed().astype("<u4").tobytes()


class BitReader:
    """Decoder side; any inconsistency raises :class:`CodecError`."""

    def __init__(self, data: bytes) -> None:
        if len(data) % 4:
            raise CodecError(f"entropy-coded body of {len(data)} bytes is not whole 32-bit words")
        words = np.frombuffer(data, dtype="<u4").astype(np.uint32)
        try:
            self._dec = constriction.stream.queue.RangeDecoder(words)
        except (ValueError, RuntimeError) as exc:
            raise CodecError(f"bad entropy-coded body: {exc}") from exc

    def _decode(self, *args: object) -> np.ndarray:
        try:
            return np.asarray(self._dec.decode(*args), dtype=np.int64)
        except (ValueError, RuntimeError, AssertionError, OverflowError) as exc:
            raise CodecError(f"entropy decoding failed: {exc}") from exc

    def get_bernoulli(self, p1: np.ndarray) -> np.ndarray:
        p = np.ascontiguousarray(p1, dtype=np.float64).ravel()
        if p.size == 0:
            return np.zeros(0, dtype=np.int64)
        return self._decode(_BERNOULLI, p)

    def get_bernoulli_fast(self, p1: np.ndarray) -> np.ndarray:
        """:meth:`get_bernoulli` for a non-empty contiguous ``p1 (n,)`` (float64, or float32
        which constriction widens exactly) without conversions (hot loops); returns the
        constriction array (int32)."""
        try:
            return self._dec.decode(_BERNOULLI, p1)
        except (ValueError, RuntimeError, AssertionError, OverflowError) as exc:
            raise CodecError(f"entropy decoding failed: {exc}") from exc

    def get_categorical(self, probs: np.ndarray, n: int | None = None) -> np.ndarray:
        probs = np.asarray(probs, dtype=np.float64)
        if probs.ndim == 1:
            if not n:
                return np.zeros(0, dtype=np.int64)
            return self._decode(_MODEL.Categorical(probs, perfect=False), int(n))
        if probs.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        return self._decode(_CATEGORICAL, np.ascontiguousarray(probs))

    def get_uniform(self, n: int, size: int) -> np.ndarray:
        if n == 0 or size <= 1:
            return np.zeros(n, dtype=np.int64)
        return self._decode(_MODEL.Uniform(int(size)), int(n))

    def get_raw(self, n: int, nbits: int) -> np.ndarray:
        out = np.zeros(n, dtype=np.uint64)
        for shift in range(0, nbits, 16):
            width = min(16, nbits - shift)
            if width == 1:
                chunk = self.get_bernoulli(np.full(n, 0.5))
            else:
                chunk = self.get_uniform(n, 1 << width)
            out |= chunk.astype(np.uint64) << np.uint64(shift)
        return out

    def get_count(self, limit: int) -> int:
        """An unsigned integer; raises CodecError if it exceeds ``limit``."""
        n = int(self.get_uniform(1, 64)[0])
        value = 0 if n == 0 else 1 if n == 1 else (1 << (n - 1)) + int(self.get_raw(1, n - 1)[0])
        if value > limit:
            raise CodecError(f"count {value} exceeds the limit {limit}")
        return value

    def get_flags(self, n: int) -> np.ndarray:
        """Inverse of :meth:`BitWriter.put_flags`: ``(n,)`` bool; CodecError if they
        disagree with their count."""
        ones = self.get_count(n)
        if ones in (0, n):
            return np.full(n, ones == n, bool)
        p = np.clip(np.full(n, ones / n), 1e-6, 1 - 1e-6)
        flags = self.get_bernoulli(p).astype(bool)
        if int(flags.sum()) != ones:
            raise CodecError(f"{int(flags.sum())} flags set, {ones} declared")
        return flags

    def get_signed(self, n: int, scale_index: int, escape_bits: int = 32) -> np.ndarray:
        if n == 0:
            return np.zeros(0, dtype=np.int64)
        p, r = signed_table(scale_index)
        sym = self.get_categorical(p, n)
        v = sym - r
        esc = sym == 2 * r + 1
        if esc.any():
            v[esc] = unzigzag(self.get_raw(int(esc.sum()), escape_bits).view(np.int64) & _POS)
        return v

    def get_geometric(self, n: int, scale_index: int) -> np.ndarray:
        if n == 0:
            return np.zeros(0, dtype=np.int64)
        p, r = geometric_table(scale_index)
        v = self.get_categorical(p, n)
        esc = v == r
        if esc.any():
            v[esc] = self.get_raw(int(esc.sum()), 32).astype(np.int64)
        return v


def adaptive_p1(ones: np.ndarray, total: np.ndarray | float) -> np.ndarray:
    """Krichevsky–Trofimov estimate of P(bit = 1) from counts, clipped to [P_MIN, 1 - P_MIN]."""
    p = (np.asarray(ones, dtype=np.float64) + 0.5) / (np.asarray(total, dtype=np.float64) + 1.0)
    return np.clip(p, P_MIN, 1.0 - P_MIN)
