"""The dashboard's copy of the map, kept apart from viser (no I/O, testable alone).

:class:`PointChunks` turns point deltas into *chunk operations*: new points of an agent go
into a fresh small chunk (one scene node) each tick, so only new points are sent; once an
agent's unsealed chunks hold ``chunk_points`` points together they are consolidated into one
sealed chunk (one resend of those points, and fewer nodes). A moved or pruned point makes
only its own chunk dirty. :class:`KeyframeTracks` keeps keyframes per agent and reports which
agents' trajectories changed. :func:`live_ate_rmse` aligns a trajectory to ground truth.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from common.evaluation.alignment import umeyama
from common.evaluation.errors import AlignmentError
from common.map_view import GroundTruth, KeyframeSet, PointSet

log = logging.getLogger(__name__)


@dataclass
class _Chunk:
    agent: int
    serial: int
    ids: np.ndarray
    p_world: np.ndarray
    pruned: np.ndarray
    alive: np.ndarray
    sealed: bool


@dataclass(frozen=True, eq=False)
class ChunkUpdate:
    """A scene node to (re)send: agent's chunk ``serial``; ``p_world (N, 3)`` float32 and
    ``pruned (N,)`` bool of its live points."""

    agent: int
    serial: int
    p_world: np.ndarray
    pruned: np.ndarray


@dataclass(frozen=True)
class ChunkOps:
    """Chunk nodes to send and to delete, as ``(agent, serial)``."""

    upserts: tuple[ChunkUpdate, ...] = ()
    removals: tuple[tuple[int, int], ...] = ()


@dataclass
class PointChunks:
    """Map points grouped in per-agent chunks; see the module docstring.

    chunk_points: size of a sealed chunk; max_points: points beyond this are dropped (the
    first drop is logged).
    """

    chunk_points: int = 16_384
    max_points: int = 2_000_000
    _chunks: dict[tuple[int, int], _Chunk] = field(default_factory=dict)
    _where: dict[int, tuple[int, int, int]] = field(default_factory=dict)
    _serial: int = 0
    _dirty: set[tuple[int, int]] = field(default_factory=set)
    _removed: set[tuple[int, int]] = field(default_factory=set)
    _sent: set[tuple[int, int]] = field(default_factory=set)
    _dropped: int = 0

    def __len__(self) -> int:
        return len(self._where)

    @property
    def n_nodes(self) -> int:
        return len(self._chunks)

    def clear(self) -> None:
        """Forget everything (before a full delta); every node becomes a removal."""
        self._removed |= set(self._chunks)
        self._dirty.clear()
        self._chunks.clear()
        self._where.clear()

    def apply(self, points: PointSet, removed_ids: np.ndarray) -> None:
        """Take in new or changed points and removed ids."""
        for pid in removed_ids.tolist():
            loc = self._where.pop(pid, None)
            if loc is not None:
                a, s, i = loc
                self._chunks[(a, s)].alive[i] = False
                self._dirty.add((a, s))
        if len(points) == 0:
            return
        known = np.fromiter((i in self._where for i in points.ids.tolist()), bool, len(points))
        for j in np.flatnonzero(known).tolist():
            a, s, i = self._where[int(points.ids[j])]
            if a != int(points.agent[j]):  # owner changed: move it as a new point
                self._chunks[(a, s)].alive[i] = False
                self._dirty.add((a, s))
                del self._where[int(points.ids[j])]
                known[j] = False
                continue
            chunk = self._chunks[(a, s)]
            chunk.p_world[i] = points.p_world[j]
            chunk.pruned[i] = points.pruned[j]
            self._dirty.add((a, s))
        new = points.subset(~known)
        room = max(self.max_points - len(self._where), 0)
        if len(new) > room:
            if self._dropped == 0:
                log.warning(
                    "dashboard holds max_points=%d; dropping further points", self.max_points
                )
            self._dropped += len(new) - room
            new = new.subset(np.arange(room))
        for a in np.unique(new.agent).tolist():
            sel = new.subset(new.agent == a)
            self._add_chunk(a, sel.ids, sel.p_world, sel.pruned, sealed=False)
            self._consolidate(a)

    def _add_chunk(
        self, agent: int, ids: np.ndarray, p: np.ndarray, pruned: np.ndarray, sealed: bool
    ) -> None:
        self._serial += 1
        key = (agent, self._serial)
        self._chunks[key] = _Chunk(
            agent,
            self._serial,
            ids.copy(),
            p.copy(),
            pruned.copy(),
            np.ones(ids.shape[0], bool),
            sealed,
        )
        for i, pid in enumerate(ids.tolist()):
            self._where[pid] = (agent, self._serial, i)
        self._dirty.add(key)

    def _consolidate(self, agent: int) -> None:
        loose = [c for c in self._chunks.values() if c.agent == agent and not c.sealed]
        total = sum(int(c.alive.sum()) for c in loose)
        if total < self.chunk_points and len(loose) <= 32:
            return
        ids = np.concatenate([c.ids[c.alive] for c in loose])
        p = np.concatenate([c.p_world[c.alive] for c in loose])
        pruned = np.concatenate([c.pruned[c.alive] for c in loose])
        for c in loose:
            key = (c.agent, c.serial)
            del self._chunks[key]
            self._dirty.discard(key)
            self._removed.add(key)
        for lo in range(0, ids.shape[0], self.chunk_points):
            hi = lo + self.chunk_points
            self._add_chunk(agent, ids[lo:hi], p[lo:hi], pruned[lo:hi], sealed=hi <= ids.shape[0])

    def take_ops(self) -> ChunkOps:
        """Nodes changed since the last call (each chunk at most once)."""
        ups = []
        for key in sorted(self._dirty):
            c = self._chunks[key]
            ups.append(ChunkUpdate(c.agent, c.serial, c.p_world[c.alive], c.pruned[c.alive]))
        gone = (self._removed - self._dirty) & self._sent  # nodes the scene really has
        self._sent = (self._sent - gone) | self._dirty
        ops = ChunkOps(tuple(ups), tuple(sorted(gone)))
        self._dirty.clear()
        self._removed.clear()
        return ops


@dataclass
class KeyframeTracks:
    """Keyframes per agent (id -> timestamp, pose, pruned) and which agents changed."""

    _by_agent: dict[int, dict[int, tuple[float, np.ndarray, bool]]] = field(default_factory=dict)
    _agent_of: dict[int, int] = field(default_factory=dict)
    _dirty: set[int] = field(default_factory=set)

    def __len__(self) -> int:
        return len(self._agent_of)

    def clear(self) -> None:
        self._dirty |= set(self._by_agent)
        self._by_agent.clear()
        self._agent_of.clear()

    def apply(self, kfs: KeyframeSet, removed_ids: np.ndarray) -> None:
        for kid in removed_ids.tolist():
            a = self._agent_of.pop(kid, None)
            if a is not None:
                del self._by_agent[a][kid]
                self._dirty.add(a)
        for j in range(len(kfs)):
            kid, a = int(kfs.ids[j]), int(kfs.agent[j])
            old = self._agent_of.get(kid)
            if old is not None and old != a:
                del self._by_agent[old][kid]
                self._dirty.add(old)
            self._agent_of[kid] = a
            self._by_agent.setdefault(a, {})[kid] = (
                float(kfs.timestamp[j]),
                kfs.T_world_body[j],
                bool(kfs.pruned[j]),
            )
            self._dirty.add(a)

    def take_dirty(self) -> list[int]:
        out = sorted(self._dirty)
        self._dirty.clear()
        return out

    def agents(self) -> list[int]:
        return sorted(self._by_agent)

    def track(self, agent: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Agent's keyframes in time order: ``timestamp (K,)``, ``T_world_body (K, 4, 4)``,
        ``pruned (K,)``."""
        items = sorted(self._by_agent.get(agent, {}).values(), key=lambda r: r[0])
        if not items:
            return np.zeros(0), np.zeros((0, 4, 4)), np.zeros(0, bool)
        t, T, pr = zip(*items, strict=True)
        return np.array(t), np.array(T), np.array(pr, bool)

    def position(self, kid: int) -> np.ndarray | None:
        """``p_world (3,)`` of a keyframe, or None when unknown."""
        a = self._agent_of.get(kid)
        if a is None:
            return None
        return self._by_agent[a][kid][1][:3, 3]


def live_ate_rmse(t_est: np.ndarray, p_est: np.ndarray, gt: GroundTruth) -> float | None:
    """ATE RMSE in metres of ``p_est (K, 3)`` at ``t_est (K,)`` against ground truth
    (interpolated at the estimate's times, rigid Umeyama alignment); None when fewer than
    three poses overlap the ground truth in time or the alignment is degenerate."""
    if gt.timestamp.size < 2:
        return None
    inside = (t_est >= gt.timestamp[0]) & (t_est <= gt.timestamp[-1])
    if np.count_nonzero(inside) < 3:
        return None
    t = t_est[inside]
    p_ref = np.stack([np.interp(t, gt.timestamp, gt.p_world[:, k]) for k in range(3)], axis=1)
    try:
        sim = umeyama(p_est[inside], p_ref)
    except AlignmentError:
        return None
    err = sim.apply_points(p_est[inside]) - p_ref
    return float(np.sqrt(np.mean(np.sum(err * err, axis=1))))
