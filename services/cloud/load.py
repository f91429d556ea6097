"""How busy the cloud's worker thread has been lately (no I/O, no clock of its own).

The cloud applies every message, and builds every optimisation, on one worker thread. When
the edges send more than it can apply, the messages wait in the edges' outboxes (each link
delivers in order, one message at a time), so the cloud sees no queue of its own; what it can
see is that its worker never rests. :class:`BusyMeter` keeps the worker's recent busy
intervals (wall time: being preempted by the optimizer process on a shared core counts, as
it delays the messages just the same) and gives their share of a trailing window, which the
runner hands to :meth:`services.cloud.core.CloudCore.load`.
"""

from __future__ import annotations

from collections import deque

from common.errors import RecslamError


class LoadError(RecslamError):
    """Local misuse of the meter (a window that is not positive, time running backwards)."""


class BusyMeter:
    """Busy intervals ``[t0, t1]`` (seconds, one monotonic clock) of one thread, and their
    share of the last ``window_s``."""

    def __init__(self, window_s: float) -> None:
        if not window_s > 0:
            raise LoadError(f"window_s must be > 0, got {window_s}")
        self.window_s = window_s
        self._spans: deque[tuple[float, float]] = deque()
        self._total = 0.0  # sum of the kept spans' lengths
        self._start: float | None = None  # the first time anything was added

    def add(self, t0: float, t1: float) -> None:
        """One busy interval, added in time order (``t0`` no earlier than the last ``t1``
        minus rounding; overlaps are clipped)."""
        if t1 < t0:
            raise LoadError(f"a busy interval that ends before it starts: {t0} > {t1}")
        if self._spans:
            t0 = max(t0, self._spans[-1][1])
            t1 = max(t1, t0)
        elif self._start is None:
            self._start = t0
        self._spans.append((t0, t1))
        self._total += t1 - t0

    def share(self, now: float) -> float:
        """Busy time within ``[now - window_s, now]`` over the window (0..1); over the time
        since the first interval while that is shorter than the window (a service that was
        busy since it started is busy, not 10 % busy)."""
        lo = now - self.window_s
        spans = self._spans
        while spans and spans[0][1] <= lo:
            t0, t1 = spans.popleft()
            self._total -= t1 - t0
        if not spans or self._start is None:
            return 0.0
        busy = self._total
        t0, t1 = spans[0]
        if t0 < lo:  # the oldest span straddles the window's start
            busy -= lo - t0
        t_last = spans[-1][1]
        if t_last > now:  # (an interval reported with a later clock reading)
            busy -= t_last - now
        span = min(self.window_s, now - self._start)
        if span <= 0:
            return 0.0
        return float(min(1.0, max(0.0, busy / span)))
