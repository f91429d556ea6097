"""When to resend on a live connection: the retransmission timer of a :class:`Session`.

Like aioquic's ``recovery.py``, the policy lives apart from the state machine and takes time
only as ``now`` (seconds). Two facts shape it:

- The peer acknowledges a message once its *application* delivered it, so the time to an ack
  is the round trip plus the peer's handler time. The timer adapts to it as TCP's does
  (RFC 6298: smoothed RTT and its variation, Karn's rule: no sample from a resent message),
  never below the configured ``retransmit_timeout`` and never above ``max_retransmit_timeout``.
- The connection is TCP: while it is alive, a frame sent on it arrives. A missing ack from a
  peer that has been heard from since the timer was armed (any frame: data, ack, heartbeat)
  means a busy handler, not a lost message, and resending would only make a duplicate (#20:
  robots re-sent ~200 frames each to a busy edge). Then the timer is re-armed and the event
  counted (``late_acks``); only a peer silent for the whole timeout gets the oldest message
  again (the dead-connection case, until the idle timeout closes it and the reconnect
  replays everything unacknowledged).
"""

from __future__ import annotations

from dataclasses import dataclass, field

CLOCK_GRANULARITY_S = 0.01
"""RFC 6298's G: the variation term never counts below this (s)."""


@dataclass
class RetransmitTimer:
    """The retransmission timer of one connection (see the module docstring).

    Attributes:
        min_s: floor of the timeout (the configured ``retransmit_timeout``).
        max_s: cap of the timeout, also of its doubling on resends.
        srtt_s / rttvar_s: smoothed time to an ack and its variation (None before a sample).
        rto_s: the current timeout.
        deadline: when it fires (None: nothing in flight).
        late_acks: times it fired while the peer was talking (no resend).
    """

    min_s: float
    max_s: float
    srtt_s: float | None = None
    rttvar_s: float = 0.0
    rto_s: float = 0.0
    deadline: float | None = None
    late_acks: int = 0
    _armed_at: float = 0.0
    _sent_at: dict[int, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 0 < self.min_s <= self.max_s:
            raise ValueError(f"need 0 < min_s <= max_s, got {self.min_s}, {self.max_s}")
        self.rto_s = self.min_s

    # ------------------------------------------------------------------ samples
    def on_sent(self, seq: int, now: float, resent: bool) -> None:
        """Message ``seq`` went out (``resent``: not for the first time: Karn, no sample)."""
        if resent:
            self._sent_at.pop(seq, None)
        else:
            self._sent_at[seq] = now

    def on_acked(self, ack: int, now: float) -> None:
        """Everything up to ``ack`` was delivered: sample the time to ``ack``'s ack."""
        sent = self._sent_at.get(ack)
        for seq in [s for s in self._sent_at if s <= ack]:
            del self._sent_at[seq]
        if sent is not None:
            self._sample(now - sent)
        self.rto_s = self._timeout()

    def _sample(self, rtt_s: float) -> None:
        rtt_s = max(0.0, rtt_s)
        if self.srtt_s is None:
            self.srtt_s, self.rttvar_s = rtt_s, rtt_s / 2
        else:
            self.rttvar_s = 0.75 * self.rttvar_s + 0.25 * abs(self.srtt_s - rtt_s)
            self.srtt_s = 0.875 * self.srtt_s + 0.125 * rtt_s

    def _timeout(self) -> float:
        if self.srtt_s is None:
            return self.min_s
        rto = self.srtt_s + max(CLOCK_GRANULARITY_S, 4 * self.rttvar_s)
        return min(max(rto, self.min_s), self.max_s)

    def forget(self) -> None:
        """A new connection: what was in flight is resent (no samples from it)."""
        self._sent_at.clear()
        self.deadline = None
        self.rto_s = self._timeout()

    # ------------------------------------------------------------------ the timer
    def arm(self, now: float) -> None:
        self.deadline = now + self.rto_s
        self._armed_at = now

    def disarm(self) -> None:
        self.deadline = None

    def due(self, now: float, last_rx: float) -> bool:
        """The timer fired at ``now``: True to resend the oldest in-flight message (and
        back off), False if the peer was heard from meanwhile (re-armed, counted late)."""
        if self.deadline is None or now < self.deadline:
            return False
        if last_rx > self._armed_at:
            self.late_acks += 1
            self.arm(now)
            return False
        self.rto_s = min(2 * self.rto_s, self.max_s)
        self.deadline = now + self.rto_s
        self._armed_at = now
        return True
