"""The result-folder convention and ground-truth sources that ``recslam eval`` reads.

Result folder (written by the services at the end of a run, read by ``recslam eval``)::

    RESULT_DIR/
      trajectories/<agent>.tum     estimated body (IMU) poses T_map_body of one agent, TUM
                                   format (see common.evaluation.tum); ALL agents in the SAME
                                   map frame (the cloud's merged map), stamps = sensor stamps
      groundtruth/<agent>.tum      optional: ground truth copied next to the result; used when
                                   no --groundtruth is given
      eval/                        default output of ``recslam eval`` (ate.json, ate.md, *.png)

``<agent>`` is the agent's name, identical to the dataset folder of its sequence. Other files
in RESULT_DIR are ignored. :func:`write_result_trajectories` writes the layout.

Ground truth (``--groundtruth``) may be:

- a multi-robot dataset folder: ``DATASET/<agent>/mav0/state_groundtruth_estimate0/data.csv``
  (EuRoC ASL layout, read by ``common.data.euroc.read_groundtruth``) or ``DATASET/<agent>.tum``;
  ``DATASET/<agent>/state_groundtruth_estimate0/data.csv`` is accepted too;
- a single EuRoC sequence folder (``SEQ/mav0/...``), a ``data.csv`` or a ``.tum`` file: only
  when the result holds exactly one agent.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

from common.evaluation.errors import ResultFolderError
from common.evaluation.trajectory import Trajectory
from common.evaluation.tum import read_tum, write_tum

log = logging.getLogger(__name__)

TRAJECTORY_DIR = "trajectories"
GROUNDTRUTH_DIR = "groundtruth"
EVAL_DIR = "eval"
MAPS_FILE = "cloud_maps.json"
"""Which map each agent is in (written by the cloud; read by the report)."""
_EUROC_GT = Path("mav0") / "state_groundtruth_estimate0" / "data.csv"


def write_result_trajectories(
    result_dir: Path | str, trajectories: Mapping[str, Trajectory]
) -> Path:
    """Write ``RESULT_DIR/trajectories/<agent>.tum`` for each agent; returns that folder."""
    folder = Path(result_dir) / TRAJECTORY_DIR
    for agent, traj in trajectories.items():
        _check_agent_name(agent)
        write_tum(folder / f"{agent}.tum", traj.renamed(agent))
    return folder


def read_result_trajectories(result_dir: Path | str) -> dict[str, Trajectory]:
    """``{agent: estimate}`` from ``RESULT_DIR/trajectories/*.tum``, sorted by agent name."""
    root = Path(result_dir)
    folder = root / TRAJECTORY_DIR
    if not root.is_dir():
        raise ResultFolderError(f"{root}: result folder does not exist")
    if not folder.is_dir():
        raise ResultFolderError(
            f"{root}: no '{TRAJECTORY_DIR}/' folder; expected {TRAJECTORY_DIR}/<agent>.tum"
        )
    files = sorted(folder.glob("*.tum"))
    if not files:
        raise ResultFolderError(f"{folder}: no <agent>.tum trajectory files")
    return {f.stem: read_tum(f, f.stem) for f in files}


def read_groundtruth_file(path: Path | str, name: str = "") -> Trajectory:
    """Ground truth from a ``.tum`` file or an EuRoC ``data.csv``."""
    p = Path(path)
    if p.suffix == ".tum" or p.suffix == ".txt":
        return read_tum(p, name or p.stem)
    from common.data.euroc import read_groundtruth

    return Trajectory.from_groundtruth(read_groundtruth(p), name)


def _single_source(path: Path) -> Path | None:
    """The one ground-truth file a path denotes, or None if it is a multi-robot folder."""
    if path.is_file():
        return path
    for candidate in (path / _EUROC_GT, path / _EUROC_GT.relative_to("mav0")):
        if candidate.is_file():
            return candidate
    return None


def _agent_source(root: Path, agent: str) -> Path | None:
    for candidate in (
        root / agent / _EUROC_GT,
        root / agent / _EUROC_GT.relative_to("mav0"),
        root / f"{agent}.tum",
    ):
        if candidate.is_file():
            return candidate
    return None


def load_groundtruth(
    agents: list[str], source: Path | str | None, result_dir: Path | str | None = None
) -> tuple[dict[str, Trajectory], dict[str, Path]]:
    """``({agent: reference}, {agent: file used})`` for the given agents.

    ``source`` is a dataset folder, sequence folder or file (module docstring); when None,
    ``RESULT_DIR/groundtruth/<agent>.tum`` is used. Missing ground truth for any agent is a
    ResultFolderError listing what was looked for.
    """
    if source is None:
        if result_dir is None:
            raise ResultFolderError("no ground truth given and no result folder to look in")
        root = Path(result_dir) / GROUNDTRUTH_DIR
        if not root.is_dir():
            raise ResultFolderError(
                f"no ground truth: pass --groundtruth, or put <agent>.tum files in {root}"
            )
    else:
        root = Path(source)
        if not root.exists():
            raise ResultFolderError(f"{root}: ground-truth path does not exist")
    files: dict[str, Path] = {}
    single = _single_source(root)
    if single is not None and _agent_source(root, agents[0]) is None:
        if len(agents) != 1:
            raise ResultFolderError(
                f"{root} holds one ground truth but the result has {len(agents)} agents "
                f"{agents}; pass a dataset folder with one <agent>/ or <agent>.tum each"
            )
        files[agents[0]] = single
    else:
        missing = []
        for agent in agents:
            found = _agent_source(root, agent)
            if found is None:
                missing.append(agent)
            else:
                files[agent] = found
        if missing:
            raise ResultFolderError(
                f"{root}: no ground truth for agent(s) {missing}; looked for "
                f"<agent>/{_EUROC_GT}, <agent>/{_EUROC_GT.relative_to('mav0')} and <agent>.tum"
            )
    refs = {agent: read_groundtruth_file(path, agent) for agent, path in files.items()}
    for agent, path in files.items():
        log.info("ground truth of %s: %s (%d poses)", agent, path, len(refs[agent]))
    return refs, files


def _check_agent_name(agent: str) -> None:
    if not agent or "/" in agent or "\\" in agent or agent.startswith("."):
        raise ResultFolderError(f"invalid agent name {agent!r} (must be a plain file stem)")
