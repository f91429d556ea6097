"""``recslam experiment links``: argument parsing, the numbers read from run folders, the
tables, the verdict and the files (no run of the services: the run folders are written here,
their reports by ``lab.run.report.write_report`` itself from fake counters)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import pytest

from common.links import CodecTimer, WireFormat
from lab.links import (
    LinksConfig,
    LinksError,
    Targets,
    aggregate,
    build_data,
    dataset_names,
    family,
    find_runs,
    parse_datasets,
    parse_wires,
    read_run,
    run_folder,
    summarize,
    verdict,
)
from lab.links_report import family_label, fmt, render_markdown, verdict_line, write_links
from lab.links_run import run_links
from lab.run.report import RunFacts, write_report
from recslam.commands import experiment
from recslam.commands.edge import codec_cpu

CAMERA_FRAMES = 1200  # 60 s at 20 Hz: 1 kbit/s at camera rate = 7500 bytes


def kbit(kbit_s: float) -> int:
    """Bytes that make ``kbit_s`` at camera rate over the fixture's 60 s."""
    return round(kbit_s * 1000 / 8 * CAMERA_FRAMES / 20)


def counters(by_type: dict[str, tuple[int, int]]) -> dict[str, Any]:
    """Transport counters as ``Server.counters()`` writes them: ``{type: (messages, bytes)}``."""
    return {
        "messages": sum(n for n, _ in by_type.values()),
        "bytes": sum(b for _, b in by_type.values()),
        "by_type": {t: {"messages": n, "bytes": b} for t, (n, b) in by_type.items()},
    }


def link(rx: dict[str, tuple[int, int]], tx: dict[str, tuple[int, int]]) -> dict[str, Any]:
    return {
        "rx": counters(rx),
        "tx": counters(tx),
        "retransmitted_messages": 0,
        "retransmitted_bytes": 0,
        "duplicates_dropped": 0,
        "connections": 1,
        "outbox_messages": 0,
        "outbox_bytes": 0,
        "connected": False,
    }


def make_run(report_dir: Path, wire: str, scale: float = 1.0, ate: float = 0.02) -> Path:
    """A finished run of two robots (a, b) in ``report_dir``: the edge's and the cloud's stats,
    the cloud's ATE and maps, ``samples.jsonl``, then the report as the demo writes it.

    raw: robot→edge 100 / 150 kbit/s (a / b), edge→robot 200 each, edge→cloud 3000;
    coded: robot→edge the same, edge→robot 20 / 10, edge→cloud 300 ``* scale``, new types
    ``KeyframeUpdateCoded`` / ``MapPointUpdateCoded`` / ``KeyframePoses``, and codec timings.
    """
    run_dir = report_dir / "run"
    (run_dir / "stats").mkdir(parents=True)
    (run_dir / "results" / "eval").mkdir(parents=True)
    coded = wire == "coded"
    fb = "InertialFeedbackCoded" if coded else "InertialFeedback"
    robot_links = {}
    for name, up, down in (("a", 100, 20 if coded else 200), ("b", 150, 10 if coded else 200)):
        rx = {"RobotFrame": (CAMERA_FRAMES, kbit(up) - 500), "Ack": (20, 460), "Hello": (1, 40)}
        tx = {fb: (60, round(kbit(down * scale)) - 1000), "Ack": (40, 1000)}
        robot_links[name] = link(rx, tx)
    edge: dict[str, Any] = {
        "robots": {
            n: {"frames_decoded": CAMERA_FRAMES - 1, "keyframes_uplinked": 50, "state": "tracking"}
            for n in robot_links
        },
        "links": robot_links,
    }
    if coded:
        up = {
            "KeyframeUpdateCoded": (100, kbit(100 * scale)),
            "MapPointUpdateCoded": (200, kbit(190 * scale)),
            "KeyframePoses": (300, kbit(10 * scale)),
            "Ack": (10, 230),
        }
        edge["codec_cpu"] = {
            "encode.KeyframeUpdateCoded": {"seconds": 0.5, "messages": 100},
            "encode.InertialFeedbackCoded": {"seconds": 0.06, "messages": 120},
        }
    else:
        up = {
            "KeyframeUpdate": (400, kbit(1000)),
            "MapPointUpdate": (100, kbit(2000)),
            "Ack": (10, 230),
        }
    cloud = {
        "keyframes": 60,
        "map_points": 9000,
        "maps": [1],
        "merges": 1,
        "loops": 3,
        "mbp_passes": 1,
        "optimizations": 4,
        "links": {"edge": link(up, {"PoseCorrection": (10, kbit(5)), "Ack": (500, 11500)})},
    }
    if coded:
        cloud["codec_cpu"] = {"decode.KeyframeUpdateCoded": {"seconds": 0.2, "messages": 100}}
    (run_dir / "stats" / "edge.json").write_text(json.dumps(edge))
    (run_dir / "stats" / "cloud.json").write_text(json.dumps(cloud))
    samples = [
        {"time": t, "edge": {}, "cloud": {"map_points": n}}
        for t, n in ((0, 0), (1, 12000), (2, 9000))
    ]
    (run_dir / "stats" / "samples.jsonl").write_text("".join(json.dumps(s) + "\n" for s in samples))
    stats = {"rmse": ate}
    ate_json = {
        "joint": {"agents": ["a", "b"], "stats_m": stats},
        "agents": {
            n: {
                "n_matched": 50,
                "individual": {"stats_m": {"rmse": ate / 2}},
                "under_joint": {"stats_m": stats},
            }
            for n in ("a", "b")
        },
    }
    (run_dir / "results" / "eval" / "ate.json").write_text(json.dumps(ate_json))
    maps = {"robots": {"a": 1, "b": 1}, "maps": [1], "joint_frame": True, "note": "one map"}
    (run_dir / "results" / "cloud_maps.json").write_text(json.dumps(maps))
    codes = {"a": 0, "b": 0, "edge": 0, "cloud": 0}
    write_report(run_dir, report_dir, RunFacts(150.0, 200.0, codes, {"a": 1200, "b": 1200}))
    return report_dir


