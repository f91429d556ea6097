"""The cloud app's atlas agents: one per (edge, robot, edge map) triple, each its own frame.

Shared by :class:`~services.cloud.app.CloudApp`, which numbers and updates them, and its
optimisation half :class:`~services.cloud.app_optimization.AppOptimization`, which addresses
each agent's corrections to the edge serving it (plain data, no I/O).
"""

from __future__ import annotations

from dataclasses import dataclass, field

AgentKey = tuple[str, str, int]
"""An atlas agent's identity: (edge id, robot name, edge map id)."""


@dataclass
class AtlasAgent:
    """One atlas agent: its id in the atlas, its robot's name, its edge and edge map, and
    what its edge last reported of it (status, frames, when, link counters)."""

    agent_id: int
    name: str
    edge_id: str
    edge_map: int
    status: str = "initializing"
    frames: int = 0
    last_seen: float = 0.0
    link_counters: dict[str, int] = field(default_factory=dict)
    detail: str = ""
