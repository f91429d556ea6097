"""A link's delivery rate, measured from its own acknowledgements (sans-I/O).

The way a delay-based congestion controller (BBR's delivery rate) measures a path: bytes
acknowledged per second over the intervals in which the link had a backlog all along (an idle
link says nothing about its capacity; BBR's "not application-limited"). The estimate is a
ratio of sums over the last ``window_s``: the bytes acknowledged in those intervals over
their total time. One acknowledgement can cover a 20 kB keyframe at once, so a single
interval's rate, or their maximum, overstates the link many times over (the first estimator
of the robot's budget, a maximum, read ~800 kbit/s off a 50 kbit/s link,
``benchmarks/results/budget.md``). It is reported from one second of such time on; the last
estimate holds while the link says nothing (a cut), since a stall is not a rate.

The same link also tells whether it moves: :meth:`DeliveryRate.stalled` is true once data has
waited with nothing acknowledged for a while (an outage).

Both ends of the budgets use it: the robot's uplink budget and the edge's cloud budget. No
clock and no sockets: ``now`` (monotonic s) and the link's counters come in.
"""

from __future__ import annotations

from collections import deque


class DeliveryRate:
    """The rate a link delivers at, from ``(now, bytes waiting, bytes acknowledged)``
    samples (:meth:`on_link`)."""

    MIN_INTERVAL_S = 0.2
    """Shorter sample intervals are too noisy: the older sample is kept instead."""
    MAX_INTERVAL_S = 2.0
    """Over longer intervals the link may have idled in between: not a capacity sample."""
    MIN_MEASURED_S = 1.0
    """Backlogged time needed before the first estimate."""

    def __init__(self, window_s: float = 10.0) -> None:
        if not window_s > 0:
            raise ValueError(f"window_s must be positive, got {window_s}")
        self.window_s = window_s
        self.outbox_bytes = 0  # bytes waiting in the link (sent or not, unacknowledged)
        self._acked: tuple[float, int] | None = None  # last sample (now, acked bytes total)
        self._rates: deque[tuple[float, float, int]] = deque()  # (now, s, B), backlogged
        self._last_rate: float | None = None  # the last estimate [B/s]
        self._acked_total: int | None = None
        self._progress_t: float | None = None  # when the link last moved [s]

    def on_link(self, now: float, outbox_bytes: int, acked_bytes: int) -> None:
        """The link's load at ``now``: bytes waiting (sent or not, unacknowledged) and the
        bytes acknowledged so far (a running total)."""
        prev, prev_outbox = self._acked, self.outbox_bytes
        self.outbox_bytes = int(outbox_bytes)
        if self.outbox_bytes == 0 or self._acked_total is None or acked_bytes > self._acked_total:
            self._progress_t = now  # the link moves (or has nothing to move)
        self._acked_total = int(acked_bytes)
        self._acked = (now, int(acked_bytes))
        if prev is None:
            return
        dt, db = now - prev[0], int(acked_bytes) - prev[1]
        backlogged = prev_outbox > 0 and self.outbox_bytes > 0
        if self.MIN_INTERVAL_S <= dt <= self.MAX_INTERVAL_S and backlogged:
            self._rates.append((now, dt, db))
        elif dt < self.MIN_INTERVAL_S:
            self._acked = prev  # keep the older sample: measure over a longer interval
        while self._rates and self._rates[0][0] < now - self.window_s:
            self._rates.popleft()

    def rate_Bps(self) -> float | None:
        """The measured rate [B/s]; None until one second of backlogged time was seen (the
        last estimate holds while there is no new sample, e.g. during a cut)."""
        secs = sum(dt for _, dt, _ in self._rates)
        acked = sum(db for _, _, db in self._rates)
        if secs >= self.MIN_MEASURED_S and acked > 0:  # (nothing acknowledged: a stall)
            self._last_rate = acked / secs
        return self._last_rate

    def stalled(self, now: float, stall_s: float) -> bool:
        """Data waits and nothing was acknowledged for ``stall_s`` [s]."""
        t = self._progress_t
        return t is not None and now - t >= stall_s
