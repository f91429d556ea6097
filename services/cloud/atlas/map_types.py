"""Plain data the atlas takes in and hands out: inputs from the edges, read-only views,
snapshots and records of merges and loops. Keys: ``key = agent_id << 32 | local_id``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from common.calibration import CameraCalibration
from common.errors import RecslamError

CameraOf = Callable[[int], CameraCalibration]
"""Atlas agent id -> the camera of that agent's robot (each robot brings its own)."""


def camera_lookup(camera: CameraCalibration | CameraOf) -> CameraOf:
    """``camera`` as a :data:`CameraOf` (one calibration: every agent's)."""
    if isinstance(camera, CameraCalibration):
        return lambda _agent: camera
    return camera


LOCAL_BITS = 32
LOCAL_ID_MAX = (1 << LOCAL_BITS) - 1


class AtlasError(RecslamError):
    """Malformed keyframe / map point input or misuse of the atlas."""


def make_key(agent_id: int, local_id: int) -> int:
    """Global key of an agent's keyframe or map point id (both non-negative, local < 2**32)."""
    if agent_id < 0 or not 0 <= local_id <= LOCAL_ID_MAX:
        raise AtlasError(f"bad id: agent {agent_id}, local {local_id}")
    return (int(agent_id) << LOCAL_BITS) | int(local_id)


def _check_ids(what: str, agents: np.ndarray, ids: np.ndarray, obs: np.ndarray) -> None:
    """AtlasError unless every agent id is >= 0 and every local id (``ids``, the keyframe
    ids in ``obs[:, 0]``) is in ``[0, LOCAL_ID_MAX]``: what :func:`make_key` takes."""
    local = np.concatenate([np.asarray(ids, np.int64).ravel(), obs[:, 0]])
    if (agents.size and agents.min() < 0) or (
        local.size and (local.min() < 0 or local.max() > LOCAL_ID_MAX)
    ):
        raise AtlasError(f"{what}: bad id (agent >= 0, ids and keyframe ids in [0, 2**32))")


def split_key(key: int) -> tuple[int, int]:
    """Inverse of :func:`make_key`: ``(agent_id, local_id)``."""
    return int(key) >> LOCAL_BITS, int(key) & LOCAL_ID_MAX


