"""Map backbone profiling (MBP): prune redundant keyframes and map points of a map.

The paper (Section VI.B) extracts "the backbone of the map" and folds good observations of
removed keyframes into virtual keyframes. Keyframes reach the cloud sparsely (about 1.3 Hz
per robot on the recorded 3-robot run: consecutive keyframes share a median 43 % of their
map points, and for half of the keyframes no single other keyframe sees half of their
points), so a keyframe is judged redundant by what the kept keyframes see *together* — the
redundancy test of ORB-SLAM's keyframe culling (Mur-Artal, Montiel & Tardós, "ORB-SLAM: a
versatile and accurate monocular SLAM system", IEEE T-RO 31(5), 2015, Sec. VI-E: a keyframe
goes when 90 % of its points are seen by three other keyframes), here with one other
keyframe and a lower fraction, applied to the whole map under a connectivity constraint:

1. Coverage: a removed keyframe r is *covered* when the kept keyframes observe at least
   ``cover_ratio`` of r's map points (those at least two keyframes observe: a point only r
   sees constrains no pose) and one kept keyframe (its *absorber*, the strongest) shares at
   least ``min_shared`` points with r.
2. Backbone (reverse-delete greedy): every keyframe starts kept; pass after pass, in
   decreasing order of redundancy (the fraction of its points other kept keyframes see), a
   keyframe is removed when it is not protected, it is covered by the others, every keyframe
   removed before stays covered, and the kept keyframes stay connected through covisibility
   edges of at least ``min_shared`` points (its removal does not separate two of its kept
   neighbours) and, with ``max_interval_s``, its agent's kept keyframes around it stay
   that close in time (the IMU interval the full BA still bridges with a preintegrated
   factor, ``FullBAConfig.imu_max_interval_s``). Passes repeat until none removes anything,
   so every kept keyframe is kept for a reason (:func:`backbone` reports which). Protected:
   each agent's first keyframe (the pose-graph anchor) and its ``keep_recent`` newest (the
   edge's live window). A heuristic: the result is minimal (no kept keyframe can go alone)
   but not minimum.
3. Loop and merge constraints are not a reason to keep a keyframe: a constraint ``T_r_b`` of a
   removed keyframe r moves to a kept keyframe a of the same agent next to r in its sequence
   (:func:`loop_anchors`) as ``T_a_b = T_map_a^-1 T_map_r T_r_b`` (current estimates; MBP runs
   right after an optimisation), so the pose graph keeps every loop between the same agents
   (a moved constraint whose ends meet in one keyframe, or that repeats a pair already
   constrained, is dropped).
4. Folding: each removed keyframe's good observations (reprojection error ≤
   ``max_virtual_reprojection_px``) of map points its absorber does not see become *virtual
   observations* of the absorber (the point projected into it, with the removed keyframe's
   descriptor), which makes the absorber a virtual keyframe; points that would still have
   fewer than ``min_observations`` kept observers are also folded into the next absorbers
   (the other kept keyframes sharing ``min_shared`` points with r, strongest first).
5. Map points left with fewer than ``min_observations`` observations are removed (a pass
   while the robots run removes only the points left without any, ``MbpScheduleConfig.
   running``: a later keyframe or loop can still observe them).
6. A removed keyframe is *retired* (:meth:`Atlas.retire_keyframe`): its pose stays, relative
   to the kept keyframe its loops moved to, so trajectories and the ATE still cover every
   keyframe (ORB-SLAM reports culled keyframes through their parents the same way), and
   relative to the kept keyframe on its other side in time, the two blended by time
   (``MbpConfig.blend_retired``).
"""

from __future__ import annotations

import bisect
import logging
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from common.calibration import CameraCalibration
from common.camera import camera_model
from common.geometry import inverse_T, transform_points
from services.cloud.atlas.atlas import Atlas
from services.cloud.atlas.map_types import CameraOf, camera_lookup
from services.cloud.config import MbpConfig

log = logging.getLogger(__name__)

