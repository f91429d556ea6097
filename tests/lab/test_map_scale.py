"""The stage tracer of a map's scale: a known scale and frame come out as put in."""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import pytest

from common.evaluation.trajectory import Trajectory
from common.geometry import R_to_quat_wxyz, make_T, quat_wxyz_to_R, so3_exp
from lab.loop_scoring import KeyframeInfo
from lab.map_scale import Snapshot, SolveTrace, snapshot_trajectories, stage_scale
from services.cloud.optimization.global_optimization import PoseGraphResult


def _truth(name: str, n: int, phase: float) -> Trajectory:
    t = np.arange(n) * 0.25
    p = np.stack([2 * np.cos(0.5 * t + phase), 2 * np.sin(0.5 * t + phase), 1 + 0.3 * t], 1)
    R = np.array([so3_exp(np.array([0.0, 0.0, 0.5 * ti])) for ti in t])
    return Trajectory((1e9 * (10 + t)).astype(np.int64), p, R_to_quat_wxyz(R), name=name)


def _snapshot(refs: dict[str, Trajectory], scale: float) -> tuple[Snapshot, dict]:
    """Every reference pose as a keyframe of one map: scaled, turned and moved."""
    T_map_world = make_T(so3_exp(np.array([0.1, -0.2, 1.0])), np.array([3.0, -1.0, 0.5]))
    keys, poses, info = [], [], {}
    for a, (name, ref) in enumerate(sorted(refs.items())):
        for i, (ts, p, q) in enumerate(
            zip(ref.timestamps_ns, ref.p_world_body, ref.q_wxyz, strict=True)
        ):
            key = 1000 * a + i
            T = np.eye(4)
            T[:3, :3] = quat_wxyz_to_R(q[None])[0]
            T[:3, 3] = scale * p
            keys.append(key)
            poses.append(T_map_world @ T)
            info[key] = KeyframeInfo(key, name, ts * 1e-9)
    return Snapshot("s", 0, np.array(keys), np.array(poses)), info


def test_a_map_scaled_by_a_known_factor_shows_that_scale_error_jointly_and_per_robot():
    refs = {"robot0": _truth("robot0", 40, 0.0), "robot1": _truth("robot1", 30, 1.5)}
    snap, info = _snapshot(refs, 0.99)
    est = snapshot_trajectories(snap, info)
    assert sorted(est) == ["robot0", "robot1"] and len(est["robot1"]) == 30
    row = stage_scale("s", 0, refs, est)
    assert row is not None
    assert row.joint == pytest.approx(-0.01, abs=1e-9)
    assert row.per_robot["robot0"] == pytest.approx(-0.01, abs=1e-9)
    assert row.ate_sim3_m == pytest.approx(0.0, abs=1e-9)
    assert row.ate_se3_m > 1e-3  # a rigid alignment cannot undo the scale


def test_the_solve_trace_keeps_poses_before_and_after_each_solve():
    class _Request:
        kind = type("K", (), {"value": "pose graph"})()
        map_id = 3
        problem = type("P", (), {"keys": np.array([1, 2]), "T_world_body": np.eye(4)[None]})()

    result = PoseGraphResult(np.array([1, 2]), 2 * np.eye(4)[None], 0.0, 0.0, 1, np.zeros(0))
    trace = SolveTrace(inner=lambda request: result)
    request = cast(Any, _Request())
    trace(request)
    trace(request)
    labels = [s.label for s in trace.snapshots]
    assert labels == [
        "0 pose graph before",
        "0 pose graph after",
        "1 pose graph before",
        "1 pose graph after",
    ]
    assert trace.snapshots[1].T_world_body[0, 0, 0] == 2.0 and trace.snapshots[0].map_id == 3
