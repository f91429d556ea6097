"""The cloud's result folder: per-robot keyframe trajectories and the ATE report.

Layout (``common.evaluation.results``)::

    RESULT_DIR/trajectories/<robot>.tum   T_map_body of each robot's keyframes, TUM format
    RESULT_DIR/cloud_maps.json            which map each robot is in, and whether all share one
    RESULT_DIR/eval/ate.json, ate.md, *.png   with ground truth (``common.evaluation.report``)

All robots whose maps were merged are in the same (merged) map frame, which is what the joint
ATE needs. A robot whose map never merged is still written in its own map frame: its file is
valid on its own, but the joint ATE then compares unrelated frames; ``cloud_maps.json`` and
the log say so.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path

from common.evaluation.errors import EvaluationError
from common.evaluation.report import evaluate_run
from common.evaluation.results import MAPS_FILE, write_result_trajectories
from common.evaluation.trajectory import Trajectory

log = logging.getLogger(__name__)

__all__ = ["MAPS_FILE", "OutputWriter"]


class OutputWriter:
    """Writes ``results_dir``; ``groundtruth`` (dataset folder or file) enables the report."""

    def __init__(self, results_dir: Path, groundtruth: str | Path | None = None) -> None:
        self.results_dir = Path(results_dir)
        self.groundtruth = groundtruth

    def write(
        self,
        trajectories: Mapping[str, Trajectory],
        map_of_robot: Mapping[str, int],
        evaluate: bool = True,
    ) -> list[Path]:
        """Write the trajectories (and the report); returns the files written."""
        if not trajectories:
            return []
        self.results_dir.mkdir(parents=True, exist_ok=True)
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
        return files
