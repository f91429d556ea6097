"""``recslam demo``'s dataset step: a synthetic dataset is reused unless the command asks for
other robots, length, seed or cameras than it was built with (a setting not given matches
any: a seed-17 dataset is never rebuilt as the default one, a mixed team never as all-EuRoC)."""

from __future__ import annotations

import json
from pathlib import Path

from recslam.commands.demo import _dataset_matches


def _meta(folder: Path, cameras: list[str] | None) -> Path:
    config: dict = {"robots": 3, "seconds": 60.0, "seed": 0}
    if cameras is not None:
        config["cameras"] = cameras
    info = {"robots": 3, "seconds": 60.0, "seed": 0, "config": config}
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "dataset.json").write_text(json.dumps(info))
    return folder


def test_default_dataset_matches_default_cameras_only(tmp_path) -> None:
    folder = _meta(tmp_path / "default", None)
    assert _dataset_matches(folder, 3, 60.0, 0)
    assert _dataset_matches(folder, 3, 60.0, 0, ())
    assert not _dataset_matches(folder, 3, 60.0, 0, ("euroc", "wide", "fisheye"))
    assert not _dataset_matches(folder, 3, 60.0, 1)


def test_mixed_dataset_matches_its_cameras_only(tmp_path) -> None:
    folder = _meta(tmp_path / "mixed", ["euroc", "wide", "fisheye"])
    assert _dataset_matches(folder, 3, 60.0, 0, ("euroc", "wide", "fisheye"))
    assert _dataset_matches(folder, 3, 60.0, 0)  # no --cameras: reused as it is
    assert not _dataset_matches(folder, 3, 60.0, 0, ())
    assert not _dataset_matches(folder, 3, 60.0, 0, ("euroc", "fisheye", "wide"))


def test_settings_not_given_match_any(tmp_path) -> None:
    folder = _meta(tmp_path / "default", None)
    assert _dataset_matches(folder, None, None, None)
    assert _dataset_matches(folder, None, 60.0, None)
    assert not _dataset_matches(folder, None, 40.0, None)
    assert not _dataset_matches(folder, None, None, 17)
    assert not _dataset_matches(tmp_path / "missing", None, None, None)


def test_resume_map_without_a_saved_map_is_refused(tmp_path, capsys) -> None:
    from recslam.cli import main

    code = main(["demo", "--out", str(tmp_path / "m2"), "--resume-map", str(tmp_path / "m1")])
    assert code == 2 and "no saved map" in capsys.readouterr().out


def test_a_new_mission_reaches_the_cloud_and_the_report(tmp_path) -> None:
    """The cloud of a resumed map runs the named mission; the report shows its merges and
    its ATE in the prior mission's frame."""
    from lab.run.orchestration import Job, JobConfig
    from lab.run.report import RunFacts, collect, render_markdown

    (tmp_path / "data" / "robot0" / "mav0").mkdir(parents=True)
    prior = tmp_path / "m1" / "ate.json"
    job = Job(JobConfig(tmp_path / "data", tmp_path / "run", mission="m2", prior_frame=prior))
    argv = job.cloud_argv()
    assert argv[argv.index("--mission") + 1] == "m2"
    assert argv[argv.index("--prior-frame") + 1] == str(prior)
    results = tmp_path / "run" / "results"
    (results / "eval").mkdir(parents=True)
    mission = {
        "mission": "m2",
        "prior_agents": 2,
        "prior_keyframes": 41,
        "robots": {"robot0": {"delay_s": 3.25}, "robot1": {"delay_s": None}},
        "first_merge_delay_s": 3.25,
    }
    (results / "mission.json").write_text(json.dumps(mission))
    frame = {"joint": {"stats_m": {"rmse": 0.0123}}, "frame_of": str(prior)}
    (results / "eval" / "ate_prior_frame.json").write_text(json.dumps(frame))
    data = collect(tmp_path / "run", RunFacts(10.0, 12.0, {}, {"robot0": 5}))
    assert data["mission"]["merge_delay_s"] == {"robot0": 3.25, "robot1": None}
    text = render_markdown(data)
    assert "robot0 3.2 s, robot1 not merged" in text and "0.012 m" in text


def _actions(parser) -> dict:
    import argparse

    parser_action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {
        name: {flag: a for a in sub._actions for flag in a.option_strings}
        for name, sub in parser_action.choices.items()
    }


def test_demo_reuses_the_services_options() -> None:
    """The options ``recslam demo`` passes on to its cloud and edge are the services' own:
    the same default, choices and help (one definition, issue 50)."""
    from recslam.cli import build_parser

    actions = _actions(build_parser())
    demo = actions["demo"]
    shared = {
        "--dashboard-port": ("cloud", "--dashboard-port"),
        "--mbp": ("cloud", "--mbp"),
        "--mbp-every": ("cloud", "--mbp-every"),
        "--early-loop-candidates": ("cloud", "--early-loop-candidates"),
        "--record-uplink": ("cloud", "--record"),
        "--wire": ("edge", "--wire"),
    }
    for flag, (service, theirs) in shared.items():
        mine, other = demo[flag], actions[service][theirs]
        for field in ("default", "choices", "help", "type", "metavar"):
            assert getattr(mine, field) == getattr(other, field), (flag, field)
