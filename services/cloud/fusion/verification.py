"""Geometric verification of a place-recognition candidate (strict: no false merge).

1. Word-guided matching (DBoW2 direct index / ORB-SLAM ``SearchByBoW``): a query keypoint is
   matched only to candidate keypoints with a map point that share its word (or its vocabulary
   ancestor at a chosen level), Hamming ≤ ``max_hamming``, best/second ratio test, one-to-one.
2. Robust 3D–2D pose: the candidate's map points against the query's distorted keypoints with
   pycolmap's LO-RANSAC P3P + non-linear refinement on the OPENCV camera model.
3. Guided expansion (ORB-SLAM ``SearchByProjection``): the map points of the candidate's
   covisible keyframes are projected with that pose, matched within a radius, and the pose is
   re-estimated on all matches; the final inlier count must reach ``min_inliers``.
4. Sanity checks: the map-to-map rotation of gravity-aligned maps must be (almost) a yaw, and
   where the query keypoints have their own map points, the inlier pairs must agree in 3D.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from common.calibration import CameraCalibration
from common.errors import RecslamError
from common.geometry import (
    DegenerateAlignmentError,
    inverse_T,
    make_T,
    refit_inliers,
    similarity_scale,
    transform_points,
    yaw_alignment,
)
from services.cloud.atlas.atlas import Atlas
from services.cloud.atlas.map_types import KeyframeView
from services.cloud.config import VerificationConfig

log = logging.getLogger(__name__)


class VerificationError(RecslamError):
    """Bad inputs to geometric verification (not a rejected candidate, which is a result)."""


@dataclass(frozen=True, eq=False)
class VerificationResult:
    """Outcome of verifying ``candidate_key`` for ``query_key``.

    accepted: the match passed every test; reason: why not (or "ok").
    T_cmap_qmap (4, 4): query map frame -> candidate map frame (6-DoF, from the pose).
    T_cbody_qbody (4, 4): relative pose of the query body in the candidate body frame.
    n_inliers / inlier_ratio: of the final pose; point_pairs (K, 2) int64 rows
    (query map point key, candidate-side map point key) of inlier 3D–3D pairs;
    matches (M, 2): inlier (query keypoint index, candidate-side map point key).
    """

    query_key: int
    candidate_key: int
    accepted: bool
    reason: str
    T_cmap_qmap: np.ndarray
    T_cbody_qbody: np.ndarray
    n_inliers: int
    inlier_ratio: float
    point_pairs: np.ndarray
    matches: np.ndarray


COLMAP_MODELS: dict[str, str] = {"radtan": "OPENCV", "equidistant": "OPENCV_FISHEYE"}
"""pycolmap camera model of each :data:`common.calibration.CAMERA_MODELS` entry: both take
``(fx, fy, cx, cy)`` then the four coefficients in our order (``OPENCV``: k1, k2, p1, p2 as
``cv2``; ``OPENCV_FISHEYE``: k1..k4 as ``cv2.fisheye``), so verification keeps its pixel
thresholds for every camera."""


def colmap_camera(cam: CameraCalibration) -> pycolmap.Camera:
    """pycolmap camera (:data:`COLMAP_MODELS`) of a calibration."""
    model = COLMAP_MODELS.get(cam.model)
    if model is None:
        raise VerificationError(f"no pycolmap camera model for {cam.model!r}")
    return pycolmap.Camera(
        model=model,
        width=cam.width,
        height=cam.height,
        params=[cam.fx, cam.fy, cam.cx, cam.cy, *cam.distortion],
    )


def pair_hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances ``(N,) int32`` of row pairs ``a[i]``, ``b[i]`` (``(N, 32) uint8``)."""
    a64 = np.ascontiguousarray(a, dtype=np.uint8).view(np.uint64)
    b64 = np.ascontiguousarray(b, dtype=np.uint8).view(np.uint64)
    return np.bitwise_count(a64 ^ b64).sum(axis=1, dtype=np.int32)


