"""Sites: the --sites / --move / --restart-edge syntax, round-robin edges, the commands a
run of several edges starts, and one view of several edges' counters (no processes)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lab.run.orchestration import Job, JobConfig, OrchestrationError, progress_line
from lab.run.report import RunFacts, collect
from lab.run.sites import (
    SitesError,
    assign_sites,
    merge_edge_stats,
    parse_move,
    parse_restart,
    parse_sites,
)


def test_sites_syntax_and_round_robin() -> None:
    assert parse_sites("edgeA=robot0,robot1; edgeB=robot2") == {
        "edgeA": ("robot0", "robot1"),
        "edgeB": ("robot2",),
    }
    for bad in ("edgeA", "edgeA=", "=robot0", "a=r0;a=r1", "a=r0;b=r0", ""):
        with pytest.raises(SitesError):
            parse_sites(bad)
    assert parse_move("robot1@150=edge1") == ("robot1", 150, "edge1")
    assert parse_restart("edge0@12.5") == ("edge0", 12.5)
    with pytest.raises(SitesError):
        parse_move("robot1=edge1")
    robots = [f"robot{i}" for i in range(6)]
    assert assign_sites(robots) == {"edge": tuple(robots)}
    assert assign_sites(robots, 2) == {
        "edge0": ("robot0", "robot2", "robot4"),
        "edge1": ("robot1", "robot3", "robot5"),
    }
    with pytest.raises(SitesError, match="the dataset has"):
        assign_sites(robots, sites={"a": ("robot0",)})


def _job(tmp_path: Path, **kw) -> Job:
    for i in range(4):
        (tmp_path / "data" / f"robot{i}" / "mav0").mkdir(parents=True, exist_ok=True)
    return Job(JobConfig(dataset=tmp_path / "data", run_dir=tmp_path / "run", **kw))


def _arg(argv: list[str], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def test_two_edges_have_their_own_port_identity_state_and_robots(tmp_path) -> None:
    job = _job(tmp_path, edges=2, moves=(("robot0", 100, "edge1"),))
    assert job.edge_names == ("edge0", "edge1")
    assert job.sites == {"edge0": ("robot0", "robot2"), "edge1": ("robot1", "robot3")}
    a, b = job.edge_argv("edge0"), job.edge_argv("edge1")
    assert _arg(a, "--agent-id") == "edge0" and _arg(b, "--agent-id") == "edge1"
    assert _arg(a, "--listen") != _arg(b, "--listen")
    assert _arg(a, "--state-dir") != _arg(b, "--state-dir")
    assert _arg(b, "--stats-out").endswith("stats/edge-edge1.json")
    assert (job.keys_dir / "edge-edge1.keys").is_file()
    assert _arg(a, "--cloud") == _arg(b, "--cloud")
    r0, r1 = job.robot_argv("robot0"), job.robot_argv("robot1")
    assert _arg(r0, "--edge") == f"127.0.0.1:{job.edge_ports['edge0']}"
    assert _arg(r0, "--handover") == f"100=127.0.0.1:{job.edge_ports['edge1']}"
    assert _arg(r1, "--edge") == f"127.0.0.1:{job.edge_ports['edge1']}"
    assert "--handover" not in r1
    # One edge stays "edge" with its historical files.
    one = _job(tmp_path / "one")
    assert one.edge_names == ("edge",)
    assert _arg(one.edge_argv(), "--stats-out").endswith("stats/edge.json")
    with pytest.raises(OrchestrationError, match="no such robot or edge"):
        _job(tmp_path / "bad", edges=2, moves=(("robot0", 100, "edge7"),))


def _edge_stats(robots: dict[str, int]) -> dict:
    def link(n: int) -> dict:
        return {
            "rx": {"bytes": 100 * n, "by_type": {"RobotFrame": {"bytes": 100 * n}}},
            "tx": {"bytes": 10 * n, "by_type": {}},
            "duplicates_dropped": 0,
        }

    return {
        "robots": {
            r: {
                "frames_decoded": n,
                "frames_processed": n,
                "queued": 0,
                "keyframes_uplinked": 1,
                "keyframes_decoded": 2,
                "state": "tracking",
            }
            for r, n in robots.items()
        },
        "links": {r: link(n) for r, n in robots.items()},
    }


def test_counters_of_a_robot_that_moved_are_summed_over_its_edges(tmp_path) -> None:
    a, b = _edge_stats({"robot0": 120, "robot2": 200}), _edge_stats({"robot0": 80})
    merged = merge_edge_stats({"edge0": a, "edge1": b})
    assert merged["robots"]["robot0"]["frames_decoded"] == 200
    assert merged["robots"]["robot0"]["state"] == "tracking"
    assert merged["links"]["robot0"]["rx"]["bytes"] == 20000
    assert merged["edge_of"] == {"robot0": ["edge0", "edge1"], "robot2": ["edge0"]}
    line = progress_line({"edge": merged, "edges": {"edge0": a, "edge1": b}, "cloud": {}}, 1.0)
    assert "edge0/edge1:robot0 200f" in line
    # The report reads every edge's stats file.
    stats = tmp_path / "stats"
    stats.mkdir()
    (stats / "edge-edge0.json").write_text(json.dumps(a))
    (stats / "edge-edge1.json").write_text(json.dumps(b))
    cloud = {"links": {"edge1": {"rx": {"bytes": 800, "by_type": {}}, "tx": {"bytes": 0}}}}
    (stats / "cloud.json").write_text(json.dumps(cloud))
    data = collect(tmp_path, RunFacts(10.0, 12.0, {}, {"robot0": 200, "robot2": 200}))
    assert data["robots"]["robot0"]["frames_decoded"] == 200
    assert data["robots"]["robot0"]["frames_lost"] == 0
    assert data["robots"]["robot0"]["edges"] == ["edge0", "edge1"]
    assert {"robot0->edge0", "robot0->edge1", "robot2->edge0"} <= set(data["links"])
    assert data["sites"]["edge1"]["robots"] == ["robot0"]
    assert data["sites"]["edge1"]["to_cloud_kbit_s"] == pytest.approx(0.64)
