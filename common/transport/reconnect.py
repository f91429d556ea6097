"""When a client reconnects, when it warns, and when it gives up: a sans-I/O policy.

:class:`ReconnectPolicy` never sleeps, connects or reads a clock: the client tells it how
each attempt ended (``now`` passed in) and it answers with a :class:`Retry` (wait this long,
warn or not) or a :class:`GiveUp` (no session for ``give_up_after`` seconds). An *outage*
starts when the client starts or when an established session ends; every attempt that does
not end in an established session (the TCP connect failed, timed out, or the server closed
the connection before the handshake completed) counts against it.

- Delays double from ``reconnect_initial_delay`` to ``reconnect_max_delay``, each jittered by
  ``reconnect_jitter``; after an established session they start again from the initial delay.
- The first failed attempt of an outage is to be logged at WARNING, then at most every
  ``unreachable_warning_interval`` seconds.
- With ``give_up_after`` > 0 the wait before the next attempt never passes the outage's
  deadline (so the last attempt is made at it, not up to a whole backoff later), and the
  first failed attempt at or past the deadline gives up. 0 retries for ever.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol


class ReconnectSettings(Protocol):
    """The fields of :class:`~common.transport.TransportConfig` the policy reads."""

    @property
    def reconnect_initial_delay(self) -> float: ...
    @property
    def reconnect_max_delay(self) -> float: ...
    @property
    def reconnect_jitter(self) -> float: ...
    @property
    def unreachable_warning_interval(self) -> float: ...
    @property
    def give_up_after(self) -> float: ...


@dataclass(frozen=True)
class Retry:
    """Attempt again after ``delay`` seconds; ``warn``: log this failure at WARNING.
    ``attempts`` and ``down_s``: failed attempts and seconds since the outage began."""

    delay: float
    warn: bool
    attempts: int
    down_s: float


@dataclass(frozen=True)
class GiveUp:
    """No session for ``down_s`` seconds over ``attempts`` attempts: stop reconnecting."""

    attempts: int
    down_s: float


class ReconnectPolicy:
    """The reconnect schedule of one client (see the module docstring).

    Args:
        settings: a ``TransportConfig`` (delays, jitter, warning interval, give-up time).
        now: when the client starts (the first outage begins then).
        uniform: ``uniform(a, b)`` for the jitter (default :func:`random.uniform`).
    """

    def __init__(
        self,
        settings: ReconnectSettings,
        now: float,
        uniform: Callable[[float, float], float] = random.uniform,
    ) -> None:
        self._s = settings
        self._uniform = uniform
        self._since = now
        self._attempts = 0
        self._delay = settings.reconnect_initial_delay
        self._warned_at: float | None = None

    def attempt_ended(self, now: float, *, established: bool) -> Retry | GiveUp:
        """An attempt ended at ``now``: ``established`` if it carried a session (which has
        now ended, starting a new outage), else it failed."""
        s = self._s
        if established:
            self._since, self._attempts, self._warned_at = now, 0, None
            self._delay = s.reconnect_initial_delay
            return Retry(self._next_delay(now), warn=False, attempts=0, down_s=0.0)
        self._attempts += 1
        down = now - self._since
        if s.give_up_after > 0 and down >= s.give_up_after:
            return GiveUp(self._attempts, down)
        warn = self._warned_at is None or now - self._warned_at >= s.unreachable_warning_interval
        if warn:
            self._warned_at = now
        return Retry(self._next_delay(now), warn=warn, attempts=self._attempts, down_s=down)

    def _next_delay(self, now: float) -> float:
        s = self._s
        delay = self._delay * self._uniform(1.0 - s.reconnect_jitter, 1.0 + s.reconnect_jitter)
        self._delay = min(2 * self._delay, s.reconnect_max_delay)
        if s.give_up_after > 0:
            delay = min(delay, max(0.0, self._since + s.give_up_after - now))
        return delay