def _first_per(group: np.ndarray, *keys: np.ndarray) -> np.ndarray:
    """Indices of the first element of each ``group`` value when sorted by ``keys`` (most
    significant first), ties broken by position: one index per group, groups ascending."""
    order = np.lexsort((np.arange(group.size), *keys[::-1], group))
    g = group[order]
    first = np.ones(g.size, bool)
    first[1:] = g[1:] != g[:-1]
    return order[first]


def match_by_words(
    desc_a: np.ndarray,
    group_a: np.ndarray,
    desc_b: np.ndarray,
    group_b: np.ndarray,
    max_hamming: int,
    ratio: float,
) -> np.ndarray:
    """One-to-one matches ``(K, 2)`` (index in a, index in b) between descriptors sharing a
    group id (word or vocabulary node), with distance ≤ ``max_hamming`` and the ratio test
    against the second-best candidate of the same group (none: passes); of equal distances
    the lower index in b is the best. Only same-group pairs are compared (a direct index,
    as DBoW2's): the cost grows with the pairs, not with ``len(a) * len(b)``."""
    empty = np.zeros((0, 2), np.int64)
    if desc_a.shape[0] == 0 or desc_b.shape[0] == 0:
        return empty
    ga, gb = np.asarray(group_a, np.int64), np.asarray(group_b, np.int64)
    order_b = np.argsort(gb, kind="stable")
    sorted_b = gb[order_b]
    lo = np.searchsorted(sorted_b, ga, "left")
    n = np.searchsorted(sorted_b, ga, "right") - lo  # candidates of each a
    if not n.any():
        return empty
    # every same-group pair (i, j), grouped by i
    pa = np.repeat(np.arange(ga.size), n)
    starts = np.repeat(lo - (np.cumsum(n) - n), n)
    pb = order_b[starts + np.arange(pa.size)]
    d = pair_hamming(desc_a[pa], desc_b[pb])
    best = _first_per(pa, d, pb)  # one pair per a that has any, a ascending
    a_has = pa[best]
    d1 = d[best]
    d2 = np.full(a_has.size, np.iinfo(np.int32).max, np.int64)
    rest = np.ones(pa.size, bool)
    rest[best] = False
    if rest.any():
        second = _first_per(pa[rest], d[rest])
        d2[np.searchsorted(a_has, pa[rest][second])] = d[rest][second]
    ok = (d1 <= max_hamming) & ((n[a_has] < 2) | (d1 < ratio * d2))
    a_idx = a_has[ok]
    b_idx = pb[best][ok]
    d_ok = d1[ok]
    # One-to-one: for each b keep the a with the smallest distance (then the lowest a).
    keep = _first_per(b_idx, d_ok)
    return np.stack([a_idx[keep], b_idx[keep]], axis=1).astype(np.int64)


def _pose(
    uv: np.ndarray, p: np.ndarray, camera: pycolmap.Camera, cfg: VerificationConfig
) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.max_error = cfg.reprojection_px
    opts.ransac.random_seed = cfg.seed
    opts.ransac.min_inlier_ratio = 0.05
    res = pycolmap.estimate_and_refine_absolute_pose(uv, p, camera, opts)
    if res is None:
        return None, None
    T = np.eye(4)
    T[:3, :] = res["cam_from_world"].matrix()
    return T, np.asarray(res["inlier_mask"], bool)


def _reject(q: int, c: int, reason: str, n: int = 0, ratio: float = 0.0) -> VerificationResult:
    log.debug("candidate %d for %d rejected: %s", c, q, reason)
    eye = np.eye(4)
    empty = np.zeros((0, 2), np.int64)
    return VerificationResult(q, c, False, reason, eye, eye, n, ratio, empty, empty)


