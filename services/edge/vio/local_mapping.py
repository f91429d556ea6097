"""Keyframe processing (local mapping): associate a new keyframe with the map points of its
tracks, triangulate new points for tracks seen in several keyframes with enough parallax, and
cull points that fail their checks."""

from __future__ import annotations

import logging

import numpy as np

from common.geometry import inverse_T
from services.edge.vio.state import Keyframe, MapPoint, PinholeUndistorter, VioMap, project
from services.edge.vio.types import MappingConfig

logger = logging.getLogger(__name__)


def associate_keyframe(
    vmap: VioMap, kf: Keyframe, camera: PinholeUndistorter, options: MappingConfig
) -> int:
    """Add ``kf``'s observation to the map point of each of its tracks that reprojects well.
    Returns the number of observations added."""
    ids = []
    for t in kf.row_of:
        mp = vmap.point_of(t)
        if mp is not None:
            ids.append(mp.id)
    if not ids:
        return 0
    P = np.array([vmap.points[p].p_world for p in ids])
    rows = np.array([kf.row_of[t] for t in kf.row_of if vmap.point_of(t) is not None])
    xy, z = project(kf.T_world_body, camera.T_body_cam, P)
    chi2 = np.sum((xy - kf.xy[rows]) ** 2, 1) / kf.sigma[rows] ** 2
    good = (z > 0) & (chi2 < options.cull_chi2)
    n = 0
    for t, r, g in zip(ids, rows.tolist(), good.tolist(), strict=True):
        if g:
            vmap.points[t].observations[kf.id] = r
            n += 1
    vmap.mark_dirty(point_ids=[t for t, g in zip(ids, good.tolist(), strict=True) if g])
    return n


def match_by_projection(
    vmap: VioMap, kf: Keyframe, camera: PinholeUndistorter, options: MappingConfig
) -> int:
    """Bind ``kf``'s features that have no map point (new robot tracks) to existing map points
    that project near them with a close ORB descriptor (ORB-SLAM's search by projection):
    re-detections of known structure then reuse the map instead of duplicating it. Only the
    local map (points of the newest ``match_keyframes`` keyframes) is searched: older, drifted
    structure is the cloud's loop closure to fix, not the local BA's.
    Returns the number of features bound."""
    if kf.descriptors is None:
        return 0
    free = [
        (t, r)
        for t, r in kf.row_of.items()
        if t not in vmap.track_point and t not in vmap.banned_tracks
    ]
    seen = {mp.id for t in kf.row_of if (mp := vmap.point_of(t)) is not None}
    rows = np.array([r for _, r in free], dtype=np.int64)
    found = search_by_projection(
        vmap,
        kf.T_world_body,
        kf.xy[rows],
        kf.levels[rows],
        kf.descriptors[rows],
        seen,
        camera,
        options,
    )
    for i, point_id in found:
        track, row = free[i]
        vmap.bind_track(track, point_id)
        vmap.points[point_id].observations[kf.id] = row
    return len(found)


