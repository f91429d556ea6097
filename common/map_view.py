"""The narrow read interface between the cloud's map and the dashboard.

The cloud implements :class:`MapSource`; the dashboard only reads these plain, frozen records
of read-only numpy arrays (it never imports ``services``). Frames: every position and pose is
in the *display world* frame the source chooses (e.g. each map's frame, with maps that have
not merged yet placed side by side); ``T_world_body`` (4, 4) maps body coordinates to it.

Versions: ``snapshot(since_version)`` returns a :class:`MapDelta` holding what changed after
``since_version`` (new or moved points and keyframes, removed ids) up to ``delta.version``.
``since_version < 0`` asks for everything (``full=True``); a source may also answer any
request with a full delta, which tells the reader to drop its state first.

MBP: points and keyframes removed by map backbone profiling may still be reported with
``pruned=True`` so that the map can be shown "without MBP" (everything) and "with MBP"
(pruned items hidden). A source that forgets pruned items reports them as removed instead.

Recordings: :func:`save_recording` / :func:`load_recording` store one full delta plus one
stats snapshot in an ``.npz`` file; :class:`StaticMapSource` replays them (optionally
revealing the map progressively so that a replay looks live).
"""

from __future__ import annotations

import enum
import json
import threading
import time
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from common.errors import RecslamError

RECORDING_FORMAT = "recslam-map-recording/1"


class MapViewError(RecslamError):
    """Malformed map view data or recording file."""


def _ro(a: object, dtype: type, shape: tuple[int | None, ...], what: str) -> np.ndarray:
    arr: np.ndarray = np.array(a, dtype=dtype, copy=True)
    if arr.size == 0 and len(shape) > 1:
        arr = arr.reshape((0, *[s or 0 for s in shape[1:]]))
    ok = arr.ndim == len(shape) and all(
        s is None or s == d for s, d in zip(shape, arr.shape, strict=False)
    )
    if not ok:
        raise MapViewError(f"{what} must have shape {shape}, got {arr.shape}")
    arr.setflags(write=False)
    return arr


class AgentState(enum.Enum):
    """Life cycle of one agent as the cloud sees it."""

    INITIALISING = "initialising"
    TRACKING = "tracking"
    LOST = "lost"
    MERGED = "merged"


@dataclass(frozen=True, eq=False)
class PointSet:
    """Map points: ``ids (N,)`` int64 global keys, ``p_world (N, 3)`` float32 metres,
    ``agent (N,)`` int32 owner agent, ``pruned (N,)`` bool (removed by MBP)."""

    ids: np.ndarray
    p_world: np.ndarray
    agent: np.ndarray
    pruned: np.ndarray

    def __post_init__(self) -> None:
        ids = _ro(self.ids, np.int64, (None,), "PointSet.ids")
        n = ids.shape[0]
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "p_world", _ro(self.p_world, np.float32, (n, 3), "p_world"))
        object.__setattr__(self, "agent", _ro(self.agent, np.int32, (n,), "PointSet.agent"))
        object.__setattr__(self, "pruned", _ro(self.pruned, np.bool_, (n,), "PointSet.pruned"))

    @classmethod
    def empty(cls) -> PointSet:
        return cls(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool))

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def subset(self, mask_or_index: np.ndarray) -> PointSet:
        """The points selected by a boolean mask or an index array."""
        i = mask_or_index
        return PointSet(self.ids[i], self.p_world[i], self.agent[i], self.pruned[i])


