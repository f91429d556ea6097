"""The atlas's state and every read of it (:class:`AtlasQueries`).

:class:`AtlasQueries` holds what :class:`~services.cloud.atlas.atlas.Atlas` is made of (keyframe and
map point records keyed by ``agent_id << 32 | local_id``, the covisibility graph, each agent's
map and ``T_map_agent``, merges, loops, removed and retired keyframes, aliases of fused points,
what is unsaved) and answers the queries: agents and maps, counts and keys, frozen views,
covisibility and spanning tree, point positions, observations and descriptors, retired poses,
persistence rows and the dashboard's snapshot. :class:`~services.cloud.atlas.atlas.Atlas` adds every
change (ingest, corrections, removal, restore); nothing mutable leaves either.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

from services.cloud.atlas.atlas_graph import CovisibilityGraph
from services.cloud.atlas.atlas_records import (
    KeyframeRecord,
    MapPointRecord,
    Unsaved,
    map_positions,
    snapshot_of,
)
from services.cloud.atlas.map_types import (
    AtlasError,
    AtlasSnapshot,
    KeyframeView,
    LoopEdge,
    MapPointView,
    MergeRecord,
    split_key,
)
from services.cloud.atlas.retired import RetiredKeyframes, retired_pose


class AtlasQueries:
    """The state of the :class:`~services.cloud.atlas.atlas.Atlas` and its read-only queries."""

    def __init__(self) -> None:
        self._kfs: dict[int, KeyframeRecord] = {}
        self._mps: dict[int, MapPointRecord] = {}
        self._graph = CovisibilityGraph()  # covisibility weights and spanning tree
        self._map_of_agent: dict[int, int] = {}
        self._T_map_agent: dict[int, np.ndarray] = {}
        self._merges: list[MergeRecord] = []
        self._loops: list[LoopEdge] = []
        self._removed_kfs: set[int] = set()
        self._retired = RetiredKeyframes()  # MBP-removed keyframes' relative poses
        self._waiting: dict[int, list[MapPointRecord]] = {}  # keyframe not arrived -> its points
        # Points a keyframe names that have not arrived: point key -> {keyframe key: keypoint
        # index}. They become map points with their first position (a point without one would
        # sit at the map's origin for verification, BA and the map view until it came).
        self._announced: dict[int, dict[int, int]] = {}
        self._alias: dict[int, int] = {}  # fused map point -> surviving map point
        self._alias_log: list[tuple[int, int]] = []  # its assignments, in order
        self._unsaved = Unsaved()  # what changed since the store last wrote it

    # ------------------------------------------------------------------ agents and maps
    def map_of_agent(self, agent_id: int) -> int:
        """Map id that currently holds ``agent_id``'s keyframes."""
        if agent_id not in self._map_of_agent:
            raise AtlasError(f"unknown agent {agent_id}")
        return self._map_of_agent[agent_id]

    def T_map_agent(self, agent_id: int) -> np.ndarray:
        """(4, 4) transform from the agent's own map frame into its current map's frame."""
        self.map_of_agent(agent_id)
        return self._T_map_agent[agent_id].copy()

    def agents(self) -> list[int]:
        return sorted(self._map_of_agent)

    def maps(self) -> list[int]:
        return sorted(set(self._map_of_agent.values()))

    def agents_in_map(self, map_id: int) -> list[int]:
        return sorted(a for a, m in self._map_of_agent.items() if m == map_id)

    # ------------------------------------------------------------------ queries
    def has_keyframe(self, key: int) -> bool:
        return key in self._kfs

    def n_keyframes(self, map_id: int | None = None) -> int:
        if map_id is None:
            return len(self._kfs)
        return sum(1 for k in self._kfs.values() if k.map_id == map_id)

    def n_map_points(self, map_id: int | None = None) -> int:
        if map_id is None:
            return len(self._mps)
        return sum(1 for m in self._mps.values() if m.map_id == map_id)

    def keyframe_keys(self, map_id: int | None = None, agent_id: int | None = None) -> list[int]:
        """Keys sorted ascending (so per agent in keyframe-id order)."""
        return sorted(
            k.key
            for k in self._kfs.values()
            if (map_id is None or k.map_id == map_id)
            and (agent_id is None or k.agent_id == agent_id)
        )

    def map_point_keys(self, map_id: int | None = None) -> list[int]:
        return sorted(m.key for m in self._mps.values() if map_id is None or m.map_id == map_id)

    def keyframe(self, key: int) -> KeyframeView:
        return self._kf(key).view()

    def _kf(self, key: int) -> KeyframeRecord:
        k = self._kfs.get(key)
        if k is None:
            raise AtlasError(f"unknown keyframe {split_key(key)}")
        return k

    def map_id_of_keyframe(self, key: int) -> int:
        return self._kf(key).map_id

    def T_map_body(self, key: int) -> np.ndarray:
        return self._kf(key).T_map_body.copy()

    def keyframe_state(
        self, key: int
    ) -> tuple[np.ndarray, int, np.ndarray, np.ndarray, np.ndarray]:
        """``(T_map_body (4, 4), map id, velocity (3,) m/s in the map frame, gyro bias (3,)
        rad/s, accelerometer bias (3,) m/s²)`` of keyframe ``key`` (read-only, not copies)."""
        k = self._kf(key)
        return k.T_map_body, k.map_id, k.velocity, k.bias_gyro, k.bias_accel

    def covisible(self, key: int, min_weight: int = 1) -> list[tuple[int, int]]:
        """``[(keyframe key, weight)]`` sorted by decreasing weight (then key)."""
        self._kf(key)
        return self._graph.covisible(key, min_weight)

    def best_covisible(self, key: int, n: int) -> list[int]:
        return [o for o, _ in self.covisible(key)[:n]]

    def spanning_parent(self, key: int) -> int | None:
        """Parent in the spanning tree, -1 for a root, None if not attached yet."""
        self._kf(key)
        return self._graph.parent(key)

    def map_point_positions(self, keys: np.ndarray) -> np.ndarray:
        """Positions (N, 3) in their map's frame of the given map point keys (must exist)."""
        mps = self._mps
        try:
            return map_positions([mps[k] for k in np.asarray(keys).tolist()])
        except KeyError as exc:
            raise AtlasError(f"unknown map point {split_key(exc.args[0])}") from None

    def _mp(self, key: int) -> MapPointRecord:
        m = self._mps.get(key)
        if m is None:
            raise AtlasError(f"unknown map point {split_key(key)}")
        return m

    def has_map_point(self, key: int) -> bool:
        return key in self._mps

    def map_point_observations(self, key: int) -> dict[int, int]:
        """``{keyframe key: keypoint index}`` of one map point (a copy)."""
        return dict(self._mp(key).obs)

    def map_point_descriptor(self, key: int) -> np.ndarray:
        """(32,) uint8 descriptor of the point, taken from its reference keyframe."""
        return self.map_point_descriptors(np.array([key]))[0]

    def map_point_descriptors(self, keys: np.ndarray) -> np.ndarray:
        """``(N, 32) uint8``: each point's descriptor, taken from its reference keyframe."""
        out = np.empty((len(keys), 32), np.uint8)
        kfs = self._kfs
        for i, key in enumerate(np.asarray(keys).tolist()):
            m = self._mp(key)
            if m.ref_kf < 0:
                raise AtlasError(f"map point {split_key(key)} has no observation")
            out[i] = kfs[m.ref_kf].descriptors[m.obs[m.ref_kf]]
        return out

    def loops(self) -> list[LoopEdge]:
        return list(self._loops)

    def merges(self) -> list[MergeRecord]:
        return list(self._merges)

    def removed_keyframes(self) -> set[int]:
        return set(self._removed_kfs)

    def retired_poses(self, agent_id: int) -> list[tuple[int, float, np.ndarray]]:
        """``(key, timestamp s, T_map_body (4, 4))`` of ``agent_id``'s retired keyframes (see
        :meth:`retire_keyframe`), poses through their anchors' current estimates."""
        out = []
        for r in self._retired.of_agent(agent_id):  # (an other that went took its blend along)
            T_other = None if r.other is None else self._kfs[r.other].T_map_body
            out.append(
                (r.key, r.timestamp, retired_pose(r, self._kfs[r.anchor].T_map_body, T_other))
            )
        return out

    def map_point(self, key: int) -> MapPointView:
        return self._mp(key).view()

    def map_point_rows(self, keys: Iterable[int]) -> Iterator[tuple[object, ...]]:
        """:meth:`MapPointRecord.row` of each of ``keys`` the atlas holds (for persistence:
        no read-only view built per point), positions relative to the reference keyframe."""
        mps = self._mps
        return (mps[k].row() for k in keys if k in mps)

    def map_point_position_rows(self, keys: Iterable[int]) -> Iterator[tuple[object, ...]]:
        """``(position, in_ref, key)`` of each of ``keys`` the atlas holds, as
        :meth:`map_point_rows` stores it."""
        mps = self._mps
        return (mps[k].position_row() for k in keys if k in mps)

    # ------------------------------------------------------------------ snapshot
    def snapshot(self) -> AtlasSnapshot:
        """The whole atlas as plain read-only arrays (the dashboard's map view)."""
        return snapshot_of(
            self._kfs,
            self._mps,
            self._graph,
            self._loops,
            self._map_of_agent,
            self._T_map_agent,
            self._merges,
        )