def search_by_projection(
    vmap: VioMap,
    T_world_body: np.ndarray,
    xy: np.ndarray,
    levels: np.ndarray,
    descriptors: np.ndarray,
    exclude: set[int],
    camera: PinholeUndistorter,
    options: MappingConfig,
    radius_scale: float = 1.0,
) -> list[tuple[int, int]]:
    """Features (normalised ``xy`` (N, 2), pyramid ``levels`` (N,), ORB ``descriptors``
    (N, 32)) seen from ``T_world_body`` matched to the local map's points (those of the newest
    ``match_keyframes`` keyframes, but not ``exclude``'s ids) that project within
    ``match_radius_px`` × 1.2^level × ``radius_scale`` with a descriptor within
    ``match_max_hamming`` passing the ratio test; one feature per point (the closest).
    Pure: nothing in the map changes. Returns [(feature index, point id)]."""
    if not len(xy) or not vmap.points:
        return []
    local = {
        mp.id
        for k in vmap.keyframe_list()[-options.match_keyframes - 1 :]
        for t in k.row_of
        if (mp := vmap.point_of(t)) is not None
    }
    cands = [
        vmap.points[p] for p in sorted(local - exclude) if vmap.points[p].descriptor is not None
    ]
    if not cands:
        return []
    xy_c, z = project(T_world_body, camera.T_body_cam, np.array([mp.p_world for mp in cands]))
    front = z > options.min_depth_m
    if not np.any(front):
        return []
    cands = [mp for mp, f in zip(cands, front.tolist(), strict=True) if f]
    xy_c = xy_c[front]
    desc_c = np.stack([d for mp in cands if (d := mp.descriptor) is not None])  # all have one
    radius = options.match_radius_px * radius_scale * 1.2 ** levels.astype(float) / camera.focal
    d2 = np.sum((xy[:, None, :] - xy_c[None, :, :]) ** 2, axis=2)
    best_for_point: dict[int, tuple[int, int]] = {}  # candidate index -> (hamming, feature)
    for i in range(len(xy)):
        js = np.flatnonzero(d2[i] < radius[i] ** 2)
        if len(js) == 0:
            continue
        ham = np.unpackbits(np.bitwise_xor(desc_c[js], descriptors[i]), axis=1).sum(1)
        order = np.argsort(ham)
        h0 = int(ham[order[0]])
        if h0 > options.match_max_hamming:
            continue
        if len(order) > 1 and h0 >= options.match_ratio * int(ham[order[1]]):
            continue
        j = int(js[order[0]])
        if j not in best_for_point or h0 < best_for_point[j][0]:
            best_for_point[j] = (h0, i)
    return [(i, cands[j].id) for j, (_, i) in best_for_point.items()]


def triangulate_multiview(T_cam_worlds: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation from K views: ``T_cam_worlds`` (K, 4, 4), ``xy`` (K, 2)."""
    A = np.empty((2 * len(xy), 4))
    P = T_cam_worlds[:, :3, :]
    A[0::2] = xy[:, 0:1] * P[:, 2] - P[:, 0]
    A[1::2] = xy[:, 1:2] * P[:, 2] - P[:, 1]
    _, _, Vt = np.linalg.svd(A)
    X = Vt[-1]
    if abs(X[3]) < 1e-12:
        return np.full(3, np.nan)
    return X[:3] / X[3]


def triangulate_new_points(
    vmap: VioMap,
    kf: Keyframe,
    camera: PinholeUndistorter,
    options: MappingConfig,
    search_keyframes: int = 20,
) -> int:
    """Create map points for ``kf``'s tracks without one that earlier keyframes also saw.
    Returns the number of points created."""
    recent = [k for k in vmap.keyframe_list()[-(search_keyframes + 1) :] if k.id != kf.id]
    if not recent:
        return 0
    cos_min = np.cos(np.radians(options.min_parallax_deg))
    T_cam_world = {k.id: inverse_T(k.T_world_body @ camera.T_body_cam) for k in [*recent, kf]}
    n_new = 0
    for track, row in kf.row_of.items():
        if track in vmap.track_point or track in vmap.banned_tracks:
            continue
        views = [(k, k.row_of[track]) for k in recent if track in k.row_of]
        if not views:
            continue
        views.append((kf, row))
        first, r0 = views[0]
        ray0 = T_cam_world[first.id][:3, :3].T @ np.array([*first.xy[r0], 1.0])
        ray1 = T_cam_world[kf.id][:3, :3].T @ np.array([*kf.xy[row], 1.0])
        cosp = ray0 @ ray1 / (np.linalg.norm(ray0) * np.linalg.norm(ray1))
        if cosp > cos_min:
            continue
        Ts = np.stack([T_cam_world[k.id] for k, _ in views])
        xys = np.stack([k.xy[r] for k, r in views])
        p = triangulate_multiview(Ts, xys)
        if not np.all(np.isfinite(p)):
            continue
        p_cam = np.einsum("kij,j->ki", Ts[:, :3, :3], p) + Ts[:, :3, 3]
        z = p_cam[:, 2]
        if np.any(z < options.min_depth_m):
            continue
        sig = np.array([k.sigma[r] for k, r in views])
        chi2 = np.sum((p_cam[:, :2] / z[:, None] - xys) ** 2, 1) / sig**2
        if np.any(chi2 > options.max_reprojection_chi2):
            continue
        desc = next((k.descriptors[r] for k, r in views if k.descriptors is not None), None)
        vmap.add_point(MapPoint(track, p, {k.id: r for k, r in views}, desc))
        n_new += 1
    return n_new
