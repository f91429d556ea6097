"""The cloud's result folder: per-robot keyframe trajectories and the ATE report.

Layout (``common.evaluation.results``)::

    RESULT_DIR/trajectories/<robot>.tum   T_map_body of each robot's keyframes, TUM format
    RESULT_DIR/frames/trajectories/<robot>.tum, frames/eval/ate.json
                                          every frame's T_map_body (the edges' frame poses
                                          on the final keyframes) and its ATE
    RESULT_DIR/cloud_maps.json            which map each robot is in, and whether all share one
    RESULT_DIR/eval/ate.json, ate.md, *.png   with ground truth (``common.evaluation.report``)
    RESULT_DIR/mission.json               the mission and its merges into a prior map
    RESULT_DIR/eval/ate_prior_frame.json  with ``prior_frame`` (an earlier mission's ate.json):
                                          the ATE under that mission's alignment

All robots whose maps were merged are in the same (merged) map frame, which is what the joint
ATE needs. A robot whose map never merged is still written in its own map frame: its file is
valid on its own, but the joint ATE then compares unrelated frames; ``cloud_maps.json`` and
the log say so.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from common.evaluation.errors import EvaluationError
from common.evaluation.report import EvalConfig, evaluate_in_frame, evaluate_run
from common.evaluation.results import MAPS_FILE, write_result_trajectories
from common.evaluation.trajectory import Trajectory
from services.cloud.atlas.atlas import Atlas
from services.cloud.store.mission import MISSION_FILE

log = logging.getLogger(__name__)

__all__ = ["FRAMES_DIR", "MAPS_FILE", "OutputWriter", "robot_trajectories"]

FRAMES_DIR = "frames"
"""``RESULT_DIR/frames/``: every frame's trajectory (``trajectories/<robot>.tum``) and its
``eval/ate.json`` (:mod:`services.cloud.store.frame_trajectories`)."""


def robot_trajectories(
    atlas: Atlas, agents: Mapping[str, Sequence[int]], retired: bool = True
) -> tuple[dict[str, Trajectory], dict[str, int]]:
    """Keyframe trajectories ``T_map_body`` per robot name, and each robot's map id.

    ``agents``: each robot's atlas agents (one per edge map the edge started for it). A robot
    contributes the keyframes of those agents that ended in the same atlas map as its largest
    one (the others are in frames its trajectory cannot be expressed in; they are logged).
    ``retired``: also the keyframes MBP removed, through their anchors (see
    ``Atlas.retire_keyframe``). Poses of equal stamps (ns) are written once."""
    trajs: dict[str, Trajectory] = {}
    maps: dict[str, int] = {}
    for name, ids in sorted(agents.items()):
        keys = {a: atlas.keyframe_keys(agent_id=a) for a in ids}
        main = max(ids, key=lambda a: len(keys[a]))
        if not keys[main]:
            continue
        map_id = atlas.map_of_agent(main)
        same = [a for a in ids if atlas.map_of_agent(a) == map_id]
        use = [k for a in same for k in keys[a]]
        if len(use) < sum(len(v) for v in keys.values()):
            log.warning("robot %s: keyframes of unmerged maps left out of its trajectory", name)
        poses = [(v.timestamp, v.T_map_body) for v in map(atlas.keyframe, use)]
        if retired:
            poses += [(t, T) for a in same for _, t, T in atlas.retired_poses(a)]
        poses.sort(key=lambda p: p[0])
        ts = np.array([round(t * 1e9) for t, _ in poses], np.int64)
        keep = np.concatenate([[True], np.diff(ts) > 0])
        T_map_body = np.array([p[1] for p, k in zip(poses, keep, strict=True) if k])
        trajs[name] = Trajectory.from_poses(ts[keep], T_map_body, name)
        maps[name] = map_id
    return trajs, maps


class OutputWriter:
    """Writes ``results_dir``; ``groundtruth`` (dataset folder or file) enables the report;
    ``prior_frame``: the ``eval/ate.json`` of the mission whose saved map this one started in
    (its trajectories are then also measured in that mission's frame)."""

    def __init__(
        self,
        results_dir: Path,
        groundtruth: str | Path | None = None,
        prior_frame: str | Path | None = None,
    ) -> None:
        self.results_dir = Path(results_dir)
        self.groundtruth = groundtruth
        self.prior_frame = prior_frame

    def write(
        self,
        trajectories: Mapping[str, Trajectory],
        map_of_robot: Mapping[str, int],
        evaluate: bool = True,
        mission: Mapping[str, object] | None = None,
        frames: Mapping[str, Trajectory] | None = None,
    ) -> list[Path]:
        """Write the trajectories (and the report, and ``mission``: the cloud's
        ``CloudApp.mission_report``; ``frames``: every frame's trajectory per robot, written
        and measured in ``RESULT_DIR/frames``); returns the files written."""
        if not trajectories:
            return []
        self.results_dir.mkdir(parents=True, exist_ok=True)
        if mission is not None:
            (self.results_dir / MISSION_FILE).write_text(json.dumps(mission, indent=2) + "\n")
        folder = write_result_trajectories(self.results_dir, trajectories)
        files = [folder / f"{name}.tum" for name in trajectories]
        maps = sorted(set(map_of_robot.values()))
        joint = len(maps) == 1
        note = (
            "all robots in one map frame"
            if joint
            else "maps not merged: each robot's trajectory is in its own map's frame, a joint "
            "ATE across different maps is not meaningful"
        )
        info = {
            "robots": dict(sorted(map_of_robot.items())),
            "maps": maps,
            "joint_frame": joint,
            "note": note,
        }
        (self.results_dir / MAPS_FILE).write_text(json.dumps(info, indent=2) + "\n")
        files.append(self.results_dir / MAPS_FILE)
        if not joint:
            log.warning("trajectories: %s (%s)", note, dict(map_of_robot))
        if frames:
            frames_dir = self.results_dir / FRAMES_DIR
            folder = write_result_trajectories(frames_dir, frames)
            files += [folder / f"{name}.tum" for name in frames]
            (frames_dir / MAPS_FILE).write_text(json.dumps(info, indent=2) + "\n")
            if evaluate and self.groundtruth is not None:
                try:
                    files.extend(
                        evaluate_run(
                            frames_dir, self.groundtruth, config=EvalConfig(plots=False)
                        ).files
                    )
                except EvaluationError as exc:
                    log.warning("per-frame ATE report not written: %s", exc)
        if evaluate and self.groundtruth is not None:
            try:
                report = evaluate_run(self.results_dir, self.groundtruth)
            except EvaluationError as exc:
                log.warning("ATE report not written: %s", exc)
            else:
                files.extend(report.files)
                if report.joint_frame:
                    log.info(
                        "joint ATE RMSE %.4f m over %s",
                        report.joint.stats.rmse,
                        sorted(trajectories),
                    )
                else:
                    log.warning("ATE report: maps did not merge, no joint ATE")
                if self.prior_frame is not None:
                    files.extend(self._in_prior_frame())
        return files

    def _in_prior_frame(self) -> list[Path]:
        assert self.prior_frame is not None
        try:
            joint, path = evaluate_in_frame(self.results_dir, self.prior_frame, self.groundtruth)
        except EvaluationError as exc:
            log.warning("ATE in the prior mission's frame not written: %s", exc)
            return []
        log.info("joint ATE RMSE %.4f m in the prior mission's frame", joint.stats.rmse)
        return [path]
