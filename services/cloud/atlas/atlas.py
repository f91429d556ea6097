"""The cloud's atlas: every agent's map, merged maps, covisibility graph and spanning tree.

Keyframes and map points arrive from the edges in their agent's map frame (a gravity-aligned
visual-inertial map). Each agent starts in its own map (``map_id == agent_id``); when two maps
are merged the atlas re-expresses the absorbed map in the kept map's frame and remembers
``T_map_agent`` for every agent, so later keyframes of that agent land in the right frame.

Identifiers: keyframe and map-point ids are only unique per agent, so the atlas keys them by
``key = agent_id << 32 | local_id`` (see :func:`make_key`). Keys are plain ``int``.

Covisibility (ORB-SLAM): the weight between two keyframes is the number of map points both
observe; it is kept up to date as observations arrive in any order (a map point may reference
a keyframe that has not arrived yet; the observation is linked when it does). The spanning
tree attaches every keyframe to its strongest covisible keyframe already in the tree; each
agent's first keyframe is a root. The graph is :mod:`services.cloud.atlas.atlas_graph`; the records
the atlas mutates and their frozen views are :mod:`services.cloud.atlas.atlas_records`; the atlas's
state and its queries are :mod:`services.cloud.atlas.atlas_queries` (this module: every change).

Nothing mutable leaves the atlas: :meth:`Atlas.keyframe` returns a frozen copy and
:meth:`Atlas.snapshot` plain read-only arrays for the dashboard.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from common.geometry import inverse_T, make_T, similarity_scale
from services.cloud.atlas.atlas_queries import AtlasQueries
from services.cloud.atlas.atlas_records import (
    KeyframeRecord,
    MapPointRecord,
    Unsaved,
    heir_reference,
    map_positions,
    place_points,
)
from services.cloud.atlas.map_types import (
    LOCAL_BITS,
    AliasSnapshot,
    AtlasError,
    AtlasSnapshot,
    AtlasState,
    KeyframeInput,
    KeyframeView,
    LoopEdge,
    MapPointInput,
    MapPointView,
    MergeRecord,
    RetiredKeyframe,
    make_key,
    ro,
    split_key,
)
from services.cloud.atlas.retired import RetiredKeyframes, retirement

__all__ = [
    "Atlas",
    "AtlasError",
    "AtlasSnapshot",
    "AtlasState",
    "KeyframeInput",
    "KeyframeView",
    "LoopEdge",
    "MapPointInput",
    "MapPointView",
    "MergeRecord",
    "RetiredKeyframe",
    "make_key",
    "split_key",
]

log = logging.getLogger(__name__)


class Atlas(AtlasQueries):
    """All maps of the cloud. Not thread-safe: one owner mutates it (the service's app)."""

    # ------------------------------------------------------------------ agents and maps
    def _ensure_agent(self, agent_id: int) -> None:
        if agent_id not in self._map_of_agent:
            self._map_of_agent[agent_id] = agent_id
            self._T_map_agent[agent_id] = np.eye(4)

    # ------------------------------------------------------------------ ingest
    def add_keyframe(self, kf: KeyframeInput) -> int:
        """Insert (or update the state of) a keyframe; returns its key.

        An update (same agent and id) replaces the pose, velocity and biases and links any new
        map point ids; keypoints and descriptors must stay the same size."""
        self._ensure_agent(kf.agent_id)
        key = make_key(kf.agent_id, kf.keyframe_id)
        if key in self._removed_kfs:
            log.debug("ignoring update of pruned keyframe %d/%d", kf.agent_id, kf.keyframe_id)
            return key
        T_ma = self._T_map_agent[kf.agent_id]
        new = key not in self._kfs
        if new:
            k = KeyframeRecord.new(key, kf, self._map_of_agent[kf.agent_id])
            self._kfs[key] = k
            # The first keyframe of the agent is a root.
            root = not any(p.agent_id == kf.agent_id for p in self._kfs.values() if p is not k)
            self._graph.add_keyframe(key, root)
        else:
            k = self._kfs[key]
            n_real = int((~k.virtual).sum())
            if kf.keypoints.shape[0] != n_real:
                raise AtlasError(
                    f"keyframe {kf.agent_id}/{kf.keyframe_id}: update changes the "
                    f"keypoint count {n_real} -> {kf.keypoints.shape[0]}"
                )
        # a new row, or a new state only (pose, velocity, biases: the features are the same)
        (self._unsaved.keyframes if new else self._unsaved.poses).add(key)
        k.timestamp = float(kf.timestamp)
        k.set_state(T_ma, kf.T_world_body, kf.velocity, kf.bias_gyro, kf.bias_accel)
        for idx in np.flatnonzero(kf.map_point_ids >= 0):
            mkey = make_key(kf.agent_id, int(kf.map_point_ids[idx]))
            mkey = self._alias.get(mkey, mkey)
            mp = self._mps.get(mkey)
            if mp is None:  # not received yet: no position, so not a map point yet either
                self._announced.setdefault(mkey, {}).setdefault(key, int(idx))
                continue
            mp.pending.setdefault(key, int(idx))
            self._link_pending(mp)
        if new:
            # Map points that referenced this keyframe before it arrived.
            for mp in self._waiting.pop(key, ()):
                self._link_pending(mp)
            self._graph.attach(key)
        return key

    def refresh_keyframe(
        self,
        agent_id: int,
        keyframe_id: int,
        T_world_body: np.ndarray,
        velocity: np.ndarray,
        bias_gyro: np.ndarray,
        bias_accel: np.ndarray,
    ) -> bool:
        """A new state of a keyframe the atlas holds (what :meth:`add_keyframe` does for an
        update without map point ids, without its features): ``T_world_body (4, 4)`` and
        ``velocity (3,)`` m/s in the agent's map frame, biases ``(3,)``. False when the atlas
        does not hold it (removed, or never received): nothing changes."""
        key = make_key(agent_id, keyframe_id)
        k = self._kfs.get(key)
        if k is None:
            return False
        T = np.asarray(T_world_body, np.float64)
        vectors = [np.asarray(v, np.float64) for v in (velocity, bias_gyro, bias_accel)]
        if T.shape != (4, 4) or any(v.shape != (3,) for v in vectors):
            raise AtlasError(f"keyframe {agent_id}/{keyframe_id}: malformed state")
        k.set_state(self._T_map_agent[agent_id], T, *vectors)
        self._unsaved.poses.add(key)
        return True

    def _new_map_point(self, mkey: int, agent_id: int) -> MapPointRecord:
        mp = MapPointRecord(mkey, agent_id, split_key(mkey)[1], self._map_of_agent[agent_id])
        self._mps[mkey] = mp
        return mp

    def add_map_point(self, mp_in: MapPointInput) -> int:
        """Insert or update a map point (position and observations); returns its key. An update
        of an unknown point without observations of live keyframes (an edge re-sending a point
        the cloud removed, e.g. by MBP, because it moved) creates nothing."""
        return self.add_map_points([mp_in])[0]

    def add_map_points(self, points: Sequence[MapPointInput]) -> list[int]:
        """:meth:`add_map_point` of each of ``points`` in order; their keys. The thousands of
        points of one update go in as arrays where they can: their map positions in one pass
        per agent, their positions relative to their reference keyframes in one pass (an edge
        re-sends every point local BA moved, most of them with the same observations)."""
        if not points:
            return []
        agents = np.array([p.agent_id for p in points], np.int64)  # (ids checked by the input)
        ids = np.array([p.map_point_id for p in points], np.int64)
        p_map = np.array([p.p_world for p in points], np.float64).reshape(-1, 3)
        for agent in np.unique(agents).tolist():
            self._ensure_agent(agent)
            sel = agents == agent
            T = self._T_map_agent[agent]
            p_map[sel] = p_map[sel] @ T[:3, :3].T + T[:3, 3]
        unsaved = self._unsaved
        alias, mps, removed = self._alias, self._mps, self._removed_kfs
        keys: list[int] = []
        todo: list[tuple[MapPointRecord, MapPointInput]] = []  # points kept, in order
        moved: list[MapPointRecord] = []  # their positions: p_map[at]
        at: list[int] = []
        all_keys = ((agents << LOCAL_BITS) | ids).tolist()
        for i, (mkey, mp_in) in enumerate(zip(all_keys, points, strict=True)):
            fused_into = alias.get(mkey)
            if fused_into is not None:
                mkey = fused_into  # fused at a merge: keep the survivor's position, link new obs
            keys.append(mkey)
            mp = mps.get(mkey)
            if mp is None:
                if mkey not in self._announced and not any(
                    make_key(mp_in.agent_id, int(k)) not in removed for k, _ in mp_in.observations
                ):
                    continue  # a moved point the cloud culled (or never had): no observer left
                mp = self._new_map_point(mkey, mp_in.agent_id)
                mp.pending.update(self._announced.pop(mkey, {}))
                unsaved.points.add(mkey)  # a new row
            if fused_into is None:
                moved.append(mp)
                at.append(i)
            todo.append((mp, mp_in))
        place_points(moved, p_map[at])
        unsaved.positions.update(mp.key for mp in moved)  # (its row, if observations change)
        for mp, mp_in in todo:
            base, mp_obs, pending = mp_in.agent_id << LOCAL_BITS, mp.obs, mp.pending
            for kf_id, kp_idx in mp_in.observations.tolist():
                kkey = base | kf_id
                if kkey not in mp_obs and kkey not in removed:
                    pending.setdefault(kkey, kp_idx)
            if pending:
                self._link_pending(mp)
        return keys

    def _link_pending(self, mp: MapPointRecord) -> None:
        for kkey in list(mp.pending):
            k = self._kfs.get(kkey)
            if k is None:
                waiting = self._waiting.setdefault(kkey, [])
                if mp not in waiting:
                    waiting.append(mp)
                continue
            idx = mp.pending.pop(kkey)
            if idx >= k.keypoints.shape[0]:
                log.warning("map point %d: keypoint index %d out of range", mp.key, idx)
                continue
            self._link(mp, k, idx)

    def _link(self, mp: MapPointRecord, k: KeyframeRecord, idx: int) -> None:
        if k.key in mp.obs:
            return
        old = int(k.mp_keys[idx])
        if old >= 0 and old != mp.key:
            return  # keypoint already bound to another point; keep the first binding
        k.mp_keys[idx] = mp.key  # (stored with the point: its row's observations)
        self._unsaved.points.add(mp.key)
        for other in mp.obs:
            self._graph.add_weight(k.key, other, 1)
        mp.obs[k.key] = idx
        if mp.ref is None:
            mp.set_ref(k)
        if not self._graph.is_attached(k.key):
            self._graph.attach(k.key)

    # ------------------------------------------------------------------ corrections
    def add_loop(self, key_a: int, key_b: int, T_a_b: np.ndarray) -> LoopEdge:
        """Record a verified constraint ``T_a_b`` (body a <- body b); both in one map."""
        ka, kb = self._kf(key_a), self._kf(key_b)
        if ka.map_id != kb.map_id:
            raise AtlasError("a loop edge needs both keyframes in one map (merge first)")
        edge = LoopEdge(key_a, key_b, ro(T_a_b), ka.agent_id != kb.agent_id)
        self._loops.append(edge)
        return edge

    def merge_maps(
        self,
        target_map: int,
        source_map: int,
        T_target_source: np.ndarray,
        query_key: int = -1,
        candidate_key: int = -1,
        fused_points: int = 0,
    ) -> MergeRecord:
        """Re-express every keyframe and map point of ``source_map`` in ``target_map``'s frame
        (``T_target_source`` rigid or a similarity: positions and velocities scale, rotations
        stay rotations)."""
        maps = self.maps()
        if target_map not in maps or source_map not in maps or target_map == source_map:
            raise AtlasError(f"cannot merge map {source_map} into {target_map} (maps: {maps})")
        T = np.asarray(T_target_source, dtype=np.float64)
        scale = similarity_scale(T)
        R = T[:3, :3] / scale
        # The points' new positions first: they follow their reference keyframes, which move
        # next, by the rigid part only (a Sim(3) also scales the points about the map origin).
        q = self._kfs.get(query_key)
        pivot = (
            q.T_map_body[:3, 3].copy() if q is not None and q.map_id == source_map else np.zeros(3)
        )
        moved = [m for m in self._mps.values() if m.map_id == source_map]
        P = map_positions(moved) @ T[:3, :3].T + T[:3, 3]
        for k in self._kfs.values():
            if k.map_id == source_map:
                self._unsaved.keyframes.add(k.key)
                k.map_id = target_map
                Tk = k.T_map_body.copy()
                k.T_map_body = np.eye(4)
                k.T_map_body[:3, :3] = R @ Tk[:3, :3]
                k.T_map_body[:3, 3] = T[:3, :3] @ Tk[:3, 3] + T[:3, 3]
                k.velocity = scale * (R @ k.velocity)
        for m, p in zip(moved, P, strict=True):
            self._unsaved.points.add(m.key)
            m.map_id = target_map
            m.p_map = p
        # An agent's later keyframes land through a rigid T_map_agent: with a scale, the one
        # that is exact at the query keyframe (the place the merge joined; anchored payloads
        # land relative to their anchor anyway, services.cloud.fusion.rebase).
        T_agent = make_T(R, T[:3, 3] + (scale - 1.0) * (R @ pivot))
        for a, mid in self._map_of_agent.items():
            if mid == source_map:
                self._map_of_agent[a] = target_map
                self._T_map_agent[a] = T_agent @ self._T_map_agent[a]
        rec = MergeRecord(target_map, source_map, ro(T), query_key, candidate_key, fused_points)
        self._merges.append(rec)
        log.info("merged map %d into %d", source_map, target_map)
        return rec

    def record_fused_points(self, n: int) -> MergeRecord:
        """Store how many points the last merge fused (set by the merge step)."""
        if not self._merges:
            raise AtlasError("no merge to annotate")
        m = self._merges[-1]
        self._merges[-1] = MergeRecord(
            m.target_map, m.source_map, m.T_target_source, m.query_key, m.candidate_key, n
        )
        return self._merges[-1]

    def fuse_map_points(self, keep_key: int, drop_key: int) -> None:
        """Move every observation of ``drop_key`` onto ``keep_key`` and delete ``drop_key``.

        Where a keyframe already observes ``keep_key`` the duplicate observation is dropped."""
        if keep_key == drop_key:
            return
        keep, drop = self._mp(keep_key), self._mp(drop_key)
        obs = dict(drop.obs)
        self.remove_map_point(drop_key)
        for kkey, idx in obs.items():
            k = self._kfs[kkey]
            if kkey not in keep.obs:
                k.mp_keys[idx] = -1
                self._link(keep, k, idx)
        self._alias[drop_key] = keep_key
        self._alias_log.append((drop_key, keep_key))

    def set_keyframe_poses(self, poses: dict[int, np.ndarray]) -> None:
        """Replace keyframe poses (map frame); each map point follows its reference keyframe
        (``p' = T'_ref @ T_ref^-1 @ p``: it is held relative to it, :class:`MapPointRecord`)."""
        for key, T in poses.items():
            k = self._kf(key)
            k.T_map_body = np.array(T, dtype=np.float64)
            self._unsaved.poses.add(key)

    def set_map_point_positions(self, positions: dict[int, np.ndarray]) -> None:
        for key, p in positions.items():
            self._mp(key).p_map = np.asarray(p, dtype=np.float64).reshape(3).copy()
            self._unsaved.positions.add(key)

    # ------------------------------------------------------------------ removal (MBP)
    def remove_map_point(self, key: int) -> None:
        m = self._mp(key)
        keys = list(m.obs)
        self._unsaved.points.add(key)
        self._unsaved.keyframes.update(keys)
        for i, a in enumerate(keys):
            self._kfs[a].mp_keys[m.obs[a]] = -1
            for b in keys[i + 1 :]:
                self._graph.add_weight(a, b, -1)
        for lst in self._waiting.values():
            if m in lst:
                lst.remove(m)
        del self._mps[key]

    def remove_observation(self, mp_key: int, kf_key: int) -> None:
        m = self._mp(mp_key)
        idx = m.obs.pop(kf_key, None)
        if idx is None:
            return
        self._unsaved.points.add(mp_key)
        self._unsaved.keyframes.add(kf_key)
        self._kfs[kf_key].mp_keys[idx] = -1
        for other in m.obs:
            self._graph.add_weight(kf_key, other, -1)
        if m.ref_kf == kf_key:
            heir = heir_reference([self._kfs[k] for k in m.obs], self._kfs[kf_key])
            m.set_ref(self._kfs.get(heir))

    def retire_keyframe(self, key: int, anchor: int, other: int | None = None) -> None:
        """Remove ``key`` as :meth:`remove_keyframe` does but keep its pose relative to
        ``anchor``, another keyframe of the same agent, and to ``other`` (one on the other side
        of it in time, or None) to blend the two (a :class:`RetiredKeyframe`)."""
        k = self._kf(key)
        for role, n in (("anchor", anchor), ("other", other)):
            if n is not None and (self._kf(n).agent_id != k.agent_id or n == key):
                raise AtlasError(
                    f"keyframe {split_key(key)}: {role} {split_key(n)} is not another "
                    "keyframe of its agent"
                )
        a, o = self._kfs[anchor], None if other in (None, anchor) else self._kfs[other]
        self._retired.add(retirement(k, a, o))
        self.remove_keyframe(key)

    def _pass_on_retired(self, key: int) -> None:
        """Re-anchor the retired keyframes anchored on ``key`` (about to go) to its heir: its
        own anchor if it is retired, else the agent's keyframe nearest in time (none: drop)."""
        self._retired.drop_other(key)
        if not self._retired.anchored_on(key):
            return
        own, k = self._retired.get(key), self._kfs[key]
        if own is not None:
            self._retired.pass_on(key, own.anchor, own.T_anchor_body)
            return
        same = [o for o in self._kfs.values() if o.agent_id == k.agent_id and o.key != key]
        h = min(same, key=lambda o: (abs(o.timestamp - k.timestamp), o.key), default=None)
        T_h_k = None if h is None else inverse_T(h.T_map_body) @ k.T_map_body
        self._retired.pass_on(key, None if h is None else h.key, T_h_k)

    def remove_keyframe(self, key: int) -> None:
        """Delete a keyframe, its observations and covisibility; its spanning-tree children are
        re-attached to its parent (or become roots). Later updates of it are ignored."""
        k = self._kf(key)
        self._pass_on_retired(key)
        for mk in np.unique(k.mp_keys[k.mp_keys >= 0]).tolist():
            self.remove_observation(int(mk), key)
        self._graph.remove_keyframe(key)
        del self._kfs[key]
        self._unsaved.keyframes.add(key)
        for mkey in [m for m, kfs in self._announced.items() if kfs.pop(key, None) is not None]:
            if not self._announced[mkey]:
                del self._announced[mkey]
        self._removed_kfs.add(key)
        self._loops = [e for e in self._loops if key not in (e.key_a, e.key_b)]

    def add_virtual_observations(
        self,
        key: int,
        keypoints: np.ndarray,
        levels: np.ndarray,
        descriptors: np.ndarray,
        word_ids: np.ndarray,
        map_point_keys: np.ndarray,
    ) -> int:
        """Append virtual observations (MBP) of existing map points to keyframe ``key``.

        keypoints (M, 2) distorted px in this keyframe; returns how many were linked."""
        k = self._kf(key)
        n0 = k.keypoints.shape[0]
        m = int(np.asarray(map_point_keys).size)
        if m == 0:
            return 0
        self._unsaved.keyframes.add(key)
        k.keypoints = np.concatenate([k.keypoints, np.asarray(keypoints, np.float64).reshape(m, 2)])
        k.levels = np.concatenate([k.levels, np.asarray(levels, np.int16).reshape(m)])
        k.descriptors = np.concatenate([k.descriptors, np.asarray(descriptors, np.uint8)])
        k.word_ids = np.concatenate([k.word_ids, np.asarray(word_ids, np.int32).reshape(m)])
        k.mp_keys = np.concatenate([k.mp_keys, np.full(m, -1, np.int64)])
        k.virtual = np.concatenate([k.virtual, np.ones(m, bool)])
        linked = 0
        for i, mk in enumerate(np.asarray(map_point_keys).tolist()):
            mp = self._mps.get(int(mk))
            if mp is not None and key not in mp.obs:
                self._link(mp, k, n0 + i)
                linked += 1
        return linked

    # ------------------------------------------------------------------ persistence
    @property
    def unsaved(self) -> Unsaved:
        """What changed since the one store that keeps this atlas last wrote it (every
        ``CloudStore`` write takes it, :meth:`Unsaved.take`, and gives it back if it fails)."""
        return self._unsaved

    def state(self) -> AtlasState:
        return AtlasState(
            map_of_agent=dict(self._map_of_agent),
            T_map_agent={a: ro(T) for a, T in self._T_map_agent.items()},
            merges=tuple(self._merges),
            loops=tuple(self._loops),
            removed_keyframes=frozenset(self._removed_kfs),
            aliases=AliasSnapshot(self._alias_log, len(self._alias_log)),
            retired=self._retired.records(),
        )

    @classmethod
    def restore(
        cls, keyframes: list[KeyframeView], map_points: list[MapPointView], state: AtlasState
    ) -> Atlas:
        """Rebuild an atlas from views (as :meth:`keyframe`, :meth:`map_point`, :meth:`state`
        return them); covisibility and spanning tree are recomputed from the observations."""
        atlas = cls()
        atlas._map_of_agent = dict(state.map_of_agent)
        atlas._T_map_agent = {a: np.array(T) for a, T in state.T_map_agent.items()}
        for v in sorted(keyframes, key=lambda v: v.key):
            k = KeyframeRecord.from_view(v)
            atlas._kfs[k.key] = k
            root = not any(p.agent_id == k.agent_id for p in atlas._kfs.values() if p is not k)
            atlas._graph.add_keyframe(k.key, root)
        for pv in map_points:
            m = MapPointRecord(pv.key, pv.agent_id, pv.map_point_id, pv.map_id)
            m.p_map = np.array(pv.p_map)
            atlas._mps[m.key] = m
            for kk, idx in zip(pv.obs_keyframes.tolist(), pv.obs_indices.tolist(), strict=True):
                if kk in atlas._kfs:
                    atlas._link(m, atlas._kfs[kk], idx)
            if pv.ref_kf in m.obs:
                m.set_ref(atlas._kfs[pv.ref_kf])
        for key in atlas._kfs:
            atlas._graph.attach(key)
        atlas._merges = list(state.merges)
        atlas._loops = [e for e in state.loops if e.key_a in atlas._kfs and e.key_b in atlas._kfs]
        atlas._removed_kfs = set(state.removed_keyframes)
        atlas._alias = dict(state.aliases)
        atlas._alias_log = list(atlas._alias.items())
        atlas._retired = RetiredKeyframes.of_live(state.retired, atlas._kfs)
        atlas._unsaved = Unsaved()  # as stored
        return atlas
