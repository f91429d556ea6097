"""Precision and recall of the cloud's loop / merge detection against ground truth.

Inputs are what a replay observed (``lab.table3``): every keyframe that reached the cloud
(:class:`KeyframeInfo`: robot name, timestamp), every verified candidate
(:class:`Detection`: query keyframe, matched keyframe, the verified relative body pose,
accepted or not) and, for every new keyframe, the keyframes the cloud held when it was
queried (:class:`QueryEvent`). Ground truth is each robot's body trajectory in the dataset's
common world frame (the synthetic robots share one room frame) plus the camera extrinsics.

Definitions (:class:`LoopCriterion` holds the thresholds):

- **True positive**: an accepted loop / merge whose verified relative pose
  ``T_match_query`` (query body in the matched keyframe's body frame) agrees with the ground
  truth ``T_gt = inv(T_world_match) @ T_world_query``: translation error
  ``|t_est - t_gt| < max_trans_err_m`` and rotation error ``angle(R_gt^T R_est) <
  max_rot_err_deg``. The maps are metric (visual-inertial) and the relative pose comes from a
  PnP against the matched map's metric points, so no scale is estimated; a map scale error
  shows as translation error. Everything else accepted is a false positive.
- **Precision** = TP / accepted.
- **Revisit partner** of a query keyframe: a keyframe the cloud held at query time, of
  another robot or of the same robot more than ``same_robot_min_gap_s`` earlier, whose
  ground-truth camera centre is within ``revisit_dist_m`` of the query's and whose optical
  axis is within ``revisit_angle_deg``.
- **Recall** = queries with a revisit partner for which a true-positive loop / merge was
  found / queries with a revisit partner. (A TP whose partner is not a "revisit partner" by
  these thresholds still counts as found when the query has one.)
- **Linked recall** = queries with a revisit partner that were found, or that share at least
  ``linked_min_shared`` map points with one of their revisit partners in the map the run
  ended with (before the shutdown MBP pass): the two visits are joined by common points, as
  a loop that fuses its point pairs (``MergeConfig.fuse_loop_points``) joins the keyframes
  after it, which are then no loop candidates themselves.
- A **rejected** candidate (verification keeps no pose for it) is a *true place* when the
  two keyframes' ground-truth cameras are within the revisit thresholds.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from common.evaluation.metrics import rotation_angles_deg
from common.evaluation.trajectory import Trajectory
from common.geometry import inverse_T
from services.cloud.fusion.map_fusion import reason_kind

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopCriterion:
    """Thresholds of :mod:`lab.loop_scoring` (see the module docstring).

    max_trans_err_m / max_rot_err_deg: a verified relative pose this close to the truth is a
    true positive (default 0.3 m, 10 deg). revisit_dist_m / revisit_angle_deg: camera centres
    and optical axes this close make two keyframes a revisit (default 1 m, 30 deg).
    same_robot_min_gap_s: a robot's own keyframes count as revisits only this far apart in
    time (default 10 s). max_gt_gap_s: ground truth farther than this from a keyframe's stamp
    is missing (default 0.02 s). linked_min_shared: map points a query shares with a revisit
    partner at the end for it to count as linked (default 15, ORB-SLAM's covisibility edge).
    """

    max_trans_err_m: float = 0.3
    max_rot_err_deg: float = 10.0
    revisit_dist_m: float = 1.0
    revisit_angle_deg: float = 30.0
    same_robot_min_gap_s: float = 10.0
    max_gt_gap_s: float = 0.02
    linked_min_shared: int = 15


@dataclass(frozen=True)
class KeyframeInfo:
    """A keyframe that reached the cloud: atlas key, robot name, timestamp [s]."""

    key: int
    robot: str
    timestamp_s: float


@dataclass(frozen=True, eq=False)
class Detection:
    """A verified candidate: ``T_match_query`` (4, 4) query body -> matched body (the
    verification's ``T_cbody_qbody``); ``kind`` "merge", "loop" or "rejected"."""

    query_key: int
    match_key: int
    T_match_query: np.ndarray
    accepted: bool
    kind: str
    reason: str
    n_inliers: int


@dataclass(frozen=True, eq=False)
class QueryEvent:
    """A new keyframe queried against ``held_keys (K,)`` int64 (the cloud's keyframes then);
    ``connected_keys (C,)`` int64: the held keyframes it already shared map points with then
    (covisible: the edge tracked their points again, so that revisit is already joined)."""

    query_key: int
    held_keys: np.ndarray
    connected_keys: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


class GroundTruthPoses:
    """Ground-truth body and camera poses of keyframes.

    references: ``{robot name: body trajectory}`` in one common world frame;
    T_body_cam (4, 4): camera -> body."""

    def __init__(
        self,
        references: Mapping[str, Trajectory],
        T_body_cam: np.ndarray,
        max_gap_s: float = 0.02,
    ) -> None:
        self.references = dict(references)
        self.T_body_cam = np.asarray(T_body_cam, np.float64)
        self.max_gap_ns = int(max_gap_s * 1e9)
        self._T = {name: ref.T_world_body for name, ref in self.references.items()}

    def T_world_body(self, robot: str, timestamp_s: float) -> np.ndarray | None:
        """(4, 4) nearest ground-truth pose within ``max_gap_s``, else None."""
        ref = self.references.get(robot)
        if ref is None or len(ref) == 0:
            return None
        ts = ref.timestamps_ns
        t = round(timestamp_s * 1e9)
        j = int(np.clip(np.searchsorted(ts, t), 1, max(len(ts) - 1, 1)))
        if len(ts) > 1 and abs(int(ts[j - 1]) - t) <= abs(int(ts[j]) - t):
            j -= 1
        j = min(j, len(ts) - 1)
        if abs(int(ts[j]) - t) > self.max_gap_ns:
            return None
        return self._T[robot][j]

    def T_world_cam(self, robot: str, timestamp_s: float) -> np.ndarray | None:
        T = self.T_world_body(robot, timestamp_s)
        return None if T is None else T @ self.T_body_cam


@dataclass(frozen=True)
class DetectionScore:
    """One detection against the truth (errors None without ground truth)."""

    detection: Detection
    query: KeyframeInfo
    match: KeyframeInfo
    trans_err_m: float | None
    rot_err_deg: float | None
    gt_distance_m: float | None
    true: bool | None


def score_detection(
    det: Detection,
    info: Mapping[int, KeyframeInfo],
    gt: GroundTruthPoses,
    criterion: LoopCriterion,
) -> DetectionScore:
    """Compare a detection's relative pose with the ground truth."""
    q, m = info[det.query_key], info[det.match_key]
    T_wq = gt.T_world_body(q.robot, q.timestamp_s)
    T_wm = gt.T_world_body(m.robot, m.timestamp_s)
    if T_wq is None or T_wm is None:
        return DetectionScore(det, q, m, None, None, None, None)
    T_gt = inverse_T(T_wm) @ T_wq
    T_est = np.asarray(det.T_match_query, np.float64)
    trans = float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))
    rot = float(rotation_angles_deg(T_gt[:3, :3].T @ T_est[:3, :3])[0])
    dist = float(np.linalg.norm(T_gt[:3, 3]))
    ok = trans < criterion.max_trans_err_m and rot < criterion.max_rot_err_deg
    return DetectionScore(det, q, m, trans, rot, dist, ok)


