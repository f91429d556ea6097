"""Keyframe processing (local mapping): associate a new keyframe with the map points of its
tracks, triangulate new points for tracks seen in several keyframes with enough parallax, and
cull points that fail their checks."""

from __future__ import annotations

import logging

import numpy as np

from common.geometry import inverse_T
from services.edge.vio.state import Keyframe, MapPoint, PinholeUndistorter, VioMap, project
from services.edge.vio.types import MappingOptions

logger = logging.getLogger(__name__)


def associate_keyframe(
    vmap: VioMap, kf: Keyframe, camera: PinholeUndistorter, options: MappingOptions
) -> int:
    """Add ``kf``'s observation to the map point of each of its tracks that reprojects well.
    Returns the number of observations added."""
    ids = [t for t in kf.row_of if t in vmap.points]
    if not ids:
        return 0
    P = np.array([vmap.points[t].p_world for t in ids])
    rows = np.array([kf.row_of[t] for t in ids])
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
    options: MappingOptions,
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
        if track in vmap.points or track in vmap.banned_tracks:
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
        vmap.add_point(MapPoint(track, p, {k.id: r for k, r in views}))
        n_new += 1
    return n_new
