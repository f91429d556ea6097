"""``recslam experiment seeds``: seeds parsed, datasets built once, runs reported against the
targets (a run whose robots stayed in two maps has no joint ATE and fails the one-map goal)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from lab.seeds import (
    SeedsConfig,
    SeedsError,
    ensure_dataset,
    parse_seeds,
    read_report,
)
from lab.seeds_run import run_seeds
from recslam.commands import experiment


def test_parse_seeds() -> None:
    assert parse_seeds("0-9") == tuple(range(10))
    assert parse_seeds("7, 3,0") == (0, 3, 7)
    assert parse_seeds("4-5,1,5") == (1, 4, 5)
    for bad in ("", "a", "5-2", "-1", "1-b"):
        with pytest.raises(SeedsError, match="--seeds"):
            parse_seeds(bad)


@pytest.mark.slow
def test_dataset_built_once_and_never_replaced(tmp_path: Path) -> None:
    folder = tmp_path / "seed-4"
    assert ensure_dataset(folder, 1, 0.5, 4) is True
    info = json.loads((folder / "dataset.json").read_text())
    assert (info["robots"], info["seconds"], info["seed"]) == (1, 0.5, 4)
    assert ensure_dataset(folder, 1, 0.5, 4) is False  # reused
    with pytest.raises(SeedsError, match=r"seed 4, not 1 x 0\.5 s, seed 5"):
        ensure_dataset(folder, 1, 0.5, 5)


def _run(root: Path, name: str, seed: int, joint: float | None, maps: list[int], lost: int = 0):
    """A finished run folder as ``recslam demo`` leaves it, on a dataset of ``seed``."""
    data = root / "data" / f"seed-{seed}"
    (data / "robot0").mkdir(parents=True)
    (data / "dataset.json").write_text(json.dumps({"robots": 2, "seconds": 60.0, "seed": seed}))
    run = root / "out" / name
    (run / "run" / "logs").mkdir(parents=True)
    (run / "run" / "logs" / "robot0.log").write_text(
        f"$ python -m recslam robot --dataset {data / 'robot0'} --edge 127.0.0.1:1\nlog line\n"
    )
    report = {
        "failed": [],
        "camera_s": 60.0,
        "robots": {
            "robot0": {"ate_rmse_m": 0.011, "frames_lost": lost},
            "robot1": {"ate_rmse_m": 0.017 if joint else 0.061, "frames_lost": 0},
        },
        "ate": {"joint_rmse_m": joint, "joint_frame": joint is not None},
        "map": {"maps": maps, "merges": 1, "loops": 9},
    }
    (run / "report.json").write_text(json.dumps(report))
    return run


def test_report_of_finished_runs_against_the_targets(tmp_path: Path) -> None:
    _run(tmp_path, "seed-0", 0, 0.012, [0])
    _run(tmp_path, "seed-1", 1, 0.014, [0], lost=3)
    _run(tmp_path, "seed-2", 2, None, [0, 1])  # never merged: no joint ATE
    out = tmp_path / "out"
    cfg = SeedsConfig(seeds=(), out=out, results=tmp_path / "results", from_runs=True)
    data, files = run_seeds(cfg)
    s = data["summary"]
    assert s["runs"] == 3 and s["one_map"] == 2 and s["failures"] == 1
    assert s["median_joint_m"] == pytest.approx(0.013)
    assert s["worst_joint_m"] is None  # a run without a joint ATE has no worst to claim
    assert s["worst_robot_m"] == pytest.approx(0.061)
    assert s["met"] == {"median": True, "worst": False, "robots": False, "one_map": False}
    assert data["runs"]["seed-1"]["dataset"] == {"robots": 2, "seconds": 60.0, "seed": 1}
    md = (out / "seeds.md").read_text()
    assert "median joint ATE **1.3 cm**" in md and "one map in 2 of 3 (**missed**)" in md
    assert "| seed-2 | 2 x 60 s, seed 2 | – | 1.1 | 6.1 | – | – | 2 | 1 | 9 | 0 | – |" in md
    assert (out / "seeds.png").stat().st_size > 1000
    assert (tmp_path / "results" / "seeds.md").read_text() == md
    assert set(files) >= {out / "seeds.md", out / "seeds.json", out / "seeds.png"}


def test_no_runs_and_broken_reports_are_errors(tmp_path: Path) -> None:
    with pytest.raises(SeedsError, match="no run report"):
        run_seeds(SeedsConfig(seeds=(), out=tmp_path, from_runs=True))
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "report.json").write_text("{not json")
    with pytest.raises(SeedsError, match="not a run report"):
        read_report(tmp_path / "bad")


def test_seeds_subcommand_parses_into_a_config(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    experiment.register(parser.add_subparsers())
    argv = ["experiment", "seeds", "--seeds", "0-2,5", "--seconds", "40", "--out", str(tmp_path)]
    args = parser.parse_args(argv)
    cfg = experiment.seeds_config(args, argv)
    assert cfg.seeds == (0, 1, 2, 5) and cfg.seconds == 40.0 and cfg.out == tmp_path
    assert cfg.results == Path("benchmarks/results") and not cfg.from_runs
    assert cfg.command == "recslam experiment seeds --seeds 0-2,5 --seconds 40 --out " + str(
        tmp_path
    )
    assert args.func is experiment.run_seeds


def test_generator_options_name_folders_and_tables() -> None:
    from lab.seeds import GeneratorOptions

    assert GeneratorOptions().tag == "" and GeneratorOptions().folder(3) == "seed-3"
    g = GeneratorOptions("Figure8+aggressive", "hall", True, 8.0)
    assert g.flight == "figure8+aggressive"
    assert g.folder(3) == "figure8+aggressive_hall_exposure_blur8ms-seed-3"
    assert SeedsConfig(seeds=(0,), out=Path("o")).table_name == "seeds"
    assert SeedsConfig(seeds=(0,), out=Path("o"), generator=g).table_name == "seeds_hard"
    with pytest.raises(SeedsError, match="spiral"):
        GeneratorOptions(flight="spiral")
    with pytest.raises(SeedsError, match="moon"):
        GeneratorOptions(world="moon")


@pytest.mark.slow
def test_dataset_built_with_generator_options_and_not_mixed_up(tmp_path: Path) -> None:
    from lab.seeds import GeneratorOptions

    g = GeneratorOptions(flight="lawnmower", world="room-random")
    folder = tmp_path / g.folder(2)
    assert ensure_dataset(folder, 1, 0.2, 2, g) is True
    info = json.loads((folder / "dataset.json").read_text())
    assert info["harder"]["flight"] == "lawnmower" and info["harder"]["world"] == "room-random"
    assert ensure_dataset(folder, 1, 0.2, 2, g) is False
    with pytest.raises(SeedsError, match="'flight': 'lawnmower'"):
        ensure_dataset(folder, 1, 0.2, 2)  # a default sweep never reuses a harder dataset


def test_hard_sweep_report_names_its_generator_settings(tmp_path: Path) -> None:
    run = _run(tmp_path, "figure8_vicon-seed-0", 0, 0.03, [0])
    data = tmp_path / "data" / "seed-0"
    harder = {"flight": "figure8", "world": "vicon", "trajectory_files": []}
    harder |= {"exposure_steps": True, "motion_blur_ms": 0.0}
    meta = {"robots": 2, "seconds": 30.0, "seed": 0, "harder": harder}
    (data / "dataset.json").write_text(json.dumps(meta))
    out = run.parent
    cfg = SeedsConfig(seeds=(), out=out, from_runs=True, name="seeds_hard")
    _, files = run_seeds(cfg)
    md = (out / "seeds_hard.md").read_text()
    assert md.startswith(
        "# Joint ATE over the generator's seeds: harder worlds "
        "(flight figure8, world vicon, exposure steps)"
    )
    assert "| 2 x 30 s, seed 0, flight figure8, world vicon, exposure steps | 3.0 |" in md
    assert "![seeds_hard.png](seeds_hard.png)" in md
    assert out / "seeds_hard.png" in files and not (out / "seeds.md").exists()


def test_seeds_subcommand_passes_generator_options(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    experiment.register(parser.add_subparsers())
    argv = ["experiment", "seeds", "--seeds", "0", "--flight", "figure8+hover", "--world"]
    argv += ["hall", "--exposure-steps", "--motion-blur-ms", "6", "--out", str(tmp_path)]
    cfg = experiment.seeds_config(parser.parse_args(argv), argv)
    g = cfg.generator
    assert (g.flight, g.world, g.exposure_steps, g.motion_blur_ms) == (
        "figure8+hover",
        "hall",
        True,
        6.0,
    )
    assert cfg.table_name == "seeds_hard" and cfg.out == tmp_path
    argv = ["experiment", "seeds", "--world", "hall"]
    cfg = experiment.seeds_config(parser.parse_args(argv), argv)
    assert cfg.out == Path("out/seeds_hard") and cfg.table_name == "seeds_hard"
    argv = ["experiment", "seeds"]
    assert experiment.seeds_config(parser.parse_args(argv), argv).out == Path("out/seeds")


@pytest.mark.slow
def test_loop_constraints_checked_against_the_ground_truth(tmp_path: Path) -> None:
    """A constraint that agrees with the truth passes; one 0.5 m off is counted as wrong."""
    import numpy as np

    from common.evaluation.results import load_groundtruth
    from common.geometry import inverse_T
    from lab.seeds import constraint_check
    from services.cloud.atlas.atlas import Atlas, KeyframeInput, make_key
    from services.cloud.store.persistence import CloudStore

    data = tmp_path / "data"
    ensure_dataset(data, 1, 1.0, 3)
    ref = load_groundtruth(["robot0"], data)[0]["robot0"]
    atlas = Atlas()
    stamps = []
    for kf_id, j in ((1, 10), (2, len(ref) - 10)):
        t = int(ref.timestamps_ns[j]) * 1e-9
        stamps.append(ref.T_world_body[j])
        atlas.add_keyframe(
            KeyframeInput(
                agent_id=0,
                keyframe_id=kf_id,
                timestamp=t,
                T_world_body=ref.T_world_body[j],
                keypoints=np.zeros((0, 2)),
                levels=np.zeros(0),
                descriptors=np.zeros((0, 32), np.uint8),
                word_ids=np.zeros(0),
                map_point_ids=np.zeros(0),
            )
        )
    T_true = inverse_T(stamps[0]) @ stamps[1]
    T_off = T_true.copy()
    T_off[:3, 3] += [0.5, 0.0, 0.0]
    atlas.add_loop(make_key(0, 1), make_key(0, 2), T_true)
    atlas.add_loop(make_key(0, 1), make_key(0, 2), T_off)
    run = tmp_path / "run1"
    with CloudStore(run / "run" / "state" / "cloud") as store:
        store.save_all(atlas, agents={0: ("robot0", "edge0", 0)})
    got = constraint_check(run, data)
    assert got["constraints"] == 2
    assert got["wrong_constraints"] == 1
    assert got["max_constraint_err_m"] == pytest.approx(0.5, abs=1e-6)
    assert constraint_check(tmp_path / "nothing", data)["constraints"] is None


def test_hard_sweep_of_several_settings_summarises_each_and_sorts_by_setting(
    tmp_path: Path,
) -> None:
    """Runs of two generator settings: one summary row per setting, and the runs sorted by
    setting and seed (``figure8``'s own digit and seed 10 after seed 2 do not reorder them)."""
    settings = {
        "figure8_vicon": {"flight": "figure8", "world": "vicon"},
        "inward_hall": {"flight": "inward", "world": "hall"},
    }
    cases = [("inward_hall", 10, 0.05), ("figure8_vicon", 2, 0.01), ("inward_hall", 2, 0.03)]
    cases += [("figure8_vicon", 10, 0.02)]
    out = tmp_path / "out"
    out.mkdir()
    for i, (tag, seed, joint) in enumerate(cases):
        root = tmp_path / f"r{i}"  # each run on its own dataset folder
        run = _run(root, f"{tag}-seed-{seed}", seed, joint, [0])
        run.rename(out / run.name)
        harder = settings[tag] | {"trajectory_files": [], "exposure_steps": False}
        meta = {"robots": 2, "seconds": 30.0, "seed": seed, "harder": harder}
        (root / "data" / f"seed-{seed}" / "dataset.json").write_text(json.dumps(meta))
    run_seeds(SeedsConfig(seeds=(), out=out, from_runs=True, name="seeds_hard"))
    md = (out / "seeds_hard.md").read_text()
    assert "| flight figure8, world vicon | 2 | 1.5 | 2.0 | 1.7 | 2 of 2 |" in md
    assert "| flight inward, world hall | 2 | 4.0 | 5.0 | 1.7 | 2 of 2 |" in md
    rows = [line.split(" | ")[0][2:] for line in md.splitlines() if "-seed-" in line]
    assert rows == [
        "figure8_vicon-seed-2",
        "figure8_vicon-seed-10",
        "inward_hall-seed-2",
        "inward_hall-seed-10",
    ]
