"""The atlas's mutable keyframe and map-point records, and their frozen views.

:class:`~services.cloud.atlas.atlas.Atlas` owns and mutates these records; what leaves it is a
:class:`~services.cloud.atlas.map_types.KeyframeView` /
:class:`~services.cloud.atlas.map_types.MapPointView` (read-only copies), and
:meth:`KeyframeRecord.from_view` turns a view back into a record when an atlas is restored. Poses
are in the record's map frame (``map_id``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from services.cloud.atlas.atlas_graph import CovisibilityGraph
from services.cloud.atlas.map_types import (
    AtlasSnapshot,
    KeyframeInput,
    KeyframeView,
    LoopEdge,
    MapPointView,
    MergeRecord,
    ro,
)


class KeyframeRecord:
    """One keyframe as the atlas holds it. ``mp_keys (N,)`` global map point keys or -1;
    ``virtual (N,)`` marks observations added by MBP (see ``KeyframeView``)."""

    __slots__ = (
        "T_map_body",
        "agent_id",
        "bias_accel",
        "bias_gyro",
        "descriptors",
        "key",
        "keyframe_id",
        "keypoints",
        "levels",
        "map_id",
        "mp_keys",
        "timestamp",
        "velocity",
        "virtual",
        "word_ids",
    )

    key: int
    agent_id: int
    keyframe_id: int
    map_id: int
    timestamp: float
    T_map_body: np.ndarray
    velocity: np.ndarray
    bias_gyro: np.ndarray
    bias_accel: np.ndarray
    keypoints: np.ndarray
    levels: np.ndarray
    descriptors: np.ndarray
    word_ids: np.ndarray
    mp_keys: np.ndarray
    virtual: np.ndarray

    @classmethod
    def new(cls, key: int, kf: KeyframeInput, map_id: int) -> KeyframeRecord:
        """A record of ``kf``'s image data, no map point linked yet; the caller sets the state
        (timestamp, pose, velocity, biases) in the map's frame."""
        k = cls()
        k.key, k.agent_id, k.keyframe_id, k.map_id = key, kf.agent_id, kf.keyframe_id, map_id
        k.keypoints = kf.keypoints
        k.levels = kf.levels
        k.descriptors = kf.descriptors
        k.word_ids = kf.word_ids
        k.mp_keys = np.full(kf.keypoints.shape[0], -1, dtype=np.int64)
        k.virtual = np.zeros(kf.keypoints.shape[0], dtype=bool)
        return k

    @classmethod
    def from_view(cls, v: KeyframeView) -> KeyframeRecord:
        """A writable record of ``v``, no map point linked yet (``mp_keys`` all -1)."""
        k = cls()
        k.key, k.agent_id, k.keyframe_id, k.map_id = v.key, v.agent_id, v.keyframe_id, v.map_id
        k.timestamp = float(v.timestamp)
        k.T_map_body = np.array(v.T_map_body)
        k.velocity, k.bias_gyro = np.array(v.velocity), np.array(v.bias_gyro)
        k.bias_accel = np.array(v.bias_accel)
        k.keypoints, k.levels = np.array(v.keypoints), np.array(v.levels)
        k.descriptors, k.word_ids = np.array(v.descriptors), np.array(v.word_ids)
        k.mp_keys = np.full(k.keypoints.shape[0], -1, np.int64)
        k.virtual = np.array(v.virtual, dtype=bool)
        return k

    def set_state(
        self,
        T_map_agent: np.ndarray,
        T_world_body: np.ndarray,
        velocity: np.ndarray,
        bias_gyro: np.ndarray,
        bias_accel: np.ndarray,
    ) -> None:
        """The edge's state of this keyframe, pose and velocity in its agent's map frame."""
        self.T_map_body = T_map_agent @ T_world_body
        self.velocity = T_map_agent[:3, :3] @ velocity
        self.bias_gyro = np.array(bias_gyro, np.float64)
        self.bias_accel = np.array(bias_accel, np.float64)

    def view(self) -> KeyframeView:
        """A read-only copy."""
        return KeyframeView(
            key=self.key,
            agent_id=self.agent_id,
            keyframe_id=self.keyframe_id,
            map_id=self.map_id,
            timestamp=self.timestamp,
            T_map_body=ro(self.T_map_body),
            velocity=ro(self.velocity),
            bias_gyro=ro(self.bias_gyro),
            bias_accel=ro(self.bias_accel),
            keypoints=ro(self.keypoints),
            levels=ro(self.levels),
            descriptors=ro(self.descriptors),
            word_ids=ro(self.word_ids),
            map_point_keys=ro(self.mp_keys),
            virtual=ro(self.virtual),
        )


