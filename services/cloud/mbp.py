"""Map backbone profiling (MBP): prune redundant keyframes and map points of a map.

The paper (Section VI.B) extracts "the backbone of the map" and folds good observations of
removed keyframes into virtual keyframes. We implement the backbone as a *connected
dominating set* of the strong-covisibility graph — the classical "virtual backbone" of a
network — with the greedy algorithm of Guha & Khuller ("Approximation algorithms for connected
dominating sets", Algorithmica 20, 1998; algorithm I: grow a tree from the highest-degree node,
each step blackening the grey node that dominates the most white nodes):

1. Strong graph: keyframes a, b are adjacent when they share ≥ ``min_shared`` map points and
   ≥ ``cover_ratio`` of the smaller one's points (so a kept neighbour sees most of what a
   removed keyframe saw).
2. Backbone: a connected dominating set of every connected component of the strong graph,
   plus protected keyframes (each agent's first and latest ones, loop endpoints); components
   are joined through a maximum spanning tree of the covisibility edges between them (both
   endpoints kept). Every removed keyframe is then adjacent to a kept one, and the kept set
   stays connected in the covisibility graph.
3. Folding: each removed keyframe's good observations (reprojection error ≤
   ``max_virtual_reprojection_px``) of map points its strongest kept neighbour does not see
   become *virtual observations* of that neighbour (the point projected into it, with the
   removed keyframe's descriptor), which makes the neighbour a virtual keyframe.
4. Map points left with fewer than ``min_observations`` observations are removed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from common.calibration import CameraCalibration
from common.geometry import inverse_T, transform_points
from services.cloud.atlas import Atlas
from services.cloud.config import MbpConfig

log = logging.getLogger(__name__)


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


def _n_points(atlas: Atlas, key: int) -> int:
    return int((atlas.keyframe(key).map_point_keys >= 0).sum())


def connected_dominating_set(adj: dict[int, dict[int, float]]) -> set[int]:
    """Greedy connected dominating set (Guha & Khuller 1998, algorithm I) of each connected
    component of an undirected weighted graph ``{node: {neighbour: weight}}``."""
    white = set(adj)
    black: set[int] = set()
    while white:
        # New component: start from the white node of highest degree (then weight).
        start = max(white, key=lambda v: (len(adj[v]), sum(adj[v].values()), -v))
        black.add(start)
        white.discard(start)
        gray = {u for u in adj[start] if u in white}
        white -= gray
        while gray:
            best = max(
                gray,
                key=lambda v: (sum(1 for u in adj[v] if u in white),
                               sum(w for u, w in adj[v].items() if u in white), -v),
            )  # fmt: skip
            if not any(u in white for u in adj[best]):
                break  # component dominated
            gray.discard(best)
            black.add(best)
            new = {u for u in adj[best] if u in white}
            white -= new
            gray |= new
    return black


def _protected(atlas: Atlas, map_id: int, keep_recent: int) -> set[int]:
    keys = set()
    for agent in atlas.agents_in_map(map_id):
        ak = atlas.keyframe_keys(map_id=map_id, agent_id=agent)
        keys.update(ak[:1])
        keys.update(ak[-keep_recent:] if keep_recent > 0 else [])
    for e in atlas.loops():
        keys.update((e.key_a, e.key_b))
    return keys


def select_backbone(atlas: Atlas, map_id: int, config: MbpConfig, keep_recent: int = 5) -> set[int]:
    """Keyframe keys MBP keeps for ``map_id`` (see the module docstring)."""
    keys = atlas.keyframe_keys(map_id=map_id)
    npts = {k: _n_points(atlas, k) for k in keys}
    strong: dict[int, dict[int, float]] = {k: {} for k in keys}
    for a in keys:
        for b, w in atlas.covisible(a, config.min_shared):
            if b in strong and w >= config.cover_ratio * min(npts[a], npts[b]):
                strong[a][b] = float(w)
    kept = connected_dominating_set(strong) | _protected(atlas, map_id, keep_recent)
    # Join strong components through the best covisibility edges between them.
    index = {k: i for i, k in enumerate(keys)}
    rows = [index[a] for a in keys for b in strong[a]]
    cols = [index[b] for a in keys for b in strong[a]]
    n = len(keys)
    n_comp, label = connected_components(
        coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False
    )
    if n_comp > 1:
        best: dict[tuple[int, int], tuple[int, int, int]] = {}
        for a in keys:
            for b, w in atlas.covisible(a):
                if b not in index:
                    continue
                ca, cb = int(label[index[a]]), int(label[index[b]])
                if ca >= cb:
                    continue  # same component, or the pair seen from the other side
                if (ca, cb) not in best or w > best[(ca, cb)][0]:
                    best[(ca, cb)] = (w, a, b)
        if best:
            pairs = list(best)
            ws = [best[p][0] for p in pairs]
            # Maximum spanning tree = minimum spanning tree on (max + 1 - w).
            top = max(ws) + 1
            g = coo_matrix(
                ([top - w for w in ws], ([p[0] for p in pairs], [p[1] for p in pairs])),
                shape=(n_comp, n_comp),
            )
            tree = minimum_spanning_tree(g).tocoo()
            for ca, cb in zip(tree.row.tolist(), tree.col.tolist(), strict=True):
                _, a, b = best[(min(ca, cb), max(ca, cb))]
                kept.update((a, b))
    return kept


def _fold(
    atlas: Atlas, removed: int, absorber: int, camera: CameraCalibration, cfg: MbpConfig
) -> int:
    """Fold the good observations of ``removed`` into ``absorber`` as virtual observations."""
    R = atlas.keyframe(removed)
    A = atlas.keyframe(absorber)
    idx = np.flatnonzero((R.map_point_keys >= 0) & ~R.virtual)
    if idx.size == 0:
        return 0
    seen = set(A.map_point_keys[A.map_point_keys >= 0].tolist())
    new = np.array([i for i in idx.tolist() if int(R.map_point_keys[i]) not in seen], np.int64)
    if new.size == 0:
        return 0
    mkeys = R.map_point_keys[new]
    P = atlas.map_point_positions(mkeys)
    K, dist = camera.K, camera.dist_coeffs
    T_body_cam = np.asarray(camera.T_body_cam)

    def project(T_map_body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p_cam = transform_points(inverse_T(T_map_body @ T_body_cam), P)
        z = p_cam[:, 2]
        uv, _ = cv2.projectPoints(p_cam, np.zeros(3), np.zeros(3), K, dist)
        return uv.reshape(-1, 2), z

    uv_r, z_r = project(np.asarray(R.T_map_body))
    good = (z_r > 0) & (
        np.linalg.norm(uv_r - R.keypoints[new], axis=1) <= cfg.max_virtual_reprojection_px
    )
    uv_a, z_a = project(np.asarray(A.T_map_body))
    inside = (z_a > 0.1) & (uv_a[:, 0] >= 0) & (uv_a[:, 0] < camera.width)
    inside &= (uv_a[:, 1] >= 0) & (uv_a[:, 1] < camera.height)
    sel = good & inside
    if not sel.any():
        return 0
    src = new[sel]
    return atlas.add_virtual_observations(
        absorber, uv_a[sel], R.levels[src], R.descriptors[src], R.word_ids[src], mkeys[sel]
    )


def run_mbp(
    atlas: Atlas,
    map_id: int,
    camera: CameraCalibration,
    config: MbpConfig,
    keep_recent: int = 5,
) -> MbpReport:
    """One MBP pass over ``map_id``: keep the backbone, fold, remove the rest and cull points.

    The caller also removes ``report.removed_keyframes`` from its place-recognition database.
    """
    keys = atlas.keyframe_keys(map_id=map_id)
    n_kf, n_mp = len(keys), atlas.n_map_points(map_id)
    connected_before = covisibility_components(atlas, keys) == 1
    if not config.enabled or n_kf < 3:
        return MbpReport(map_id, n_kf, n_kf, n_mp, n_mp, 0, (), connected_before, connected_before)
    kept = select_backbone(atlas, map_id, config, keep_recent)
    removed = [k for k in keys if k not in kept]
    n_virtual = 0
    for r in removed:
        nbrs = [(w, b) for b, w in atlas.covisible(r) if b in kept]
        if nbrs:
            n_virtual += _fold(atlas, r, max(nbrs)[1], camera, config)
    for r in removed:
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
    )
    log.info("MBP map %d: keyframes %d -> %d, map points %d -> %d", map_id, n_kf,
             report.keyframes_after, n_mp, report.map_points_after)  # fmt: skip
    return report