@pytest.fixture
def runs_out(tmp_path: Path) -> Path:
    """``OUT/synth/{raw,coded}/run1`` and a second coded run (edge→cloud ×1.2, ATE 0.03)."""
    out = tmp_path / "out"
    make_run(run_folder(out, "synth", WireFormat.RAW, 1), "raw")
    make_run(run_folder(out, "synth", WireFormat.CODED, 1), "coded")
    make_run(run_folder(out, "synth", WireFormat.CODED, 2), "coded", scale=1.2, ate=0.03)
    return out


# ---------------------------------------------------------------------- options
def test_links_subcommand_parses_into_a_config() -> None:
    parser = argparse.ArgumentParser()
    experiment.register(parser.add_subparsers())
    argv = [
        "experiment",
        "links",
        "--data",
        "data/a,data/b",
        "--data",
        "data/c",
        "--runs",
        "2",
        "--wire",
        "coded,raw",
        "--results",
        "",
        "--out",
        "o",
    ]
    args = parser.parse_args(argv)
    assert args.func is experiment.run_links
    config = experiment.links_config(args, argv)
    assert config.datasets == (Path("data/a"), Path("data/b"), Path("data/c"))
    assert config.wires == (WireFormat.CODED, WireFormat.RAW)
    assert config.runs == 2 and config.results is None and config.out == Path("o")
    assert not config.from_runs
    assert config.command.startswith("recslam experiment links --data data/a,data/b")

    defaults = experiment.links_config(parser.parse_args(["experiment", "links"]), [])
    assert defaults.datasets == (Path("data/synth"),)
    assert defaults.wires == (WireFormat.RAW, WireFormat.CODED)
    assert defaults.results == Path("benchmarks/results") and defaults.runs == 1


def test_option_parsers() -> None:
    assert parse_wires(" raw , coded,raw") == (WireFormat.RAW, WireFormat.CODED)
    with pytest.raises(LinksError, match="'zip'"):
        parse_wires("raw,zip")
    with pytest.raises(LinksError, match="no wire"):
        parse_wires(",")
    assert parse_datasets(["x,y", "x", "z"]) == (Path("x"), Path("y"), Path("z"))
    names = dataset_names([Path("d1/synth"), Path("d2/synth"), Path("euroc")])
    assert list(names) == ["synth", "synth-2", "euroc"]
    assert run_folder(Path("o"), "synth", WireFormat.RAW, 3) == Path("o/synth/raw/run3")