@dataclass(frozen=True, eq=False)
class KeyframeSet:
    """Keyframes: ``ids (K,)`` int64 global keys, ``agent (K,)`` int32, ``timestamp (K,)``
    float64 seconds, ``T_world_body (K, 4, 4)`` float64, ``pruned (K,)`` bool (removed by MBP)."""

    ids: np.ndarray
    agent: np.ndarray
    timestamp: np.ndarray
    T_world_body: np.ndarray
    pruned: np.ndarray

    def __post_init__(self) -> None:
        ids = _ro(self.ids, np.int64, (None,), "KeyframeSet.ids")
        n = ids.shape[0]
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "agent", _ro(self.agent, np.int32, (n,), "KeyframeSet.agent"))
        object.__setattr__(self, "timestamp", _ro(self.timestamp, np.float64, (n,), "timestamp"))
        T = _ro(self.T_world_body, np.float64, (n, 4, 4), "KeyframeSet.T_world_body")
        object.__setattr__(self, "T_world_body", T)
        object.__setattr__(self, "pruned", _ro(self.pruned, np.bool_, (n,), "KeyframeSet.pruned"))

    @classmethod
    def empty(cls) -> KeyframeSet:
        return cls(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 4, 4)), np.zeros(0, bool))

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def subset(self, mask_or_index: np.ndarray) -> KeyframeSet:
        i = mask_or_index
        return KeyframeSet(
            self.ids[i], self.agent[i], self.timestamp[i], self.T_world_body[i], self.pruned[i]
        )


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Reference trajectory of one agent: ``timestamp (T,)`` s and ``p_world (T, 3)`` metres,
    already expressed in the display world frame."""

    agent_id: int
    timestamp: np.ndarray
    p_world: np.ndarray

    def __post_init__(self) -> None:
        t = _ro(self.timestamp, np.float64, (None,), "GroundTruth.timestamp")
        object.__setattr__(self, "timestamp", t)
        p = _ro(self.p_world, np.float64, (t.shape[0], 3), "GroundTruth.p_world")
        object.__setattr__(self, "p_world", p)


@dataclass(frozen=True, eq=False)
class MapDelta:
    """What changed in the map after ``since_version`` up to ``version``.

    ``points`` / ``keyframes``: new or changed (moved, pruned) items; ``removed_*_ids``: gone.
    ``current_pose``: latest ``T_world_body (4, 4)`` per agent. ``loops`` and ``merges``:
    complete lists (they are short) of keyframe id pairs ``(L, 2)`` int64. ``ground_truth``:
    complete list when it changed (or in a full delta), else empty.
    """

    version: int
    since_version: int
    full: bool
    points: PointSet = field(default_factory=PointSet.empty)
    removed_point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    keyframes: KeyframeSet = field(default_factory=KeyframeSet.empty)
    removed_keyframe_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    current_pose: Mapping[int, np.ndarray] = field(default_factory=dict)
    loops: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    merges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    ground_truth: tuple[GroundTruth, ...] = ()

    def __post_init__(self) -> None:
        for name in ("removed_point_ids", "removed_keyframe_ids"):
            object.__setattr__(self, name, _ro(getattr(self, name), np.int64, (None,), name))
        for name in ("loops", "merges"):
            object.__setattr__(self, name, _ro(getattr(self, name), np.int64, (None, 2), name))
        poses = {
            int(a): _ro(T, np.float64, (4, 4), f"current_pose[{a}]")
            for a, T in self.current_pose.items()
        }
        object.__setattr__(self, "current_pose", poses)

    @property
    def empty(self) -> bool:
        """True when nothing changed (the reader may skip it)."""
        return (
            not self.full
            and len(self.points) == 0
            and len(self.keyframes) == 0
            and self.removed_point_ids.size == 0
            and self.removed_keyframe_ids.size == 0
            and not self.current_pose
            and not self.ground_truth
        )


@dataclass(frozen=True)
class AgentRecord:
    """One agent's status: frames seen, keyframes in the map, ``last_seen`` (source clock, s),
    the map it belongs to, its live ATE RMSE in metres when the source knows it, which robot
    it is (``name``) on which edge (``edge``; "" when the source does not say), and the
    edge's ``detail`` (why a robot is not tracking, the camera-IMU offset)."""

    agent_id: int
    status: AgentState
    frames: int
    keyframes: int
    last_seen: float
    map_id: int
    ate_rmse_m: float | None = None
    name: str = ""
    edge: str = ""
    detail: str = ""  # why it is in its state, with numbers ("" when the source does not say)


class Direction(enum.Enum):
    """Direction of traffic on a link: ``UP`` towards the cloud, ``DOWN`` towards robots."""

    UP = "up"
    DOWN = "down"


@dataclass(frozen=True)
class BandwidthSample:
    """Bytes (headers included) of one message type sent on one link around ``time`` (s).

    ``link`` names the two ends, e.g. ``"robot1→edge"`` or ``"edge→cloud"``."""

    time: float
    link: str
    direction: Direction
    message_type: str
    n_bytes: int


@dataclass(frozen=True)
class MapCounts:
    """Sizes of the map: keyframes and points (all / kept after MBP), loops and merges."""

    keyframes: int
    keyframes_kept: int
    map_points: int
    map_points_kept: int
    loops: int
    merges: int


@dataclass(frozen=True)
class StatsSnapshot:
    """Panels' data at source time ``time`` (s): agents, counts and the bandwidth samples of a
    recent window (the source decides its length, e.g. the last two minutes), and ``status``:
    what the source says of its own state in words ('' = nothing to say; e.g. a cloud that
    sheds work under load)."""

    time: float
    agents: tuple[AgentRecord, ...]
    counts: MapCounts
    bandwidth: tuple[BandwidthSample, ...] = ()
    status: str = ""


