"""Loop-detection scoring against ground truth labels known loops correctly."""

from __future__ import annotations

import numpy as np

from common.evaluation.trajectory import Trajectory
from common.geometry import inverse_T
from lab.loop_scoring import (
    Detection,
    GroundTruthPoses,
    KeyframeInfo,
    LoopCriterion,
    QueryEvent,
    score_loops,
)
from sim.cloud import R_BODY_CAM, circle_poses, yaw_T


def _gt() -> tuple[GroundTruthPoses, dict[int, KeyframeInfo], np.ndarray, np.ndarray]:
    """Two robots on the same circle, robot b half a lap behind; one pose per second."""
    poses = circle_poses(40, turns=2.0)  # 20 s a lap
    ts = (np.arange(40) * 1e9).astype(np.int64)
    refs = {"a": Trajectory.from_poses(ts, poses, "a"), "b": Trajectory.from_poses(ts, poses, "b")}
    T_body_cam = np.eye(4)
    T_body_cam[:3, :3] = R_BODY_CAM
    info = {i: KeyframeInfo(i, "a", float(i)) for i in range(40)}
    info.update({100 + i: KeyframeInfo(100 + i, "b", float(i)) for i in range(10)})
    return GroundTruthPoses(refs, T_body_cam), info, poses, ts


def test_true_and_false_loops_are_labelled_and_counted():
    gt, info, poses, _ = _gt()
    T_true = inverse_T(poses[5]) @ poses[25]  # a at 25 s revisits a at 5 s (one lap later)
    T_false = T_true @ yaw_T(0.0, np.array([1.0, 0.0, 0.0]))  # 1 m off
    T_near = T_true @ yaw_T(np.radians(3.0), np.array([0.1, 0.05, 0.0]))  # within 0.3 m, 10 deg
    dets = [
        Detection(25, 5, T_true, True, "loop", "ok", 120),
        Detection(26, 6, T_false, True, "loop", "ok", 40),
        Detection(27, 7, T_near, True, "loop", "ok", 90),
        Detection(28, 8, np.eye(4), False, "rejected", "inliers 12/30", 12),  # same place
        Detection(29, 14, np.eye(4), False, "rejected", "no 3D-2D pose", 0),  # half a lap off
    ]
    held = np.arange(30, dtype=np.int64)
    queries = [QueryEvent(k, held[held < k]) for k in (25, 26, 27, 28, 12)]
    s = score_loops(dets, queries, info, gt, LoopCriterion())
    assert [d.true for d in s.accepted] == [True, False, True]
    assert s.accepted[0].trans_err_m < 1e-9 and s.accepted[1].trans_err_m > 0.9
    assert (s.true_positives, s.false_positives) == (2, 1)
    assert abs(s.precision - 2 / 3) < 1e-12
    # 25..28 have a partner one lap earlier; 12 has none (a only 12 s old, b not held).
    assert (s.queries, s.queries_with_partner, s.found) == (5, 4, 2)
    assert s.recall == 0.5
    assert [d.true for d in s.rejected] == [True, False] and s.rejected_true == 1
    assert s.rejected_reasons == {"inliers": 1, "no 3D-2D pose": 1}


def test_revisit_partner_needs_time_gap_or_other_robot():
    gt, info, _, _ = _gt()
    crit = LoopCriterion()
    # a at 3 s: its own previous keyframes are < 10 s old -> no partner ...
    assert (
        score_loops([], [QueryEvent(3, np.array([0, 1, 2]))], info, gt, crit).queries_with_partner
        == 0
    )
    # ... but robot b's keyframe at the same place (b at 3 s) is one.
    s = score_loops([], [QueryEvent(3, np.array([0, 1, 2, 103]))], info, gt, crit)
    assert s.queries_with_partner == 1 and s.found == 0 and s.recall == 0.0


def test_recall_unconnected_leaves_out_revisits_already_joined_by_shared_points():
    gt, info, poses, _ = _gt()
    T_true = inverse_T(poses[5]) @ poses[25]
    dets = [Detection(25, 5, T_true, True, "loop", "ok", 120)]
    held = np.arange(30, dtype=np.int64)
    # 25 was closed by a loop; 26 and 27 have partners, but 26 shares points with all of
    # its partners (near 6 s) already, 27 with none.
    partners_26 = [int(k) for k in held if 4 <= k <= 8]
    queries = [
        QueryEvent(25, held[held < 25]),
        QueryEvent(26, held[held < 26], np.array(partners_26, np.int64)),
        QueryEvent(27, held[held < 27]),
    ]
    s = score_loops(dets, queries, info, gt, LoopCriterion())
    assert (s.queries_with_partner, s.found) == (3, 1)
    assert (s.queries_with_unconnected_partner, s.found_unconnected) == (2, 1)
    assert s.recall_unconnected == 0.5


def test_recall_linked_counts_queries_sharing_points_with_a_partner_at_the_end():
    gt, info, poses, _ = _gt()
    T_true = inverse_T(poses[5]) @ poses[25]
    dets = [Detection(25, 5, T_true, True, "loop", "ok", 120)]
    held = np.arange(30, dtype=np.int64)
    queries = [QueryEvent(k, held[held < k]) for k in (25, 26, 27, 28)]
    # At the end 26 shares 40 points with its partner 6 (a loop fused them), 27 only 5 with
    # 7 (under linked_min_shared), and 28 shares 40 with 20, which is no revisit partner.
    covisible = {26: {6: 40, 25: 80}, 27: {7: 5}, 28: {20: 40}}
    s = score_loops(dets, queries, info, gt, LoopCriterion(), final_covisible=covisible)
    assert (s.queries_with_partner, s.found, s.linked) == (4, 1, 2)
    assert s.recall == 0.25 and s.recall_linked == 0.5
    # Without the map at the end, linked counts the found ones only.
    assert score_loops(dets, queries, info, gt, LoopCriterion()).recall_linked == 0.25