class MapPointRecord:
    """One map point as the atlas holds it: its position ``p_ref (3,)`` in its reference
    keyframe's body frame (``ref``; None: no observer, and ``p_ref`` is in the map frame),
    the linked observations, and those of keyframes not arrived yet.

    The point follows its reference keyframe: ``p_map`` is computed from the keyframe's
    current pose, so moving keyframes (a pose graph, the edge's re-sent poses) moves their
    points without touching them. Setting ``p_map`` stores it relative to the current pose;
    :meth:`set_ref` changes the reference and keeps ``p_map``."""

    __slots__ = ("agent_id", "key", "map_id", "map_point_id", "obs", "p_ref", "pending", "ref")

    def __init__(self, key: int, agent_id: int, map_point_id: int, map_id: int) -> None:
        self.key = key
        self.agent_id = agent_id
        self.map_point_id = map_point_id
        self.map_id = map_id
        self.p_ref = np.zeros(3)
        self.ref: KeyframeRecord | None = None
        self.obs: dict[int, int] = {}  # linked keyframe key -> keypoint index
        self.pending: dict[int, int] = {}  # keyframe not arrived yet -> keypoint index

    @property
    def ref_kf(self) -> int:
        """The reference keyframe's key (-1: none)."""
        return -1 if self.ref is None else self.ref.key

    @property
    def p_map(self) -> np.ndarray:
        """``(3,)`` in the map frame (a new array)."""
        if self.ref is None:
            return self.p_ref.copy()
        T = self.ref.T_map_body
        return T[:3, :3] @ self.p_ref + T[:3, 3]

    @p_map.setter
    def p_map(self, p: np.ndarray) -> None:
        p = np.asarray(p, np.float64).reshape(3)
        if self.ref is None:
            self.p_ref = p.copy()
        else:
            T = self.ref.T_map_body
            self.p_ref = T[:3, :3].T @ (p - T[:3, 3])

    def set_ref(self, ref: KeyframeRecord | None) -> None:
        """Make ``ref`` the reference keyframe; the point stays where it is."""
        if ref is self.ref:
            return
        p = self.p_map
        self.ref = ref
        self.p_map = p

    def row(self) -> tuple[int, int, int, int, int, bytes, bytes, int]:
        """Plain data for persistence, without a view: key, agent, map point id, map,
        reference keyframe, position (:meth:`stored_position`), the observations sorted by
        keyframe key as "<i8 (N, 2)" bytes [keyframe key, keypoint index], in_ref."""
        obs = np.array(sorted(self.obs.items()), "<i8").reshape(-1, 2)
        p, in_ref = self.stored_position()
        return (
            self.key,
            self.agent_id,
            self.map_point_id,
            self.map_id,
            self.ref_kf,
            p,
            obs.tobytes(),
            in_ref,
        )

    def position_row(self) -> tuple[bytes, int, int]:
        """:meth:`stored_position` and the key."""
        return (*self.stored_position(), self.key)

    def stored_position(self) -> tuple[bytes, int]:
        """The position as "<f8 (3,)" bytes in the reference keyframe's body frame and 1, or
        without one in the map frame and 0."""
        return np.asarray(self.p_ref, "<f8").tobytes(), int(self.ref is not None)

    def view(self) -> MapPointView:
        """A read-only copy (observations sorted by keyframe key)."""
        items = sorted(self.obs.items())
        return MapPointView(
            key=self.key,
            agent_id=self.agent_id,
            map_point_id=self.map_point_id,
            map_id=self.map_id,
            p_map=ro(self.p_map),
            obs_keyframes=ro(np.array([a for a, _ in items], np.int64)),
            obs_indices=ro(np.array([b for _, b in items], np.int64)),
            ref_kf=self.ref_kf,
        )


@dataclass
class Unsaved:
    """Keys the atlas changed since its store last wrote them (see ``CloudStore.save_all``):
    a keyframe whose whole row changed (new, its features: MBP's virtual observations, its
    map, removed) or a map point's (new, its observations, map, removed), and those of which
    only the keyframe's pose and state (velocity, biases) / the point's position changed. A
    keyframe's links to map points are stored with the points (their observations)."""

    keyframes: set[int] = field(default_factory=set)
    poses: set[int] = field(default_factory=set)
    points: set[int] = field(default_factory=set)
    positions: set[int] = field(default_factory=set)

    def update(self, other: Unsaved) -> None:
        """Also what ``other`` holds."""
        for f in fields(self):
            getattr(self, f.name).update(getattr(other, f.name))

    def take(self) -> Unsaved:
        """What changed until now, forgotten here (changes after this call are kept)."""
        taken = Unsaved(**{f.name: getattr(self, f.name) for f in fields(self)})
        for f in fields(self):
            setattr(self, f.name, set())
        return taken


