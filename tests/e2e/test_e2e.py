"""End to end: 3 robots, the edge and the cloud as real processes talking TCP on loopback.

Short synthetic sequences (3 robots x 10 s, generated once per session; a second set, 15 s, gives
each robot its own camera: EuRoC's 752x480, a wide 640x480 on a pitched mount and a 512x512
fisheye). What is asserted is what the system achieves on such short data today: every frame
decoded exactly once, every keyframe the edge uplinked present at the cloud exactly once (also
across an edge SIGKILL + restart on the same state directory), each robot's keyframe trajectory
within ATE_BOUND_M of ground truth, and the cloud merging the three robots' maps into one
(joint-frame ATE within the same bound: a false merge would put a robot metres off).
"""

from __future__ import annotations

import signal
import sqlite3
import time
from pathlib import Path

import pytest

from common.data.synth import SynthConfig, generate_dataset
from common.links.sensors import decode_sensors
from lab.run.orchestration import Job, JobConfig, robot_frames
from lab.run.report import RunFacts, write_report
from services.cloud.atlas.map_types import split_key

pytestmark = [pytest.mark.slow, pytest.mark.timeout(400)]

SECONDS = 10.0
# Per robot, own SE(3) alignment, keyframe trajectory (paths 6-8 m in 10 s). Measured 0.05-1.05 m:
# the aggressive robot's VI initialisation often fails on 10 s, which is what bounds this.
ATE_BOUND_M = 2.0


