"""The cloud's :class:`~common.map_view.MapSource` for the dashboard.

The service's worker thread builds a :class:`CloudView` (plain, read-only data: an
``AtlasSnapshot``, agent records and link counters) and hands it to
:meth:`CloudMapSource.publish`; the dashboard polls :meth:`CloudMapSource.snapshot` and
:meth:`CloudMapSource.stats` from its own thread. Everything shared is replaced, never
mutated, under one lock, and every array handed out is read-only.

Versions: each publish that changes something bumps the version and stamps the changed
keyframes and points with it, so ``snapshot(since)`` returns exactly the items stamped after
``since`` and the ids removed after it (removal logs are kept for ``history`` publishes; an
older ``since`` gets a full delta).

Display frame: each map's own frame; maps that have not merged yet are shifted along x by
``display_spacing_m`` times their rank so that they can be told apart. Items removed by MBP
stay with ``pruned=True`` (their last pose/position), so the dashboard can show the map with
and without MBP; items the edges culled are reported as removed.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.map_view import (
    AgentRecord,
    AgentState,
    BandwidthSample,
    Direction,
    GroundTruth,
    KeyframeSet,
    MapCounts,
    MapDelta,
    PointSet,
    StatsSnapshot,
)
from services.cloud.atlas.map_types import AtlasSnapshot

_LOCAL_BITS = 32


@dataclass(frozen=True)
class AgentInfo:
    """One robot as the cloud knows it (``status`` is the edge's word: "initializing",
    "tracking", "lost", "finished"; ``link_counters`` its robot->edge counters)."""

    agent_id: int
    name: str
    edge_id: str
    status: str
    frames: int
    keyframes: int
    last_seen: float
    map_id: int
    link_counters: Mapping[str, int] = field(default_factory=dict)
    detail: str = ""  # the edge's why, with numbers (refused VI init, camera-IMU offset)


@dataclass(frozen=True, eq=False)
class CloudView:
    """What the worker publishes: the atlas snapshot, agents, MBP-pruned keys, the edge
    links' traffic counters ``{edge: TrafficCounters.snapshot()}`` and, when it changed,
    the ground truth per agent aligned to its map's frame (None = unchanged)."""

    atlas: AtlasSnapshot
    agents: tuple[AgentInfo, ...]
    pruned_keyframes: frozenset[int]
    pruned_points: frozenset[int]
    edge_counters: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    ground_truth: tuple[GroundTruth, ...] | None = None
    status: str = ""  # the service's state in words (StatsSnapshot.status)


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class _Items:
    ids: np.ndarray
    agent: np.ndarray
    data: np.ndarray  # keyframes: (K, 4, 4) T; points: (P, 3) positions
    timestamp: np.ndarray  # keyframes only (points: zeros)
    pruned: np.ndarray
    stamp: np.ndarray  # version of the last change

    @classmethod
    def empty(cls, row: tuple[int, ...]) -> _Items:
        z = np.zeros(0, np.int64)
        return cls(z, z.astype(np.int32), np.zeros((0, *row)), np.zeros(0), z.astype(bool), z)


def _merge_items(
    old: _Items,
    ids: np.ndarray,
    agent: np.ndarray,
    data: np.ndarray,
    timestamp: np.ndarray,
    pruned_keys: frozenset[int],
    version: int,
) -> tuple[_Items, np.ndarray, bool]:
    """New item table (live items plus MBP-pruned ones kept from ``old``), ids removed, and
    whether anything changed."""
    keep_old = np.isin(old.ids, ids, invert=True) & np.isin(
        old.ids, np.fromiter(pruned_keys, np.int64, len(pruned_keys))
    )
    all_ids = np.concatenate([ids, old.ids[keep_old]])
    order = np.argsort(all_ids, kind="stable")
    all_ids = all_ids[order]
    agent = np.concatenate([agent, old.agent[keep_old]])[order]
    data = np.concatenate([data, old.data[keep_old]])[order]
    timestamp = np.concatenate([timestamp, old.timestamp[keep_old]])[order]
    pruned = np.concatenate([np.zeros(ids.shape[0], bool), np.ones(int(keep_old.sum()), bool)])
    pruned = pruned[order]
    pos = np.searchsorted(old.ids, all_ids)
    pos_c = np.minimum(pos, max(old.ids.shape[0] - 1, 0))
    known = (
        (pos < old.ids.shape[0]) & (old.ids[pos_c] == all_ids)
        if old.ids.size
        else (np.zeros(all_ids.shape[0], bool))
    )
    stamp = np.full(all_ids.shape[0], version, np.int64)
    if old.ids.size:
        same = known.copy()
        k = np.flatnonzero(known)
        diff = np.abs(data[k] - old.data[pos_c[k]]).reshape(k.size, -1).max(axis=1, initial=0.0)
        same[k] = (diff < 1e-9) & (pruned[k] == old.pruned[pos_c[k]])
        stamp[same] = old.stamp[pos_c[same]]
    removed = old.ids[np.isin(old.ids, all_ids, invert=True)]
    changed = bool(np.any(stamp == version) or removed.size)
    items = _Items(
        _ro(all_ids),
        _ro(agent.astype(np.int32)),
        _ro(data),
        _ro(timestamp),
        _ro(pruned),
        _ro(stamp),
    )
    return items, removed, changed


