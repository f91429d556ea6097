"""The cloud service's counters, as ``CloudServer.stats`` returns them and ``--stats-out``
writes them (plain data)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class CloudStats:
    """Counters of a running service (plain data)."""

    messages: int
    rejected: int
    optimizations: int
    corrections_sent: int
    mbp_passes: int
    keyframes: int
    map_points: int
    maps: tuple[int, ...]
    merges: int
    loops: int
    full_ba_passes: int = 0
    worker_queue: int = 0
    """Messages received and waiting for (or being applied on) the worker thread now."""
    worker_queue_max: int = 0
    """The most there ever were (one per edge link at most: each delivers in order; the rest
    wait in the edges' outboxes, held back by the receive window)."""
    rebase: dict[str, float] = field(default_factory=dict)  # FrameRebase.summary
    overload: dict[str, float] = field(default_factory=dict)
    """The core's load shedding: ``overloaded`` (0/1 now), ``busy`` (the worker's busy
    share of the last window), ``overloads``, ``overloaded_s``, ``full_bas_deferred``."""
    stages: dict[str, dict[str, float]] = field(default_factory=dict)
    """Time per stage, ``{"stage.place_recognition": {"seconds": s, "messages": n}, ...}``:
    the worker thread's CPU time in the app's
    :attr:`~services.cloud.app.CloudApp.stage_timer` and ``handle.<Type>`` (a message on the
    worker, all of it); wall time in ``wall.<Type>`` (the same, with the waits: SQLite's
    fsync), ``wait.worker`` (received -> applied) and ``solve.<kind>`` (in the optimizer,
    waited for on the event loop)."""
    solves_abandoned: int = 0
    """Solves whose result the service did not wait for (cancelled: only a stop that was
    itself cut short abandons one; a stop waits for the solve in flight)."""
