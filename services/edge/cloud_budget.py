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

- **rate**: each robot gets an equal share of ``headroom`` of the link's rate. A new robot
  keyframe carries the features that share paid for since the robot's last uplinked one
  (its camera time since then × the share / the link's measured bytes per uplinked
  feature, everything it carried over the last ``window_s`` included: points, poses,
  status), those on map points first, the rest spread over the image. If that is fewer than
  ``min_features`` it stays on the edge, and the next one has more time behind it. So at a
  low rate keyframes go up further apart and smaller, rather than only further apart:
  keeping whole keyframes back made the map too sparse to merge (``budget_cloud.md``);
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
        window_s: bytes per feature and the acknowledgement rate are measured over this long
            (20 s: several keyframes of every robot).
        min_features: a keyframe that could carry fewer stays on the edge (300, as on the
            robot: fewer cost place recognition and the merge's verification their matches).
    """

    budget_kbps: float | None = None
    auto: bool = False
    max_delay_s: float = 3.0
    headroom: float = 0.8
    window_s: float = 20.0
    min_features: int = 300

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
    """What one robot's session may uplink next: ``share_Bps`` of the link [B/s] at
    ``bytes_per_feature`` [B] (everything the link carries per uplinked feature), keyframes
    of at least ``min_features``; none while ``hold`` (the link is behind)."""

    share_Bps: float = 0.0
    bytes_per_feature: float = 1.0
    min_features: int = 300
    hold: bool = False

    def features(self, since_s: float) -> int:
        """Features a keyframe ``since_s`` [s] of camera time after the robot's last uplinked
        one may carry (in steps of 50: the measured sizes move a little all the time); 0:
        it stays on the edge."""
        if self.hold:
            return 0
        n = 50 * int(self.share_Bps * since_s / self.bytes_per_feature / 50)
        return n if n >= self.min_features else 0


class CloudBudget:
    """Measures the edge->cloud link and hands out :class:`KeyframeAllowance` (see the
    module docstring). One per edge: its robots share the link."""

    def __init__(self, config: CloudBudgetConfig | None = None) -> None:
        self.config = config or CloudBudgetConfig()
        self.link = DeliveryRate(self.config.window_s)
        self._sent: deque[tuple[float, int, int]] = deque()  # (now, bytes, features)
        self.sent_bytes = 0
        self.sent_keyframes = 0

    # ------------------------------------------------------------------ in
    def on_link(self, now: float, outbox_bytes: int, acked_bytes: int) -> None:
        """The link's load at ``now``: bytes waiting and bytes acknowledged so far."""
        self.link.on_link(now, outbox_bytes, acked_bytes)

    def on_sent(self, now: float, nbytes: int, features: int = 0) -> None:
        """A message of ``nbytes`` was handed to the link (a keyframe: with ``features``)."""
        self._sent.append((now, int(nbytes), int(features)))
        self.sent_bytes += int(nbytes)
        self.sent_keyframes += int(features > 0)
        while self._sent and self._sent[0][0] < now - self.config.window_s:
            self._sent.popleft()

    # ------------------------------------------------------------------ out
    def rate_Bps(self) -> float | None:
        """The link's rate [B/s] the allowance uses (None: no budget, or none measured)."""
        cfg = self.config
        if cfg.auto:
            return self.link.rate_Bps()
        return None if cfg.budget_kbps is None else cfg.budget_kbps * 1000.0 / 8.0

    def bytes_per_feature(self) -> float | None:
        """Everything the link carried over the window per keyframe feature in it [B] (None:
        no keyframe in the window)."""
        n = sum(f for _, _, f in self._sent)
        return sum(b for _, b, _ in self._sent) / n if n else None

    def allowance(self, robots: int) -> KeyframeAllowance | None:
        """The allowance of each of ``robots`` sharing the link (None: every keyframe goes
        whole: no budget, or nothing measured yet)."""
        rate = self.rate_Bps()
        if rate is None:
            return None
        cfg = self.config
        if self.link.outbox_bytes / rate > cfg.max_delay_s:
            return KeyframeAllowance(hold=True)
        per_feature = self.bytes_per_feature()
        if per_feature is None:
            return None
        share = cfg.headroom * rate / max(1, robots)
        return KeyframeAllowance(share, per_feature, cfg.min_features)

    def stats(self) -> dict[str, Any]:
        rate = self.rate_Bps()
        per_feature = self.bytes_per_feature()
        return {
            "budget_kbps": self.config.budget_kbps,
            "auto": self.config.auto,
            "rate_kbps": None if rate is None else round(rate * 8e-3, 1),
            "bytes_per_feature": None if per_feature is None else round(per_feature, 1),
            "sent_keyframes": self.sent_keyframes,
            "sent_bytes": self.sent_bytes,
        }
