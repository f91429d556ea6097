"""Two missions over the same synthetic room: the second starts inside the map the first left
(``services.cloud.store.mission``), relocalises against it, merges into it and comes out in its
frame, while the prior map stays exactly as it was."""

from __future__ import annotations

import asyncio
import dataclasses
import sqlite3

import numpy as np
import pytest

from common.links.edge_cloud import decode_pose_correction
from common.vocabulary import Vocabulary
from services.cloud.app import CloudApp
from services.cloud.fusion.map_fusion import MapFusion
from services.cloud.optimization.full_ba import solve_full_ba
from services.cloud.optimization.global_optimization import optimize_pose_graph
from services.cloud.service_config import (
    CloudServiceConfig,
    FullBAScheduleConfig,
    MapViewConfig,
    OptimizationScheduleConfig,
    StoreConfig,
)
from services.cloud.store.persistence import CloudStore, PersistenceError
from sim.cloud import (
    circle_poses,
    default_camera,
    encode_session,
    make_session,
    make_world,
    yaw_T,
)

WORLD_SEED = 51
FRAMES = {  # each robot's map frame T_map_world, per mission
    ("m1", "robot0"): np.eye(4),
    ("m1", "robot1"): yaw_T(np.radians(-60.0), np.array([-1.5, 0.5, 0.0])),
    ("m2", "robot0"): yaw_T(np.radians(35.0), np.array([1.0, -2.0, 0.3])),
    ("m2", "robot1"): yaw_T(np.radians(-110.0), np.array([0.5, 1.5, -0.2])),
}


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return Vocabulary.load()


@pytest.fixture(scope="module")
def missions(vocab):
    """Per mission: per robot its messages per keyframe (as an edge sends them) and the true
    poses ``T_world_body``; keyframes every 0.5 s, mission 2 a day later."""
    world = make_world(WORLD_SEED, n_points=2500)
    cam = default_camera()
    plan = {
        "m1": {
            "robot0": (circle_poses(16, turns=1.0), 1, 0.0),
            "robot1": (circle_poses(8, turns=0.5, phase=2.0), 2, 50.0),
        },
        "m2": {
            "robot0": (circle_poses(12, turns=0.7, phase=1.0), 3, 86400.0),
            "robot1": (circle_poses(10, turns=0.6, phase=4.0), 4, 86400.0),
        },
    }
    out: dict[str, dict[str, tuple[list, np.ndarray]]] = {}
    for mission, robots in plan.items():
        out[mission] = {}
        for name, (poses, seed, t0) in robots.items():
            kfs, mps = make_session(world, cam, 0, poses, FRAMES[mission, name], seed=seed, t0=t0)
            out[mission][name] = (encode_session(kfs, mps, name, vocab, 7), poses)
    return out


def _app(path, vocab, mission: str | None = None) -> CloudApp:
    cfg = CloudServiceConfig(store=StoreConfig(mission=mission))
    store = CloudStore(path)
    if mission is not None:
        store.enter_mission(mission)
    fusion = MapFusion(default_camera(), vocab.idf, cfg.domain, store.load())
    return CloudApp(fusion, store, vocab, cfg)


def _feed(app: CloudApp, edge: str, stream: bytes, robots: dict, seq: int = 0) -> int:
    """The robots' keyframes interleaved as in a live mission; each merge optimised."""
    groups = {n: list(msgs) for n, (msgs, _) in robots.items()}
    for i in range(max(len(g) for g in groups.values())):
        for g in groups.values():
            for m in g[i] if i < len(g) else []:
                seq += 1
                if app.handle(edge, m, stream, seq).merged:
                    _optimize(app, app.atlas.maps()[0])
    return seq


def _optimize(app: CloudApp, map_id: int) -> list:
    problem, token = app.optimization_problem(map_id)
    result = optimize_pose_graph(problem, app.config.domain.optimization)
    return app.apply_optimization(map_id, result, token) or []