# Why a keyframe is kept (:attr:`Backbone.reasons`: the first that holds, in this order).
PROTECTED = "protected"  # an agent's first or one of its newest keyframes
NOT_COVERED = "not_covered"  # the other kept keyframes do not cover it
CONNECTOR = "connector"  # its removal would disconnect the kept keyframes
COVERS_REMOVED = "covers_removed"  # a removed keyframe would lose its coverage
INERTIAL = "inertial"  # its removal would leave a longer IMU interval than the full BA takes
REASONS = (PROTECTED, NOT_COVERED, CONNECTOR, COVERS_REMOVED, INERTIAL)

CONSTRAINING_OBSERVERS = 2
"""Coverage (step 1) counts a map point only when at least this many keyframes observe it:
the full BA's own rule for a point that constrains poses
(``services.cloud.optimization.full_ba``)."""


@dataclass(frozen=True)
class MbpReport:
    """Counts before / after one MBP pass over a map, and the keys removed."""

    map_id: int
    keyframes_before: int
    keyframes_after: int
    map_points_before: int
    map_points_after: int
    virtual_observations: int
    removed_keyframes: tuple[int, ...]
    connected_before: bool
    connected_after: bool
    loops_moved: int = 0


@dataclass(frozen=True)
class Backbone:
    """MBP's selection for one map: ``kept`` keys, the reason each is kept (one of
    :data:`REASONS`), and the absorbers of each removed key (the kept keyframes sharing at
    least ``min_shared`` points with it, strongest first; the first is *the* absorber)."""

    kept: frozenset[int]
    reasons: dict[int, str]
    absorbers: dict[int, tuple[int, ...]]


def covisibility_components(atlas: Atlas, keys: list[int], min_weight: int = 1) -> int:
    """Number of connected components of the covisibility graph restricted to ``keys``."""
    if not keys:
        return 0
    index = {k: i for i, k in enumerate(keys)}
    rows, cols = [], []
    for a in keys:
        for b, _ in atlas.covisible(a, min_weight):
            if b in index:
                rows.append(index[a])
                cols.append(index[b])
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(keys), len(keys)))
    return int(connected_components(g, directed=False)[0])


def protected_keyframes(
    atlas: Atlas, map_id: int, keep_recent: int, hold: frozenset[int] = frozenset()
) -> set[int]:
    """Each agent's first keyframe in ``map_id`` and its ``keep_recent`` newest; every
    keyframe of the agents in ``hold`` (a prior map, see ``services.cloud.store.mission``)."""
    keys = set()
    for agent in atlas.agents_in_map(map_id):
        ak = atlas.keyframe_keys(map_id=map_id, agent_id=agent)
        if agent in hold:
            keys.update(ak)
            continue
        keys.update(ak[:1])
        keys.update(ak[-keep_recent:] if keep_recent > 0 else [])
    return keys


class _Coverage:
    """Observer counts of the map points of a set of keyframes while some are removed.

    ``count[p]`` is how many kept keyframes observe point index p; ``points[k]`` the point
    indices keyframe k observes (real and virtual observations) among the points at least
    :data:`CONSTRAINING_OBSERVERS` of the keyframes observe: a point only k sees constrains
    no pose (the full BA leaves it out), so k need not be covered on it."""

    def __init__(self, atlas: Atlas, keys: list[int]) -> None:
        index: dict[int, int] = {}
        points: dict[int, np.ndarray] = {}
        for k in keys:
            mk = atlas.keyframe(k).map_point_keys
            ids = [index.setdefault(m, len(index)) for m in np.unique(mk[mk >= 0]).tolist()]
            points[k] = np.array(ids, np.int64)
        self.count = np.zeros(len(index), np.int64)
        for p in points.values():
            self.count[p] += 1
        self.points = {k: p[self.count[p] >= CONSTRAINING_OBSERVERS] for k, p in points.items()}

    def fraction(self, key: int, kept: bool) -> float:
        """Fraction of ``key``'s points seen by at least one *other* kept keyframe."""
        p = self.points[key]
        if p.size == 0:
            return 1.0
        return float(np.mean(self.count[p] - int(kept) >= 1))


