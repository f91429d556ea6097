"""What every link module shares: the wire format a service chooses and the CPU timer of the
link codecs (re-exported by :mod:`common.links`; the link modules import it from here, so
that the package's ``__init__`` and its links import one way)."""

from __future__ import annotations

import contextlib
import enum
import time
from collections.abc import Callable, Iterable, Iterator


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