@pytest.mark.slow
def test_second_mission_merges_into_the_saved_map_and_reports_in_its_frame(
    tmp_path, vocab, missions
):
    # Mission 1 (no --mission: the directory's first mission), ended with MBP as at shutdown.
    app = _app(tmp_path, vocab)
    _feed(app, "edge-a", b"s1", missions["m1"])
    assert app.atlas.maps() == [app.atlas.map_of_agent(0)] and len(app.agents()) == 2
    prior_map = app.atlas.maps()[0]
    app.prune(prior_map, final=True)
    prior_keys = app.atlas.keyframe_keys()
    prior_poses = {k: app.atlas.T_map_body(k).copy() for k in prior_keys}
    prior_points = np.array(app.atlas.map_point_keys())
    app.close()

    # Mission 2: the same robot names and edge map ids, a new edge and stream.
    app = _app(tmp_path, vocab, mission="m2")
    assert set(app.prior_agents()) == {0, 1} and app.agents() == {}
    assert app.positions.load("edge-a") is None  # the old mission's streams are over
    seq = _feed(app, "edge-b", b"s2", missions["m2"])
    assert app.agents() == {2: ("robot0", "edge-b", 7), 3: ("robot1", "edge-b", 7)}
    assert app.atlas.maps() == [prior_map]  # merged into the old map, not a new one

    # Optimisations and MBP on the merged map leave the prior map exactly where it was.
    corrections = _optimize(app, prior_map)
    problem, token = app.full_ba_problem(prior_map)
    cfg = app.config.domain
    corrections += app.apply_optimization(
        prior_map, solve_full_ba(problem, cfg.full_ba, cfg.optimization), token
    )
    report = app.prune(prior_map, final=True)
    assert report.keyframes_after < report.keyframes_before  # mission 2's were pruned
    assert set(prior_keys) <= set(app.atlas.keyframe_keys())
    for k in prior_keys:
        np.testing.assert_array_equal(app.atlas.T_map_body(k), prior_poses[k])
    kept = [k for k in prior_points.tolist() if app.atlas.has_map_point(k)]
    assert len(kept) > 0.9 * prior_points.size

    # Corrections go to mission 2's edge only, each in its robot's own map frame.
    assert corrections and {c.edge_id for c in corrections} == {"edge-b"}
    for c in corrections:
        ids, T = decode_pose_correction(c.message)
        truth = missions["m2"][c.message.agent_id][1]
        T_map_world = FRAMES["m2", c.message.agent_id]
        err = np.linalg.norm(T[:, :3, 3] - (T_map_world @ truth[ids])[:, :3, 3], axis=1)
        assert err.max() < 0.05

    # Its trajectories are mission 2's robots, in mission 1's map frame.
    trajs, maps = app.trajectories()
    assert sorted(trajs) == ["robot0", "robot1"] and set(maps.values()) == {prior_map}
    T_prior_world = FRAMES["m1", f"robot{prior_map}"]
    for name, traj in trajs.items():
        truth = missions["m2"][name][1]
        i = np.round((traj.timestamps_ns * 1e-9 - 86400.0) / 0.5).astype(int)
        expected = (T_prior_world @ truth[i])[:, :3, 3]
        assert np.linalg.norm(traj.p_world_body - expected, axis=1).max() < 0.05

    # Both robots merged within their first 10 s of keyframes.
    mission = app.mission_report()
    assert mission["mission"] == "m2" and mission["prior_agents"] == 2
    delays = {n: r["delay_s"] for n, r in mission["robots"].items()}
    assert set(delays) == {"robot0", "robot1"}
    assert all(d is not None and 0 <= d <= 10.0 for d in delays.values()), delays
    app.close()

    # A crash restart with the same command line continues mission 2 (same agents, stream).
    app = _app(tmp_path, vocab, mission="m2")
    try:
        assert app.agents() == {2: ("robot0", "edge-b", 7), 3: ("robot1", "edge-b", 7)}
        assert set(app.prior_agents()) == {0, 1}
        pos = app.positions.load("edge-b")
        assert pos is not None and (pos.stream_id, pos.last_delivered) == (b"s2", seq)
        assert app.mission_report()["in_prior_map"] == ["robot0", "robot1"]
    finally:
        app.close()
    with CloudStore(tmp_path) as store, pytest.raises(PersistenceError, match="ended"):
        store.enter_mission("mission-0")  # an earlier mission cannot be continued


def test_a_schema_5_directory_is_upgraded_and_its_agents_are_mission_0(tmp_path):
    db = sqlite3.connect(tmp_path / "cloud.sqlite", isolation_level=None)
    db.executescript(
        "CREATE TABLE meta (name TEXT PRIMARY KEY, value INTEGER NOT NULL);"
        "INSERT INTO meta VALUES ('schema', 5);"
        "CREATE TABLE agent_names (agent INTEGER PRIMARY KEY, name TEXT NOT NULL, "
        "edge_id TEXT NOT NULL, edge_map INTEGER NOT NULL, UNIQUE (name, edge_map));"
        "INSERT INTO agent_names VALUES (0, 'robot0', 'edge', 0);"
    )
    db.close()
    with CloudStore(tmp_path) as store:
        assert store.agents() == {0: ("robot0", "edge", 0)}
        assert store.agent_missions() == {0: 0} and store.mission == 0
        assert store.enter_mission("next") == (1, True)
        assert store.enter_mission("next") == (1, False)
    with CloudStore(tmp_path) as store:  # the same name and edge map, in the new mission
        from services.cloud.atlas.atlas import Atlas

        store.commit(Atlas(), agents={1: ("robot0", "edge", 0)})
        assert store.agent_missions() == {0: 0, 1: 1}
        assert store.missions() == {0: "mission-0", 1: "next"}


