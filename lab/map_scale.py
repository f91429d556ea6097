"""Where a map's scale goes: the Sim(3) scale of a run's keyframes after every stage.

A monocular-inertial map's scale comes from its IMU only. To see which stage of the chain
moves it, :func:`trace_recording` replays a recording (``recslam demo --record-uplink``)
through the cloud service's own core (:func:`lab.table3.replay`, modelled schedule,
deterministic) with a solve function that keeps every solve's keyframe poses before and after
(:class:`SolveTrace`), and :func:`uplinked_trajectories` reads the edge's own keyframe poses
from the recording (as first uplinked, and as last re-sent). :func:`stage_scales` then aligns
each snapshot to the ground truth with a similarity (all robots of the map at once, and each
robot on its own) and reports the map's scale error, ``map size / true size - 1``.

The input of a solve is what the stages before it left (the merges and the previous solves),
its output what it made of them, so a solve that moves the scale shows as a step between its
``before`` and ``after`` rows.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.evaluation.metrics import AlignMode, AteConfig, compute_joint_ate
from common.evaluation.trajectory import Trajectory
from common.geometry import R_to_quat_wxyz
from common.links.edge_cloud import KeyframePoses, KeyframeUpdate, KeyframeUpdateCoded
from common.links.edge_cloud_payloads import decode_states
from lab.loop_scoring import KeyframeInfo
from services.cloud.core_actions import SolveRequest, SolveResult, solve
from services.cloud.store.recording import Record, Step, read_schedule

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Snapshot:
    """Keyframe poses of one map at one moment: ``keys (N,)`` atlas keys, ``T_world_body
    (N, 4, 4)`` map frame."""

    label: str
    map_id: int
    keys: np.ndarray
    T_world_body: np.ndarray


@dataclass
class SolveTrace:
    """A solve function (:func:`services.cloud.core_actions.solve` by default) that keeps
    each solve's keyframe poses before and after (``snapshots``, in solve order)."""

    inner: Callable[[SolveRequest], SolveResult] = solve
    snapshots: list[Snapshot] = field(default_factory=list)

    def __call__(self, request: SolveRequest) -> SolveResult:
        n = sum(1 for s in self.snapshots if s.label.endswith("before"))
        kind = request.kind.value
        p = request.problem
        self.snapshots.append(
            Snapshot(f"{n} {kind} before", request.map_id, p.keys.copy(), p.T_world_body.copy())
        )
        result = self.inner(request)
        self.snapshots.append(
            Snapshot(
                f"{n} {kind} after", request.map_id, result.keys.copy(), result.T_world_body.copy()
            )
        )
        return result


def _trajectory(stamps_s: list[float], T: list[np.ndarray], name: str) -> Trajectory:
    order = np.argsort(stamps_s)
    ts = np.round(np.asarray(stamps_s)[order] * 1e9).astype(np.int64)
    Ts = np.asarray(T)[order].reshape(-1, 4, 4)
    keep = np.concatenate([[True], np.diff(ts) > 0]) if ts.size else np.zeros(0, bool)
    return Trajectory(ts[keep], Ts[keep, :3, 3], R_to_quat_wxyz(Ts[keep, :3, :3]), name=name)


def snapshot_trajectories(
    snapshot: Snapshot, info: Mapping[int, KeyframeInfo]
) -> dict[str, Trajectory]:
    """The snapshot's keyframes per robot (``info``: every keyframe's robot and stamp)."""
    per: dict[str, tuple[list[float], list[np.ndarray]]] = {}
    for k, T in zip(snapshot.keys.tolist(), snapshot.T_world_body, strict=True):
        kf = info.get(int(k))
        if kf is None:
            continue
        stamps, poses = per.setdefault(kf.robot, ([], []))
        stamps.append(kf.timestamp_s)
        poses.append(T)
    return {r: _trajectory(s, T, r) for r, (s, T) in per.items() if len(s) >= 3}


def uplinked_trajectories(recording: Path, last: bool = False) -> dict[str, Trajectory]:
    """Each robot's keyframe poses as its edge uplinked them (edge map frame): the pose a
    keyframe first arrived with, or with ``last`` the newest the edge re-sent
    (``KeyframePoses``). Only the robot's edge map with the most keyframes is kept (a
    robot whose tracking was lost has several, each in its own frame)."""
    poses: dict[tuple[str, int], dict[int, tuple[float, np.ndarray]]] = {}
    for rec in read_schedule(recording, allow_truncated_tail=True):
        if isinstance(rec, Step) or not isinstance(rec, Record):
            continue
        m = rec.message
        if isinstance(m, KeyframeUpdateCoded):
            st = decode_states(m.state)
            held = poses.setdefault((m.agent_id, m.map_id), {})
            held.setdefault(m.keyframe_id, (m.timestamp_ns * 1e-9, st.T_world_body[0]))
        elif isinstance(m, KeyframeUpdate):
            T = np.frombuffer(m.T_world_body, "<f8").reshape(4, 4)
            held = poses.setdefault((m.agent_id, m.map_id), {})
            held.setdefault(m.keyframe_id, (m.timestamp_ns * 1e-9, T))
        elif last and isinstance(m, KeyframePoses):
            st = decode_states(m.states)
            held = poses.setdefault((m.agent_id, m.map_id), {})
            for kid, T in zip(st.keyframe_ids.tolist(), st.T_world_body, strict=True):
                if kid in held:
                    held[kid] = (held[kid][0], T)
    best: dict[str, dict[int, tuple[float, np.ndarray]]] = {}
    for (robot, _), held in poses.items():
        if len(held) > len(best.get(robot, {})):
            best[robot] = held
    return {
        r: _trajectory([v[0] for v in h.values()], [v[1] for v in h.values()], r)
        for r, h in best.items()
    }


@dataclass(frozen=True)
class StageScale:
    """One snapshot against the ground truth: map scale error (``map size / true size - 1``)
    of all its robots aligned together (``joint``) and of each alone (``per_robot``), joint
    ATE SE(3) and Sim(3) [m], keyframes."""

    label: str
    map_id: int
    keyframes: int
    joint: float
    per_robot: dict[str, float]
    ate_se3_m: float
    ate_sim3_m: float


def stage_scale(
    label: str, map_id: int, references: Mapping[str, Trajectory], est: Mapping[str, Trajectory]
) -> StageScale | None:
    """:class:`StageScale` of trajectories ``est`` (one map frame); None if too few poses."""
    est = {n: t for n, t in est.items() if n in references and len(t) >= 3}
    if not est:
        return None
    refs = {n: references[n] for n in est}
    sim = compute_joint_ate(refs, est, AteConfig(align=AlignMode.SIM3))
    se3 = compute_joint_ate(refs, est, AteConfig(align=AlignMode.SE3))
    return StageScale(
        label=label,
        map_id=map_id,
        keyframes=sum(len(t) for t in est.values()),
        joint=1.0 / sim.transform.scale - 1.0,
        per_robot={n: 1.0 / r.transform.scale - 1.0 for n, r in sim.individual.items()},
        ate_se3_m=float(se3.stats.rmse),
        ate_sim3_m=float(sim.stats.rmse),
    )


def stage_scales(
    snapshots: list[Snapshot],
    info: Mapping[int, KeyframeInfo],
    references: Mapping[str, Trajectory],
) -> list[StageScale]:
    """:func:`stage_scale` of every snapshot (those with too few poses left out)."""
    out = []
    for s in snapshots:
        row = stage_scale(s.label, s.map_id, references, snapshot_trajectories(s, info))
        if row is not None:
            out.append(row)
    return out
