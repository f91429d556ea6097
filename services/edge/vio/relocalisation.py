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
    has: np.ndarray,
    seen: set[int],
    T_world_body: np.ndarray,
    camera: PinholeUndistorter,
    options: VioConfig,
) -> dict[int, int]:
    """The features of ``obs`` (normalised ``xy`` (N, 2); it has descriptors) whose track
    has no map point (``~has``, (N,) bool), matched to local map points other than ``seen``
    projected from ``T_world_body``: {row: point id}."""
    if obs.descriptors is None:
        return {}
    free = np.flatnonzero(~has)
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


def with_found(
    vmap: VioMap, P_world: np.ndarray, has: np.ndarray, found: dict[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """A frame's map points ``P_world`` (has.sum(), 3) of its rows ``has`` (N,) bool, with
    the points ``found`` for other rows added: (P_world (M, 3), has (N,)), in row order."""
    P_rows = np.full((len(has), 3), np.nan)
    P_rows[has] = P_world
    for row, point_id in found.items():
        P_rows[row] = vmap.points[point_id].p_world
    has = has.copy()
    has[list(found)] = True
    return P_rows[has], has