def _write_truth(folder, mission: str, robots: dict) -> None:
    """Each robot's keyframe truth as TUM (keyframes every 0.5 s from its start time)."""
    from common.evaluation.trajectory import Trajectory
    from common.evaluation.tum import write_tum
    from common.geometry import R_to_quat_wxyz

    folder.mkdir(parents=True)
    for name, (_, T) in robots.items():
        t0 = {"m1": {"robot0": 0.0, "robot1": 50.0}, "m2": {}}[mission].get(name, 86400.0)
        ts = np.round((t0 + 0.5 * np.arange(T.shape[0])) * 1e9).astype(np.int64)
        q = np.array([R_to_quat_wxyz(t[:3, :3]) for t in T])
        write_tum(folder / f"{name}.tum", Trajectory(ts, T[:, :3, 3], q, name))


@pytest.mark.slow
def test_the_service_runs_mission_2_in_mission_1s_map_and_reports_it(tmp_path, vocab, missions):
    """Over loopback TCP, as ``recslam cloud --mission m2 --prior-frame ...`` runs it."""
    import json

    from common.protocol import SessionConfig
    from common.transport import Client, TransportConfig, run
    from services.cloud.server import CloudServer

    secret = b"mission-test-secret"
    fast = TransportConfig(reconnect_initial_delay=0.01, reconnect_max_delay=0.2)
    _write_truth(tmp_path / "gt1", "m1", missions["m1"])
    _write_truth(tmp_path / "gt2", "m2", missions["m2"])

    async def mission(name: str | None, edge: str, robots: dict, prior_frame=None) -> list:
        cfg = CloudServiceConfig(
            schedule=OptimizationScheduleConfig(debounce_s=0.2),
            full_ba=FullBAScheduleConfig(at_shutdown_s=5.0),
            map_view=MapViewConfig(gt_every_s=0),
            store=StoreConfig(output_every_s=0),
        )
        cloud = CloudServer(
            SessionConfig("cloud", "cloud", secret),
            tmp_path / "state",
            default_camera(),
            vocab,
            dataclasses.replace(cfg, store=dataclasses.replace(cfg.store, mission=name)),
            results_dir=tmp_path / (name or "m1"),
            groundtruth=tmp_path / ("gt2" if name else "gt1"),
            transport=fast,
            prior_frame=prior_frame,
        )
        _, port = await cloud.start()
        got: list = []

        async def on(d) -> None:
            got.append(d.message)

        client = Client(SessionConfig("edge", edge, secret), on, "127.0.0.1", port, transport=fast)
        await client.start()
        try:
            groups = [list(msgs) for msgs, _ in robots.values()]
            for i in range(max(map(len, groups))):
                for g in groups:
                    for m in g[i] if i < len(g) else []:
                        await client.send(m)
            await client.flush()
            await cloud.flush_optimizations()
            # The corrections are on their way when the round ends; on a loaded machine the
            # client would close before they arrive (then the next session delivers them).
            for _ in range(200):
                if name is None or {c.agent_id for c in got} == {"robot0", "robot1"}:
                    break
                await asyncio.sleep(0.05)
        finally:
            await client.close()
            await cloud.stop()
        return got

    run(mission(None, "edge-a", missions["m1"]))
    m1_ate = tmp_path / "m1" / "eval" / "ate.json"
    assert json.loads(m1_ate.read_text())["joint"]["stats_m"]["rmse"] < 0.05
    got = run(mission("m2", "edge-b", missions["m2"], prior_frame=m1_ate))

    assert got and {c.agent_id for c in got} == {"robot0", "robot1"}
    report = json.loads((tmp_path / "m2" / "mission.json").read_text())
    assert report["mission"] == "m2" and report["prior_agents"] == 2
    assert all(0 <= r["delay_s"] <= 10.0 for r in report["robots"].values()), report
    maps = json.loads((tmp_path / "m2" / "cloud_maps.json").read_text())
    assert maps["robots"] == {"robot0": maps["maps"][0], "robot1": maps["maps"][0]}
    # Under mission 1's alignment (not re-aligned), mission 2 lies on its ground truth.
    # (A mission in another frame is metres off here: 1.16 m on the live run of two rooms.)
    frame = json.loads((tmp_path / "m2" / "eval" / "ate_prior_frame.json").read_text())
    own = json.loads((tmp_path / "m2" / "eval" / "ate.json").read_text())
    in_prior, aligned = frame["joint"]["stats_m"]["rmse"], own["joint"]["stats_m"]["rmse"]
    assert in_prior < 0.08 and in_prior < aligned + 0.02, (in_prior, aligned)