def verify_candidate(
    atlas: Atlas,
    query_key: int,
    candidate_key: int,
    camera: CameraCalibration,
    config: VerificationConfig,
    word_group: np.ndarray | None = None,
    early: bool = False,
    max_scale_change: float = 0.0,
) -> VerificationResult:
    """Verify ``candidate_key`` for ``query_key``; ``camera`` is the query keyframe's (its
    robot's: the query's keypoints are located against the candidate's map points).
    ``word_group (S,)`` optionally maps each
    word to the id of the vocabulary node whose members may match (e.g.
    ``Vocabulary.ancestor_at_level(np.arange(S), level)``); None = same word only.
    ``early``: the candidate was not yet consistent over consecutive queries; a match is then
    accepted only when :func:`covisible_agreement` confirms it. ``max_scale_change``: the two
    maps may differ in scale by this fraction (one of them a map fragment,
    ``MergeConfig.fragment_max_scale_change``): when the point pairs do not agree through the
    pose, they may agree after a yaw + translation + scale alignment within it (0: rigid
    only)."""
    cfg = config
    Q = atlas.keyframe(query_key)
    C = atlas.keyframe(candidate_key)
    col_cam = colmap_camera(camera)
    qi = np.flatnonzero(~Q.virtual)
    ci = np.flatnonzero(C.map_point_keys >= 0)

    def grp(words: np.ndarray) -> np.ndarray:
        return words if word_group is None else np.asarray(word_group)[words]

    m = match_by_words(
        Q.descriptors[qi],
        grp(Q.word_ids[qi]),
        C.descriptors[ci],
        grp(C.word_ids[ci]),
        cfg.max_hamming,
        cfg.ratio,
    )
    n_put = m.shape[0]
    if n_put < cfg.min_initial_matches:
        return _reject(query_key, candidate_key, f"{n_put} word matches", n_put)
    q_idx = qi[m[:, 0]]
    mp_keys = C.map_point_keys[ci[m[:, 1]]]
    T_cam_cmap, inl = _pose(Q.keypoints[q_idx], atlas.map_point_positions(mp_keys), col_cam, cfg)
    if T_cam_cmap is None or inl is None:  # both or neither
        return _reject(query_key, candidate_key, "no 3D-2D pose")
    ratio = float(inl.sum()) / n_put
    if ratio < cfg.min_inlier_ratio or inl.sum() < cfg.min_initial_matches:
        return _reject(
            query_key, candidate_key, f"initial inliers {inl.sum()}/{n_put}", int(inl.sum()), ratio
        )

    # Guided expansion with the map points of the candidate's covisible group.
    group = CandidateGroup(atlas, candidate_key, cfg)
    q_idx, rows = project_and_match(group, Q, qi, T_cam_cmap, col_cam, camera, cfg)
    if rows.size < cfg.min_inliers:
        return _reject(query_key, candidate_key, f"{rows.size} projected matches", int(rows.size))
    T_cam_cmap, inl = _pose(Q.keypoints[q_idx], group.P[rows], col_cam, cfg)
    if T_cam_cmap is None or inl is None:  # both or neither
        return _reject(query_key, candidate_key, "no refined pose")
    n_inl = int(inl.sum())
    ratio = n_inl / len(q_idx)
    if n_inl < cfg.min_inliers or ratio < cfg.min_inlier_ratio:
        return _reject(
            query_key, candidate_key, f"final inliers {n_inl}/{len(q_idx)}", n_inl, ratio
        )

    T_cmap_qbody = inverse_T(T_cam_cmap) @ inverse_T(np.asarray(camera.T_body_cam))
    T_cmap_qmap = T_cmap_qbody @ inverse_T(Q.T_map_body)
    T_cbody_qbody = inverse_T(C.T_map_body) @ T_cmap_qbody
    if cfg.max_tilt_deg is not None:
        z = T_cmap_qmap[:3, :3] @ np.array([0.0, 0.0, 1.0])
        tilt = float(np.degrees(np.arccos(np.clip(z[2], -1.0, 1.0))))
        if tilt > cfg.max_tilt_deg:
            return _reject(query_key, candidate_key, f"tilt {tilt:.1f} deg", n_inl, ratio)
    inl_q = q_idx[inl]
    inl_keys = group.keys[rows[inl]]
    q_mp = Q.map_point_keys[inl_q]
    has = q_mp >= 0
    point_pairs = np.stack([q_mp[has], inl_keys[has]], axis=1).astype(np.int64)
    if has.sum() >= 5:
        p_q = transform_points(T_cmap_qmap, atlas.map_point_positions(point_pairs[:, 0]))
        dist = np.linalg.norm(p_q - atlas.map_point_positions(point_pairs[:, 1]), axis=1)
        agree = dist < cfg.agreement_distance_m
        if agree.mean() < cfg.min_3d3d_agreement and max_scale_change > 0:
            agree = _scaled_agreement(atlas, point_pairs, cfg, max_scale_change, agree)
        if agree.mean() < cfg.min_3d3d_agreement:
            return _reject(
                query_key, candidate_key, f"3D agreement {agree.mean():.2f}", n_inl, ratio
            )
        point_pairs = point_pairs[agree]
    result = VerificationResult(
        query_key,
        candidate_key,
        True,
        "ok",
        T_cmap_qmap,
        T_cbody_qbody,
        n_inl,
        ratio,
        point_pairs,
        np.stack([inl_q, inl_keys], axis=1).astype(np.int64),
    )
    if early:
        agree, checked = covisible_agreement(atlas, result, camera, cfg, group)
        if agree < cfg.covisible_agree:
            reason = f"covisible agreement {agree}/{checked}"
            return _reject(query_key, candidate_key, reason, n_inl, ratio)
    return result


