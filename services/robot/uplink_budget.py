"""The robot's uplink budget: which non-keyframes go to the edge (sans-I/O rate control).

The link carries two classes of data (the issue's "fresh before complete"):

- **complete**: keyframes, the sensor description and every IMU sample go exactly once and in
  order, whatever the budget (the transport's reliable stream);
- **fresh**: non-keyframes are latest-wins. One is coded and handed to the link only if (a)
  the non-keyframe rate the budget affords has come round again and (b) what already waits
  in the link drains within ``max_delay_s`` at the link's rate; otherwise it is left out
  before coding (the tracker still tracks it; its IMU goes with the next frame sent, so the
  edge's VIO integrates across the gap). A non-keyframe is therefore never queued behind
  seconds of backlog: like ROS "keep last" QoS with a depth of one, or a QUIC datagram beside
  a stream, but on the one ordered, lossless stream the paper asks for (what is sent stays
  bit-exact; only the subset is chosen). Frames left out are counted by reason.

Keyframes are planned to fit (:meth:`UplinkBudget.keyframe_plan`): fewer features and further
apart at low rates. Even lost tracking takes a keyframe no sooner than the link has carried
the last one (a stretch of lost tracking on a real flight otherwise sent a 7 kB keyframe every
0.1-0.2 s, seconds of backlog at 50 kbit/s; the tracker tops its tracks up with corners on the
frames between). While the link is behind (an outage), keyframes are held to those tracking
needs (tracking lost), so the reliable backlog stays small and drains soon after the link is
back; once nothing has been acknowledged for ``stall_s`` with data waiting (the link is
down), every frame is left out, keyframes too: what is made during an outage would arrive
stale, and the edge's VIO starts a new map after the gap, which the cloud merges by place
recognition like any other, when it recognises the place (the frames before the outage stay
exactly-once in the reliable backlog).

The non-keyframe rate is the highest of ``rates_hz`` whose bytes fit in what the budget leaves
after the IMU and the keyframes (all measured over the last ``window_s`` of what was sent;
the IMU always goes, and a real MAV's vibrating IMU costs ~12 kbit/s, twice a clean one's;
keyframes keep their share: fewer of them cost the edge's VIO accuracy), with
``headroom`` to spare: at 50 kbit/s and ~20 kB keyframes every two seconds nothing is left
and the rate is the lowest; the backlog rule then drops what would still be late.

The link's rate is the budget the user gives (``--uplink-budget KBPS``), or, with ``auto``,
estimated from the transport's acknowledgements the way a delay-based congestion controller
(BBR's delivery rate) does: bytes acknowledged per second over the intervals in which the
link had a backlog (an idle link says nothing about its capacity): the bytes acknowledged in
those intervals over their total time, in the last ``window_s`` (a ratio of sums: one ack can
cover a 20 kB keyframe at once, so a single interval's rate, or their maximum, overstates the
link many times over), reported from one second of such time on; the last estimate holds while
the link says nothing (cut); before the first estimate every frame goes.

No clock, no sockets here: ``now`` (monotonic s) and the link's load
(:meth:`UplinkBudget.on_link`) come in, decisions go out.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

from common.protocol.delivery_rate import DeliveryRate

logger = logging.getLogger(__name__)

REASONS = ("rate", "backlog", "outage")
"""Why a frame was left out: the budget's non-keyframe rate, the link's backlog (both
non-keyframes only), or an outage (keyframes too)."""


@dataclass(frozen=True)
class KeyframePlan:
    """Keyframes that fit the budget: at most ``n_features`` features, at least
    ``min_interval_s`` apart, and at least ``lost_min_interval_s`` apart when tracking is
    lost (``FrontEnd.set_keyframe_plan`` applies it)."""

    n_features: int
    min_interval_s: float
    lost_min_interval_s: float = 0.0


@dataclass(frozen=True)
class UplinkBudgetConfig:
    """The robot's uplink budget (``recslam robot --uplink-budget``).

    Attributes:
        budget_kbps: the link's rate [kbit/s]; None: no budget (every frame is sent, in order,
            as fast as the link takes it: the lossless recorder, today's default).
        auto: estimate the rate from the link's acknowledgements instead (``budget_kbps``
            is then ignored).
        max_delay_s: a non-keyframe is left out when the backlog ahead of it would take
            longer than this to drain at the link's rate, and a keyframe is planned no
            bigger than this much of the link (0.7 s: the pose is due back within 1 s of the
            camera, and tracking, the edge's VIO and the way back took 0.2-0.3 s in the
            one-robot runs of ``budget.md``).
        rates_hz: the non-keyframe rates to choose from, highest first (the camera's 20 Hz,
            then 10 and 5: the VIO bridges a 0.2 s gap with the IMU alone).
        headroom: share of the rate the frames are planned to fill (0.8: the transport's
            framing, acks and the edge's poses on the way back share the link).
        window_s: the sizes and the acknowledgement rate are measured over this long (10 s:
            several keyframes).
        keyframe_share: share of the planned rate for keyframes (0.6; the rest carries the
            IMU, measured, and the non-keyframes in what the IMU leaves).
        bytes_per_feature: a keyframe's bytes per feature until one was sent (21: ~170
            bits, keypoint ~20 b + ORB descriptor ~150 b under the context model,
            ``codec.md``); then what the keyframes sent in the last ``window_s`` cost (a
            feature that continues a track costs no descriptor, so it depends on the motion).
        stall_s: nothing acknowledged for this long [s] with data waiting is an outage
            (2 s: a 6 kB keyframe's ack at 50 kbit/s takes ~1 s).
        min_features, keyframe_period_s: a keyframe plan keeps the features that
            ``keyframe_period_s`` of the keyframes' share pays for, at least ``min_features``
            (300: fewer cost the edge's VIO its robustness), and spaces keyframes so that they
            fit (at 50 kbit/s: 300 features about every 2 s).
    """

    budget_kbps: float | None = None
    auto: bool = False
    max_delay_s: float = 0.7
    rates_hz: tuple[float, ...] = (20.0, 10.0, 5.0)
    headroom: float = 0.8
    window_s: float = 10.0
    keyframe_share: float = 0.6
    bytes_per_feature: float = 21.0
    min_features: int = 300
    keyframe_period_s: float = 1.5
    stall_s: float = 2.0

    def __post_init__(self) -> None:
        if self.budget_kbps is not None and not self.budget_kbps > 0:
            raise ValueError(f"budget_kbps must be positive, got {self.budget_kbps}")
        if not self.max_delay_s > 0 or not self.window_s > 0:
            raise ValueError("max_delay_s and window_s must be positive")
        if not self.rates_hz or any(not r > 0 for r in self.rates_hz):
            raise ValueError(f"rates_hz must be positive rates, got {self.rates_hz}")
        if not 0 < self.headroom <= 1:
            raise ValueError(f"headroom must be in (0, 1], got {self.headroom}")

    @property
    def active(self) -> bool:
        """A budget applies (given or estimated)."""
        return self.auto or self.budget_kbps is not None

    @staticmethod
    def parse(text: str | None) -> UplinkBudgetConfig:
        """``None``/``"unlimited"``: no budget; ``"auto"``: estimated; else kbit/s."""
        if text is None or text in ("", "unlimited", "none"):
            return UplinkBudgetConfig()
        if text == "auto":
            return UplinkBudgetConfig(auto=True)
        try:
            kbps = float(text)
        except ValueError:
            msg = f"uplink budget {text!r}: give kbit/s, 'auto' or 'unlimited'"
            raise ValueError(msg) from None
        return UplinkBudgetConfig(budget_kbps=kbps)


class UplinkBudget:
    """Decides, frame by frame, whether a non-keyframe goes (see the module docstring)."""

    def __init__(self, config: UplinkBudgetConfig | None = None) -> None:
        self.config = config or UplinkBudgetConfig()
        self.left_out: dict[str, int] = dict.fromkeys(REASONS, 0)
        self.sent_keyframes = self.sent_non_keyframes = 0
        # (now, feature bytes, IMU bytes, keyframe) of each frame sent in the last window_s
        self._sent: deque[tuple[float, int, int, bool]] = deque()
        self._kf_sent: deque[tuple[float, int, int]] = deque()  # (now, bytes, features)
        self._last_nkf: float | None = None  # when the last non-keyframe went [s]
        self.link = DeliveryRate(self.config.window_s)  # the link's load and measured rate
        self.rate_hz = self.config.rates_hz[0]

    # ------------------------------------------------------------------ in
    def on_link(self, now: float, outbox_bytes: int, acked_bytes: int) -> None:
        """The link's load at ``now``: bytes waiting (sent or not, unacknowledged) and the
        bytes acknowledged so far (a running total)."""
        self.link.on_link(now, outbox_bytes, acked_bytes)

    def on_sent(
        self, now: float, nbytes: int, keyframe: bool, features: int = 0, imu_bytes: int = 0
    ) -> None:
        """A frame of ``nbytes`` was handed to the link (a keyframe: of ``features``), of
        which ``imu_bytes`` are its IMU samples."""
        own = int(nbytes) - int(imu_bytes)
        self._sent.append((now, own, int(imu_bytes), bool(keyframe)))
        if keyframe:
            self.sent_keyframes += 1
            if features > 0:
                self._kf_sent.append((now, own, int(features)))
                while len(self._kf_sent) > 1 and self._kf_sent[0][0] < now - self.config.window_s:
                    self._kf_sent.popleft()
        else:
            self.sent_non_keyframes += 1
            self._last_nkf = now
        while self._sent and self._sent[0][0] < now - self.config.window_s:
            self._sent.popleft()

    # ------------------------------------------------------------------ out
    def bytes_per_feature(self) -> float:
        """What a keyframe's feature costs [B]: measured over the keyframes of the last
        ``window_s`` (at least the last one), ``bytes_per_feature`` before any."""
        features = sum(f for _, _, f in self._kf_sent)
        if not features:
            return self.config.bytes_per_feature
        return sum(b for _, b, _ in self._kf_sent) / features

    def rate_Bps(self) -> float | None:
        """The link's rate [B/s] the decisions use (None: no budget, or none measured yet)."""
        cfg = self.config
        if cfg.auto:  # (no sample for a while, e.g. an outage: the last estimate holds)
            return self.link.rate_Bps()
        return None if cfg.budget_kbps is None else cfg.budget_kbps * 1000.0 / 8.0

    def keyframe_plan(self, max_features: int = 1000) -> KeyframePlan | None:
        """The keyframes the budget affords (None: no budget, or no rate measured yet):
        features for ``keyframe_period_s`` of the keyframes' share, at most what the link
        carries in ``max_delay_s`` (between ``min_features`` and ``max_features``), and the
        interval at which such keyframes fit."""
        rate = self.rate_Bps()
        if rate is None:
            return None
        cfg = self.config
        share = cfg.keyframe_share * cfg.headroom * rate  # B/s for keyframes
        per_feature = self.bytes_per_feature()
        n = share * cfg.keyframe_period_s / per_feature
        # ... and no keyframe holds the frames behind it back longer than max_delay_s
        n = min(n, rate * cfg.headroom * cfg.max_delay_s / per_feature)
        n = max(cfg.min_features, min(max_features, 50 * round(n / 50)))
        # Even when tracking is lost, no keyframe before the link has carried the last one.
        lost_s = round(n * per_feature / (cfg.headroom * rate), 1)
        if self.link.outbox_bytes / rate > cfg.max_delay_s:
            # The link is behind (an outage, or a keyframe still going out): no keyframe
            # but those tracking needs (tracking lost), so the backlog the link must drain
            # once it is back holds no more than the map needs.
            return KeyframePlan(n, math.inf, lost_s)
        # (in steps of 50 features and 0.1 s: an estimated rate moves a little all the time)
        return KeyframePlan(n, round(n * per_feature / share, 1), lost_s)

    def _window_s(self) -> float:
        """The span [s] the sizes in the window cover (at least 1 s)."""
        if not self._sent:
            return 1.0
        return min(self.config.window_s, max(1.0, self._sent[-1][0] - self._sent[0][0]))

    def _imu_Bps(self) -> float:
        """What the IMU cost over the window [B/s]."""
        return sum(i for _, _, i, _ in self._sent) / self._window_s()

    def _left_by_imu(self, rate: float) -> float:
        """What the planned rate leaves after the IMU [B/s] (the IMU always goes), at least a
        tenth of it."""
        planned = self.config.headroom * rate
        return max(0.1 * planned, planned - self._imu_Bps())

    def hold_back(self, now: float) -> str:
        """Why the next frame, unless the tracker makes it a keyframe, is left out (one of
        :data:`REASONS`), or ``""``: it goes. :meth:`left` counts it once it is known."""
        rate = self.rate_Bps()
        if rate is None:
            return ""
        if self.outage(now):
            return "outage"
        if self.link.outbox_bytes / rate > self.config.max_delay_s:
            return "backlog"
        self.rate_hz = self._choose_rate(rate)
        if self._last_nkf is not None and now - self._last_nkf < 0.9 / self.rate_hz:
            return "rate"
        return ""

    def outage(self, now: float) -> bool:
        """Data waits and nothing was acknowledged for ``stall_s`` (a budget applies)."""
        return self.config.active and self.link.stalled(now, self.config.stall_s)

    def left(self, reason: str) -> None:
        """A non-keyframe was left out for ``reason``."""
        self.left_out[reason] += 1

    def _choose_rate(self, rate: float) -> float:
        """The highest non-keyframe rate whose bytes fit beside the IMU's and the keyframes'."""
        cfg = self.config
        kf = [b for _, b, _, k in self._sent if k]
        nkf = [b for _, b, _, k in self._sent if not k]
        if not nkf:
            return cfg.rates_hz[0]
        left = self._left_by_imu(rate) - sum(kf) / self._window_s()
        size = sum(nkf) / len(nkf)
        for hz in cfg.rates_hz:
            if hz * size <= left:
                return hz
        return cfg.rates_hz[-1]

    def stats(self) -> dict[str, Any]:
        rate = self.rate_Bps()
        return {
            "budget_kbps": self.config.budget_kbps,
            "auto": self.config.auto,
            "rate_kbps": None if rate is None else round(rate * 8e-3, 1),
            "bytes_per_feature": round(self.bytes_per_feature(), 1),
            "imu_kbps": round(8e-3 * self._imu_Bps(), 1),
            "non_keyframe_hz": self.rate_hz,
            "left_out": dict(self.left_out),
            "sent_keyframes": self.sent_keyframes,
            "sent_non_keyframes": self.sent_non_keyframes,
        }
