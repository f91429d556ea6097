"""How long a service's event loop went without turning: the measure of its responsiveness.

A peer times out when the loop that should answer it does not run for ``idle_timeout``
seconds, so the longest stall is the number that matters (#20: an edge starting six VIO
workers once stalled long enough for every robot to time out).

:class:`StallStats` is the policy-free record (lags in, a plain-data snapshot out);
:class:`StallMonitor` is the thin asyncio part: a task that sleeps ``interval_s`` and records
how late it woke. A wake-up later than ``warn_s`` is logged as a warning with its length, so a
stall is visible in the service's log where it happened.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from dataclasses import dataclass, field
from typing import Any

logger = logging.getLogger(__name__)

BUCKETS_S = (0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0)
"""Upper bounds (s) of the stall histogram; the last bucket counts everything longer."""


@dataclass
class StallStats:
    """Lags (s) of one loop's wake-ups: count, max, a histogram over :data:`BUCKETS_S`."""

    samples: int = 0
    max_s: float = 0.0
    total_s: float = 0.0
    histogram: list[int] = field(default_factory=lambda: [0] * (len(BUCKETS_S) + 1))

    def observe(self, lag_s: float) -> None:
        lag_s = max(0.0, lag_s)
        self.samples += 1
        self.total_s += lag_s
        self.max_s = max(self.max_s, lag_s)
        for i, bound in enumerate(BUCKETS_S):
            if lag_s <= bound:
                self.histogram[i] += 1
                return
        self.histogram[-1] += 1

    def over(self, seconds: float) -> int:
        """Wake-ups later than ``seconds`` (rounded up to a bucket bound of BUCKETS_S)."""
        first = next((i + 1 for i, b in enumerate(BUCKETS_S) if b >= seconds), len(BUCKETS_S))
        return sum(self.histogram[first:])

    def snapshot(self) -> dict[str, Any]:
        return {
            "samples": self.samples,
            "max_s": round(self.max_s, 4),
            "mean_s": round(self.total_s / self.samples, 5) if self.samples else 0.0,
            "over_1s": self.over(1.0),
            "histogram": {
                **{f"<={b:g}s": n for b, n in zip(BUCKETS_S, self.histogram, strict=False)},
                f">{BUCKETS_S[-1]:g}s": self.histogram[-1],
            },
        }


class StallMonitor:
    """Measures the running loop's stalls: ``start()`` (in the loop) ... ``await stop()``."""

    def __init__(self, name: str, interval_s: float = 0.05, warn_s: float = 1.0) -> None:
        if interval_s <= 0:
            raise ValueError(f"interval_s must be > 0: {interval_s}")
        self.name = name
        self.interval_s = interval_s
        self.warn_s = warn_s
        self.stats = StallStats()
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name=f"stall-monitor-{self.name}"
            )

    async def _run(self) -> None:
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(self.interval_s)
            lag = time.monotonic() - t0 - self.interval_s
            self.stats.observe(lag)
            if lag > self.warn_s:
                logger.warning("%s: event loop stalled for %.2f s", self.name, lag)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