@runtime_checkable
class MapSource(Protocol):
    """What the dashboard reads. Called from the dashboard's own thread: implementations must
    be thread-safe (e.g. copy under a lock) and must not block for long."""

    def snapshot(self, since_version: int) -> MapDelta:
        """Changes after ``since_version`` (``< 0``: everything)."""
        ...

    def stats(self) -> StatsSnapshot:
        """Current agents, counts and recent bandwidth."""
        ...


def counts_of(points: PointSet, keyframes: KeyframeSet, loops: int, merges: int) -> MapCounts:
    """Counts of a complete map."""
    return MapCounts(
        keyframes=len(keyframes),
        keyframes_kept=int(np.count_nonzero(~keyframes.pruned)),
        map_points=len(points),
        map_points_kept=int(np.count_nonzero(~points.pruned)),
        loops=loops,
        merges=merges,
    )


# ----------------------------------------------------------------------------- recordings


def save_recording(path: str | Path, delta: MapDelta, stats: StatsSnapshot) -> None:
    """Write a full ``delta`` and ``stats`` to an ``.npz`` file (no pickles)."""
    if not delta.full:
        raise MapViewError("save_recording needs a full delta (snapshot(-1))")
    pose_agents = sorted(delta.current_pose)
    meta = {
        "format": RECORDING_FORMAT,
        "version": delta.version,
        "time": stats.time,
        "agents": [{**a.__dict__, "status": a.status.value} for a in stats.agents],
        "bandwidth": [
            [b.time, b.link, b.direction.value, b.message_type, b.n_bytes] for b in stats.bandwidth
        ],
        "current_pose_agents": pose_agents,
        "ground_truth_agents": [g.agent_id for g in delta.ground_truth],
    }
    arrays: dict[str, np.ndarray] = {
        "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8),
        "pt_ids": delta.points.ids,
        "pt_p_world": delta.points.p_world,
        "pt_agent": delta.points.agent,
        "pt_pruned": delta.points.pruned,
        "kf_ids": delta.keyframes.ids,
        "kf_agent": delta.keyframes.agent,
        "kf_timestamp": delta.keyframes.timestamp,
        "kf_T_world_body": delta.keyframes.T_world_body,
        "kf_pruned": delta.keyframes.pruned,
        "loops": delta.loops,
        "merges": delta.merges,
        "current_pose": np.array([delta.current_pose[a] for a in pose_agents]).reshape(-1, 4, 4),
    }
    for i, g in enumerate(delta.ground_truth):
        arrays[f"gt{i}_timestamp"] = g.timestamp
        arrays[f"gt{i}_p_world"] = g.p_world
    with open(path, "wb") as f:
        np.savez_compressed(f, allow_pickle=False, **arrays)


def load_recording(path: str | Path) -> tuple[MapDelta, StatsSnapshot]:
    """Read a file written by :func:`save_recording`; errors name the file and what is wrong."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise MapViewError(f"{path}: not a readable map recording ({exc})") from exc
    try:
        meta = json.loads(bytes(data["meta"]).decode())
        if meta.get("format") != RECORDING_FORMAT:
            raise MapViewError(f"{path}: format {meta.get('format')!r}, want {RECORDING_FORMAT}")
        points = PointSet(data["pt_ids"], data["pt_p_world"], data["pt_agent"], data["pt_pruned"])
        kfs = KeyframeSet(
            data["kf_ids"],
            data["kf_agent"],
            data["kf_timestamp"],
            data["kf_T_world_body"],
            data["kf_pruned"],
        )
        gts = tuple(
            GroundTruth(a, data[f"gt{i}_timestamp"], data[f"gt{i}_p_world"])
            for i, a in enumerate(meta["ground_truth_agents"])
        )
        poses = dict(zip(meta["current_pose_agents"], data["current_pose"], strict=True))
        delta = MapDelta(
            version=int(meta["version"]),
            since_version=-1,
            full=True,
            points=points,
            keyframes=kfs,
            current_pose=poses,
            loops=data["loops"],
            merges=data["merges"],
            ground_truth=gts,
        )
        agents = tuple(
            AgentRecord(**{**a, "status": AgentState(a["status"])}) for a in meta["agents"]
        )
        bw = tuple(
            BandwidthSample(float(t), str(link), Direction(d), str(m), int(n))
            for t, link, d, m, n in meta["bandwidth"]
        )
    except MapViewError:
        raise
    except (KeyError, TypeError, ValueError, UnicodeDecodeError) as exc:
        raise MapViewError(
            f"{path}: malformed map recording ({type(exc).__name__}: {exc})"
        ) from exc
    counts = counts_of(points, kfs, len(delta.loops), len(delta.merges))
    return delta, StatsSnapshot(float(meta["time"]), agents, counts, bw)


# ----------------------------------------------------------------------------- replay


def _reveal_rank(agent: np.ndarray) -> np.ndarray:
    """Fraction in (0, 1] at which each item appears: its rank within its agent's items."""
    rank = np.zeros(agent.shape[0])
    for a in np.unique(agent):
        idx = np.flatnonzero(agent == a)
        rank[idx] = np.arange(1, idx.size + 1) / idx.size
    return rank


