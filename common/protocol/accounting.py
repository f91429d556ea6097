"""Traffic counters per link: bytes and messages per direction and per message type.

Bytes are bytes on the wire (frame header included). Other components (dashboard, reports,
benchmarks) read :meth:`TrafficCounters.snapshot`, which returns plain data::

    {"tx": {"messages": 12, "bytes": 3456,
            "by_type": {"Blob": {"messages": 10, "bytes": 3300}, "Hello": {...}}},
     "rx": {...},
     "retransmitted_messages": 0, "retransmitted_bytes": 0,
     "duplicates_dropped": 0, "late_acks": 0, "connections": 1}
"""

from __future__ import annotations

from typing import Any, Literal

Direction = Literal["tx", "rx"]


class TrafficCounters:
    """Mutable counters owned by one link (plain ints, cheap to update)."""

    def __init__(self) -> None:
        self._by_type: dict[Direction, dict[str, list[int]]] = {"tx": {}, "rx": {}}
        self.retransmitted_messages = 0
        self.retransmitted_bytes = 0
        self.duplicates_dropped = 0
        self.late_acks = 0  # retransmit timeouts while the peer was talking (no resend)
        self.connections = 0

    def record(self, direction: Direction, type_name: str, nbytes: int) -> None:
        """Count one frame of ``nbytes`` bytes (header included)."""
        entry = self._by_type[direction].get(type_name)
        if entry is None:
            entry = self._by_type[direction][type_name] = [0, 0]
        entry[0] += 1
        entry[1] += nbytes

    def merge(self, other: TrafficCounters) -> None:
        """Add ``other``'s counts into these (used when a handshake learns its link)."""
        for direction in ("tx", "rx"):
            for name, (n, b) in other._by_type[direction].items():
                entry = self._by_type[direction].setdefault(name, [0, 0])
                entry[0] += n
                entry[1] += b
        self.retransmitted_messages += other.retransmitted_messages
        self.retransmitted_bytes += other.retransmitted_bytes
        self.duplicates_dropped += other.duplicates_dropped
        self.late_acks += other.late_acks
        self.connections += other.connections

    def total(self, direction: Direction) -> tuple[int, int]:
        """(messages, bytes) in one direction, all types."""
        entries = self._by_type[direction].values()
        return sum(e[0] for e in entries), sum(e[1] for e in entries)

    def snapshot(self) -> dict[str, Any]:
        """Plain-data copy of every counter (safe to keep, serialise or plot)."""
        out: dict[str, Any] = {}
        for direction in ("tx", "rx"):
            n, b = self.total(direction)
            out[direction] = {
                "messages": n,
                "bytes": b,
                "by_type": {
                    name: {"messages": e[0], "bytes": e[1]}
                    for name, e in sorted(self._by_type[direction].items())
                },
            }
        out["retransmitted_messages"] = self.retransmitted_messages
        out["retransmitted_bytes"] = self.retransmitted_bytes
        out["duplicates_dropped"] = self.duplicates_dropped
        out["late_acks"] = self.late_acks
        out["connections"] = self.connections
        return out