_STATUS = {
    "initializing": AgentState.INITIALISING,
    "initialising": AgentState.INITIALISING,
    "tracking": AgentState.TRACKING,
    "lost": AgentState.LOST,
    "finished": AgentState.TRACKING,
}


class CloudMapSource:
    """Thread-safe :class:`~common.map_view.MapSource` fed by :meth:`publish`.

    display_spacing_m: x offset between unmerged maps; bandwidth_window_s: bandwidth samples
    kept; history: publishes whose removals are remembered for incremental deltas;
    clock: seconds for stats and bandwidth samples (default ``time.monotonic``)."""

    def __init__(
        self,
        display_spacing_m: float = 0.0,
        bandwidth_window_s: float = 120.0,
        history: int = 256,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._spacing = float(display_spacing_m)
        self._window = float(bandwidth_window_s)
        self._clock = clock
        self._lock = threading.Lock()
        self._version = 0
        self._kfs = _Items.empty((4, 4))
        self._pts = _Items.empty((3,))
        self._removed: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=history)
        self._oldest_incremental = 0
        self._poses: dict[int, np.ndarray] = {}
        self._loops = np.zeros((0, 2), np.int64)
        self._merges = np.zeros((0, 2), np.int64)
        self._stats = StatsSnapshot(clock(), (), MapCounts(0, 0, 0, 0, 0, 0))
        self._bandwidth: deque[BandwidthSample] = deque()
        self._last_counts: dict[tuple[str, Direction, str], int] = {}
        self._gt: tuple[GroundTruth, ...] = ()
        self._gt_version = 0

    @property
    def version(self) -> int:
        with self._lock:
            return self._version

    # ------------------------------------------------------------------ writer side
    def publish(self, view: CloudView) -> int:
        """Take a new view of the map; returns the (possibly unchanged) version."""
        s = view.atlas
        maps = sorted(set(s.map_of_agent.values()))
        offset = {m: np.array([i * self._spacing, 0.0, 0.0]) for i, m in enumerate(maps)}
        T = np.array(s.T_map_body, np.float64).copy()
        for i, m in enumerate(s.keyframe_map.tolist()):
            T[i, :3, 3] += offset.get(m, 0.0)
        P = np.array(s.p_map, np.float64).copy()
        for m in maps:
            P[s.point_map == m] += offset[m]
        now = self._clock()
        with self._lock:
            v = self._version + 1
            kfs, kf_removed, kf_changed = _merge_items(
                self._kfs,
                s.keyframe_keys,
                s.keyframe_agent,
                T,
                s.keyframe_timestamp,
                view.pruned_keyframes,
                v,
            )
            pts, pt_removed, pt_changed = _merge_items(
                self._pts,
                s.point_keys,
                (s.point_keys >> _LOCAL_BITS),
                P.astype(np.float32).astype(np.float64),
                np.zeros(s.point_keys.shape[0]),
                view.pruned_points,
                v,
            )
            poses = {}
            for a in np.unique(s.keyframe_agent).tolist():
                idx = np.flatnonzero(s.keyframe_agent == a)
                poses[int(a)] = _ro(T[idx[np.argmax(s.keyframe_timestamp[idx])]])
            pose_changed = poses.keys() != self._poses.keys() or any(
                not np.array_equal(poses[a], self._poses[a]) for a in poses
            )
            merges = np.array([(m.query_key, m.candidate_key) for m in s.merges], np.int64)
            gt_changed = view.ground_truth is not None
            if view.ground_truth is not None:
                map_of = {a.agent_id: a.map_id for a in view.agents}
                self._gt = tuple(
                    GroundTruth(
                        g.agent_id,
                        g.timestamp,
                        g.p_world + offset.get(map_of.get(g.agent_id, -1), 0.0),
                    )
                    for g in view.ground_truth
                )
                self._gt_version = v
            if kf_changed or pt_changed or pose_changed or gt_changed:
                self._version = v
                self._kfs, self._pts, self._poses = kfs, pts, poses
                if self._removed.maxlen and len(self._removed) == self._removed.maxlen:
                    self._oldest_incremental = self._removed[0][0]
                self._removed.append((v, _ro(kf_removed), _ro(pt_removed)))
            self._loops = _ro(np.array(s.loops, np.int64).reshape(-1, 2))
            self._merges = _ro(merges.reshape(-1, 2))
            self._update_stats(view, now)
            return self._version

    def _update_stats(self, view: CloudView, now: float) -> None:
        own_map = {a.agent_id: a.map_id for a in view.agents}
        shared = {m for m in own_map.values() if list(own_map.values()).count(m) > 1}
        agents = []
        for a in view.agents:
            status = _STATUS.get(a.status, AgentState.TRACKING)
            if a.map_id != a.agent_id or a.map_id in shared:
                status = AgentState.MERGED
            agents.append(
                AgentRecord(
                    a.agent_id,
                    status,
                    a.frames,
                    a.keyframes,
                    a.last_seen,
                    a.map_id,
                    name=a.name,
                    edge=a.edge_id,
                    detail=a.detail,
                )
            )
        for edge, snap in view.edge_counters.items():
            for key, direction in (("rx", Direction.UP), ("tx", Direction.DOWN)):
                for mtype, c in snap.get(key, {}).get("by_type", {}).items():
                    self._sample(now, f"{edge}→cloud", direction, mtype, int(c["bytes"]))
        for a in view.agents:
            for key, n in a.link_counters.items():
                d, _, mtype = key.partition(".")
                if d in ("rx", "tx") and mtype:
                    direction = Direction.UP if d == "rx" else Direction.DOWN
                    self._sample(now, f"{a.name}→{a.edge_id}", direction, mtype, int(n))
        while self._bandwidth and self._bandwidth[0].time < now - self._window:
            self._bandwidth.popleft()
        kf_pruned = int(self._kfs.pruned.sum())
        pt_pruned = int(self._pts.pruned.sum())
        counts = MapCounts(
            keyframes=len(self._kfs.ids),
            keyframes_kept=len(self._kfs.ids) - kf_pruned,
            map_points=len(self._pts.ids),
            map_points_kept=len(self._pts.ids) - pt_pruned,
            loops=len(self._loops),
            merges=len(self._merges),
        )
        self._stats = StatsSnapshot(now, tuple(agents), counts, tuple(self._bandwidth), view.status)

    def _sample(self, now: float, link: str, direction: Direction, mtype: str, total: int) -> None:
        key = (link, direction, mtype)
        prev = self._last_counts.get(key)
        self._last_counts[key] = total
        delta = total if prev is None or total < prev else total - prev
        if delta > 0:
            self._bandwidth.append(BandwidthSample(now, link, direction, mtype, delta))

    # ------------------------------------------------------------------ reader side
    def snapshot(self, since_version: int) -> MapDelta:
        with self._lock:
            v = self._version
            full = since_version < 0 or since_version < self._oldest_incremental
            full = full or since_version > v
            if not full and since_version == v:
                return MapDelta(version=v, since_version=since_version, full=False)
            k, p = self._kfs, self._pts
            ks = slice(None) if full else np.flatnonzero(k.stamp > since_version)
            ps = slice(None) if full else np.flatnonzero(p.stamp > since_version)
            rm_k = [r[1] for r in self._removed if not full and r[0] > since_version]
            rm_p = [r[2] for r in self._removed if not full and r[0] > since_version]
            return MapDelta(
                version=v,
                since_version=since_version,
                full=full,
                points=PointSet(p.ids[ps], p.data[ps], p.agent[ps], p.pruned[ps]),
                removed_point_ids=np.concatenate([np.zeros(0, np.int64), *rm_p]),
                keyframes=KeyframeSet(
                    k.ids[ks], k.agent[ks], k.timestamp[ks], k.data[ks], k.pruned[ks]
                ),
                removed_keyframe_ids=np.concatenate([np.zeros(0, np.int64), *rm_k]),
                current_pose=dict(self._poses),
                loops=self._loops,
                merges=self._merges,
                ground_truth=self._gt if full or self._gt_version > since_version else (),
            )

    def stats(self) -> StatsSnapshot:
        with self._lock:
            return self._stats
