"""scripts/compose_check.py, the checker of `make compose-test` and `make swarm-test`, on a
result folder written here: the joint ATE bound of ``--max-joint-ate``."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROBOTS = ["robot0", "robot1"]


def _checker() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "compose_check", ROOT / "scripts/compose_check.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(tmp_path: Path, joint_m: float, one_map: bool = True) -> tuple[Path, Path]:
    """A cloud result folder and a dataset of 3 frames per robot, every frame decoded."""
    results, dataset = tmp_path / "results", tmp_path / "datasets"
    for robot in ROBOTS:
        cam = dataset / robot / "mav0" / "cam0"
        cam.mkdir(parents=True)
        (cam / "data.csv").write_text("#timestamp,filename\n1,a\n2,b\n3,c\n")
        (results / "trajectories").mkdir(parents=True, exist_ok=True)
        (results / "trajectories" / f"{robot}.tum").write_text("0 0 0 0 0 0 0 1\n" * 3)
    maps = [0] if one_map else [0, 3]
    (results / "cloud_maps.json").write_text(json.dumps({"maps": maps, "joint_frame": one_map}))
    (results / "eval").mkdir()
    row = f"| **joint** | 6 | {joint_m:.4f} |" if one_map else "Maps did not merge (2 maps)"
    (results / "eval" / "ate.md").write_text(row + "\n")
    stats = {"individual": {"stats_m": {"rmse": joint_m}}}
    ate = {
        "joint": {"stats_m": {"rmse": joint_m}},
        "joint_frame": one_map,
        "agents": dict.fromkeys(ROBOTS, stats),
    }
    (results / "eval" / "ate.json").write_text(json.dumps(ate))
    edge = {"robots": {r: {"frames_decoded": 3} for r in ROBOTS}}
    (results / "edge-stats.json").write_text(json.dumps(edge))
    return results, dataset


@pytest.mark.parametrize(
    ("joint_m", "one_map", "bound", "passed"),
    [(0.02, True, 0.03, True), (0.04, True, 0.03, False), (0.02, False, 0.03, False)],
)
def test_the_joint_ate_bound(tmp_path, joint_m, one_map, bound, passed) -> None:
    results, dataset = _run(tmp_path, joint_m, one_map)
    checker = _checker()
    checks = checker.check_outputs(results, dataset, ROBOTS, bound)
    (ok, line) = next(c for c in checks if c[1].startswith("joint ATE"))
    assert ok is passed, line
    assert f"{joint_m:.4f} m <= {bound} m" in line
    argv = ["outputs", str(results), str(dataset), *ROBOTS, "--max-joint-ate", str(bound)]
    assert checker.main(argv) == (0 if passed else 1)
    # without it (the compose test's call) maps that did not merge pass, with their line
    assert checker.main(argv[:-2]) == 0