def backbone(
    atlas: Atlas,
    map_id: int,
    config: MbpConfig,
    keep_recent: int = 5,
    hold: frozenset[int] = frozenset(),
) -> Backbone:
    """MBP's keyframe selection for ``map_id`` (steps 1–2 of the module docstring)."""
    keys = atlas.keyframe_keys(map_id=map_id)
    in_map = set(keys)
    w_of = {k: {b: w for b, w in atlas.covisible(k) if b in in_map} for k in keys}
    strong = {k: [b for b, w in w_of[k].items() if w >= config.min_shared] for k in keys}
    cov = _Coverage(atlas, keys)
    protected = protected_keyframes(atlas, map_id, keep_recent, hold)
    kept = set(keys)
    removed: list[int] = []
    reasons: dict[int, str] = {}
    chain: dict[int, tuple[list[int], int]] = {}  # key -> (its agent's keys in time, index)
    stamp: dict[int, float] = {}
    if config.max_interval_s is not None:  # (built only for the interval test)
        stamp = {k: atlas.keyframe(k).timestamp for k in keys}
        for agent in atlas.agents_in_map(map_id):
            ak = sorted(atlas.keyframe_keys(map_id=map_id, agent_id=agent), key=stamp.__getitem__)
            chain.update((k, (ak, i)) for i, k in enumerate(ak))

    def keeps_interval(k: int) -> bool:
        """Its agent's kept keyframes around it stay within ``max_interval_s``."""
        if config.max_interval_s is None:
            return True
        ak, i = chain[k]
        before = next((ak[j] for j in range(i - 1, -1, -1) if ak[j] in kept), None)
        after = next((ak[j] for j in range(i + 1, len(ak)) if ak[j] in kept), None)
        if before is None or after is None:
            return True
        return stamp[after] - stamp[before] <= config.max_interval_s

    def covered(r: int, without: int) -> bool:
        # r is removed (or about to be); ``without`` is about to be removed too.
        if not any(b in kept and b != without for b in strong[r]):
            return False
        return cov.fraction(r, kept=False) >= config.cover_ratio

    def keeps_connected(k: int) -> bool:
        nbrs = [b for b in strong[k] if b in kept]
        if len(nbrs) <= 1:
            return True
        todo, seen, queue = set(nbrs[1:]), {nbrs[0]}, deque([nbrs[0]])
        while queue and todo:
            for b in strong[queue.popleft()]:
                if b in kept and b != k and b not in seen:
                    seen.add(b)
                    todo.discard(b)
                    queue.append(b)
        return not todo

    def why_kept(k: int) -> str | None:
        """None if ``k`` can go now, else the reason it stays."""
        if k in protected:
            return PROTECTED
        if not any(b in kept and b != k for b in strong[k]):
            return NOT_COVERED
        if cov.fraction(k, kept=True) < config.cover_ratio:
            return NOT_COVERED
        if not keeps_connected(k):
            return CONNECTOR
        if not keeps_interval(k):
            return INERTIAL
        cov.count[cov.points[k]] -= 1  # tentatively remove k
        ok = all(covered(r, k) for r in removed if k in w_of[r])
        cov.count[cov.points[k]] += 1
        return None if ok else COVERS_REMOVED

    changed = True
    while changed:
        changed = False
        order = sorted(kept - protected, key=lambda k: (-cov.fraction(k, kept=True), k))
        for k in order:
            why = why_kept(k)
            if why is not None:
                reasons[k] = why
                continue
            kept.discard(k)
            reasons.pop(k, None)
            cov.count[cov.points[k]] -= 1
            removed.append(k)
            changed = True
    for k in kept:
        reasons[k] = PROTECTED if k in protected else reasons.get(k, NOT_COVERED)
    absorbers = {
        r: tuple(
            b
            for b, _ in sorted(w_of[r].items(), key=lambda t: (-t[1], t[0]))
            if b in kept and w_of[r][b] >= config.min_shared
        )
        for r in removed
    }
    return Backbone(frozenset(kept), {k: reasons[k] for k in sorted(kept)}, absorbers)


def select_backbone(atlas: Atlas, map_id: int, config: MbpConfig, keep_recent: int = 5) -> set[int]:
    """Keyframe keys MBP keeps for ``map_id`` (see :func:`backbone`)."""
    return set(backbone(atlas, map_id, config, keep_recent).kept)


