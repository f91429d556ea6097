"""Relocalisation in the local map (ORB-SLAM3's RECENTLY_LOST, by projection).

A VI-initialised map whose tracking fails (after a gap in the frames: an uplink budget that
leaves most frames out, a cut link) is kept for ``TrackingConfig.recently_lost_s`` while the
IMU predicts the pose. A robot keyframe meanwhile carries ORB descriptors: its features
without a map point are searched among the local map's points projected from the predicted
pose (a window ``relocalise_radius_scale`` times the mapping's), and the frame is tracked on
its tracks' points and those found. Pure functions: the map is not changed (the keyframe's
insertion then binds what it matches with the tracked pose).
"""

from __future__ import annotations

import numpy as np

from services.edge.vio.local_mapping import search_by_projection
from services.edge.vio.state import PinholeUndistorter, VioMap
from services.edge.vio.types import FrameObservation, VioConfig


def search_local_map(
    vmap: VioMap,
    obs: FrameObservation,
    xy: np.ndarray,
    seen: set[int],
    T_world_body: np.ndarray,
    camera: PinholeUndistorter,
    options: VioConfig,
) -> dict[int, int]:
    """The features of ``obs`` (normalised ``xy`` (N, 2); it has descriptors) whose track
    has no map point, matched to local map points other than ``seen`` projected from
    ``T_world_body``: {row: point id}."""
    if obs.descriptors is None:
        return {}
    free = np.flatnonzero([vmap.point_of(t) is None for t in obs.track_ids.tolist()])
    found = search_by_projection(
        vmap,
        T_world_body,
        xy[free],
        obs.levels[free],
        obs.descriptors[free],
        seen,
        camera,
        options.mapping,
        options.tracking.relocalise_radius_scale,
    )
    return {int(free[i]): point_id for i, point_id in found}


def map_points_of(
    vmap: VioMap, track_ids: np.ndarray, found: dict[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """(P_world (M, 3), has (N,) bool): the map point of each of a frame's ``track_ids``
    (N,), that of its track or the one ``found`` for its row."""
    has = np.zeros(len(track_ids), dtype=bool)
    rows = []
    for r, t in enumerate(track_ids.tolist()):
        mp = vmap.point_of(t)
        p_world = mp.p_world if mp is not None else None
        if p_world is None and r in found:
            p_world = vmap.points[found[r]].p_world
        if p_world is not None:
            has[r] = True
            rows.append(p_world)
    return np.array(rows).reshape(-1, 3), has
