"""What every link module shares: the wire format a service chooses and the CPU timer of the
link codecs (re-exported by :mod:`common.links`; the link modules import it from here, so
that the package's ``__init__`` and its links import one way)."""

from __future__ import annotations

import contextlib
import enum
import time
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from common.geometry import R_to_quat_wxyz, quat_wxyz_to_R
from common.protocol.errors import RemoteProtocolError

POSE_BYTES = 28
"""Size of a packed pose: 7 little-endian float32, the unit quaternion (w, x, y, z) and the
position [m]."""


class WireFormat(enum.Enum):
    """How a service encodes the messages it sends (receivers accept both)."""

    CODED = "coded"
    """Entropy-coded and quantised at stated precisions (the default)."""
    RAW = "raw"
    """Schema-1 messages: float64 / int64 arrays as they were before the links were coded,
    kept as the baseline of ``recslam experiment links``."""


class CodecTimer:
    """CPU time spent encoding / decoding link messages, per ``"encode.Type"`` /
    ``"decode.Type"`` key (``time.process_time`` of the calling thread is not used: the
    timings are wall-clock ``perf_counter`` spans of pure-CPU codec calls).

    The cloud uses the same accumulator for the stages of its worker (``stage.*`` keys,
    :attr:`services.cloud.app.CloudApp.stage_timer`), with ``clock=time.thread_time``: the
    CPU time of the calling thread, which a loaded machine's other processes do not inflate.
    :meth:`span` reads ``clock``; :meth:`add` takes any seconds."""

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self._acc: dict[str, list[float]] = {}
        self.clock = clock

    def add(self, key: str, seconds: float, messages: int = 1) -> None:
        """Count ``messages`` coded in ``seconds``."""
        entry = self._acc.setdefault(key, [0.0, 0.0])
        entry[0] += seconds
        entry[1] += messages

    @contextlib.contextmanager
    def span(self, key: str) -> Iterator[None]:
        """Count the time (``clock``) of the ``with`` block as one call under ``key`` (also
        when it raises)."""
        t0 = self.clock()
        try:
            yield
        finally:
            self.add(key, self.clock() - t0)

    def merge(self, other: CodecTimer) -> None:
        """Add ``other``'s counts into these."""
        for key, (s, n) in list(other._acc.items()):  # a copy: another thread may add
            self.add(key, s, int(n))

    def snapshot(self) -> dict[str, dict[str, float]]:
        """``{"encode.KeyframeUpdate": {"seconds": s, "messages": n}, ...}``."""
        return {k: {"seconds": s, "messages": int(n)} for k, (s, n) in sorted(self._acc.items())}


def codec_cpu(owners: Iterable[object]) -> dict[str, dict[str, float]] | None:
    """The merged ``codec_timer.snapshot()`` of those ``owners`` that have a ``codec_timer``
    (a :class:`CodecTimer`; a timer shared by two owners counts once): ``{"encode.Type":
    {"seconds": s, "messages": n}, ...}``; None when no owner has one."""
    timers: dict[int, CodecTimer] = {}
    for owner in owners:
        timer = getattr(owner, "codec_timer", None)
        if timer is not None:
            timers.setdefault(id(timer), timer)
    if not timers:
        return None
    out: dict[str, dict[str, float]] = {}
    for timer in timers.values():
        for key, entry in timer.snapshot().items():
            acc = out.setdefault(key, {"seconds": 0.0, "messages": 0})
            acc["seconds"] += float(entry["seconds"])
            acc["messages"] += int(entry["messages"])
    return dict(sorted(out.items()))


def pack_pose(T: np.ndarray) -> bytes:
    """A (4, 4) rigid transform as :data:`POSE_BYTES` bytes (no finiteness check: callers
    that send a pose alone use :func:`pack_finite_pose`)."""
    T = np.asarray(T, np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"a pose must be (4, 4), got {T.shape}")
    q = R_to_quat_wxyz(T[:3, :3])
    return np.concatenate([q, T[:3, 3]]).astype("<f4").tobytes()


def pack_finite_pose(T: np.ndarray) -> bytes:
    """:func:`pack_pose`, ValueError unless every value is finite in float32."""
    if not np.isfinite(np.asarray(T, np.float64)).all():
        raise ValueError("a pose must be finite (and fit float32)")
    out = pack_pose(T)
    if not np.isfinite(np.frombuffer(out, "<f4")).all():
        raise ValueError("a pose must be finite (and fit float32)")
    return out


def unpack_pose(data: bytes) -> np.ndarray:
    """The (4, 4) transform of the first :data:`POSE_BYTES` bytes of ``data``, exactly as both
    ends compute it (no checks: see :func:`unpack_sent_pose`)."""
    s = np.frombuffer(data[:POSE_BYTES], "<f4").astype(np.float64)
    T = np.eye(4)
    T[:3, :3] = quat_wxyz_to_R(s[:4])
    T[:3, 3] = s[4:7]
    return T


def unpack_sent_pose(data: bytes, what: str) -> np.ndarray:
    """:func:`unpack_pose` of a pose a peer sent: RemoteProtocolError naming ``what`` if it is
    not :data:`POSE_BYTES` bytes of finite values."""
    if len(data) != POSE_BYTES:
        raise RemoteProtocolError(f"{what} has {len(data)} bytes, expected {POSE_BYTES}")
    if not np.isfinite(np.frombuffer(data, "<f4")).all():
        raise RemoteProtocolError(f"{what} is not finite")
    T = unpack_pose(data)
    if not np.isfinite(T).all():
        raise RemoteProtocolError(f"{what} is not finite")
    return T