def kept_neighbours(atlas: Atlas, map_id: int, kept: frozenset[int]) -> dict[int, list[int]]:
    """For each removed keyframe of ``map_id``, the kept keyframes of the same agent just
    before and just after it in the agent's sequence (one of them at its ends)."""
    out = {}
    for agent in atlas.agents_in_map(map_id):
        ak = atlas.keyframe_keys(map_id=map_id, agent_id=agent)
        pos = [i for i, k in enumerate(ak) if k in kept]
        for i, r in enumerate(ak):
            if r in kept or not pos:
                continue
            j = bisect.bisect_left(pos, i)
            out[r] = [ak[pos[x]] for x in (j - 1, j) if 0 <= x < len(pos)]
    return out


def loop_anchors(
    atlas: Atlas,
    map_id: int,
    kept: frozenset[int],
    neighbours: dict[int, list[int]] | None = None,
) -> dict[int, int]:
    """For each removed keyframe of ``map_id``, the kept keyframe of the same agent its loop
    constraints move to: the kept one just before or just after it in the agent's sequence
    (``neighbours``, default :func:`kept_neighbours`), whichever shares more map points with
    it (then the earlier). The same agent, so that an inter-agent constraint stays between the
    two agents and composes only with a short stretch of the agent's own odometry."""
    if neighbours is None:
        neighbours = kept_neighbours(atlas, map_id, kept)
    out = {}
    for r, near in neighbours.items():
        w = dict(atlas.covisible(r))
        out[r] = max(near, key=lambda k: (w.get(k, 0), -k))
    return out


def _move_loops(atlas: Atlas, anchor: dict[int, int]) -> int:
    """Re-anchor loop / merge constraints of removed keyframes (step 3); returns how many
    moved. A constraint whose ends meet in one keyframe, or that would join two keyframes
    already joined by one, is dropped (copies would weigh one relation several times)."""
    loops = atlas.loops()
    pairs = {
        frozenset((e.key_a, e.key_b))
        for e in loops
        if e.key_a not in anchor and e.key_b not in anchor
    }
    moved = 0
    for e in loops:
        a, b = anchor.get(e.key_a, e.key_a), anchor.get(e.key_b, e.key_b)
        if (a, b) == (e.key_a, e.key_b) or a == b or frozenset((a, b)) in pairs:
            continue
        pairs.add(frozenset((a, b)))
        T_a_ra = inverse_T(atlas.T_map_body(a)) @ atlas.T_map_body(e.key_a)
        T_rb_b = inverse_T(atlas.T_map_body(e.key_b)) @ atlas.T_map_body(b)
        atlas.add_loop(a, b, T_a_ra @ np.asarray(e.T_a_b) @ T_rb_b)
        moved += 1
    return moved