def ro(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


def _check(arr: object, shape: tuple[int | None, ...], dtype: type, what: str) -> np.ndarray:
    a = np.asarray(arr)
    ok = a.ndim == len(shape) and all(
        s is None or s == d for s, d in zip(shape, a.shape, strict=False)
    )
    if not ok:
        raise AtlasError(f"{what} must have shape {shape}, got {a.shape}")
    if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
        raise AtlasError(f"{what} contains non-finite values")
    return np.array(a, dtype=dtype, copy=True)


@dataclass(frozen=True, eq=False)
class KeyframeInput:
    """A keyframe as the edge sends it.

    T_world_body (4, 4): body pose in the agent's map frame. velocity (3,) m/s in that frame;
    bias_gyro (3,) rad/s, bias_accel (3,) m/s². keypoints (N, 2): distorted pixels at level 0;
    levels (N,) pyramid level; descriptors (N, 32) uint8 ORB; word_ids (N,) visual word of each
    keypoint; map_point_ids (N,) the agent's map point id observed at that keypoint or -1.
    """

    agent_id: int
    keyframe_id: int
    timestamp: float
    T_world_body: np.ndarray
    keypoints: np.ndarray
    levels: np.ndarray
    descriptors: np.ndarray
    word_ids: np.ndarray
    map_point_ids: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias_gyro: np.ndarray = field(default_factory=lambda: np.zeros(3))
    bias_accel: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        what = f"keyframe {self.agent_id}/{self.keyframe_id}"
        kp = _check(self.keypoints, (None, 2), np.float64, f"{what}: keypoints")
        n = kp.shape[0]
        fields = {
            "T_world_body": _check(self.T_world_body, (4, 4), np.float64, f"{what}: T_world_body"),
            "keypoints": kp,
            "levels": _check(self.levels, (n,), np.int16, f"{what}: levels"),
            "word_ids": _check(self.word_ids, (n,), np.int32, f"{what}: word_ids"),
            "map_point_ids": _check(self.map_point_ids, (n,), np.int64, f"{what}: map_point_ids"),
            "velocity": _check(self.velocity, (3,), np.float64, f"{what}: velocity"),
            "bias_gyro": _check(self.bias_gyro, (3,), np.float64, f"{what}: bias_gyro"),
            "bias_accel": _check(self.bias_accel, (3,), np.float64, f"{what}: bias_accel"),
        }
        desc = np.asarray(self.descriptors)
        if desc.shape != (n, 32) or desc.dtype != np.uint8:
            raise AtlasError(
                f"{what}: descriptors must be ({n}, 32) uint8, got {desc.shape} {desc.dtype}"
            )
        fields["descriptors"] = np.array(desc, copy=True)
        R = fields["T_world_body"][:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-5):
            raise AtlasError(f"{what}: T_world_body rotation is not orthonormal")
        for name, value in fields.items():
            value.setflags(write=False)
            object.__setattr__(self, name, value)


@dataclass(frozen=True, eq=False)
class MapPointInput:
    """A map point as the edge sends it: ``p_world (3,)`` metres in the agent's map frame,
    ``observations (M, 2)`` int rows ``(keyframe_id, keypoint_index)`` of the same agent.
    Its ids are checked as :func:`make_key` needs them, so keys are built without checks."""

    agent_id: int
    map_point_id: int
    p_world: np.ndarray
    observations: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))

    def __post_init__(self) -> None:
        what = f"map point {self.agent_id}/{self.map_point_id}"
        p = _check(self.p_world, (3,), np.float64, f"{what}: p_world")
        obs = _check(
            np.asarray(self.observations).reshape(-1, 2),
            (None, 2),
            np.int64,
            f"{what}: observations",
        )
        _check_ids(what, np.array([self.agent_id]), np.array([self.map_point_id]), obs)
        for v in (p, obs):
            v.setflags(write=False)
        object.__setattr__(self, "p_world", p)
        object.__setattr__(self, "observations", obs)

    @classmethod
    def batch(
        cls,
        agent_id: int,
        ids: np.ndarray,
        p_world: np.ndarray,
        observations: np.ndarray,
        starts: np.ndarray,
        ends: np.ndarray,
    ) -> list[MapPointInput]:
        """One point per id, checked as whole arrays (what ``__post_init__`` checks per point,
        at a fraction of its cost for the thousands of points of one update): ``ids (N,)``,
        ``p_world (N, 3)``, ``observations (M, 2)`` rows ``(keyframe_id, keypoint_index)``,
        point ``i``'s being rows ``starts[i]:ends[i]``."""
        what = f"map points of agent {agent_id}"
        n = int(np.asarray(ids).shape[0])
        P = _check(p_world, (n, 3), np.float64, f"{what}: p_world")
        obs = _check(np.asarray(observations).reshape(-1, 2), (None, 2), np.int64, what)
        lo, hi = np.asarray(starts, np.int64), np.asarray(ends, np.int64)
        if lo.shape != (n,) or hi.shape != (n,) or np.any(lo < 0) or np.any(hi < lo):
            raise AtlasError(f"{what}: observation ranges do not fit the ids")
        if n and int(hi.max()) > obs.shape[0]:
            raise AtlasError(f"{what}: observation ranges beyond the observations")
        _check_ids(what, np.array([agent_id]), np.asarray(ids), obs)
        for v in (P, obs):
            v.setflags(write=False)
        out = []
        rows = zip(np.asarray(ids).tolist(), lo.tolist(), hi.tolist(), strict=True)
        for i, (mp_id, a, b) in enumerate(rows):
            mp = object.__new__(cls)
            object.__setattr__(mp, "agent_id", int(agent_id))
            object.__setattr__(mp, "map_point_id", int(mp_id))
            object.__setattr__(mp, "p_world", P[i])
            object.__setattr__(mp, "observations", obs[a:b])
            out.append(mp)
        return out


@dataclass(frozen=True, eq=False)
class KeyframeView:
    """Read-only copy of one keyframe as the atlas holds it (pose in its map's frame).

    ``map_point_keys (N,)`` global map point keys or -1; ``virtual (N,)`` marks observations
    folded in by map backbone profiling (they have no real keypoint in this image).
    """

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
    map_point_keys: np.ndarray
    virtual: np.ndarray


@dataclass(frozen=True, eq=False)
class MapPointView:
    """Read-only copy of one map point: ``p_map (3,)`` in its map's frame, observations as
    ``obs_keyframes (M,)`` keys with ``obs_indices (M,)`` keypoint indices."""

    key: int
    agent_id: int
    map_point_id: int
    map_id: int
    p_map: np.ndarray
    obs_keyframes: np.ndarray
    obs_indices: np.ndarray
    ref_kf: int