@pytest.fixture(scope="session")
def dataset(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("e2e_synth")
    generate_dataset(folder, SynthConfig(robots=3, seconds=SECONDS, seed=0))
    return folder


def _cloud_keyframe_ids(run_dir: Path) -> tuple[dict[str, list[tuple[str, int, int]]], int]:
    """{robot: (edge, agent, keyframe id) (with repeats, if any)} from the cloud's SQLite state,
    kept and retired by MBP alike, and how many are kept (an agent is one of the robot's maps
    on one edge)."""
    db = sqlite3.connect(f"file:{run_dir / 'state' / 'cloud' / 'cloud.sqlite'}?mode=ro", uri=True)
    try:
        rows = db.execute("SELECT agent, name, edge_id FROM agent_names").fetchall()
        names = {a: (n, e) for a, n, e in rows}
        out: dict[str, list[tuple[str, int, int]]] = {}
        kept = db.execute("SELECT agent, keyframe_id FROM keyframes").fetchall()
        for agent, kf in kept:
            name, edge = names[agent]
            out.setdefault(name, []).append((edge, agent, int(kf)))
        for key, agent in db.execute("SELECT key, agent FROM retired_keyframes"):
            name, edge = names[agent]
            out.setdefault(name, []).append((edge, agent, split_key(int(key))[1]))
    finally:
        db.close()
    return out, len(kept)


def _run(dataset: Path, run_dir: Path, on_tick=None, **config) -> tuple[Job, dict]:
    t0 = time.monotonic()
    with Job(JobConfig(dataset=dataset, run_dir=run_dir, **config)) as job:
        job.start()
        t_robots = time.monotonic()
        robot_codes = job.wait_robots(300, on_tick=on_tick)
        stream_s = time.monotonic() - t_robots
        job.wait_edge_idle(quiet_s=4.0)
        codes = job.stop()
    frames = robot_frames(dataset, job.robot_names)
    facts = RunFacts(stream_s, time.monotonic() - t0, codes, frames)
    data = write_report(run_dir, run_dir / "report", facts)
    assert robot_codes == dict.fromkeys(job.robot_names, 0), job.services["edge"].log_text()[-3000:]
    assert codes == dict.fromkeys([*job.robot_names, *job.edge_names, "cloud"], 0), codes
    return job, data


def _assert_nothing_lost(run_dir: Path, data: dict, restarted: tuple[str, ...] = ()) -> None:
    """Every frame decoded once, every uplinked keyframe at the cloud once per map.
    ``restarted``: edges killed and restarted (their robots' stats count the re-run, a new
    map; the first run's keyframes stay at the cloud too)."""
    # Frames: each robot sent its whole sequence, the edge decoded each frame exactly once.
    for name, r in data["robots"].items():
        assert r["frames_sent"] > 150, (name, r)
        assert r["frames_decoded"] == r["frames_sent"], (name, r)
    # Keyframes: the cloud holds every keyframe the edge uplinked, exactly once. (Ids have gaps:
    # the VIO's own keyframes between the robot's are not uplinked.)
    # MBP (at shutdown) retires keyframes: they stay in the state with their poses.
    ids, n_kept = _cloud_keyframe_ids(run_dir)
    for name, r in data["robots"].items():
        got = ids.get(name, [])
        assert r["keyframes_uplinked"] and r["keyframes_uplinked"] > 0, (name, r)
        assert len(got) == len(set(got)), (name, sorted(got))
        # An edge's stats file can lag its last uplink by one keyframe (written each second
        # and at exit), so the cloud may hold one more than it says per edge; never fewer.
        edges = r.get("edges", []) or list(restarted)
        n_edges = max(1, len(edges))
        assert r["keyframes_uplinked"] <= len(got), name
        if not set(edges) & set(restarted):
            assert len(got) <= r["keyframes_uplinked"] + n_edges, name
    assert data["map"]["keyframes_after_mbp"] == n_kept


@pytest.fixture(scope="session")
def clean_run(dataset, tmp_path_factory) -> tuple[Path, dict]:
    run_dir = tmp_path_factory.mktemp("e2e_run")
    _, data = _run(dataset, run_dir)
    return run_dir, data


def test_three_robots_nothing_lost_or_duplicated(clean_run) -> None:
    run_dir, data = clean_run
    _assert_nothing_lost(run_dir, data)
    link = data["links"]["edge->cloud"]
    assert link["by_type_kbit_s"]["KeyframeUpdateCoded"] > 0  # the coded wire is the default
    assert (
        "KeyframeUpdate" not in link["by_type_kbit_s"]
        and "MapPointUpdate" not in link["by_type_kbit_s"]
    )
    assert (run_dir / "report" / "report.md").is_file()


def test_three_robots_ate_within_bound(clean_run) -> None:
    _, data = clean_run
    for name, r in data["robots"].items():
        assert r["ate_rmse_m"] is not None, name
        assert r["ate_rmse_m"] < ATE_BOUND_M, (name, r["ate_rmse_m"])


def test_three_robots_maps_merged(clean_run) -> None:
    _, data = clean_run
    assert data["map"]["merges"] >= 2, data["map"]
    assert len(data["map"]["maps"]) == 1, data["map"]
    assert data["ate"]["joint_frame"] is True, data["ate"]
    assert data["ate"]["joint_rmse_m"] < ATE_BOUND_M, data["ate"]


def test_edge_killed_and_restarted_loses_no_keyframe(dataset, tmp_path) -> None:
    killed: list[int] = []

    def kill_once(job: Job, sample: dict) -> None:
        robots = sample["edge"].get("robots", {})
        if not killed and robots and min(r["frames_decoded"] for r in robots.values()) >= 60:
            killed.append(job.kill("edge", signal.SIGKILL))
            job.start_edge()

    job, data = _run(dataset, tmp_path, on_tick=kill_once)
    assert killed == [-signal.SIGKILL]
    text = job.services["edge"].log_text()
    assert text.count("edge listening") == 2 and "Traceback" not in text, text[-3000:]
    _assert_nothing_lost(tmp_path, data, restarted=("edge",))


def test_two_sites_a_robot_moves_and_an_edge_restart_loses_nothing(dataset, tmp_path) -> None:
    """Two edges, one cloud: robot0 and robot1 on edge-a, robot2 on edge-b; robot1 moves to
    edge-b at frame 80 (edge-a takes its frames 0..79, edge-b 80..end on a new stream);
    edge-a is SIGKILLed mid-run and restarted on its journal. Nothing is lost or counted
    twice at either edge, edge-b's robot is untouched, every agent's keyframes reach the cloud
    once under its own (edge, robot) identity, and the maps merge across the edges."""
    killed: list[int] = []
    move_at = 80

    def kill_a_once(job: Job, sample: dict) -> None:
        robots = sample["edges"]["edge-a"].get("robots", {})
        if (
            not killed
            and len(robots) == 2
            and min(r["frames_decoded"] for r in robots.values()) >= 40
        ):
            killed.append(job.kill("edge-a", signal.SIGKILL))
            job.start_edge("edge-a")

    sites = {"edge-a": ("robot0", "robot1"), "edge-b": ("robot2",)}
    job, data = _run(
        dataset, tmp_path, kill_a_once, sites=sites, moves=(("robot1", move_at, "edge-b"),)
    )
    assert killed == [-signal.SIGKILL]
    a, b = job.services["edge-a"].log_text(), job.services["edge-b"].log_text()
    assert a.count("edge listening") == 2 and "Traceback" not in a, a[-3000:]
    assert b.count("edge listening") == 1 and "Traceback" not in b, b[-3000:]
    _assert_nothing_lost(tmp_path, data, restarted=("edge-a",))
    per_edge = job.sample()["edges"]
    assert per_edge["edge-a"]["robots"]["robot1"]["frames_decoded"] == move_at
    total = data["robots"]["robot1"]["frames_sent"]
    assert per_edge["edge-b"]["robots"]["robot1"]["frames_decoded"] == total - move_at
    assert data["robots"]["robot1"]["edges"] == ["edge-a", "edge-b"]
    assert data["robots"]["robot2"]["edges"] == ["edge-b"]
    assert data["links"]["robot2->edge-b"]["duplicates_dropped"] == 0
    ids, _ = _cloud_keyframe_ids(tmp_path)
    assert {e for e, _, _ in ids["robot1"]} == {"edge-a", "edge-b"}
    assert {e for e, _, _ in ids["robot2"]} == {"edge-b"}
    assert set(data["sites"]) == {"edge-a", "edge-b"}
    # Merged across the edges: the robots of both sites share one frame.
    assert data["map"]["merges"] >= 2, data["map"]
    assert data["ate"]["joint_frame"] is True, data["ate"]
    assert data["ate"]["joint_rmse_m"] < ATE_BOUND_M, data["ate"]


MIXED_CAMERAS = ("euroc", "wide", "fisheye")
MIXED_SECONDS = 15.0  # the second merge came at 12.7 s of sequence in a 60 s run of this team


@pytest.fixture(scope="session")
def mixed_run(tmp_path_factory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("e2e_mixed")
    generate_dataset(
        folder, SynthConfig(robots=3, seconds=MIXED_SECONDS, seed=0, cameras=MIXED_CAMERAS)
    )
    run_dir = tmp_path_factory.mktemp("e2e_mixed_run")
    _, data = _run(folder, run_dir)
    return run_dir, data


def test_three_cameras_one_fisheye_merge_into_one_map(mixed_run) -> None:
    """A team whose cameras differ (one fisheye): the edge takes no camera, each robot's own
    calibration reaches the cloud, nothing is lost and the three maps merge into one."""
    run_dir, data = mixed_run
    _assert_nothing_lost(run_dir, data)
    db = sqlite3.connect(f"file:{run_dir / 'state' / 'cloud' / 'cloud.sqlite'}?mode=ro", uri=True)
    try:
        rows = dict(db.execute("SELECT name, sensors FROM robot_sensors").fetchall())
    finally:
        db.close()
    cameras = {name: decode_sensors(blob).camera for name, blob in rows.items()}
    assert sorted((c.model, c.width, c.height) for c in cameras.values()) == [
        ("equidistant", 512, 512),
        ("radtan", 640, 480),
        ("radtan", 752, 480),
    ], cameras
    for name, r in data["robots"].items():
        assert r["ate_rmse_m"] is not None and r["ate_rmse_m"] < ATE_BOUND_M, (name, r)
    assert data["map"]["merges"] >= 2 and len(data["map"]["maps"]) == 1, data["map"]
    assert data["ate"]["joint_frame"] is True, data["ate"]
    assert data["ate"]["joint_rmse_m"] < ATE_BOUND_M, data["ate"]