def same_place(
    a: KeyframeInfo, b: KeyframeInfo, gt: GroundTruthPoses, criterion: LoopCriterion
) -> bool | None:
    """Ground-truth camera centres within ``revisit_dist_m`` and optical axes within
    ``revisit_angle_deg`` (None without ground truth)."""
    T_a = gt.T_world_cam(a.robot, a.timestamp_s)
    T_b = gt.T_world_cam(b.robot, b.timestamp_s)
    if T_a is None or T_b is None:
        return None
    near = np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) < criterion.revisit_dist_m
    return bool(near and T_a[:3, 2] @ T_b[:3, 2] > np.cos(np.radians(criterion.revisit_angle_deg)))


def revisit_partners(
    query: KeyframeInfo,
    held: Iterable[KeyframeInfo],
    gt: GroundTruthPoses,
    criterion: LoopCriterion,
) -> list[int]:
    """Keys of ``held`` keyframes that are ground-truth revisits of ``query``."""
    T_q = gt.T_world_cam(query.robot, query.timestamp_s)
    if T_q is None:
        return []
    keys, centres, axes = [], [], []
    for h in held:
        if h.key == query.key:
            continue
        if h.robot == query.robot and (
            abs(h.timestamp_s - query.timestamp_s) <= criterion.same_robot_min_gap_s
        ):
            continue
        T_h = gt.T_world_cam(h.robot, h.timestamp_s)
        if T_h is not None:
            keys.append(h.key)
            centres.append(T_h[:3, 3])
            axes.append(T_h[:3, 2])  # optical axis (camera z) in the world
    if not keys:
        return []
    near = np.linalg.norm(np.array(centres) - T_q[:3, 3], axis=1) < criterion.revisit_dist_m
    aligned = np.array(axes) @ T_q[:3, 2] > np.cos(np.radians(criterion.revisit_angle_deg))
    return [k for k, ok in zip(keys, near & aligned, strict=True) if ok]