def _fold(
    atlas: Atlas,
    removed: int,
    absorbers: list[int],
    kept: frozenset[int],
    camera_of: CameraOf,
    cfg: MbpConfig,
) -> int:
    """Fold the good observations of ``removed`` as virtual observations into ``absorbers``
    (kept keyframes, strongest first) where the point projects inside their image: into the
    first every one it does not see yet, into the others those of points that still have
    fewer than ``min_observations`` kept observers (so that they survive the cull)."""
    R = atlas.keyframe(removed)
    idx = np.flatnonzero((R.map_point_keys >= 0) & ~R.virtual)
    if idx.size == 0 or not absorbers:
        return 0
    mkeys = R.map_point_keys[idx]
    P = atlas.map_point_positions(mkeys)

    def project(
        camera: CameraCalibration, T_map_body: np.ndarray, p_map: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (M, 2) and depths (M,) of map points (M, 3) in a keyframe of ``camera``."""
        p_cam = transform_points(inverse_T(T_map_body @ np.asarray(camera.T_body_cam)), p_map)
        z = p_cam[:, 2]
        uv = np.full((len(p_cam), 2), np.nan)
        front = z > 0
        if front.any():
            uv[front] = camera_model(camera).project(p_cam[front])
        return uv, z

    uv_r, z_r = project(camera_of(R.agent_id), np.asarray(R.T_map_body), P)
    err = np.linalg.norm(uv_r - R.keypoints[idx], axis=1)
    with np.errstate(invalid="ignore"):
        good = (z_r > 0) & (err <= cfg.max_virtual_reprojection_px)
    idx, mkeys, P = idx[good], mkeys[good], P[good]
    n_kept = np.array(
        [sum(1 for k in atlas.map_point_observations(m) if k in kept) for m in mkeys.tolist()],
        np.int64,
    )
    total = 0
    for i, a in enumerate(absorbers):
        A = atlas.keyframe(a)
        want = ~np.isin(mkeys, A.map_point_keys)
        if i > 0:
            want &= n_kept < cfg.min_observations
        sel = np.flatnonzero(want)
        if sel.size == 0:
            continue
        cam_a = camera_of(A.agent_id)
        uv_a, z_a = project(cam_a, np.asarray(A.T_map_body), P[sel])
        with np.errstate(invalid="ignore"):
            inside = (z_a > 0.1) & (uv_a[:, 0] >= 0) & (uv_a[:, 0] < cam_a.width)
            inside &= (uv_a[:, 1] >= 0) & (uv_a[:, 1] < cam_a.height)
        sel, src = sel[inside], idx[sel[inside]]
        total += atlas.add_virtual_observations(
            a, uv_a[inside], R.levels[src], R.descriptors[src], R.word_ids[src], mkeys[sel]
        )
        n_kept[sel] += 1
    return total


def run_mbp(
    atlas: Atlas,
    map_id: int,
    camera: CameraCalibration | CameraOf,
    config: MbpConfig,
    keep_recent: int = 5,
    hold: frozenset[int] = frozenset(),
) -> MbpReport:
    """One MBP pass over ``map_id``: keep the backbone, move loops, fold, remove the rest and
    cull points. ``camera``: each agent's camera (or one for all); ``hold``: agents whose
    keyframes all stay (a prior map). The caller also removes ``report.removed_keyframes``
    from its place-recognition database."""
    camera_of = camera_lookup(camera)
    keys = atlas.keyframe_keys(map_id=map_id)
    n_kf, n_mp = len(keys), atlas.n_map_points(map_id)
    connected_before = covisibility_components(atlas, keys) == 1
    if not config.enabled or n_kf < 3:
        return MbpReport(map_id, n_kf, n_kf, n_mp, n_mp, 0, (), connected_before, connected_before)
    bb = backbone(atlas, map_id, config, keep_recent, hold)
    removed = [k for k in keys if k not in bb.kept]
    near = kept_neighbours(atlas, map_id, bb.kept)
    anchors = loop_anchors(atlas, map_id, bb.kept, near)
    n_loops = _move_loops(atlas, anchors)
    n_virtual = 0
    for r in removed:
        n_virtual += _fold(atlas, r, list(bb.absorbers[r]), bb.kept, camera_of, config)
    for r in removed:  # drops its (already re-anchored) loop edges
        if r in anchors:
            other = next((k for k in near[r] if k != anchors[r]), None)
            atlas.retire_keyframe(r, anchors[r], other if config.blend_retired else None)
        else:
            atlas.remove_keyframe(r)
    for mk in atlas.map_point_keys(map_id):
        if len(atlas.map_point_observations(mk)) < config.min_observations:
            atlas.remove_map_point(mk)
    after = atlas.keyframe_keys(map_id=map_id)
    report = MbpReport(
        map_id=map_id,
        keyframes_before=n_kf,
        keyframes_after=len(after),
        map_points_before=n_mp,
        map_points_after=atlas.n_map_points(map_id),
        virtual_observations=n_virtual,
        removed_keyframes=tuple(removed),
        connected_before=connected_before,
        connected_after=covisibility_components(atlas, after) == 1,
        loops_moved=n_loops,
    )
    log.info(
        "MBP map %d: keyframes %d -> %d, map points %d -> %d, %d loop edges moved",
        map_id,
        n_kf,
        report.keyframes_after,
        n_mp,
        report.map_points_after,
        n_loops,
    )
    return report