def map_positions(mps: Sequence[MapPointRecord]) -> np.ndarray:
    """``(N, 3)``: the ``p_map`` of each of ``mps``, in one pass."""
    if not mps:
        return np.zeros((0, 3))
    eye = np.eye(4)
    P = np.array([m.p_ref for m in mps], np.float64).reshape(-1, 3)
    Ts = np.array([eye if m.ref is None else m.ref.T_map_body for m in mps]).reshape(-1, 4, 4)
    return np.einsum("nij,nj->ni", Ts[:, :3, :3], P) + Ts[:, :3, 3]


def place_points(mps: Sequence[MapPointRecord], p_map: np.ndarray) -> None:
    """Set each of ``mps`` at its row of ``p_map (N, 3)`` (map frame), in order (a point
    listed twice ends at its last row): ``MapPointRecord.p_map``'s setter for all at once,
    the inverse of :func:`map_positions`."""
    refs = [i for i, mp in enumerate(mps) if mp.ref is not None]
    p_ref = np.array(p_map, np.float64).reshape(-1, 3)  # (no reference keyframe: map frame)
    if refs:
        T = np.array([mps[i].ref.T_map_body for i in refs])  # type: ignore[union-attr]
        d = p_ref[refs] - T[:, :3, 3]
        p_ref[refs] = np.einsum("nji,nj->ni", T[:, :3, :3], d)
    for mp, row in zip(mps, p_ref, strict=True):
        mp.p_ref = row


def snapshot_of(
    kf_records: Mapping[int, KeyframeRecord],
    mp_records: Mapping[int, MapPointRecord],
    graph: CovisibilityGraph,
    loops: Sequence[LoopEdge],
    map_of_agent: Mapping[int, int],
    T_map_agent: Mapping[int, np.ndarray],
    merges: Sequence[MergeRecord],
) -> AtlasSnapshot:
    """An :class:`AtlasSnapshot` (copies, read-only) of an atlas's records."""
    kfs = [kf_records[k] for k in sorted(kf_records)]
    mps = [mp_records[k] for k in sorted(mp_records)]
    cov = graph.edges()
    i64 = np.int64
    return AtlasSnapshot(
        keyframe_keys=ro(np.array([k.key for k in kfs], i64)),
        keyframe_agent=ro(np.array([k.agent_id for k in kfs], i64)),
        keyframe_map=ro(np.array([k.map_id for k in kfs], i64)),
        keyframe_timestamp=ro(np.array([k.timestamp for k in kfs], np.float64)),
        T_map_body=ro(np.array([k.T_map_body for k in kfs]).reshape(-1, 4, 4)),
        point_keys=ro(np.array([m.key for m in mps], i64)),
        point_map=ro(np.array([m.map_id for m in mps], i64)),
        p_map=ro(map_positions(mps)),
        covisibility=ro(np.array([(a, b) for a, b, _ in cov], i64).reshape(-1, 2)),
        covisibility_weight=ro(np.array([w for _, _, w in cov], i64)),
        spanning_tree=ro(np.array(graph.tree(), i64).reshape(-1, 2)),
        loops=ro(np.array([(e.key_a, e.key_b) for e in loops], i64).reshape(-1, 2)),
        map_of_agent=dict(map_of_agent),
        T_map_agent={a: ro(T) for a, T in T_map_agent.items()},
        merges=tuple(merges),
    )


def heir_reference(observers: Iterable[KeyframeRecord], gone: KeyframeRecord) -> int:
    """The key of the reference keyframe a map point takes when ``gone`` (its reference)
    stops observing it: of its remaining ``observers``, the one of the same agent nearest in
    time, else the nearest in time of any agent (-1: none left). The point then keeps following
    the robot whose keyframes made it when later updates move that robot's keyframes (the
    edge's re-sent poses, a pose graph), not another robot's."""
    best, best_rank = -1, (True, math.inf, 0)
    for o in observers:
        rank = (o.agent_id != gone.agent_id, abs(o.timestamp - gone.timestamp), o.key)
        if rank < best_rank:
            best, best_rank = o.key, rank
    return best