class StaticMapSource:
    """A :class:`MapSource` over a fixed map (e.g. a recording).

    With ``reveal_seconds > 0`` the map appears progressively in ``reveal_steps`` versions
    over that many seconds (each agent's points and keyframes in their stored order, poses
    following the latest revealed keyframe), which makes a replay exercise the dashboard's
    incremental path. ``clock`` returns seconds (default ``time.monotonic``).
    """

    def __init__(
        self,
        delta: MapDelta,
        stats: StatsSnapshot,
        reveal_seconds: float = 0.0,
        reveal_steps: int = 100,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not delta.full:
            raise MapViewError("StaticMapSource needs a full delta")
        if reveal_steps < 1:
            raise MapViewError(f"reveal_steps must be >= 1, got {reveal_steps}")
        self._map = delta
        self._stats = stats
        self._reveal_s = float(reveal_seconds)
        self._steps = int(reveal_steps) if reveal_seconds > 0 else 1
        self._clock = clock
        self._t0 = clock()
        self._lock = threading.Lock()
        self._pt_rank = _reveal_rank(delta.points.agent)
        self._kf_rank = _reveal_rank(delta.keyframes.agent)
        bw_t = np.array([b.time for b in stats.bandwidth])
        self._bw_t0 = float(bw_t.min()) if bw_t.size else 0.0
        self._bw_span = float(bw_t.max() - bw_t.min()) if bw_t.size else 0.0

    @classmethod
    def from_file(cls, path: str | Path, reveal_seconds: float = 0.0) -> StaticMapSource:
        delta, stats = load_recording(path)
        return cls(delta, stats, reveal_seconds=reveal_seconds)

    def _step(self) -> int:
        if self._reveal_s <= 0:
            return self._steps
        frac = (self._clock() - self._t0) / self._reveal_s
        return int(np.clip(np.floor(frac * self._steps), 1, self._steps))

    def snapshot(self, since_version: int) -> MapDelta:
        with self._lock:
            step = self._step()
            since = min(since_version, step)
            lo, hi = max(since, 0) / self._steps, step / self._steps
            full = since_version < 1
            if full:
                lo = 0.0
            m = self._map
            pt = (self._pt_rank > lo) & (self._pt_rank <= hi)
            kf_upto = self._kf_rank <= hi
            kf = kf_upto & (self._kf_rank > lo)
            poses = {}
            for a in np.unique(m.keyframes.agent[kf_upto]):
                last = np.flatnonzero(kf_upto & (m.keyframes.agent == a))[-1]
                poses[int(a)] = m.keyframes.T_world_body[last]
            if step == self._steps:
                poses.update(m.current_pose)
            kf_ids = set(m.keyframes.ids[kf_upto].tolist())
            loops = [r for r in m.loops if r[0] in kf_ids and r[1] in kf_ids]
            merges = [r for r in m.merges if r[0] in kf_ids and r[1] in kf_ids]
            if not full and since == step:
                poses = {}
            return MapDelta(
                version=step,
                since_version=since_version,
                full=full,
                points=m.points.subset(pt),
                keyframes=m.keyframes.subset(kf),
                current_pose=poses,
                loops=np.array(loops, np.int64).reshape(-1, 2),
                merges=np.array(merges, np.int64).reshape(-1, 2),
                ground_truth=m.ground_truth if full else (),
            )

    def stats(self) -> StatsSnapshot:
        with self._lock:
            frac = self._step() / self._steps
        s = self._stats
        if frac >= 1.0:
            return s
        kf = self._kf_rank <= frac
        pt = self._pt_rank <= frac
        agents = tuple(
            replace(
                a,
                keyframes=int(np.count_nonzero(kf & (self._map.keyframes.agent == a.agent_id))),
                frames=round(a.frames * frac),
                status=AgentState.TRACKING if a.status is AgentState.MERGED else a.status,
            )
            for a in s.agents
        )
        t_cut = self._bw_t0 + frac * self._bw_span
        bw = tuple(b for b in s.bandwidth if b.time <= t_cut)
        m = self._map
        kf_ids = m.keyframes.ids[kf]
        n_loops = int(np.count_nonzero(np.isin(m.loops, kf_ids).all(axis=1)))
        n_merges = int(np.count_nonzero(np.isin(m.merges, kf_ids).all(axis=1)))
        counts = counts_of(m.points.subset(pt), m.keyframes.subset(kf), n_loops, n_merges)
        return StatsSnapshot(s.time * frac, agents, counts, bw)