@dataclass
class LoopScores:
    """Precision / recall summary and the per-detection scores."""

    criterion: LoopCriterion
    accepted: list[DetectionScore] = field(default_factory=list)
    rejected: list[DetectionScore] = field(default_factory=list)
    queries: int = 0
    queries_with_partner: int = 0
    found: int = 0
    queries_with_unconnected_partner: int = 0
    found_unconnected: int = 0
    linked: int = 0
    rejected_reasons: Counter[str] = field(default_factory=Counter)

    @property
    def true_positives(self) -> int:
        return sum(1 for s in self.accepted if s.true)

    @property
    def false_positives(self) -> int:
        return sum(1 for s in self.accepted if s.true is False)

    @property
    def precision(self) -> float | None:
        judged = self.true_positives + self.false_positives
        return self.true_positives / judged if judged else None

    @property
    def recall(self) -> float | None:
        return self.found / self.queries_with_partner if self.queries_with_partner else None

    @property
    def recall_unconnected(self) -> float | None:
        """Recall over the queries with a revisit partner they shared no map point with."""
        n = self.queries_with_unconnected_partner
        return self.found_unconnected / n if n else None

    @property
    def recall_linked(self) -> float | None:
        """Queries with a revisit partner that were found or share map points with a partner
        at the end (module docstring) / queries with a revisit partner."""
        return self.linked / self.queries_with_partner if self.queries_with_partner else None

    @property
    def rejected_true(self) -> int:
        """Rejected candidates that are a true place (a ground-truth revisit by camera
        geometry: :func:`same_place`); verification keeps no pose for a rejected one."""
        return sum(1 for s in self.rejected if s.true)


def score_loops(
    detections: Iterable[Detection],
    queries: Iterable[QueryEvent],
    info: Mapping[int, KeyframeInfo],
    gt: GroundTruthPoses,
    criterion: LoopCriterion | None = None,
    final_covisible: Mapping[int, Mapping[int, int]] | None = None,
) -> LoopScores:
    """Precision and recall (module docstring) of a replay's detections; the linked recall
    counts found queries only unless ``final_covisible`` ({keyframe: {keyframe: shared map
    points}} of the map at the end) is given."""
    crit = criterion or LoopCriterion()
    scores = LoopScores(crit)
    true_found: set[int] = set()
    for det in detections:
        s = score_detection(det, info, gt, crit)
        if det.accepted:
            scores.accepted.append(s)
            if s.true:
                true_found.add(det.query_key)
        else:
            # A rejected candidate carries no pose: judge the place, not the transform.
            s = dataclasses.replace(s, true=same_place(s.query, s.match, gt, crit))
            scores.rejected.append(s)
            scores.rejected_reasons[reason_kind(det.reason) or "?"] += 1
    for q in queries:
        scores.queries += 1
        held = [info[int(k)] for k in q.held_keys.tolist() if int(k) in info]
        partners = revisit_partners(info[q.query_key], held, gt, crit)
        if partners:
            scores.queries_with_partner += 1
            found = q.query_key in true_found
            scores.found += found
            shared = (final_covisible or {}).get(q.query_key, {})
            scores.linked += found or any(
                shared.get(p, 0) >= crit.linked_min_shared for p in partners
            )
            if set(partners) - set(q.connected_keys.tolist()):
                scores.queries_with_unconnected_partner += 1
                scores.found_unconnected += found
    return scores