def _scaled_agreement(
    atlas: Atlas,
    point_pairs: np.ndarray,
    cfg: VerificationConfig,
    max_scale_change: float,
    rigid: np.ndarray,
) -> np.ndarray:
    """Agreement (K,) bool of the pairs (query map point, candidate-side point) after a
    yaw + translation + scale alignment of the query's points onto the candidate's (closed
    form, again on the pairs within ``max(3 × median, agreement distance / 2)`` of the first
    fit); ``rigid`` (the agreement through the pose) when the fitted scale is off by more
    than ``max_scale_change`` or the pairs are degenerate."""
    p_q = atlas.map_point_positions(point_pairs[:, 0])
    p_c = atlas.map_point_positions(point_pairs[:, 1])

    def fit(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        R, t, scale = yaw_alignment(a, b, with_scale=True)
        return make_T(scale * R, t)

    try:
        T, _ = refit_inliers(fit, p_q, p_c, cfg.agreement_distance_m / 2)
    except DegenerateAlignmentError:
        return rigid
    s = similarity_scale(T)
    if abs(s - 1.0) > max_scale_change:
        return rigid
    agree = np.linalg.norm(transform_points(T, p_q) - p_c, axis=1) < cfg.agreement_distance_m
    log.debug(
        "3D agreement %.2f through the pose, %.2f at scale %.3f", rigid.mean(), agree.mean(), s
    )
    return agree


class CandidateGroup:
    """The map points the guided search projects: those of candidate keyframe ``key`` and of
    its ``covisible_expansion`` best covisible keyframes. ``keys (K,) int64`` ascending and
    their positions ``P (K, 3)`` in the candidate's map frame are gathered on first use;
    descriptors (each the median of a point's observations: costly) once per point and only
    for the rows asked for. One group serves verification and the covisibility check."""

    def __init__(self, atlas: Atlas, key: int, config: VerificationConfig) -> None:
        self.atlas = atlas
        self.key = key
        self.config = config

    @functools.cached_property
    def keys(self) -> np.ndarray:
        members = [self.key, *self.atlas.best_covisible(self.key, self.config.covisible_expansion)]
        keys: set[int] = set()
        for g in members:
            mk = self.atlas.keyframe(g).map_point_keys
            keys.update(mk[mk >= 0].tolist())
        return np.array(sorted(keys), np.int64)

    @functools.cached_property
    def P(self) -> np.ndarray:
        return self.atlas.map_point_positions(self.keys)

    @functools.cached_property
    def _desc(self) -> tuple[np.ndarray, np.ndarray]:
        n = self.keys.shape[0]
        return np.zeros((n, 32), np.uint8), np.zeros(n, bool)

    def descriptors(self, rows: np.ndarray) -> np.ndarray:
        """Descriptors ``(n, 32) uint8`` of ``rows`` (indices into :attr:`keys`)."""
        desc, have = self._desc
        missing = np.unique(rows[~have[rows]])
        if missing.size:
            desc[missing] = self.atlas.map_point_descriptors(self.keys[missing])
            have[missing] = True
        return desc[rows]


def project_and_match(
    group: CandidateGroup,
    Q: KeyframeView,
    qi: np.ndarray,
    T_cam_cmap: np.ndarray,
    col_cam: pycolmap.Camera,
    camera: CameraCalibration,
    cfg: VerificationConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """ORB-SLAM's ``SearchByProjection``: the points of ``group`` (in the candidate's map
    frame) projected into keyframe ``Q`` with ``T_cam_cmap (4, 4)`` and matched
    to its keypoints ``qi`` within ``projection_radius_px`` and ``max_hamming``, one-to-one.
    Returns ``(q_idx, rows)``: keypoint indices of ``Q`` (ascending, as ``qi``) and the
    matched rows of ``group.P``."""
    p_cam = transform_points(T_cam_cmap, group.P)
    front = np.flatnonzero(p_cam[:, 2] > 0.1)
    uv = col_cam.img_from_cam(p_cam[front])
    inside = (
        (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    )
    front, uv = front[inside], uv[inside]
    empty = np.zeros(0, np.int64)
    if front.size == 0 or qi.size == 0:
        return empty, empty
    # every (projected point, query keypoint) pair within the radius, by point then keypoint
    near = cKDTree(uv).sparse_distance_matrix(
        cKDTree(Q.keypoints[qi]), cfg.projection_radius_px, output_type="ndarray"
    )
    order = np.lexsort((near["j"], near["i"]))
    pr = near["i"][order].astype(np.int64)
    pq = near["j"][order].astype(np.int64)
    d = pair_hamming(group.descriptors(front[pr]), Q.descriptors[qi[pq]])
    # each projected point's nearest query descriptor (first in the ball's order on ties) ...
    best = _first_per(pr, d)
    best = best[d[best] <= cfg.max_hamming]
    # ... and each query keypoint's nearest such point (the lowest row on ties)
    won = best[_first_per(pq[best], d[best])]
    return qi[pq[won]], front[pr[won]]


def covisible_agreement(
    atlas: Atlas,
    result: VerificationResult,
    camera: CameraCalibration,
    config: VerificationConfig,
    group: CandidateGroup | None = None,
) -> tuple[int, int]:
    """ORB-SLAM3's covisibility consistency of an accepted ``result``: the candidate group's
    map points are projected, through the verified ``T_cmap_qmap``, into each of the query's
    ``covisible_checks`` best covisible keyframes at its own pose (no new estimate). A
    keyframe agrees when ``covisible_min_matches`` of its keypoints match a projected point
    within ``reprojection_px``. The check stops once ``covisible_agree`` keyframes agree or
    too few are left to. Returns ``(agreeing, checked)``; ``camera`` is the query agent's (its
    covisible keyframes are the same robot's)."""
    cfg = config
    if group is None:
        group = CandidateGroup(atlas, result.candidate_key, cfg)
    col_cam = colmap_camera(camera)
    T_qmap_cmap = inverse_T(result.T_cmap_qmap)
    T_cam_body = inverse_T(np.asarray(camera.T_body_cam))
    neighbours = atlas.best_covisible(result.query_key, cfg.covisible_checks)
    agreeing = checked = 0
    for k in neighbours:
        if agreeing >= cfg.covisible_agree or agreeing + len(neighbours) - checked < (
            cfg.covisible_agree
        ):
            break
        checked += 1
        K = atlas.keyframe(k)
        T_cam_cmap = T_cam_body @ inverse_T(K.T_map_body) @ T_qmap_cmap
        qi = np.flatnonzero(~K.virtual)
        q_idx, rows = project_and_match(group, K, qi, T_cam_cmap, col_cam, camera, cfg)
        if rows.size < cfg.covisible_min_matches:
            continue
        uv = col_cam.img_from_cam(transform_points(T_cam_cmap, group.P[rows]))
        err = np.linalg.norm(uv - K.keypoints[q_idx], axis=1)
        if int((err <= cfg.reprojection_px).sum()) >= cfg.covisible_min_matches:
            agreeing += 1
    return agreeing, checked