def test_edge_and_demo_take_the_wire_and_the_job_passes_it(tmp_path: Path) -> None:
    from lab.run.orchestration import Job, JobConfig
    from recslam.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["edge", "--wire", "raw"]).wire == "raw"
    assert parser.parse_args(["edge"]).wire == "coded"
    assert parser.parse_args(["demo", "--wire", "raw"]).wire == "raw"
    with pytest.raises(SystemExit):
        parser.parse_args(["demo", "--wire", "zip"])
    (tmp_path / "data" / "r0" / "mav0").mkdir(parents=True)
    job = Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "run", wire=WireFormat.RAW))
    argv = job.edge_argv()
    assert argv[argv.index("--wire") + 1] == "raw"
    job = Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "run2"))
    assert job.edge_argv()[job.edge_argv().index("--wire") + 1] == "coded"


def test_codec_cpu_merges_the_timers_of_those_that_have_one() -> None:
    class Owner:
        def __init__(self, timer: CodecTimer | None) -> None:
            if timer is not None:
                self.codec_timer = timer

    t1, t2 = CodecTimer(), CodecTimer()
    t1.add("encode.X", 0.5, 2)
    t2.add("encode.X", 0.25)
    t2.add("decode.Y", 1.0, 4)
    assert codec_cpu([Owner(None), object()]) is None
    merged = codec_cpu([Owner(t1), Owner(t2), Owner(t1), None])  # t1 twice: counted once
    assert merged == {
        "decode.Y": {"seconds": 1.0, "messages": 4},
        "encode.X": {"seconds": 0.75, "messages": 3},
    }


# ---------------------------------------------------------------------- numbers
def test_read_run_rates_per_direction_and_type(runs_out: Path) -> None:
    raw = read_run(run_folder(runs_out, "synth", WireFormat.RAW, 1))
    coded = read_run(run_folder(runs_out, "synth", WireFormat.CODED, 1))
    assert raw["camera_s"] == 60.0 and raw["robots"] == 2 and raw["run"] == 1
    up = raw["links"]["robot->edge"]
    assert up["endpoints"] == 2
    assert up["kbit_s"] == pytest.approx(125.0)  # per robot: mean of 100 and 150
    assert up["kbit_s_max"] == pytest.approx(150.0)
    assert up["types"]["RobotFrame"]["messages"] == 2 * CAMERA_FRAMES
    assert raw["links"]["edge->cloud"]["kbit_s"] == pytest.approx(3000.0, abs=0.1)  # total
    assert coded["links"]["edge->robot"]["kbit_s_max"] == pytest.approx(20.0, abs=0.01)
    assert coded["per_robot"]["b"]["edge->robot"] == pytest.approx(10.0, abs=0.01)
    assert coded["per_robot"]["a"]["ate_m"] == pytest.approx(0.01)
    assert coded["items"] == {
        "frames_decoded": 2398,
        "keyframes_uplinked": 100,
        "map_points_peak": 12000,
    }
    assert coded["codec_cpu"]["edge"]["encode.KeyframeUpdateCoded"]["messages"] == 100
    assert raw["codec_cpu"] == {}
    assert raw["accuracy"]["ate_joint_m"] == 0.02 and raw["accuracy"]["maps"] == 1
    assert raw["accuracy"]["frames_lost"] == 2 and raw["failed"] == []
    with pytest.raises(LinksError, match=r"no report\.json"):
        read_run(runs_out / "nothing")


def test_summaries_and_families() -> None:
    assert summarize([1.0, None, 3.0]) == {"mean": 2.0, "min": 1.0, "max": 3.0, "n": 2}
    assert summarize([None]) is None
    agg = aggregate([{"a": 1, "b": {"c": 2.0}, "s": "x"}, {"a": 3, "b": {"c": None}}])
    assert agg == {
        "a": {"mean": 2.0, "min": 1.0, "max": 3.0, "n": 2},
        "b": {"c": {"mean": 2.0, "min": 2.0, "max": 2.0, "n": 1}},
    }
    assert family("KeyframeUpdateCoded") == "KeyframeUpdate" and family("Coded") == "Coded"
    assert family_label("KeyframeUpdate", ["KeyframeUpdate", "KeyframeUpdateCoded"]) == (
        "KeyframeUpdate(+Coded)"
    )
    assert family_label("KeyframePoses", ["KeyframePoses"]) == "KeyframePoses"
    assert fmt({"mean": 2.0, "min": 1.0, "max": 3.0, "n": 2}) == "2.0 (1.0–3.0)"
    assert fmt({"mean": 2.0, "min": 2.0, "max": 2.0, "n": 1}, ".2f") == "2.00"
    assert fmt({"mean": 2.0, "min": 1.99, "max": 2.01, "n": 3}, ".1f") == "2.0"  # runs agree
    assert fmt(None) == "–"