class AliasSnapshot(Mapping[int, int]):
    """The fused map points' aliases (dropped key -> surviving key) as they were when the
    snapshot was taken: the first ``n`` assignments of the atlas' append-only ``log``
    (a later assignment of a key overrides an earlier one). Taking one costs nothing, so
    that a store can write only the assignments since its last snapshot
    (:meth:`since`), not a copy of every alias per transaction (tens of thousands once
    loops fuse their points). The dict behind the lookups is built on first use."""

    def __init__(self, log: list[tuple[int, int]], n: int) -> None:
        self.log, self.n = log, n
        self._dict: dict[int, int] | None = None

    def _mapping(self) -> dict[int, int]:
        if self._dict is None:
            self._dict = dict(self.log[: self.n])
        return self._dict

    def __getitem__(self, key: int) -> int:
        return self._mapping()[key]

    def __iter__(self) -> Iterator[int]:
        return iter(self._mapping())

    def __len__(self) -> int:
        return len(self._mapping())

    def since(self, earlier: Mapping[int, int]) -> list[tuple[int, int]] | None:
        """The assignments made after ``earlier`` (a snapshot of the same log), in order;
        None when ``earlier`` is not one (then compare the mappings)."""
        if not isinstance(earlier, AliasSnapshot) or earlier.log is not self.log:
            return None
        if earlier.n > self.n:
            return None
        return self.log[earlier.n : self.n]


@dataclass(frozen=True, eq=False)
class AtlasState:
    """Everything besides keyframes and map points needed to rebuild an atlas."""

    map_of_agent: dict[int, int]
    T_map_agent: dict[int, np.ndarray]
    merges: tuple[MergeRecord, ...]
    loops: tuple[LoopEdge, ...]
    removed_keyframes: frozenset[int]
    aliases: Mapping[int, int]
    retired: tuple[RetiredKeyframe, ...] = ()


@dataclass(frozen=True)
class RetiredKeyframe:
    """A keyframe MBP removed, kept only as its pose relative to a kept keyframe of the same
    agent (``anchor``), as ORB-SLAM keeps a culled keyframe's pose relative to its parent, so
    that trajectories still hold every keyframe: ``T_map_body = T_map_body(anchor) @
    T_anchor_body``. When the anchor goes too, the record moves to the anchor's heir.

    ``other``: the agent's kept keyframe on the other side of it in time (None: none), with
    its pose in that one's frame ``T_other_body``; the pose is then the blend of the two
    (:func:`services.cloud.atlas.retired.retired_pose`), ``w_other`` (0..1) of the way to what
    ``other`` says, by time, so that a correction that bends the stretch between two kept
    keyframes after the removal carries the removed one along the bend, not rigidly with one
    end. It goes (the blend with it) when ``other`` goes."""

    key: int
    agent_id: int
    timestamp: float
    anchor: int
    T_anchor_body: np.ndarray
    other: int | None = None
    T_other_body: np.ndarray | None = None
    w_other: float = 0.0


@dataclass(frozen=True)
class MergeRecord:
    """One map merge: ``source_map`` absorbed into ``target_map`` with ``T_target_source``."""

    target_map: int
    source_map: int
    T_target_source: np.ndarray
    query_key: int
    candidate_key: int
    fused_points: int


@dataclass(frozen=True)
class LoopEdge:
    """A verified loop / merge constraint: measured ``T_a_b`` between keyframe bodies."""

    key_a: int
    key_b: int
    T_a_b: np.ndarray
    inter_agent: bool


@dataclass(frozen=True, eq=False)
class AtlasSnapshot:
    """Plain read-only arrays describing the atlas (for the dashboard and reports).

    keyframe_keys (K,), keyframe_agent (K,), keyframe_map (K,), keyframe_timestamp (K,),
    T_map_body (K, 4, 4); point_keys (P,), point_map (P,), p_map (P, 3);
    covisibility (E, 2) keyframe keys with covisibility_weight (E,);
    spanning_tree (T, 2) rows (child, parent); loops (L, 2) keyframe keys;
    map_of_agent {agent: map}; T_map_agent {agent: (4, 4)}; merges tuple of MergeRecord.
    """

    keyframe_keys: np.ndarray
    keyframe_agent: np.ndarray
    keyframe_map: np.ndarray
    keyframe_timestamp: np.ndarray
    T_map_body: np.ndarray
    point_keys: np.ndarray
    point_map: np.ndarray
    p_map: np.ndarray
    covisibility: np.ndarray
    covisibility_weight: np.ndarray
    spanning_tree: np.ndarray
    loops: np.ndarray
    map_of_agent: dict[int, int]
    T_map_agent: dict[int, np.ndarray]
    merges: tuple[MergeRecord, ...]
