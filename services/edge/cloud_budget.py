"""The edge's cloud budget: which robot keyframes go up to the cloud (sans-I/O rate control).

``recslam edge --cloud-budget KBPS|auto``. Everything the edge sends the cloud stays
exactly-once and in order (keyframes, their points, pose updates, culls, status); what the
budget chooses is the subset of robot keyframes that go up. A robot keyframe the budget does
not take stays on the edge, as the VIO's own keyframes do: the next uplinked keyframe chains
to the previous uplinked one and carries the IMU since it, points are sent once an uplinked
keyframe observes them and their observations in kept-back keyframes are not sent, and the
edge's VIO still uses every keyframe. The cloud's map is then sparser in time, as after map
backbone profiling, which prunes 18-34 % of the keyframes anyway (``mbp_live.md``).

Two rules, as on the robot's uplink (``services/robot/uplink_budget.py``):

- **rate**: a robot's next keyframe goes up once ``min_interval_s`` of its camera time has
  passed since its last uplinked one, where the interval is what the link affords: the
  edge->cloud bytes per uplinked keyframe (everything the link carried over the last
  ``window_s``, points and poses included, over the keyframes in it) times the robots sharing
  the link, over ``headroom`` of the link's rate;
- **backlog**: while what already waits in the link would take longer than ``max_delay_s``
  to drain, new keyframes stay on the edge (a cut, or a burst): the reliable backlog stays
  what the map needs, and drains soon after the link is back.

A map's first keyframe always goes (the cloud must know the map to merge it). The link's rate
is the budget the user gives, or with ``auto`` the one its acknowledgements show
(:class:`~common.protocol.delivery_rate.DeliveryRate`); before a first estimate every keyframe
goes. The driver (``EdgeApp``) gives the budget the link's load and each message sent, and
hands each robot's session a :class:`KeyframeAllowance` before it turns the VIO's next
results into messages; the session applies it (``SessionUplink``).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Any

from common.protocol.delivery_rate import DeliveryRate

logger = logging.getLogger(__name__)

REASONS = ("rate", "backlog")
"""Why a robot keyframe stayed on the edge."""


@dataclass(frozen=True)
class CloudBudgetConfig:
    """The edge's cloud budget (``recslam edge --cloud-budget``).

    Attributes:
        budget_kbps: the edge->cloud link's rate [kbit/s]; None: no budget (every robot
            keyframe goes up: today's default).
        auto: estimate the rate from the link's acknowledgements instead.
        max_delay_s: new keyframes stay on the edge while the link's backlog would take
            longer than this to drain (3 s: the cloud's work is not per frame, but a map that
            falls further behind merges later and sends its corrections later).
        headroom: share of the rate the keyframes (and what they bring) are planned to fill
            (0.8: status, heartbeats and the transport's framing share the link).
        window_s: bytes per keyframe and the acknowledgement rate are measured over this long
            (20 s: several keyframes of every robot).
    """

    budget_kbps: float | None = None
    auto: bool = False
    max_delay_s: float = 3.0
    headroom: float = 0.8
    window_s: float = 20.0

    def __post_init__(self) -> None:
        if self.budget_kbps is not None and not self.budget_kbps > 0:
            raise ValueError(f"cloud budget_kbps must be positive, got {self.budget_kbps}")
        if not self.max_delay_s > 0 or not self.window_s > 0:
            raise ValueError("cloud budget max_delay_s and window_s must be positive")
        if not 0 < self.headroom <= 1:
            raise ValueError(f"cloud budget headroom must be in (0, 1], got {self.headroom}")

    @property
    def active(self) -> bool:
        """A budget applies (given or estimated)."""
        return self.auto or self.budget_kbps is not None

    @staticmethod
    def parse(text: str | None) -> CloudBudgetConfig:
        """``None``/``"unlimited"``: no budget; ``"auto"``: estimated; else kbit/s."""
        if text is None or text in ("", "unlimited", "none"):
            return CloudBudgetConfig()
        if text == "auto":
            return CloudBudgetConfig(auto=True)
        try:
            kbps = float(text)
        except ValueError:
            msg = f"cloud budget {text!r}: give kbit/s, 'auto' or 'unlimited'"
            raise ValueError(msg) from None
        return CloudBudgetConfig(budget_kbps=kbps)


@dataclass(frozen=True)
class KeyframeAllowance:
    """What one robot's session may uplink next: robot keyframes at least ``min_interval_s``
    of camera time apart, none while ``hold`` (the link is behind)."""

    min_interval_s: float
    hold: bool = False


class CloudBudget:
    """Measures the edge->cloud link and hands out :class:`KeyframeAllowance` (see the
    module docstring). One per edge: its robots share the link."""

    def __init__(self, config: CloudBudgetConfig | None = None) -> None:
        self.config = config or CloudBudgetConfig()
        self.link = DeliveryRate(self.config.window_s)
        self._sent: deque[tuple[float, int, bool]] = deque()  # (now, bytes, keyframe)
        self.sent_bytes = 0
        self.sent_keyframes = 0

    # ------------------------------------------------------------------ in
    def on_link(self, now: float, outbox_bytes: int, acked_bytes: int) -> None:
        """The link's load at ``now``: bytes waiting and bytes acknowledged so far."""
        self.link.on_link(now, outbox_bytes, acked_bytes)

    def on_sent(self, now: float, nbytes: int, keyframe: bool) -> None:
        """A message of ``nbytes`` (a keyframe or not) was handed to the link."""
        self._sent.append((now, int(nbytes), bool(keyframe)))
        self.sent_bytes += int(nbytes)
        self.sent_keyframes += int(keyframe)
        while self._sent and self._sent[0][0] < now - self.config.window_s:
            self._sent.popleft()

    # ------------------------------------------------------------------ out
    def rate_Bps(self) -> float | None:
        """The link's rate [B/s] the allowance uses (None: no budget, or none measured)."""
        cfg = self.config
        if cfg.auto:
            return self.link.rate_Bps()
        return None if cfg.budget_kbps is None else cfg.budget_kbps * 1000.0 / 8.0

    def bytes_per_keyframe(self) -> float | None:
        """Everything the link carried over the window per keyframe in it [B] (None: no
        keyframe in the window)."""
        n = sum(1 for _, _, k in self._sent if k)
        return sum(b for _, b, _ in self._sent) / n if n else None

    def allowance(self, robots: int) -> KeyframeAllowance | None:
        """The allowance of each of ``robots`` sharing the link (None: every keyframe goes:
        no budget, or nothing measured yet)."""
        rate = self.rate_Bps()
        if rate is None:
            return None
        cfg = self.config
        if self.link.outbox_bytes / rate > cfg.max_delay_s:
            return KeyframeAllowance(0.0, hold=True)
        per_kf = self.bytes_per_keyframe()
        if per_kf is None:
            return None
        # (in steps of 0.1 s: the measured sizes move a little all the time)
        interval = max(1, robots) * per_kf / (cfg.headroom * rate)
        return KeyframeAllowance(round(interval, 1))

    def stats(self) -> dict[str, Any]:
        rate = self.rate_Bps()
        per_kf = self.bytes_per_keyframe()
        return {
            "budget_kbps": self.config.budget_kbps,
            "auto": self.config.auto,
            "rate_kbps": None if rate is None else round(rate * 8e-3, 1),
            "bytes_per_keyframe": None if per_kf is None else round(per_kf),
            "sent_keyframes": self.sent_keyframes,
            "sent_bytes": self.sent_bytes,
        }