def test_verdict_against_the_targets(runs_out: Path) -> None:
    raw = [read_run(run_folder(runs_out, "synth", WireFormat.RAW, 1))]
    coded = [read_run(f) for f in find_runs(runs_out, list(WireFormat))["synth"]["coded"]]
    checks = {c["link"]: c for c in verdict(coded, Targets())}
    assert checks["robot->edge"]["ok"] and checks["robot->edge"]["value"] == pytest.approx(150)
    assert checks["edge->robot"]["ok"]  # worst robot: 20 (run 1) and 24 (run 2)
    assert checks["edge->robot"]["value"] == pytest.approx(22.0, abs=0.01)
    limit = checks["edge->cloud"]["limit"]
    assert limit == pytest.approx(400.0)  # 600 for three robots, scaled to two
    assert (
        checks["edge->cloud"]["value"] == pytest.approx(330.0, abs=0.1)
        and checks["edge->cloud"]["ok"]
    )
    raw_checks = verdict(raw, Targets())
    assert [c["ok"] for c in raw_checks] == [True, False, False]
    line = verdict_line("raw", raw_checks)
    assert "edge→robot 200.0 > 25 ✗" in line and line.endswith("1 of 3 targets met")
    tight = verdict(coded, Targets(robot_edge_kbit_s=149.0))
    assert tight[0]["ok"] is False


# ---------------------------------------------------------------------- tables and files
def test_tables_json_and_plot_from_run_folders(runs_out: Path, tmp_path: Path) -> None:
    config = LinksConfig(
        out=runs_out,
        results=tmp_path / "results",
        from_runs=True,
        command="recslam experiment links --from-runs",
    )
    _, files = run_links(config)
    assert {f.name for f in files} == {"links.md", "links.json", "links.png"}
    assert (tmp_path / "results" / "links.md").is_file()
    assert (tmp_path / "results" / "links.png").stat().st_size > 10_000
    assert not (tmp_path / "results" / "links.json").exists()
    stored = json.loads((runs_out / "links.json").read_text())
    assert stored["wires"] == ["raw", "coded"] and stored["errors"] == []
    synth = stored["datasets"]["synth"]
    assert [len(synth["wires"][w]["runs"]) for w in ("raw", "coded")] == [1, 2]
    up = synth["wires"]["coded"]["summary"]["links"]["edge->cloud"]["kbit_s"]
    assert up["mean"] == pytest.approx(330.0, abs=0.1) and up["n"] == 2

    md = (runs_out / "links.md").read_text()
    assert "`recslam experiment links --from-runs`" in md and "commit " in md
    assert "min–max spread" in md  # two coded runs
    rows = {line.split(" | ")[1]: line for line in md.splitlines() if line.startswith("| |")}
    # raw KeyframeUpdate and coded KeyframeUpdateCoded share a row; the ratio is raw / coded
    kf = rows["KeyframeUpdate(+Coded)"]
    assert "| 1000.0 | 110.0 (100.0–120.0) | ×9.09 |" in kf
    assert "| – |" in rows["KeyframePoses"]  # a type only the coded wire has
    assert "other (Hello)" in md  # below 0.05 kbit/s in both formats
    assert "| **125.0** | **125.0** | **×1** |" in md  # robot→edge per robot
    assert "Keyframe* per keyframe uplinked" in md
    assert "| edge | encode.KeyframeUpdateCoded | – | 100 | – | 5.000 |" in md
    assert "- **coded**: robot→edge 150.0 ≤ 150 ✓" in md
    assert "| joint ATE m | 0.020 | 0.025 (0.020–0.030) |" in md


def test_one_run_each_and_one_format(runs_out: Path, tmp_path: Path) -> None:
    folders = {"synth": {"raw": [run_folder(runs_out, "synth", WireFormat.RAW, 1)]}}
    data = build_data(folders, LinksConfig(wires=(WireFormat.RAW,)))
    md = render_markdown(data)
    assert "One run per format" in md and "raw / coded" not in md
    assert "No codec timings" in md
    files = write_links(data, tmp_path / "single", None)
    assert len(files) == 3


def test_from_runs_needs_runs(tmp_path: Path) -> None:
    with pytest.raises(LinksError, match="no finished run"):
        run_links(LinksConfig(out=tmp_path, from_runs=True, results=None))
    with pytest.raises(LinksError, match="no such dataset"):
        run_links(LinksConfig(datasets=(tmp_path / "none",), out=tmp_path, results=None))
